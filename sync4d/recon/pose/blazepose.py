"""BlazePose (MediaPipe's legacy pose models) run frame by frame: our own pre- and post-processing.

What MediaPipe's graph does around the two ``.tflite`` models, re-implemented from its published
calculator options (``pose_detection_cpu.pbtxt``, ``pose_landmark_cpu.pbtxt``):

1. Detector: the frame letterboxed to 224x224 in [-1, 1]; 2254 SSD anchors (5 layers, strides 8, 16,
   32, 32, 32, scales 0.1484375..0.75, fixed size); boxes and 4 keypoints decoded per anchor (scale
   224), sigmoid scores, weighted non-maximum suppression; the best person is kept.
2. Region of interest: centred on keypoint 0 (mid-hip), side ``2 |k1 - k0|`` (k1 bounds the body),
   rotated so k0 -> k1 points up, enlarged 1.25x; in later frames it comes from the previous frame's
   landmarks 33 and 34 (the same two points), so the detector runs only when the track is lost.
3. Landmark model on the 256x256 crop in [0, 1]: 33 landmarks (+6 auxiliary) mapped back to the image,
   visibility = sigmoid, metric world landmarks (hip-centred) rotated back by the crop's angle, a person
   segmentation warped back into the frame.
4. Flip test: the model also runs on the mirrored crop (x flipped back, left and right landmarks
   exchanged) and the two passes are averaged, unless they disagree about which limb is left.
5. Optical flow (OpenCV DIS) at each landmark's pixel to the next frame, kept where it is reliable; the
   body fit asks the joints' image motion to follow it.

Coordinates: image pixels (u right, v down) with pixel centres at +0.5 (as the project's renderer);
world landmarks in metres with the camera's axes (x right, y down, z away from the camera).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from sync4d.errors import InputError
from sync4d.recon.pose.models import TFLiteModel

log = logging.getLogger(__name__)

DET_SIZE = 224
LMK_SIZE = 256
NUM_LANDMARKS = 33
ROI_SCALE = 1.25
# longer image side [px] at which the landmarks' optical flow is computed (larger frames are shrunk)
FLOW_MAX_SIDE = 480

# BlazePose landmark indices used by the body fit.
LANDMARK_NAMES = (
    "nose", "l_eye_inner", "l_eye", "l_eye_outer", "r_eye_inner", "r_eye", "r_eye_outer", "l_ear", "r_ear",
    "mouth_l", "mouth_r", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist", "r_wrist", "l_pinky",
    "r_pinky", "l_index", "r_index", "l_thumb", "r_thumb", "l_hip", "r_hip", "l_knee", "r_knee", "l_ankle",
    "r_ankle", "l_heel", "r_heel", "l_foot_index", "r_foot_index",
)


@dataclass(frozen=True)
class PoseTrack:
    """Per-frame BlazePose output for one person.

    Attributes:
        landmarks_2d: (T, 33, 2) image positions (u, v) [px].
        landmarks_z: (T, 33) relative depth of each landmark, in crop pixels scaled to image pixels [px]
            (smaller = nearer); only its differences within a frame mean anything.
        world: (T, 33, 3) metric landmarks, origin between the hips, camera axes [m].
        visibility: (T, 33) probability in [0, 1] that each landmark is visible.
        presence: (T,) pose-presence score per frame in [0, 1].
        masks: (T, H, W) bool person segmentation.
        found: (T,) bool, a person was tracked in the frame (else the frame's arrays are copies of the
            nearest found frame and its mask is empty).
        flow: (T-1, 33, 2) optical-flow displacement of each landmark's pixel from frame t to t+1 [px],
            NaN where the flow is not forward-backward consistent; None when not measured.
    """

    landmarks_2d: np.ndarray
    landmarks_z: np.ndarray
    world: np.ndarray
    visibility: np.ndarray
    presence: np.ndarray
    masks: np.ndarray
    found: np.ndarray
    flow: np.ndarray | None = None


@dataclass(frozen=True)
class Roi:
    """A rotated square region of the image.

    Attributes:
        center: (2,) centre (u, v) [px].
        size: side length [px].
        angle: rotation [rad]; a crop point (a, b) in [0, 1]^2 maps to ``center + size R(angle) (a-.5, b-.5)``.
    """

    center: np.ndarray
    size: float
    angle: float


def ssd_anchors() -> np.ndarray:
    """(2254, 2) anchor centres (x, y) in [0, 1] of the pose detector (MediaPipe SsdAnchorsCalculator).

    Layers of equal stride are merged: strides 8 and 16 give 2 anchors per cell, the three stride-32
    layers 6 per cell (fixed anchor size, so only the centres matter).
    """
    strides = [8, 16, 32, 32, 32]
    centres = []
    layer = 0
    while layer < len(strides):
        same = 0
        while layer + same < len(strides) and strides[layer + same] == strides[layer]:
            same += 1
        per_cell = 2 * same  # one anchor per aspect ratio (1.0) + one interpolated scale, per layer
        n = int(math.ceil(DET_SIZE / strides[layer]))
        ys, xs = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n, indexing="ij")
        grid = np.stack([xs.ravel(), ys.ravel()], axis=1)
        centres.append(np.repeat(grid, per_cell, axis=0))
        layer += same
    return np.concatenate(centres)


def letterbox(frame: np.ndarray, size: int) -> tuple[np.ndarray, float, np.ndarray]:
    """Resize keeping the aspect ratio and pad to ``size`` x ``size``.

    Returns:
        (image (size, size, 3) uint8, scale [input px per output px], pad (2,) offset of the image in
        the output [output px]).
    """
    import cv2

    h, w = frame.shape[:2]
    scale = max(h, w) / size
    nw, nh = int(round(w / scale)), int(round(h / scale))
    out = np.zeros((size, size, 3), dtype=np.uint8)
    pad = np.array([(size - nw) // 2, (size - nh) // 2])
    out[pad[1]: pad[1] + nh, pad[0]: pad[0] + nw] = cv2.resize(frame, (nw, nh), interpolation=cv2.INTER_AREA)
    return out, scale, pad


def decode_detections(
    raw_boxes: np.ndarray, raw_scores: np.ndarray, anchors: np.ndarray, *, min_score: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """Decode detector outputs into scored keypoint sets in the 224x224 input (weighted NMS).

    Args:
        raw_boxes: (2254, 12): x, y, w, h offsets then 4 keypoints (x, y), in input pixels.
        raw_scores: (2254,) logits.
        anchors: (2254, 2) anchor centres in [0, 1].
        min_score: score threshold after the sigmoid.

    Returns:
        (scores (D,), keypoints (D, 4, 2) in [0, 1] of the input), best first; D may be 0.
    """
    scores = 1.0 / (1.0 + np.exp(-np.clip(raw_scores, -50.0, 50.0)))
    keep = np.flatnonzero(scores >= min_score)
    if len(keep) == 0:
        return np.zeros(0), np.zeros((0, 4, 2))
    raw = raw_boxes[keep] / DET_SIZE
    centre = raw[:, :2] + anchors[keep]
    half = raw[:, 2:4] / 2
    boxes = np.concatenate([centre - half, centre + half], axis=1)
    kps = raw[:, 4:12].reshape(-1, 4, 2) + anchors[keep][:, None, :]
    order = np.argsort(-scores[keep])
    boxes, kps, sc = boxes[order], kps[order], scores[keep][order]
    out_scores, out_kps = [], []
    remaining = np.arange(len(sc))
    while len(remaining):
        iou = _iou(boxes[remaining[0]], boxes[remaining])
        group = remaining[iou > 0.3]
        w = sc[group] / sc[group].sum()
        out_scores.append(sc[group].max())
        out_kps.append((kps[group] * w[:, None, None]).sum(0))
        remaining = remaining[iou <= 0.3]
    return np.asarray(out_scores), np.asarray(out_kps)


def _iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    lo = np.maximum(box[:2], boxes[:, :2])
    hi = np.minimum(box[2:], boxes[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
    area = lambda b: np.prod(np.clip(b[..., 2:] - b[..., :2], 0, None), axis=-1)  # noqa: E731
    return inter / np.maximum(area(box) + area(boxes) - inter, 1e-12)


def roi_from_points(centre: np.ndarray, scale_point: np.ndarray) -> Roi:
    """The crop around a body: centre at ``centre``, side 2|scale_point - centre| x 1.25, upright along it."""
    d = scale_point - centre
    size = 2.0 * float(np.linalg.norm(d)) * ROI_SCALE
    # MediaPipe: rotation = 90 deg - atan2(-dy, dx) (image y points down).
    angle = math.pi / 2 - math.atan2(-d[1], d[0])
    angle = (angle + math.pi) % (2 * math.pi) - math.pi
    return Roi(center=np.asarray(centre, dtype=np.float64), size=size, angle=angle)


def roi_affine(roi: Roi, out_size: int) -> np.ndarray:
    """(2, 3) affine mapping crop pixels (out_size x out_size, centres at +0.5) to image pixels."""
    c, s = math.cos(roi.angle), math.sin(roi.angle)
    k = roi.size / out_size
    lin = np.array([[c, -s], [s, c]]) * k
    # crop pixel index i has its centre at a = (i + 0.5) / out_size; image pixel index = u - 0.5
    offset = roi.center - lin @ np.full(2, out_size / 2.0) + lin @ np.full(2, 0.5) - 0.5
    return np.concatenate([lin, offset[:, None]], axis=1)


def crop(frame: np.ndarray, roi: Roi, out_size: int) -> np.ndarray:
    """(out_size, out_size, 3) uint8 rotated crop (zero border) of the image."""
    import cv2

    aff = roi_affine(roi, out_size)
    return cv2.warpAffine(frame, aff, (out_size, out_size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))


def crop_to_image(points: np.ndarray, roi: Roi, out_size: int) -> np.ndarray:
    """(N, 2) crop coordinates (continuous, [0, out_size]) -> image coordinates [px]."""
    c, s = math.cos(roi.angle), math.sin(roi.angle)
    rel = (points / out_size - 0.5) * roi.size
    return roi.center + rel @ np.array([[c, -s], [s, c]]).T


def detect(detector: TFLiteModel, frame: np.ndarray, anchors: np.ndarray) -> Roi | None:
    """Run the detector on one frame; the region of interest of the best person, or None."""
    img, scale, pad = letterbox(frame, DET_SIZE)
    out = detector.run(img[None].astype(np.float32) / 127.5 - 1.0)
    boxes, scores = _detector_outputs(out)
    sc, kps = decode_detections(boxes, scores, anchors)
    if len(sc) == 0:
        return None
    kp = (kps[0] * DET_SIZE - pad) * scale  # (4, 2) image pixels
    return roi_from_points(kp[0], kp[1])


def _detector_outputs(out: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    arrays = sorted(out.values(), key=lambda a: -a.shape[-1])
    return arrays[0][0], arrays[1][0, :, 0]


@dataclass(frozen=True)
class FramePose:
    """BlazePose on one frame (see :class:`PoseTrack` for units); ``aux`` are landmarks 33-38 [px]."""

    uv: np.ndarray
    z: np.ndarray
    world: np.ndarray
    visibility: np.ndarray
    presence: float
    mask: np.ndarray
    aux: np.ndarray


def _mirror_permutation() -> np.ndarray:
    """(39,) index of each model landmark's left/right twin (itself on the midline and for 33-38)."""
    perm = np.arange(NUM_LANDMARKS + 6)
    for i, name in enumerate(LANDMARK_NAMES):
        for a, b in (("l_", "r_"), ("r_", "l_"), ("_l", "_r"), ("_r", "_l")):
            twin = name.replace(a, b, 1) if (name.startswith(a) or name.endswith(a)) else None
            if twin is not None and twin != name and twin in LANDMARK_NAMES:
                perm[i] = LANDMARK_NAMES.index(twin)
                break
    return perm


