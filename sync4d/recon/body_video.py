"""``recon=body_video``: an articulated reference (bones, capsule body, skinning, motion) from a video of a
person (``subject: human``) or a four-legged animal (``subject: quadruped``).

* human: BlazePose (MediaPipe's legacy models under LiteRT, :mod:`sync4d.recon.pose.blazepose`) gives 2D
  landmarks, metric 3D world landmarks and a person mask per frame; a 17-joint skeleton is fitted to
  them over the clip (:mod:`sync4d.recon.pose.human_fit`: reprojection, world pose, shared bone lengths,
  joint limits, smoothness), seen by the clip's per-frame camera when it moves (``VideoClip.extrinsics``,
  e.g. the video front end's: its rotations, with its path re-measured in metres from the ground beside
  the feet, :func:`ground_camera`).
* quadruped: a skinned body template (the glTF fox by default, :mod:`sync4d.recon.pose.templates`) fitted to
  the masks (input, or a static-camera background model) by its soft mesh silhouette with bone length and
  girth priors, seen by the clip's per-frame camera when it moves (``VideoClip.extrinsics``); several
  heading and leg-swap hypotheses chosen by the video's optical flow (:mod:`sync4d.recon.pose.quadruped_fit`).

The fitted joints then go through ``recon=mocap``'s builder (:meth:`MocapReconstructor.from_motion`):
segments merged to ``bones`` bones, a capsule body, distance skinning, rigid per-bone motion.

The camera: the video's own intrinsics if known, else a pinhole with ``fov_deg`` across the longer image
side; the world frame is the camera's turned to y-up (x right, y up, z towards the camera) unless the
reference gives a camera pose. Pictures of the fit over the frames (``recon/body_fit.png`` and ``.mp4``)
go into the run folder when the stage runs (not when its cache is reused), drawn by :meth:`write_figures`
after the pipeline has cached the reconstruction.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from sync4d.errors import ConfigError, InputError
from sync4d.io.mocap import SkeletonMotion
from sync4d.recon.mocap import MocapReconstructor
from sync4d.recon.pose.human_fit import HumanFitConfig, fit_human
from sync4d.recon.pose.quadruped_fit import QuadrupedFitConfig, fit_quadruped
from sync4d.registry import register
from sync4d.types import Camera, Reference, ReferenceInput, VideoClip

log = logging.getLogger(__name__)

DEFAULT_BONES = {"human": 11, "quadruped": 13}
FEET = ("l_ankle", "r_ankle", "l_toe", "r_toe")
# camera (OpenCV: x right, y down, z forward) -> a y-up world when the camera pose is unknown
CAM_TO_YUP = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class BodyVideoFit:
    """A skeleton fitted to a video.

    Attributes:
        joints: (T, J, 3) joint positions in the (first frame's) camera frame (OpenCV axes) [m].
        names: (J,) joint names.
        parents: (J,) parent per joint, -1 for the root.
        camera: the camera used (given, or from the assumed field of view; world_to_cam = identity when
            the pose is unknown).
        masks: (T, H, W) bool subject masks used or produced by the fit.
        landmarks_2d: (T, L, 2) detected image landmarks [px] (humans), or None.
        seconds: wall time of detection and fit [s].
        silhouettes: (T, H, W) bool the fitted body seen by each frame's camera (quadrupeds), or None.
        extrinsics: (T, 4, 4) world-to-camera per frame when the camera moves, else None (humans: the
            clip's rotations with translations in metres from :func:`ground_camera`).
    """

    joints: np.ndarray
    names: tuple[str, ...]
    parents: np.ndarray
    camera: Camera
    masks: np.ndarray
    landmarks_2d: np.ndarray | None
    seconds: float
    silhouettes: np.ndarray | None = None
    extrinsics: np.ndarray | None = None


def assumed_camera(width: int, height: int, fov_deg: float) -> Camera:
    """A pinhole with ``fov_deg`` across the longer side, principal point at the centre, identity pose."""
    f = 0.5 * max(width, height) / math.tan(math.radians(fov_deg) / 2)
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return Camera(K=K, world_to_cam=np.eye(4), width=width, height=height).validate()


def clip_camera(clip: VideoClip, camera: Camera | None, fov_deg: float) -> Camera:
    """The given camera, else one with the clip's intrinsics, else :func:`assumed_camera`."""
    if camera is not None:
        return camera
    h, w = clip.frames.shape[1:3]
    if clip.intrinsics is not None:
        return Camera(K=clip.intrinsics, world_to_cam=np.eye(4), width=w, height=h).validate()
    return assumed_camera(w, h, fov_deg)


@register("recon", "body_video")
class BodyVideoReconstructor:
    """A person or a quadruped from a monocular video (``reference=video``)."""

    @dataclass
    class Config:
        """``recon=body_video`` options.

        Attributes:
            subject: ``human`` (learned pose model) or ``quadruped`` (template skeleton on masks).
            bones: B; 0 = the subject's default (11 human, 13 quadruped), as in the paper.
            fov_deg: field of view across the longer image side when the video has no intrinsics [deg].
            model_dir: folder of the pose models; empty = ``$SYNC4D_MODEL_DIR`` or ``<project>/models/mediapipe``.
            figures: write pictures of the fit over the frames into the run folder.
            human: the human body fit's weights.
            quadruped: the quadruped fit's weights and starts.
        """

        subject: Literal["human", "quadruped"] = "human"
        bones: int = 0
        fov_deg: float = 60.0
        model_dir: str = ""
        figures: bool = True
        human: HumanFitConfig = field(default_factory=HumanFitConfig)
        quadruped: QuadrupedFitConfig = field(default_factory=QuadrupedFitConfig)

        def validate(self) -> None:
            if self.bones < 0:
                raise ConfigError(f"recon.bones={self.bones}: use 0 (the subject's default) or a positive B")
            if not 1.0 < self.fov_deg < 170.0:
                raise ConfigError(f"recon.fov_deg={self.fov_deg}: the field of view must be in (1, 170) degrees")

    def __init__(self, config: Config, *, device: str = "cpu") -> None:
        config.validate()
        self.config = config
        self.device = device
        self.pictures: FitPictures | None = None

    def fit(self, source: ReferenceInput) -> BodyVideoFit:
        """Detect and fit the subject in ``source.video`` (camera frame)."""
        if source.video is None:
            raise InputError(
                f"recon=body_video needs a video, but reference '{source.name}' has none; "
                "use reference=video reference.video=<file>"
            )
        clip = source.video
        camera = clip_camera(clip, source.camera, self.config.fov_deg)
        started = time.perf_counter()
        if self.config.subject == "human":
            from sync4d.recon.pose.blazepose import track_video
            from sync4d.recon.pose.models import load_models

            detector, landmarks = load_models(self.config.model_dir)
            track = track_video(clip.frames, detector, landmarks, source=clip.source or source.name)
            fps = float(source.fps or clip.fps)
            fit = fit_human(track, camera.K, self.config.human, fps=fps)
            if moving_camera(clip.extrinsics):
                # a moving camera (given, or the front end's, whose translations are in units of the background's
                # depth or missing when it found turns only): its turns are kept, its path is re-measured in
                # metres from the ground at the feet, and its pan and shake are then not the body's motion
                assert clip.extrinsics is not None
                feet = fit.joints[:, [fit.names.index(n) for n in FEET]]
                up = np.array([0.0, 1.0, 0.0]) if source.world_up is None else source.world_up
                metric = ground_camera(clip.frames, track.masks, camera.K, clip.extrinsics[:, :3, :3], feet, up)
                if metric is None:
                    log.warning("body_video: too little ground beside the feet to measure the moving camera's path; "
                                "the body is fitted as if the camera stood still")
                else:
                    fit = fit_human(track, camera.K, self.config.human, fps=fps, extrinsics=metric)
            return BodyVideoFit(
                fit.joints,
                fit.names,
                fit.parents,
                camera,
                track.masks,
                track.landmarks_2d,
                time.perf_counter() - started,
                extrinsics=fit.extrinsics,
            )
        masks = clip.masks
        if not masks.any():
            from sync4d.recon.video import background_masks

            masks = background_masks(clip.frames, threshold=self.config.quadruped.background_threshold)
        qfit = fit_quadruped(
            masks,
            camera,
            self.config.quadruped,
            source=clip.source or source.name,
            world_up=source.world_up,
            frames=clip.frames,
            fps=float(source.fps or clip.fps),
            extrinsics=clip.extrinsics,
        )
        return BodyVideoFit(qfit.joints, qfit.names, qfit.parents, camera, masks, None,
                            time.perf_counter() - started, qfit.silhouettes, clip.extrinsics)

    def reconstruct(self, source: ReferenceInput) -> Reference:
        """The validated :class:`Reference` of the subject in ``source.video``."""
        fit = self.fit(source)
        video = source.video
        assert video is not None  # fit() refused a source without one
        cam_to_world = np.linalg.inv(fit.camera.world_to_cam if fit.extrinsics is None else fit.extrinsics[0])
        if source.camera is None and fit.extrinsics is None:
            cam_to_world = CAM_TO_YUP
        homo = np.concatenate([fit.joints, np.ones(fit.joints.shape[:2] + (1,))], axis=-1)
        world = (homo @ cam_to_world.T)[..., :3]
        up = 1
        if source.world_up is not None:
            up = int(np.argmax(np.abs(source.world_up)))
        motion = SkeletonMotion(
            fit.names,
            fit.parents,
            world,
            None,
            float(source.fps or video.fps),
            up_axis=up,
            source=video.source,
        )
        bones = self.config.bones or DEFAULT_BONES[self.config.subject]
        mocap = MocapReconstructor(MocapReconstructor.Config(bones=bones), device=self.device)
        reference = mocap.from_motion(motion, name=source.name)
        log.info(
            "body_video %s: %d joints, %d bones, %d frames in %.1f s",
            self.config.subject,
            len(fit.names),
            reference.num_bones,
            reference.num_frames,
            fit.seconds,
        )
        self.pictures = FitPictures(video, fit, reference, np.linalg.inv(cam_to_world))
        return reference

    def write_figures(self, folder: Path) -> list[Path]:
        """Pictures of the last fit over its frames into ``folder`` (``body_fit.png``, ``.mp4``); the pipeline
        calls this after the reconstruction is cached, so a failed picture never costs the fit."""
        if not self.config.figures or self.pictures is None:
            return []
        pic = self.pictures
        paths = write_fit_pictures(folder, pic.clip, pic.fit, pic.reference, pic.world_to_cam)
        log.info("body_video: pictures of the fit in %s", ", ".join(str(p) for p in paths))
        return paths


def moving_camera(extrinsics: np.ndarray | None) -> bool:
    """Whether (T, 4, 4) world-to-camera poses move at all (a static camera's are one pose repeated)."""
    return extrinsics is not None and bool(np.ptp(extrinsics[:, :3], axis=0).max() > 1e-9)


def ground_tracks(grey: list[np.ndarray], masks: np.ndarray, K: np.ndarray, feet: np.ndarray, normal: np.ndarray,
                  t: int, r: int, *, above: float = 0.04) -> tuple[np.ndarray, np.ndarray] | None:
    """Corners of the ground around the feet in frame ``t``, placed in 3D and tracked to frame ``r``:
    ((N, 3) points in camera t [m], (N, 2) their pixels in frame r), or None.

    The lowest foot point in the image (ankles and toes, ``feet`` (T, F, 3) in each frame's camera [m])
    stands on the ground, the plane through it with the ``normal`` (3,) (the world's up in camera t). Corners
    from ``above`` x the image height over its row down to the image's bottom, off the person, are on that
    plane (the floor in front of and beside the person; walls start behind it), placed on it, and tracked
    (forward-backward checked).
    """
    import cv2

    height, width = grey[t].shape
    z = feet[t, :, 2]
    if not (z > 1e-3).all():
        return None
    uv = feet[t, :, :2] / z[:, None] * K[[0, 1], [0, 1]] + K[:2, 2]
    low = int(np.argmax(uv[:, 1]))
    v = uv[low, 1]
    if not 0 <= v < height:
        return None
    region = np.zeros((height, width), np.uint8)
    region[max(0, int(v - above * height)):] = 255
    region[cv2.dilate(masks[t].astype(np.uint8), np.ones((9, 9), np.uint8)) > 0] = 0
    corners = cv2.goodFeaturesToTrack(grey[t], 120, 0.01, 4, mask=region)
    if corners is None:
        return None
    ahead, ok1, _ = cv2.calcOpticalFlowPyrLK(grey[t], grey[r], corners, None, winSize=(15, 15), maxLevel=3)
    back, ok2, _ = cv2.calcOpticalFlowPyrLK(grey[r], grey[t], ahead, None, winSize=(15, 15), maxLevel=3)
    good = (ok1[:, 0] == 1) & (ok2[:, 0] == 1) & (np.linalg.norm((back - corners)[:, 0], axis=1) < 1.0)
    rays = np.concatenate([corners[:, 0], np.ones((len(corners), 1))], 1) @ np.linalg.inv(K).T
    along = rays @ normal
    depth = (feet[t, low] @ normal) / np.where(np.abs(along) > 1e-9, along, np.nan)
    good &= np.isfinite(depth) & (depth > 0) & (depth < 20 * z[low])
    if good.sum() < 3:
        return None
    return rays[good] * depth[good, None], ahead[good, 0].astype(np.float64)


def ground_camera(frames: np.ndarray, masks: np.ndarray, K: np.ndarray, rotations: np.ndarray, feet: np.ndarray,
                  up: np.ndarray, *, gaps: tuple[int, ...] = (2, 4), smooth: float = 10.0, huber: float = 2.0) -> np.ndarray | None:
    """(T, 4, 4) world-to-camera with the given rotations and metric translations from the ground at the feet
    (the first camera's centre at the world's origin), or None with too little ground.

    The ground around the feet (:func:`ground_tracks`: the plane through the lowest foot, normal to the
    world's ``up``) gives known points of camera t [m]; where it is seen in frame r (``gaps`` frames on) places camera r's centre C_r
    relative to C_t: ``[q]x R_r (C_t - C_r) = -[q]x R_r R_t^T X`` for the ray q of the tracked pixel. All pairs
    are solved at once by least squares (IRLS, Huber at ``huber`` px), with a weak second-difference prior
    (``smooth``, [1/m] per frame at the focal's unit) bridging frames without ground.

    Args:
        frames: (T, H, W, 3) uint8 RGB.
        masks: (T, H, W) bool person masks.
        K: (3, 3) intrinsics [px].
        rotations: (T, 3, 3) world-to-camera rotations.
        feet: (T, F, 3) ankle and toe positions in each frame's camera [m] (a fit with the camera still).
        up: (3,) the world's up (the ground's normal; its sign does not matter).
    """
    import cv2

    count = len(frames)
    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]
    k_inv = np.linalg.inv(K)
    rows, rhs, pairs = [], [], []
    for t in range(count):
        for gap in gaps:
            r = t + gap
            tracks = ground_tracks(grey, masks, K, feet, rotations[t] @ up, t, r) if r < count else None
            if tracks is None:
                continue
            x_t, b = tracks  # (N, 3) in camera t [m], (N, 2) pixels in r
            q = np.concatenate([b, np.ones((len(b), 1))], 1) @ k_inv.T  # (N, 3) rays in camera r
            cross = np.zeros((len(q), 3, 3))
            cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -q[:, 2], q[:, 1], -q[:, 0]
            cross = cross - np.swapaxes(cross, 1, 2)
            coef = cross @ rotations[r]  # (N, 3, 3) acting on C_t - C_r
            rhs.append(-(cross @ (rotations[r] @ rotations[t].T @ x_t.T).T[..., None])[..., 0].reshape(-1))
            rows.append(coef.reshape(-1, 3))
            pairs.append(np.repeat([[t, r]], 3 * len(q), axis=0))
    if not rows or sum(len(x) for x in rows) < 3 * 20:
        return None
    coef_all, b_all, idx = np.concatenate(rows), np.concatenate(rhs), np.concatenate(pairs)
    n = 3 * count
    a_all = np.zeros((len(b_all), n))
    for k in range(3):
        a_all[np.arange(len(b_all)), 3 * idx[:, 0] + k] += coef_all[:, k]
        a_all[np.arange(len(b_all)), 3 * idx[:, 1] + k] -= coef_all[:, k]
    prior = np.zeros((3 * max(count - 2, 0) + 3, n))
    for t in range(count - 2):
        for k in range(3):
            prior[3 * t + k, [3 * t + k, 3 * (t + 1) + k, 3 * (t + 2) + k]] = np.array([1.0, -2.0, 1.0]) * smooth
    prior[-3:, :3] = np.eye(3) * 1e3  # the first camera's centre at the origin
    weight = np.ones(len(b_all))
    delta = huber / float(K[0, 0])
    for _ in range(4):
        sw = np.sqrt(weight)[:, None]
        system = np.concatenate([a_all * sw, prior])
        target = np.concatenate([b_all * sw[:, 0], np.zeros(len(prior))])
        centres = np.linalg.lstsq(system, target, rcond=None)[0]
        resid = np.abs(a_all @ centres - b_all)
        weight = np.where(resid < delta, 1.0, delta / np.maximum(resid, 1e-12))
    centres = centres.reshape(count, 3)
    out = np.tile(np.eye(4), (count, 1, 1))
    out[:, :3, :3] = rotations
    out[:, :3, 3] = -np.einsum("tij,tj->ti", rotations, centres)
    return out


@dataclass(frozen=True)
class FitPictures:
    """What the pictures of a fit are drawn from: the clip, the fit, its reference and the camera pose."""

    clip: VideoClip
    fit: BodyVideoFit
    reference: Reference
    world_to_cam: np.ndarray


def write_fit_pictures(
    folder: Path,
    clip: VideoClip,
    fit: BodyVideoFit,
    reference: Reference,
    world_to_cam: np.ndarray,
    *,
    max_points: int = 1500,
) -> list[Path]:
    """Draw the fit (mask, parts coloured by bone, skeleton, landmarks) over every frame; write png + mp4."""
    from sync4d.recon.pose.overlay import draw_fit, enlarged, write_pictures

    rng = np.random.default_rng(0)
    pick = rng.choice(len(reference.rest_vertices), min(max_points, len(reference.rest_vertices)), replace=False)
    labels = reference.part_labels()[pick]
    pictures = []
    for t in range(min(clip.num_frames, reference.num_frames)):
        w2c = world_to_cam if fit.extrinsics is None else fit.extrinsics[t]  # a moving camera: frame t's
        posed = reference.posed_vertices(t, apply_global=True)[pick]
        cam = posed @ w2c[:3, :3].T + w2c[:3, 3]
        first_to_t = w2c @ np.linalg.inv(world_to_cam)  # the fit's joints are in the first frame's camera frame
        frame, K, mask, marks = enlarged(clip.frames[t], fit.camera.K, fit.masks[t],
                                         None if fit.landmarks_2d is None else fit.landmarks_2d[t])
        pictures.append(
            draw_fit(
                frame,
                K=K,
                joints=fit.joints[t] @ first_to_t[:3, :3].T + first_to_t[:3, 3],
                parents=fit.parents,
                mask=mask,
                part_points=cam,
                part_labels=labels,
                landmarks=marks,
                names=fit.names,
            )
        )
    return write_pictures(folder, pictures, clip.fps)
