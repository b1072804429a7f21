"""What moves against the background: dense flow with the camera's own motion explained away.

For a frame pair the background's motion is fitted robustly to a grid of dense-flow samples (a homography,
:func:`background_residual`); what it cannot explain, in pixels and in units of the background's own
robust spread, is the evidence that a pixel moves by itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: dense-flow samples per frame pair used to fit the background's motion
GRID_SAMPLES = 1500
#: background planes (homographies) fitted per frame pair at most ...
MAX_PLANES = 4
#: ... each after the first explaining at least this share of the image ...
MIN_PLANE_SHARE = 0.08
#: ... with at least this share of its samples on the image's border
BORDER_SHARE = 0.1
#: a pixel the background's motion explains changes by less than this many grey levels (of 255) ...
PHOTOMETRIC_LEVELS = 10.0
#: ... and so do its neighbours within 2 px (a textured subject's plain patches count as changed)
NEAR = np.ones((5, 5), np.uint8)
#: a textured pixel whose flow the background's motion explains within this [px] is still
STILL_PX = 0.5
#: a pixel is textured when its 5x5 neighbourhood's grey levels spread by more than this (std)
TEXTURE_LEVELS = 6.0
#: the picture's consistency is tested against the frames this many frames before and after ...
PICTURE_OFFSETS = (2, 4)
#: ... a pixel whose picture (and its neighbours' within 1 px) one of the background's planes brings from at
#: least this many of them within ``PICTURE_LEVELS`` (RGB distance, of 255) is background, whatever its flow
PICTURE_MATCHES = 2
PICTURE_LEVELS = 10.0


def dense_flow(grey_a: np.ndarray, grey_b: np.ndarray) -> np.ndarray:
    """(H, W, 2) optical flow [px] from ``grey_a`` to ``grey_b`` (OpenCV DIS, medium preset)."""
    import cv2

    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)  # type: ignore[attr-defined]
    return dis.calc(grey_a, grey_b, None)


def grid_points(height: int, width: int, count: int) -> np.ndarray:
    """(N, 2) integer pixel positions (u, v) on a regular grid of about ``count`` points."""
    step = max(1, int(np.sqrt(height * width / count)))
    vv, uu = np.mgrid[step // 2: height: step, step // 2: width: step]
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def plane_predictions(here: np.ndarray, there: np.ndarray, index: np.ndarray,
                      border: np.ndarray) -> tuple[list[np.ndarray], list[float]]:
    """Where up to ``MAX_PLANES`` background planes send every pixel (each (N, 2) [px]): homographies
    fitted in turn (RANSAC) to the grid samples ``index`` of the correspondences here -> there (N, 2), each
    on what the previous ones left, kept while it explains at least ``MIN_PLANE_SHARE`` of all samples and
    reaches the image border (``border``: (len(index),) bool samples on the grid's outer ring) with at
    least ``BORDER_SHARE`` of its samples: a floor or a wall runs out of the picture, a subject rarely
    does; and each one's robust spread [px]."""
    import cv2

    predictions: list[np.ndarray] = []
    spreads: list[float] = []
    left = np.arange(len(index))
    for _ in range(MAX_PLANES):
        if len(left) < 8:
            break
        H, inliers = cv2.findHomography(here[index[left]], there[index[left]], cv2.RANSAC, 1.0)
        if H is None:
            break
        fits = inliers.ravel() > 0
        if predictions and (fits.sum() < MIN_PLANE_SHARE * len(index) or border[left[fits]].mean() < BORDER_SHARE):
            break
        predicted = cv2.perspectiveTransform(here.reshape(-1, 1, 2), H).reshape(-1, 2)
        fit = np.linalg.norm(predicted - there, axis=1)[index[left[fits]]]
        predictions.append(predicted)
        spreads.append(max(1.4826 * float(np.median(fit)) if len(fit) else 0.25, 0.1))
        left = left[~fits]
    return predictions, spreads


def pixel_grid(height: int, width: int) -> np.ndarray:
    """(H * W, 2) every pixel's position (u, v) [px], row by row."""
    uu, vv = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([uu, vv], axis=-1).reshape(-1, 2)


def background_planes(flow: np.ndarray, *, static: bool) -> tuple[list[np.ndarray], list[float]]:
    """Where the background's planes send every pixel of a (H, W, 2) ``flow`` [px] (each (H * W, 2) [px];
    :func:`plane_predictions`), and each plane's robust spread [px]; a static camera's one plane stays put."""
    h, w = flow.shape[:2]
    here = pixel_grid(h, w)
    if static:
        return [here], [0.25]
    grid = grid_points(h, w, GRID_SAMPLES)
    ring = (grid[:, 0] == grid[:, 0].min()) | (grid[:, 0] == grid[:, 0].max()) \
        | (grid[:, 1] == grid[:, 1].min()) | (grid[:, 1] == grid[:, 1].max())
    predictions, spreads = plane_predictions(here, here + flow.reshape(-1, 2), grid[:, 1] * w + grid[:, 0], ring)
    if not predictions:
        return [here], [max(float(np.median(np.linalg.norm(flow, axis=-1))), 0.25)]
    return predictions, spreads


def background_residual(flow: np.ndarray, *, static: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the background's motion cannot explain in a flow field: the residual in units of the
    background's robust spread (H, W), in pixels (H, W), and where the background's motion sends each
    pixel (H, W, 2) [px].

    The background is a few planes (floor, walls, a far backdrop), each moving by a homography under any
    camera motion: homographies are fitted in turn by RANSAC to a grid of flow samples while each explains
    a large share of the image (:func:`plane_predictions`), and a pixel's residual is the smallest over them.
    A fundamental matrix would absorb all parallax, but also a subject moving along the epipolar lines, the
    common case of a phone panning to follow a walking animal (``cat-pikachu-0``: the cat vanishes).

    Args:
        flow: (H, W, 2) flow [px] from this frame to another.
        static: the camera does not move (the background's motion is zero; spread 0.25 px assumed).
    """
    h, w = flow.shape[:2]
    there = pixel_grid(h, w) + flow.reshape(-1, 2)
    predictions, spreads = background_planes(flow, static=static)
    stacked = np.stack([np.linalg.norm(p - there, axis=1) for p in predictions])
    best = np.argmin(stacked, axis=0)
    residual = stacked[best, np.arange(stacked.shape[1])]
    score = residual / np.asarray(spreads)[best]
    target = np.stack(predictions)[best, np.arange(len(best))]
    return score.reshape(h, w), residual.reshape(h, w), target.reshape(h, w, 2).astype(np.float32)


def photometric_change(grey_t: np.ndarray, grey_s: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(H, W) grey-level difference between frame t and frame s sampled where the background's motion sends
    each pixel (H, W, 2): near zero wherever the background's motion explains the picture, textureless
    regions included (whose flow is unreliable)."""
    import cv2

    a = cv2.GaussianBlur(grey_t.astype(np.float32), (3, 3), 0)
    b = cv2.GaussianBlur(grey_s.astype(np.float32), (3, 3), 0)
    warped = cv2.remap(b, target[..., 0], target[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.abs(a - warped)


def picture_matches(frame_t: np.ndarray, frame_s: np.ndarray, grey_t: np.ndarray, grey_s: np.ndarray, *,
                    static: bool) -> np.ndarray:
    """(H, W) bool: pixels of frame t (blurred RGB, float) whose picture one of the background's planes
    (fitted to the dense flow t -> s, :func:`background_planes`) brings from frame s within
    ``PICTURE_LEVELS``, their neighbours within 1 px too; where a plane maps outside frame s, no match."""
    import cv2

    h, w = grey_t.shape
    flow = np.zeros((h, w, 2), np.float32) if static else dense_flow(grey_t, grey_s)
    out = np.zeros((h, w), bool)
    for target in background_planes(flow, static=static)[0]:
        source = target.reshape(h, w, 2).astype(np.float32)
        warped = cv2.remap(frame_s, source[..., 0], source[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=(-1e3, -1e3, -1e3))
        differs = np.linalg.norm(frame_t - warped, axis=-1) > PICTURE_LEVELS
        out |= cv2.dilate(differs.astype(np.uint8), np.ones((3, 3), np.uint8)) == 0
    return out


def picture_explained(frames: np.ndarray, grey: np.ndarray, *, static: bool) -> np.ndarray:
    """(T, H, W) bool: pixels whose picture the background's planes bring from at least ``PICTURE_MATCHES`` of
    the frames ``PICTURE_OFFSETS`` before and after (:func:`picture_matches`).

    A moving subject's flow drags the floor beside it along (DIS smooths across its outline), so the flow
    alone cannot call that floor background; its picture can: under the floor's homography it is the same a
    few frames away, where a moving subject's is not (it has moved, or the camera's parallax has moved it).
    """
    import cv2

    blurred = np.stack([cv2.GaussianBlur(f.astype(np.float32), (3, 3), 0) for f in frames])
    counts = np.zeros(grey.shape, np.int32)
    for t in range(len(frames)):
        for s in (t + d * o for o in PICTURE_OFFSETS for d in (-1, 1)):
            if 0 <= s < len(frames):
                counts[t] += picture_matches(blurred[t], blurred[s], grey[t], grey[s], static=static)
    return counts >= PICTURE_MATCHES


@dataclass(frozen=True)
class MotionEvidence:
    """What moves in a clip.

    Attributes:
        moving: (T, H, W) bool, moving against the background (see :func:`motion_evidence`).
        still: (T, H, W) bool, textured pixels the background's motion explains in every neighbouring pair
            (flow within ``STILL_PX`` and picture within ``PHOTOMETRIC_LEVELS``): surely background unless a
            known subject part holds still there.
        flows: ``{(t, s): (H, W, 2) flow from t to s [px]}`` for |t - s| = 1.
        explained: (T, H, W) bool, pixels (textured or not) the background's motion explains in every
            neighbouring pair, as ``still`` without asking for texture (a plain floor tile included); the
            front end adds those whose picture it explains a few frames away (:func:`picture_explained`).
    """

    moving: np.ndarray
    still: np.ndarray
    flows: dict[tuple[int, int], np.ndarray]
    explained: np.ndarray | None = None


def textured(grey: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose 5x5 neighbourhood varies by more than ``TEXTURE_LEVELS`` grey levels (std)."""
    import cv2

    g = grey.astype(np.float32)
    mean = cv2.blur(g, (5, 5))
    return np.sqrt(np.maximum(cv2.blur(g * g, (5, 5)) - mean * mean, 0.0)) > TEXTURE_LEVELS


def motion_evidence(grey: np.ndarray, *, static: bool, sigma: float, min_px: float) -> MotionEvidence:
    """Pixels of each frame moving against the background, and those surely explained by it.

    A pixel moves when the flows to the previous and to the next frame both leave more than ``sigma``
    robust spreads and ``min_px`` pixels unexplained by the background's motion, and the picture there
    (within 2 px) is not explained by it either (:func:`photometric_change`): a pixel the subject covers or
    uncovers has a wrong flow in one direction only, so asking both keeps the subject and drops that halo
    (the clip's first and last frames get no evidence).
    """
    import cv2

    n_frames, h, w = grey.shape
    moving = np.zeros((n_frames, h, w), bool)
    still = np.zeros((n_frames, h, w), bool)
    explained = np.zeros((n_frames, h, w), bool)
    flows: dict[tuple[int, int], np.ndarray] = {}
    for t in range(n_frames):
        both = np.ones((h, w), bool)
        calm = np.ones((h, w), bool)
        for s in (t - 1, t + 1):
            if not 0 <= s < n_frames:
                continue
            flows[(t, s)] = dense_flow(grey[t], grey[s])
            score, pixels, target = background_residual(flows[(t, s)], static=static)
            change = photometric_change(grey[t], grey[s], target)
            changed = cv2.dilate((change > PHOTOMETRIC_LEVELS).astype(np.uint8), NEAR) > 0
            both &= (score > sigma) & (pixels > min_px) & changed
            calm &= (pixels < STILL_PX) & (change < PHOTOMETRIC_LEVELS)
        moving[t] = both if 0 < t < n_frames - 1 else False
        still[t] = calm & textured(grey[t])
        explained[t] = calm
    return MotionEvidence(moving, still, flows, explained)