MIRROR = _mirror_permutation()


@dataclass(frozen=True)
class CropOutput:
    """The landmark model's raw outputs on one crop, in the crop's own frame.

    Attributes:
        raw: (39, 5) x, y [crop px in [0, 256]], z [crop px], visibility and presence logits.
        world: (39, 3) metric landmarks in the crop's axes [m].
        seg: (256, 256) person probability in [0, 1].
        presence: pose-presence score in [0, 1].
    """

    raw: np.ndarray
    world: np.ndarray
    seg: np.ndarray
    presence: float


def run_crop(model: TFLiteModel, img: np.ndarray, *, flip: bool = False) -> CropOutput:
    """The landmark model on one 256x256 crop; ``flip`` runs it on the mirrored crop and mirrors back.

    A mirrored person is a person whose left is the original's right, so the mirrored outputs are
    flipped in x and their left/right landmarks exchanged (the flip test of pose estimation).
    """
    x = img[:, ::-1] if flip else img
    out = model.run(np.ascontiguousarray(x)[None].astype(np.float32) / 255.0)
    by_size = {a.size: a for a in out.values()}
    raw = by_size[39 * 5].reshape(39, 5).astype(np.float64)
    world = by_size[39 * 3].reshape(39, 3).astype(np.float64)
    seg = by_size[LMK_SIZE * LMK_SIZE].reshape(LMK_SIZE, LMK_SIZE).astype(np.float64)
    seg = 1.0 / (1.0 + np.exp(-np.clip(seg, -50.0, 50.0)))
    presence = float(by_size[1].ravel()[0])
    if presence > 1.0 or presence < 0.0:  # some exports give a logit
        presence = float(1.0 / (1.0 + np.exp(-presence)))
    if flip:
        raw, world, seg = raw[MIRROR].copy(), world[MIRROR].copy(), seg[:, ::-1]
        raw[:, 0] = LMK_SIZE - raw[:, 0]
        world[:, 0] = -world[:, 0]
    return CropOutput(raw=raw, world=world, seg=seg, presence=presence)


LIMB_LANDMARKS = np.array([13, 14, 15, 16, 25, 26, 27, 28])  # elbows, wrists, knees, ankles


def labels_agree(a: np.ndarray, b: np.ndarray) -> bool:
    """Two passes' (33, 2) landmarks name the limbs alike: b's limbs lie nearer a's than with left and right exchanged.

    On some frames one pass calls the left limbs right; their average would put both arms (or legs) on
    the midline, so such a pass is left out.
    """
    same = np.linalg.norm(a[LIMB_LANDMARKS] - b[LIMB_LANDMARKS], axis=-1).mean()
    crossed = np.linalg.norm(a[LIMB_LANDMARKS] - b[MIRROR[LIMB_LANDMARKS]], axis=-1).mean()
    return bool(same <= crossed)


def image_pose(out: CropOutput, roi: Roi, shape: tuple[int, int]) -> FramePose:
    """The landmark model's outputs on the crop ``roi`` mapped back to the image (mask as a probability)."""
    import cv2

    # The model's crop coordinates are continuous in [0, 256]; move to the image.
    uv_all = crop_to_image(out.raw[:, :2], roi, LMK_SIZE)
    z = out.raw[:NUM_LANDMARKS, 2] * roi.size / LMK_SIZE
    vis = 1.0 / (1.0 + np.exp(-out.raw[:NUM_LANDMARKS, 3]))
    c, s = math.cos(roi.angle), math.sin(roi.angle)
    world = out.world[:NUM_LANDMARKS].copy()
    world[:, :2] = world[:, :2] @ np.array([[c, -s], [s, c]]).T
    h, w = shape
    # roi_affine maps crop -> image, which is warpAffine's forward direction here
    prob = cv2.warpAffine(out.seg.astype(np.float32), roi_affine(roi, LMK_SIZE), (w, h), flags=cv2.INTER_LINEAR,
                          borderValue=0.0)
    return FramePose(uv=uv_all[:NUM_LANDMARKS], z=z, world=world, visibility=vis, presence=out.presence, mask=prob,
                     aux=uv_all[NUM_LANDMARKS:])


def mean_pose(poses: list[FramePose]) -> FramePose:
    """The average of several passes in the image; the mask is the mean probability > 0.5."""
    mean = lambda k: np.mean([getattr(p, k) for p in poses], axis=0)  # noqa: E731
    return FramePose(uv=mean("uv"), z=mean("z"), world=mean("world"), visibility=mean("visibility"),
                     presence=float(mean("presence")), mask=mean("mask") > 0.5, aux=mean("aux"))


def landmarks_in_roi(model: TFLiteModel, frame: np.ndarray, roi: Roi, *, flip_test: bool = True) -> FramePose:
    """Run the landmark model on the crop ``roi`` of ``frame`` and map its outputs back to the image.

    With ``flip_test`` the model also runs on the mirrored crop, and the two passes are averaged when
    they name the limbs alike (:func:`labels_agree`); else the unflipped pass is kept alone.
    """
    img = crop(frame, roi, LMK_SIZE)
    poses = [image_pose(run_crop(model, img, flip=flip), roi, frame.shape[:2])
             for flip in ((False, True) if flip_test else (False,))]
    return mean_pose([p for p in poses if labels_agree(poses[0].uv, p.uv)])


def track_video(
    frames: np.ndarray, detector: TFLiteModel, landmark_model: TFLiteModel, *, source: str, min_presence: float = 0.5, flip_test: bool = True,
    with_flow: bool = True,
) -> PoseTrack:
    """BlazePose over a clip: detect, then track the region of interest from the previous landmarks.

    Args:
        frames: (T, H, W, 3) uint8 RGB.
        detector: the detector model (:class:`~sync4d.recon.pose.models.TFLiteModel`).
        landmark_model: the landmark model.
        source: the video's name, for the error message.
        min_presence: below this pose-presence score the track is lost and the detector runs again.
        flip_test: average each crop's landmarks with those of its mirror image (:func:`run_crop`).
        with_flow: measure the optical flow at the landmarks (:func:`landmark_flow`).

    Raises:
        InputError: nobody is found in any frame (names the video).
    """
    anchors = ssd_anchors()
    n, h, w = frames.shape[:3]
    poses: list[FramePose | None] = []
    roi: Roi | None = None
    for t in range(n):
        pose = None
        for attempt in range(2):
            if roi is None:
                roi = detect(detector, frames[t], anchors)
                if roi is None:
                    break
            pose = landmarks_in_roi(landmark_model, frames[t], roi, flip_test=flip_test)
            if pose.presence >= min_presence:
                break
            pose, roi = None, None  # lost: detect again in this frame
        poses.append(pose)
        roi = None if pose is None else roi_from_points(pose.aux[0], pose.aux[1])
    found = np.array([p is not None for p in poses])
    if not found.any():
        raise InputError(f"{source}: no person found in any of its {n} frames; use a video showing one person")
    log.info("pose: a person in %d of %d frames of %s", int(found.sum()), n, source)
    idx = np.flatnonzero(found)
    nearest = idx[np.abs(np.arange(n)[:, None] - idx[None]).argmin(1)]
    pick = [poses[i] for i in nearest]
    masks = np.stack([p.mask if found[t] else np.zeros((h, w), bool) for t, p in enumerate(pick)])
    return PoseTrack(
        landmarks_2d=np.stack([p.uv for p in pick]), landmarks_z=np.stack([p.z for p in pick]),
        world=np.stack([p.world for p in pick]), visibility=np.stack([p.visibility for p in pick]),
        presence=np.array([p.presence for p in pick]), masks=masks, found=found,
        flow=landmark_flow(frames, np.stack([p.uv for p in pick]), masks) if with_flow else None,
    )


def landmark_flow(frames: np.ndarray, uv: np.ndarray, masks: np.ndarray, *, fb_tol_px: float = 1.0,
                  max_side: int = FLOW_MAX_SIDE) -> np.ndarray:
    """(T-1, L, 2) DIS optical flow at each landmark's pixel to the next frame [px]; NaN where unreliable.

    Unreliable: the landmark lies off the person's mask in frame t or its flow's end off the mask in
    frame t+1 (a landmark beside the body would read the background's flow), or the flow does not come
    back within ``fb_tol_px`` (occluded). Frames larger than ``max_side`` pixels are shrunk for the flow
    (its cost grows with the pixel count; the displacements are scaled back).
    """
    import cv2

    from sync4d.recon.video.images import optical_flow, sample_image

    out = np.full((max(len(frames) - 1, 0),) + uv.shape[1:], np.nan)
    if len(frames) < 2:
        return out
    h, w = frames.shape[1:3]
    k = min(1.0, max_side / max(h, w))
    small = frames if k == 1.0 else np.stack(
        [cv2.resize(f, (round(w * k), round(h * k)), interpolation=cv2.INTER_AREA) for f in frames])
    fwd, bwd = optical_flow(small)
    for t in range(len(frames) - 1):
        d = sample_image(fwd[t], uv[t] * k - 0.5) / k  # pixel centres at +0.5, array indices at 0
        back = sample_image(bwd[t], (uv[t] + d) * k - 0.5) / k
        on = sample_image(masks[t].astype(np.float32)[..., None], uv[t] - 0.5)[:, 0] > 0.5
        lands = sample_image(masks[t + 1].astype(np.float32)[..., None], uv[t] + d - 0.5)[:, 0] > 0.5
        ok = (np.linalg.norm(d + back, axis=-1) < fb_tol_px) & on & lands
        out[t, ok] = d[ok]
    return out
