"""``recon=video``: a BANMo-style articulated fit from a monocular video on the CPU.

Model (paper Sec. 3.2): a canonical shape of N isotropic Gaussians (means in the object frame, which is
the world frame of the first video frame), B Gaussian bones with skinning
``W = softmax(-d_M(x, bones) + W_delta(x))`` and per-frame bone transforms J_{t,b} (J_0 = identity: the
canonical pose is the first frame's pose). Posed Gaussians are projected with the known static camera.

Silhouette stage (``silhouette_rounds`` > 0, B > 1; :mod:`sync4d.recon._video_silhouette`): with the
known static camera, a dense first-frame point cloud is tracked by derivative-free pattern search on the
silhouette IoU (root 6 DoF or static when its flow tracks do not move; other parts about joints at their
part boundary, turned into 1-DoF hinges when their rotations share an axis); each round re-estimates the
non-root parts' plane tilts (grid), the joint positions and tilts (whole-sequence search) and the labels
(silhouette and flow-track consistency over all frames). The stage runs from ``silhouette_restarts``
starts (other samples for the first clustering), and the start whose moving parts best predict the
motions of image corners wins: silhouettes cannot rank the basins the stage ends in, corner motions can.
Options, measured mixed and so off by default:
a sequence's score minus a frame-to-frame optical-flow term (``silhouette_flow_weight``: the texture's
motion judges what the silhouettes leave open, a hinged part's tilt against its swing), fresh tilt-grid
hypotheses with re-detected hinges after the rounds (``silhouette_hypotheses``), and relabelling that
judges each point on each part's surface (``silhouette_relabel_surface``). A static root's surface, which
its silhouette cannot place, becomes the horizontal plane through its joints when the source knows its world up, else
stays a fronto-parallel stand-in (``silhouette_root_depth``; occlusion- and contact-based planes in
:mod:`sync4d.recon._video_occlusion` are options). Its labels, depths and poses initialise the model below (one small
Gaussian per raster cell, ``silhouette_dense_gaussians``, so rendered labels do not bleed across part
boundaries), the skinning is fitted to its labels, and the gradient stages are skipped unless
``refine_after_silhouette``.

Fit (coarse to fine, Adam):
    * initialisation: the first frame's mask back-projected at an estimated depth (the world origin's
      depth when the camera is known, else ``init_depth``) and thickened along the viewing rays; pixel
      tracks through the optical flow of the input; bones by k-means over canonical position plus
      track displacement (so parts that move differently separate); per-frame bone transforms
      initialised by PnP of each cluster's canonical points against its tracks;
    * losses: soft silhouette against the masks; rendered 2D motion (soft front-most Gaussians) against
      dense OpenCV optical flow (DIS or Farneback) of the input, on forward-backward-consistent pixels;
      temporal smoothness of the bone transforms; skinning-delta and entropy regularisers;
    * masks from the input, or from a median background model when the camera is static (logged).

Works for any B (``bones``); nothing is specific to a laptop.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import torch

from sync4d.errors import ConfigError, InputError
from sync4d.recon import _video_occlusion as vocc
from sync4d.recon import _video_silhouette as vsil
from sync4d.recon import skinning as sk
from sync4d.recon._softsplat import front_weights, project_points, soft_silhouette, splat_alpha
from sync4d.registry import register
from sync4d.types import Camera, Reference, ReferenceInput, VideoClip

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------------
# Image-side helpers (NumPy / OpenCV)
# --------------------------------------------------------------------------------------------------


def optical_flow(frames: np.ndarray, method: str = "dis") -> tuple[np.ndarray, np.ndarray]:
    """Dense forward and backward optical flow between consecutive frames.

    Args:
        frames: (T, H, W, 3) uint8 RGB.
        method: ``dis`` (OpenCV DIS, medium preset) or ``farneback``.

    Returns:
        (forward (T-1, H, W, 2), backward (T-1, H, W, 2)) displacements [px] as (du, dv);
        forward[t] maps frame t to t+1, backward[t] maps frame t+1 to t.
    """
    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]
    if method == "dis":
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)

        def flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return dis.calc(a, b, None)
    elif method == "farneback":

        def flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 4, 15, 5, 5, 1.2, 0)
    else:
        raise ConfigError(f"recon.flow={method!r}: use 'dis' or 'farneback'")
    fwd = np.stack([flow(grey[t], grey[t + 1]) for t in range(len(grey) - 1)]) if len(grey) > 1 else np.zeros((0,) + frames.shape[1:3] + (2,), np.float32)
    bwd = np.stack([flow(grey[t + 1], grey[t]) for t in range(len(grey) - 1)]) if len(grey) > 1 else fwd.copy()
    return fwd.astype(np.float32), bwd.astype(np.float32)


def sample_image(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples of an (H, W, C) image at (N, 2) pixel coordinates (u = column, v = row) -> (N, C)."""
    h, w = image.shape[:2]
    u = np.clip(uv[:, 0], 0, w - 1.001)
    v = np.clip(uv[:, 1], 0, h - 1.001)
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = (u - u0)[:, None], (v - v0)[:, None]
    img = image.reshape(h, w, -1).astype(np.float64)
    return (img[v0, u0] * (1 - fu) * (1 - fv) + img[v0, u0 + 1] * fu * (1 - fv)
            + img[v0 + 1, u0] * (1 - fu) * fv + img[v0 + 1, u0 + 1] * fu * fv)


def flow_consistency(fwd: np.ndarray, bwd: np.ndarray, *, tol_px: float = 1.0) -> np.ndarray:
    """(T-1, H, W) bool: forward flow whose backward flow returns within ``tol_px`` pixels."""
    n, h, w, _ = fwd.shape
    vv, uu = np.mgrid[0:h, 0:w]
    out = np.zeros((n, h, w), dtype=bool)
    grid = np.stack([uu.ravel(), vv.ravel()], 1).astype(np.float64)
    for t in range(n):
        f = fwd[t].reshape(-1, 2)
        back = sample_image(bwd[t], grid + f)
        out[t] = (np.linalg.norm(f + back, axis=1) < tol_px).reshape(h, w)
    return out


def track_points(uv0: np.ndarray, fwd: np.ndarray) -> np.ndarray:
    """(T, N, 2) pixel tracks by chaining forward flow from (N, 2) start positions [px]."""
    tracks = [uv0.astype(np.float64)]
    for t in range(len(fwd)):
        tracks.append(tracks[-1] + sample_image(fwd[t], tracks[-1]))
    return np.stack(tracks)


def trusted_tracks(uv0: np.ndarray, fwd: np.ndarray, valid_flow: np.ndarray, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel tracks (T, N, 2) [px] from (N, 2) starts and a (T, N) bool of the frames each is trusted in.

    A track stays trusted while its flow is forward-backward consistent (``valid_flow`` (T-1, H, W)) and
    it stays inside the masks (T, H, W); once lost it is not trusted again.
    """
    tracks = track_points(uv0, fwd)
    h, w = masks.shape[1:]
    ok = np.ones((len(masks), len(uv0)), dtype=bool)
    for t in range(len(fwd)):
        ui = np.clip(np.round(tracks[t]).astype(int), 0, [w - 1, h - 1])
        un = np.clip(np.round(tracks[t + 1]).astype(int), 0, [w - 1, h - 1])
        ok[t + 1] = ok[t] & valid_flow[t][ui[:, 1], ui[:, 0]] & masks[t + 1][un[:, 1], un[:, 0]]
    return tracks, ok


@dataclass
class FeatureMotions:
    """Frame-to-frame motions of tracked image corners.

    Attributes:
        frame: (P,) int frame t of each motion.
        start: (P, 2) the corner's pixel (u, v) in frame t [px] (pixel k covers [k, k + 1), as the rasters).
        end: (P, 2) its pixel in frame t + 1 [px].
    """

    frame: np.ndarray
    start: np.ndarray
    end: np.ndarray

    def __len__(self) -> int:
        return len(self.frame)


def feature_motions(frames: np.ndarray, masks: np.ndarray, *, max_corners: int = 500, check_px: float = 0.3,
                    min_move_px: float = 0.5) -> FeatureMotions:
    """Corner motions between consecutive frames: Shi-Tomasi corners inside each mask, pyramidal
    Lucas-Kanade to the next frame and back; kept where the round trip returns within ``check_px`` [px]
    and the corner moved more than ``min_move_px`` [px] (only moving texture tells one motion from another).

    Args:
        frames: (T, H, W, 3) uint8 RGB.
        masks: (T, H, W) bool foreground.
    """
    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]
    lk = dict(winSize=(15, 15), maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    frame, start, end = [], [], []
    for t in range(len(frames) - 1):
        corners = cv2.goodFeaturesToTrack(grey[t], maxCorners=max_corners, qualityLevel=0.01, minDistance=3,
                                          mask=masks[t].astype(np.uint8) * 255)
        if corners is None:
            continue
        nxt, found, _ = cv2.calcOpticalFlowPyrLK(grey[t], grey[t + 1], corners, None, **lk)
        back, found_back, _ = cv2.calcOpticalFlowPyrLK(grey[t + 1], grey[t], nxt, None, **lk)
        # OpenCV puts pixel k's centre at k; the rasters and the projection put it at k + 0.5
        a, b = corners.reshape(-1, 2).astype(np.float64) + 0.5, nxt.reshape(-1, 2).astype(np.float64) + 0.5
        keep = (found.ravel() == 1) & (found_back.ravel() == 1)
        keep &= np.linalg.norm(back.reshape(-1, 2) + 0.5 - a, axis=1) < check_px
        keep &= np.linalg.norm(b - a, axis=1) > min_move_px
        frame.append(np.full(int(keep.sum()), t))
        start.append(a[keep])
        end.append(b[keep])
    if not frame:
        return FeatureMotions(np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 2)))
    return FeatureMotions(np.concatenate(frame), np.concatenate(start), np.concatenate(end))


def refine_motion_labels(
    uv0: np.ndarray, tracks: np.ndarray, ok: np.ndarray, labels: np.ndarray, *, iterations: int = 8,
    compactness: float = 0.1,
) -> np.ndarray:
    """Re-assign tracked points to the cluster whose per-frame 2D affine motion explains their track best.

    k-means on displacements puts points near a joint (which barely move) with the static part; a
    rigid part's image motion is close to affine, and a point near a hinge still follows its part's
    affine map. Each iteration fits, per cluster and frame, the affine map uv0 -> uv_t to the cluster's
    valid tracks, then assigns every point to the cluster with the smallest mean squared residual plus
    ``compactness`` x its squared distance to the cluster centroid (both in units of the image spread).

    Args:
        uv0: (N, 2) start pixels [px].
        tracks: (T, N, 2) tracks [px].
        ok: (T, N) bool valid track samples.
        labels: (N,) initial clusters in [0, B).
        iterations: reassignment rounds.
        compactness: weight of the spatial term.

    Returns:
        (N,) labels; every cluster keeps at least 3 points.
    """
    n_bones = int(labels.max()) + 1
    spread2 = float(((uv0 - uv0.mean(0)) ** 2).sum(1).mean()) + 1e-9
    homo = np.concatenate([uv0, np.ones((len(uv0), 1))], 1)
    labels = labels.copy()
    for _ in range(iterations):
        cost = np.zeros((len(uv0), n_bones))
        for b in range(n_bones):
            members = labels == b
            if members.sum() < 3:
                cost[:, b] = np.inf
                continue
            err = np.zeros(len(uv0))
            count = np.zeros(len(uv0))
            for t in range(1, tracks.shape[0]):
                sel = members & ok[t]
                if sel.sum() < 3:
                    continue
                affine, *_ = np.linalg.lstsq(homo[sel], tracks[t, sel], rcond=None)
                res = ((homo @ affine - tracks[t]) ** 2).sum(1)
                err += np.where(ok[t], res, 0.0)
                count += ok[t]
            centroid = uv0[members].mean(0)
            # residuals of ~1 px against a spread of tens of px: x1e3 brings them to order 1
            cost[:, b] = err / np.maximum(count, 1) / spread2 * 1e3 + compactness * ((uv0 - centroid) ** 2).sum(1) / spread2
        new = np.argmin(cost, 1)
        if any((new == b).sum() < 3 for b in range(n_bones)) or np.array_equal(new, labels):
            break
        labels = new
    return labels


def background_masks(frames: np.ndarray, *, threshold: float = 30.0, open_px: int = 3) -> np.ndarray:
    """(T, H, W) bool foreground by a median background model (static camera assumed).

    Pixels whose colour differs from the temporal median by more than ``threshold`` (0-255 RGB distance)
    are foreground; a morphological opening removes speckle. Parts that never move are absorbed into
    the background (a known limit of the model).
    """
    median = np.median(frames.astype(np.float32), axis=0)
    diff = np.linalg.norm(frames.astype(np.float32) - median[None], axis=-1)
    masks = diff > threshold
    kernel = np.ones((open_px, open_px), np.uint8)
    return np.stack([cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_OPEN, kernel) > 0 for m in masks])


def box_blur(masks: np.ndarray, size: int) -> np.ndarray:
    """(T, H, W) float masks averaged over ``size`` x ``size`` boxes (the coarse levels' targets)."""
    if size <= 1:
        return masks.astype(np.float32)
    return np.stack([cv2.blur(m.astype(np.float32), (size, size)) for m in masks])


def default_camera(clip: VideoClip, fov_deg: float) -> Camera:
    """Camera at the origin looking down +z (OpenCV axes) with the clip's K or a ``fov_deg`` guess."""
    h, w = clip.frames.shape[1:3]
    if clip.intrinsics is not None:
        K = clip.intrinsics
    else:
        f = 0.5 * w / math.tan(math.radians(fov_deg) / 2)
        K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    return Camera(K=np.asarray(K, np.float64), world_to_cam=np.eye(4), width=w, height=h).validate()


def backproject(uv: np.ndarray, depth: np.ndarray, camera: Camera) -> np.ndarray:
    """(N, 3) world points at camera depths (N,) [m] under pixels (N, 2) [px]."""
    K = camera.K
    x = (uv[:, 0] - K[0, 2]) / K[0, 0] * depth
    y = (uv[:, 1] - K[1, 2]) / K[1, 1] * depth
    pc = np.stack([x, y, depth], 1)
    inv = sk.rigid_inverse(camera.world_to_cam)
    return pc @ inv[:3, :3].T + inv[:3, 3]


def pnp_transforms(points: np.ndarray, tracks: np.ndarray, valid: np.ndarray, camera: Camera) -> np.ndarray:
    """(T, 4, 4) rigid motion (rest -> t, world frame) of a point cluster from its 2D tracks by PnP.

    Args:
        points: (N, 3) canonical points [m] (their frame-0 projections are tracks[0]).
        tracks: (T, N, 2) pixel tracks [px].
        valid: (T, N) bool, tracks still trusted.
        camera: the static camera.

    Returns:
        Transforms with identity at t = 0; a frame with fewer than 6 valid points copies the previous one.
    """
    n_frames = tracks.shape[0]
    out = np.tile(np.eye(4), (n_frames, 1, 1))
    w2c = camera.world_to_cam
    c2w = sk.rigid_inverse(w2c)
    rvec, tvec = cv2.Rodrigues(w2c[:3, :3])[0], w2c[:3, 3].reshape(3, 1).copy()
    for t in range(1, n_frames):
        ok = valid[t]
        if ok.sum() < 6:
            out[t] = out[t - 1]
            continue
        found, rv, tv = cv2.solvePnP(points[ok].astype(np.float64), tracks[t, ok].astype(np.float64), camera.K,
                                     None, rvec.copy(), tvec.copy(), useExtrinsicGuess=True,
                                     flags=cv2.SOLVEPNP_ITERATIVE)
        if not found or not np.isfinite(rv).all():
            out[t] = out[t - 1]
            continue
        m = np.eye(4)
        m[:3, :3] = cv2.Rodrigues(rv)[0]
        m[:3, 3] = tv.ravel()
        out[t] = c2w @ m  # world -> cam(t) of the object, then back through the static camera
        rvec, tvec = rv, tv
    return out


def rotation_angle_deg(rot: np.ndarray) -> np.ndarray:
    """(...,) rotation angle [deg] of (..., 3, 3) rotation matrices."""
    cos = np.clip((np.trace(rot, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(cos))


# --------------------------------------------------------------------------------------------------
# The reconstructor
# --------------------------------------------------------------------------------------------------


@register("recon", "video")
class VideoReconstructor:
    """Fit Gaussians, bones, skinning and per-frame bone transforms to ``ReferenceInput.video``."""

    @dataclass
    class Config:
        """``recon=video`` options.

        Attributes:
            bones: number of bones B (int >= 1).
            gaussians: number of canonical Gaussians N.
            init_depth: depth of the back-projected first mask [m]; 0 = the depth of the world origin when
                the camera is known (else 1 m).
            init_thickness: depth spread of the back-projection, as a fraction of the object's width.
            fov_deg: horizontal field of view assumed when the video has no intrinsics [deg].
            mask_source: ``auto`` (input masks if any pixel is set, else background model), ``input`` or
                ``background``.
            background_threshold: colour distance (0-255) from the median frame that counts as foreground.
            flow: optical flow method: ``dis`` or ``farneback``.
            flow_check_px: forward-backward consistency tolerance of a flow vector [px].
            levels: pixel stride of each coarse-to-fine level (e.g. [4, 2]).
            iterations: Adam steps per level (same length as ``levels``).
            frames_per_step: frames in each step's batch.
            pixels_per_frame: silhouette pixels sampled per frame and step.
            flow_pixels_per_frame: flow pixels sampled per frame and step.
            lr: Adam learning rate (parameters in units of the object width).
            lr_motion: learning rate of the per-frame bone transforms.
            silhouette_weight: weight of the mean squared silhouette error.
            flow_weight: weight of the flow error (robust, in units of the level's pixel stride).
            smooth_weight: weight of the temporal smoothness of bone transforms.
            delta_weight: weight of the mean squared skinning-delta logit.
            entropy_weight: weight of the mean skinning entropy [nats].
            cluster_motion_weight: weight of the track displacements in the bone clustering, relative to
                the canonical positions (both normalised to the same spread).
            affine_label_iterations: rounds re-assigning tracked points to the part whose per-frame 2D
                affine motion explains their track best, after the k-means initialisation (0 = off).
            init_pnp: initialise bone transforms by PnP of each cluster's flow tracks (only reliable while
                the tracked surface stays visible).
            track_steps: Adam steps per frame of the sequential tracking stage (0 skips it).
            lr_track: learning rate of the tracking stage.
            first_frame_steps: Adam steps fitting Gaussian sizes and opacities to the first silhouette.
            depth_softness: soft z-buffer temperature, as a fraction of the object width.
            opacity: initial Gaussian opacity.
            global_from: ``root_bone`` (G_t = motion of the bone with the most skinning mass, J relative
                to it) or ``identity``.
            seed: random seed (sampling, initialisation).
        """

        bones: Any = 2
        gaussians: int = 500
        init_depth: float = 0.0
        init_thickness: float = 0.1
        fov_deg: float = 60.0
        mask_source: str = "auto"
        background_threshold: float = 30.0
        flow: str = "dis"
        flow_check_px: float = 1.0
        levels: list[int] = field(default_factory=lambda: [4, 2])
        iterations: list[int] = field(default_factory=lambda: [100, 50])
        frames_per_step: int = 4
        pixels_per_frame: int = 500
        flow_pixels_per_frame: int = 300
        lr: float = 0.01
        lr_motion: float = 0.01
        silhouette_weight: float = 1.0
        flow_weight: float = 0.1
        smooth_weight: float = 1.0
        delta_weight: float = 1e-4
        entropy_weight: float = 1e-3
        cluster_motion_weight: float = 2.0
        init_pnp: bool = False
        affine_label_iterations: int = 8
        track_steps: int = 25
        first_frame_steps: int = 40
        lr_track: float = 0.02
        depth_softness: float = 0.02
        opacity: float = 0.6
        global_from: str = "root_bone"
        seed: int = 0
        silhouette_rounds: int = 3  # silhouette tracking + relabelling rounds before the gradient fit (0 = off)
        silhouette_stride: int = 2  # [px] raster stride of the silhouette IoU
        silhouette_tilt_frames: int = 14  # first frames tracked to score each part's plane tilt
        silhouette_tilt_grid_deg: list[float] = field(default_factory=lambda: [-40.0, -20.0, 0.0, 20.0, 40.0])
        silhouette_tilt_refine_deg: float = 10.0  # [deg] first step of the later rounds' local tilt search
        silhouette_pivot_step: float = 0.05  # [object widths] first step of the joint position search
        silhouette_search_evals: int = 30  # whole-sequence trackings per part in the joint/tilt search
        silhouette_search_axis: bool = False  # also search hinge axes there (measured worse: 12.7 vs 5.3 deg)
        silhouette_evals: int = 300  # IoU evaluations per frame of the pattern search
        silhouette_root_motion: str = "auto"  # auto (moves iff its tracks move > static_root_px) | on | off
        static_root_px: float = 1.0  # [px] median track motion below which the root part counts as static
        skin_fit_steps: int = 200  # Adam steps fitting bones + skinning delta to the silhouette labels
        detect_hinges: bool = True  # ball joints whose rotations share one axis become 1-DoF hinges
        hinge_min_ratio: float = 0.9  # share of the rotation energy on the principal axis of a hinge
        silhouette_final_ball: bool = False  # a last tracking pass with ball joints from the hinge poses
        refine_after_silhouette: bool = False  # run the joint gradient refinement after the silhouette stage
        # the final Gaussians are the silhouette stage's dense cloud (one per raster cell, sigma = one cell)
        # instead of the ``gaussians`` sampled at initialisation (whose labelling seeds that stage)
        # also move joints along their viewing rays. Measured worse (8.96 vs 5.13 deg), and for a part hinged
        # to a static root it cannot help: moving the joint along its ray scales the part's plane, joint and
        # arc about the camera centre, which leaves every projection unchanged (tested: identical IoUs)
        silhouette_search_depth: bool = False
        silhouette_dense_gaussians: bool = True
        # the static root's surface after the silhouette stage (its silhouette cannot place it):
        # ``stand_in`` (fronto-parallel, as tracked); ``horizontal`` (the plane through its joints
        # perpendicular to the source's world up: a static part rests on a support); ``auto`` (horizontal
        # when the source knows its world up, else stand_in); ``occlusion`` (the plane through its joints
        # that best explains where the moving parts hide it, by colour change); ``contact`` (the plane
        # closest behind everything the moving parts sweep over). Measured (composited agreement): filmed
        # default laptop horizontal 0.958 vs stand_in 0.949; hinge renders (no world up given) stand_in
        # 0.957, contact 0.948, horizontal told z up 0.940; occlusion fails where shading changes the
        # visible base's colours as the lid moves.
        silhouette_root_depth: str = "auto"
        # relabelling: a point moves to the part whose motion keeps it inside the masks best, when that beats
        # its current part by ``silhouette_relabel_margin`` cells; ``root`` ties: a point the root explains
        # within that margin goes to the root (near a joint the child barely moves, and the flow clustering's
        # label there is a guess); ``keep``: ties keep the current label. Measured on the laptop-hinge
        # renders at seed 0 (soft z-buffer agreement, as reported before): keep 5.13 deg / 0.895, root 2.04 /
        # 0.947 (seeds 1, 2: 12.1, 9.8 deg: the lid's tilt and its swing still trade off).
        silhouette_relabel_ties: str = "root"
        silhouette_relabel_margin: float = 0.05  # [raster cells], mean over frames
        # weight of the flow-track term in relabelling (0 = silhouettes only): a point also pays the
        # distance [cells, capped] between its trusted flow track and its projection under each bone, so a
        # part that moves in the image plane (where the silhouette barely changes) keeps its points
        silhouette_relabel_flow: float = 1.0
        # where a point sits when relabelling judges it under another part's motion: ``own`` (its current
        # part's surface) or ``candidate`` (that part's surface: a mislabelled point near a joint then
        # follows the right arc; with the flow term and hypotheses, seed 0's frame-0 label accuracy on the
        # renders went from 0.916 to 0.980)
        silhouette_relabel_surface: str = "own"
        # weight of the frame-to-frame flow term in each frame's score [IoU per raster cell of mean residual
        # over all points]; 0 = silhouettes only. Each frame's pose still maximises its IoU; the term judges
        # the shape hypotheses (tilts, joints, axes). A lid's first-frame tilt and its swing trade off in the
        # silhouettes (laptop-hinge renders, same labels: the true and a 15-deg-off tilt/axis pair score IoU
        # 0.9805 and 0.9826), not in the flow (cap-2 penalties 0.138 and 0.149). With 0.5, 5 rounds, 2
        # hypotheses and candidate-surface relabelling, seeds 0/1/2: renders 2.3/7.2/8.4 deg (defaults
        # 2.0/12.1/9.8), filmed laptop 1.5/11.4/6.5 (defaults 1.8/10.9/2.7), 1.6x slower: opt-in. 1.0 lost
        # seed 2 (11.6 deg)
        silhouette_flow_weight: float = 0.0
        silhouette_flow_cap: float = 2.0  # [raster cells] cap of one point's flow residual
        # after the rounds: this many fresh tilt-grid cells per part, each with its hinge re-detected and its
        # joint searched, compete with the rounds' result by score (0 = off)
        silhouette_hypotheses: int = 0
        silhouette_hypothesis_cells: int = 6  # grid cells screened by one whole-sequence tracking each
        # independent starts of the part clustering and silhouette stage: start 0 from ``seed``, start r from
        # Gaussians re-sampled with the seed (seed, r); the start whose moving parts best predict the motions
        # of image corners (:func:`._video_silhouette.motion_residual`) wins. Why: which basin the silhouette
        # stage ends in depends on the first labels, and the silhouettes cannot rank the basins (a wrong lid
        # tilt can score the higher IoU) while the corners' motions can. Measured (docs/results.md), seeds
        # 0/1/2: hinge renders 2.04/2.37/8.3 deg with 3 starts against 2.04/12.06/9.84 with 1, filmed laptop
        # 1.84/1.76/2.72 against 1.84/10.86/2.72; the stage takes 3x as long. 1 = one start.
        silhouette_restarts: int = 3
        silhouette_restart_min_corners: int = 20  # a start scoring fewer corners is ranked by IoU after the rest

        def validate(self) -> None:
            if isinstance(self.bones, str) and self.bones.strip().isdigit():
                self.bones = int(self.bones)
            if self.bones == "auto":
                raise ConfigError("recon.bones=auto: supported by recon=skinning_fit; give recon=video an integer")
            if isinstance(self.bones, bool) or not isinstance(self.bones, int) or self.bones < 1:
                raise ConfigError(f"recon.bones={self.bones!r}: needs a positive integer")
            if len(self.levels) != len(self.iterations) or not self.levels:
                raise ConfigError(f"recon.levels={self.levels} and recon.iterations={self.iterations}: same length needed")
            if any(s < 1 for s in self.levels):
                raise ConfigError(f"recon.levels={self.levels}: pixel strides must be >= 1")
            if self.mask_source not in ("auto", "input", "background"):
                raise ConfigError(f"recon.mask_source={self.mask_source!r}: use auto, input or background")
            if self.flow not in ("dis", "farneback"):
                raise ConfigError(f"recon.flow={self.flow!r}: use dis or farneback")
            if self.global_from not in ("root_bone", "identity"):
                raise ConfigError(f"recon.global_from={self.global_from!r}: use root_bone or identity")
            if self.silhouette_root_depth not in ("auto", "stand_in", "horizontal", "occlusion", "contact"):
                raise ConfigError(f"recon.silhouette_root_depth={self.silhouette_root_depth!r}: use auto, stand_in, "
                                  "horizontal, "
                                  "occlusion or contact")
            if self.silhouette_relabel_ties not in ("root", "keep"):
                raise ConfigError(f"recon.silhouette_relabel_ties={self.silhouette_relabel_ties!r}: use root or keep")
            if self.silhouette_relabel_surface not in ("own", "candidate"):
                raise ConfigError(f"recon.silhouette_relabel_surface={self.silhouette_relabel_surface!r}: use own or "
                                  "candidate")
            if self.silhouette_relabel_flow < 0:
                raise ConfigError(f"recon.silhouette_relabel_flow={self.silhouette_relabel_flow}: needs >= 0")
            if self.silhouette_flow_weight < 0 or self.silhouette_flow_cap <= 0:
                raise ConfigError(f"recon.silhouette_flow_weight={self.silhouette_flow_weight} and "
                                  f"silhouette_flow_cap={self.silhouette_flow_cap}: need >= 0 and > 0")
            if self.silhouette_restarts < 1:
                raise ConfigError(f"recon.silhouette_restarts={self.silhouette_restarts}: needs >= 1 (1 = one start)")
            if self.silhouette_restart_min_corners < 1:
                raise ConfigError(f"recon.silhouette_restart_min_corners={self.silhouette_restart_min_corners}: "
                                  "needs >= 1")
            if self.silhouette_hypotheses < 0 or self.silhouette_hypothesis_cells < self.silhouette_hypotheses:
                raise ConfigError(f"recon.silhouette_hypotheses={self.silhouette_hypotheses} and "
                                  f"silhouette_hypothesis_cells={self.silhouette_hypothesis_cells}: need 0 <= "
                                  "hypotheses <= cells")
            if self.silhouette_relabel_margin < 0:
                raise ConfigError(f"recon.silhouette_relabel_margin={self.silhouette_relabel_margin}: needs >= 0")
            if self.silhouette_root_motion not in ("auto", "on", "off"):
                raise ConfigError(f"recon.silhouette_root_motion={self.silhouette_root_motion!r}: use auto, on or off")
            if self.gaussians < self.bones:
                raise ConfigError(f"recon.gaussians={self.gaussians}: needs at least recon.bones={self.bones}")

    def __init__(self, cfg: Config, *, device: str = "cpu") -> None:
        cfg.validate()
        self.cfg = cfg
        self.device = device  # the fit is sized for the CPU
        self.last_fit_report: dict[str, Any] = {}
        self._world_up: np.ndarray | None = None  # (3,) of the source being reconstructed, when it gives one
        self.last_state: dict[str, Any] = {}

    # ----------------------------------------------------------------------------------------------
    def masks_for(self, clip: VideoClip) -> np.ndarray:
        """(T, H, W) bool masks: the input's or a background model's (logged)."""
        mode = self.cfg.mask_source
        if mode == "auto":
            mode = "input" if clip.masks.any() else "background"
        if mode == "input":
            if not clip.masks.any():
                raise InputError(f"recon.mask_source=input but the video '{clip.source}' has empty masks")
            log.info("recon=video: masks from the input (%s)", clip.source)
            return clip.masks
        log.info("recon=video: masks from a median background model (static camera assumed; threshold %.0f)",
                 self.cfg.background_threshold)
        masks = background_masks(clip.frames, threshold=self.cfg.background_threshold)
        if not masks[0].any():
            raise InputError(f"recon=video: the background model finds no foreground in the first frame of "
                             f"'{clip.source}'; supply masks")
        return masks

    def reconstruct(self, source: ReferenceInput) -> Reference:
        """Fit the video of ``source`` (validated Reference; report in :attr:`last_fit_report`)."""
        if source.video is None:
            raise InputError(f"recon=video (the default reconstructor) needs a video, but reference '{source.name}' has "
                             "none; use reference=video (or reference.video=true on the laptop), or pick the "
                             "reconstructor for this input: recon=mocap, recon=lab4d, recon=skinning_fit or "
                             "recon=ground_truth")
        clip = source.video.validate()
        if clip.num_frames < 2:
            raise InputError(f"recon=video: '{clip.source}' has {clip.num_frames} frame; need at least 2")
        camera = source.camera if source.camera is not None else default_camera(clip, self.cfg.fov_deg)
        start = time.perf_counter()
        masks = self.masks_for(clip)
        self._world_up = None if source.world_up is None else np.asarray(source.world_up, dtype=np.float64)
        if self.cfg.silhouette_root_depth == "horizontal" and self._world_up is None:
            raise InputError(f"recon.silhouette_root_depth=horizontal needs the world's up direction, which reference "
                             f"'{source.name}' does not give; use silhouette_root_depth=auto or stand_in")
        fit = self._fit(clip.frames, masks, camera)
        ref = self._reference(fit, clip, camera, source)
        fit["report"]["seconds"] = time.perf_counter() - start
        self.last_fit_report = fit["report"]
        self.last_state = fit
        log.info("recon=video: %s", {k: v for k, v in fit["report"].items() if not isinstance(v, list)})
        return ref

    # ----------------------------------------------------------------------------------------------
    def _init_shape(self, frames: np.ndarray, masks: np.ndarray, camera: Camera, fwd: np.ndarray,
                    valid_flow: np.ndarray, rng: np.random.Generator) -> dict[str, Any]:
        cfg = self.cfg
        K = camera.K
        vv, uu = np.nonzero(masks[0])
        if len(uu) < cfg.bones:
            raise InputError("recon=video: the first mask has fewer pixels than bones")
        pick = rng.choice(len(uu), size=min(cfg.gaussians, len(uu)), replace=len(uu) < cfg.gaussians)
        uv0 = np.stack([uu[pick], vv[pick]], 1).astype(np.float64) + rng.uniform(0.0, 1.0, (len(pick), 2))
        if cfg.init_depth > 0:
            depth = cfg.init_depth
        else:
            origin_cam = camera.world_to_cam[:3, 3]
            depth = float(origin_cam[2]) if origin_cam[2] > 1e-3 and not np.allclose(camera.world_to_cam, np.eye(4)) else 1.0
        extent_px = float(np.hypot(uu.max() - uu.min() + 1, vv.max() - vv.min() + 1))
        width_m = extent_px * depth / K[0, 0]
        depths = depth + rng.uniform(-1.0, 1.0, len(pick)) * cfg.init_thickness * width_m
        points = backproject(uv0, depths, camera)
        spacing_px = math.sqrt(masks[0].sum() / len(pick))
        sigma = spacing_px * depth / K[0, 0]
        tracks, ok = trusted_tracks(uv0, fwd, valid_flow, masks)
        disp = (tracks - tracks[:1]) * (depth / K[0, 0]) / width_m  # in object widths
        disp = np.where(ok[..., None], disp, 0.0)
        pos_feat = (points - points.mean(0)) / width_m
        motion_feat = disp.transpose(1, 0, 2).reshape(len(pick), -1)
        # Drifted tracks are outliers that would each take a k-means centre: clip their norm at the
        # 90th percentile of the distances from the median track.
        rel = motion_feat - np.median(motion_feat, axis=0)
        norm = np.linalg.norm(rel, axis=1)
        cap = float(np.quantile(norm, 0.9)) + 1e-12
        motion_feat = np.median(motion_feat, axis=0) + rel * np.minimum(1.0, cap / np.maximum(norm, 1e-12))[:, None]
        motion_spread = float(np.sqrt(((motion_feat - motion_feat.mean(0)) ** 2).sum(1).mean()))
        pos_spread = float(np.sqrt(((pos_feat - pos_feat.mean(0)) ** 2).sum(1).mean()))
        # Scale-free: the trajectories get cluster_motion_weight times the spread of the positions, so
        # parts that move differently separate whether the motion is large or small in the image.
        if motion_spread > 1e-9:
            motion_feat = motion_feat * (cfg.cluster_motion_weight * pos_spread / motion_spread)
        feats = np.concatenate([pos_feat, motion_feat], 1)
        labels = sk.kmeans(points, cfg.bones, features=feats)
        if cfg.bones > 1 and cfg.affine_label_iterations > 0:
            labels = refine_motion_labels(uv0, tracks, ok, labels, iterations=cfg.affine_label_iterations)
        return {"uv0": uv0, "points": points, "sigma": sigma, "depth": depth, "width": width_m,
                "tracks": tracks, "track_ok": ok, "labels": labels, "flow": fwd, "flow_valid": valid_flow}

    def _silhouette_starts(self, frames: np.ndarray, masks: np.ndarray, camera: Camera, fwd: np.ndarray,
                           valid: np.ndarray, init: dict[str, Any]) -> tuple[np.ndarray, dict[str, Any]]:
        """The silhouette stage from ``silhouette_restarts`` starts (``init`` first, then Gaussians re-sampled
        with the seed (seed, r)): the (T, B, 4, 4) transforms and the updated ``init`` of the start whose
        moving parts best predict the image corners' motions; starts scoring under
        ``silhouette_restart_min_corners`` corners rank after the others, by mean IoU."""
        cfg = self.cfg
        if cfg.silhouette_restarts == 1:
            return self._silhouette_stage(masks, camera, init, frames), init
        motions = feature_motions(frames, masks)
        log.info("recon=video: %d moving image corners score %d silhouette-stage starts", len(motions),
                 cfg.silhouette_restarts)
        starts = []
        for r in range(cfg.silhouette_restarts):
            start = init if r == 0 else self._init_shape(frames, masks, camera, fwd, valid,
                                                         np.random.default_rng([cfg.seed, r]))
            transforms = self._silhouette_stage(masks, camera, start, frames, motions)
            residual, count = start["silhouette_motion_residual"]
            iou = float(np.mean(start["silhouette_iou"]))
            log.info("recon=video: start %d: corner-motion residual %.3f px over %d corners, mean IoU %.4f",
                     r, residual, count, iou)
            scored = count >= cfg.silhouette_restart_min_corners
            starts.append(((0 if scored else 1, residual if scored else -iou), r, transforms, start))
        summary = [{"start": r, "corner_residual_px": round(float(s["silhouette_motion_residual"][0]), 4),
                    "corners": int(s["silhouette_motion_residual"][1]),
                    "mean_iou": round(float(np.mean(s["silhouette_iou"])), 4)} for _, r, _, s in starts]
        _, best, transforms, chosen = min(starts, key=lambda s: (s[0], s[1]))
        log.info("recon=video: start %d chosen", best)
        chosen["silhouette_start"] = best
        chosen["silhouette_starts"] = summary
        return transforms, chosen

    def _silhouette_stage(self, masks: np.ndarray, camera: Camera, init: dict[str, Any],
                          frames: np.ndarray | None = None, motions: FeatureMotions | None = None) -> np.ndarray:
        """Labels, shape and per-frame bone transforms by silhouette tracking (:mod:`._video_silhouette`).

        Updates ``init["points"]`` (canonical Gaussian means on their first-frame rays) and
        ``init["labels"]`` in place and returns the (T, B, 4, 4) world-frame bone transforms. With
        ``motions``, also ``init["silhouette_motion_residual"]``: (mean residual [px], corners scored) of
        the final articulation (:func:`._video_silhouette.motion_residual`).
        """
        cfg = self.cfg
        n_bones = cfg.bones
        start = time.perf_counter()
        c2w = sk.rigid_inverse(camera.world_to_cam)
        # the first mask's cells at the raster stride: dense enough for the silhouette, and cheap
        vv, uu = np.nonzero(vsil.downsample_mask(masks[0], cfg.silhouette_stride))
        uv_dense = (np.stack([uu, vv], 1) + 0.5) * cfg.silhouette_stride
        rays = vsil.pixel_rays(uv_dense, camera.K, c2w[:3, :3])
        # the root's initial surface: the fronto-parallel plane at the initial depth (a single view cannot
        # tell more; a static part's shape does not change its silhouette)
        base_depth = init["depth"] / (rays @ c2w[:3, 2])
        scene = vsil.SilhouetteScene(
            uv0=uv_dense, rays=rays, cam_center=c2w[:3, 3], cam_rot=c2w[:3, :3], K=camera.K,
            world_to_cam=camera.world_to_cam,
            masks=np.stack([vsil.downsample_mask(m, cfg.silhouette_stride) for m in masks]),
            stride=cfg.silhouette_stride, image_shape=masks.shape[1:], base_depth=base_depth, width=init["width"],
            flow=init["flow"], flow_valid=init["flow_valid"], flow_weight=cfg.silhouette_flow_weight,
            flow_cap=cfg.silhouette_flow_cap)
        nearest = vsil.nearest_index(init["uv0"], uv_dense)
        labels = init["labels"][nearest]
        # root: the part whose flow tracks move least (with a static camera, the part at rest)
        moves = vsil.part_motion_px(init["tracks"], init["track_ok"], init["labels"], n_bones)
        root = int(np.nanargmin(moves))
        root_motion = {"auto": bool(moves[root] > cfg.static_root_px), "on": True, "off": False}[cfg.silhouette_root_motion]
        log.info("recon=video: silhouette stage: %d dense points, root bone %d (median track motion %.2f px; "
                 "root motion %s)", len(uv_dense), root, moves[root], root_motion)
        art = vsil.make_articulation(scene, labels, n_bones, root)
        # every dense point's flow track: relabelling weighs which bone's motion its track follows
        dense_tracks, dense_ok = trusted_tracks(uv_dense, init["flow"], init["flow_valid"], masks)
        # first round: each part's plane tilt from a coarse grid over the first frames (ball joints), then
        # hinge detection; every round: joint position and tilt by a local search over the whole sequence,
        # tracking, and relabelling by silhouette consistency
        for rnd in range(cfg.silhouette_rounds):
            # the tilt grid again each round: with better labels its best cell can change basin
            art = vsil.search_tilts(scene, art, frames=cfg.silhouette_tilt_frames,
                                    grid_deg=tuple(cfg.silhouette_tilt_grid_deg), root_motion=root_motion,
                                    max_evals=cfg.silhouette_evals)
            if cfg.detect_hinges and rnd == 0:
                # once: re-detecting in later rounds measured worse (6-13 deg axis jitter, 8.8 vs 5.3 deg error)
                art = self._detect_hinges(scene, art, root_motion)
            art, score = vsil.search_joint_and_tilt(scene, art, root_motion=root_motion, max_evals=cfg.silhouette_evals,
                                                    tilt_step_deg=cfg.silhouette_tilt_refine_deg,
                                                    pivot_step=cfg.silhouette_pivot_step,
                                                    search_evals=cfg.silhouette_search_evals,
                                                    search_axis=cfg.silhouette_search_axis,
                                                    search_depth=cfg.silhouette_search_depth)
            params, ious = vsil.track(scene, art, None, root_motion=root_motion, max_evals=cfg.silhouette_evals)
            new = vsil.relabel(scene, art, params, margin=cfg.silhouette_relabel_margin,
                               tie_part=root if cfg.silhouette_relabel_ties == "root" else None,
                               tracks=dense_tracks if cfg.silhouette_relabel_flow > 0 else None,
                               track_ok=dense_ok, flow_weight=cfg.silhouette_relabel_flow,
                               candidate_surface=cfg.silhouette_relabel_surface == "candidate")
            log.info("recon=video: silhouette round %d: mean IoU %.4f, min %.4f, tilts %s deg, %d labels changed "
                     "(%.0f s)", rnd, ious.mean(), ious.min(), np.round(np.degrees(art.tilts), 1).tolist(),
                     int((new != art.labels).sum()), time.perf_counter() - start)
            if np.array_equal(new, art.labels):  # converged: another round would repeat this one
                break
            if rnd < cfg.silhouette_rounds - 1:
                moved = vsil.make_articulation(scene, new, n_bones, root, art.tilts, art.axes)
                # the joint stays where the search put it, shifted by the boundary's own move
                old_boundary = vsil.make_articulation(scene, art.labels, n_bones, root).pivots
                moved.pivots = np.where((art.parent >= 0)[:, None], art.pivots + moved.pivots - old_boundary, moved.pivots)
                art = moved
        if cfg.silhouette_hypotheses > 0:
            chosen, _ = self._hypotheses(scene, art, root_motion, float(ious.mean()))
            if chosen is not art:
                art = chosen
                params, ious = vsil.track(scene, art, None, root_motion=root_motion, max_evals=cfg.silhouette_evals)
        if cfg.silhouette_final_ball:
            # last pass with ball joints, started from the hinge poses: frees the residual error of the axis
            ball = vsil.Articulation(labels=art.labels, parent=art.parent, pivots=art.pivots, tilts=art.tilts)
            init_ball = vsil.hinge_params_to_ball(params, art)
            params, ious = vsil.track(scene, ball, init_ball, root_motion=root_motion, max_evals=cfg.silhouette_evals,
                                      rot_step_deg=2.0)
            art = ball
            log.info("recon=video: ball-joint pass: mean IoU %.4f, min %.4f", ious.mean(), ious.min())
        if motions is not None:
            init["silhouette_motion_residual"] = vsil.motion_residual(scene, art, params, motions.frame,
                                                                      motions.start, motions.end)
        return self._silhouette_finish(scene, art, params, ious, root, root_motion, camera, init, frames)

    def _silhouette_finish(self, scene: Any, art: Any, params: np.ndarray, ious: np.ndarray, root: int,
                           root_motion: bool, camera: Camera, init: dict[str, Any],
                           frames: np.ndarray | None) -> np.ndarray:
        """The silhouette stage's output: canonical points, labels and (T, B, 4, 4) transforms written to
        ``init`` from its tracked articulation ``art`` and per-frame parameters ``params`` (T, D)."""
        cfg = self.cfg
        c2w = sk.rigid_inverse(camera.world_to_cam)
        uv_dense = scene.uv0
        points = vsil.canonical_points(scene, art)
        transforms = np.stack([vsil.pose_transforms(p, art, init["width"]) for p in params])
        mode = cfg.silhouette_root_depth
        world_up = self._world_up
        if mode == "auto":
            mode = "horizontal" if world_up is not None else "stand_in"
        if mode == "horizontal" and not root_motion and world_up is not None:
            # a static part rests on a support: its surface is the horizontal plane through its joints
            sel = art.labels == root
            depth = vsil.horizontal_root_depths(scene, art, root, world_up)
            if depth is not None:
                points = points.copy()
                points[sel] = scene.cam_center + depth[:, None] * scene.rays[sel]
                log.info("recon=video: static root on the horizontal plane through its joints (world up %s)",
                         np.round(world_up, 3).tolist())
        elif mode in ("occlusion", "contact") and not root_motion and frames is not None:
            # the static root's depth is invisible to its silhouette; the colour changes where the moving
            # parts hide it are not (see _video_occlusion)
            depths, rep = vocc.root_plane_depths(scene, art, params, frames, root,
                                                 color_threshold=cfg.background_threshold,
                                                 contact=mode == "contact")
            if depths is not None:
                points = scene.cam_center + depths[:, None] * scene.rays
                log.info("recon=video: root surface from occlusion ordering: %s",
                         {k: round(v, 4) for k, v in rep.items()})
        if cfg.silhouette_dense_gaussians:
            # one Gaussian per raster cell of the first mask, sized to the cell: the part labels a soft
            # z-buffer renders bleed over a part boundary by a few Gaussian radii wherever the nearer part
            # is far in front (a static root's depth is unobservable), so small, dense Gaussians keep the
            # rendered labels where the silhouette stage put them
            init["uv0"] = uv_dense
            init["points"] = points
            init["labels"] = art.labels.copy()
            depth = np.linalg.norm(points - scene.cam_center, axis=1)
            init["sigma"] = float(cfg.silhouette_stride * np.median(depth) / camera.K[0, 0])
        else:
            # each Gaussian keeps its own first-frame ray and takes the depth and part of its nearest pixel
            own = vsil.nearest_index(uv_dense, init["uv0"])
            depth = np.linalg.norm(points[own] - scene.cam_center, axis=1)
            init["points"] = scene.cam_center + depth[:, None] * vsil.pixel_rays(init["uv0"], camera.K, c2w[:3, :3])
            init["labels"] = art.labels[own]
        # the tracked scores are the IoUs unless a flow term was subtracted
        init["silhouette_iou"] = vsil.sequence_ious(scene, art, params) if scene.uses_flow else ious
        return transforms

    def _detect_hinges(self, scene: Any, art: Any, root_motion: bool) -> Any:
        """Turn ball joints whose rotations over the first ``silhouette_tilt_frames`` frames share one axis
        into hinges (:func:`._video_silhouette.detect_hinges`)."""
        axes = vsil.detect_hinges(scene, art, root_motion=root_motion, frames=self.cfg.silhouette_tilt_frames,
                                  max_evals=self.cfg.silhouette_evals, min_ratio=self.cfg.hinge_min_ratio)
        for b in np.flatnonzero(np.isfinite(axes).all(1) & ~np.isfinite(art.axes).all(1)):
            log.info("recon=video: joint of bone %d is a hinge, axis %s (world)", b, np.round(axes[b], 3).tolist())
        art.axes = axes
        return art

    def _hypotheses(self, scene: Any, art: Any, root_motion: bool, score: float) -> tuple[Any, float]:
        """The best-scoring of ``art`` (mean score ``score`` over the sequence) and, per non-root part,
        fresh hypotheses: the top ``silhouette_hypothesis_cells`` cells of a ball-joint tilt grid (scored
        over the first frames), each with its hinge re-detected and scored over the whole sequence; the
        best ``silhouette_hypotheses`` of those get their joint and tilt searched.

        Why: a hinge's axis and its part's tilt are found once, from the first round's labels, and a wrong
        pair is a local optimum that the later rounds' local searches cannot leave (laptop-hinge renders,
        seed 1, from its final articulation: 4.3 deg hinge error; a fresh grid with the final labels finds
        a pair that scores higher and errs 1.0-1.5 deg). End to end the result still varies with the seed
        (docs/results.md), so this is opt-in."""
        cfg = self.cfg
        for b in art.order():
            if art.parent[b] < 0:
                continue
            ball = art.copy()
            ball.axes[b] = np.nan
            cells = vsil.tilt_grid(scene, ball, b, frames=cfg.silhouette_tilt_frames,
                                   grid_deg=tuple(cfg.silhouette_tilt_grid_deg), root_motion=root_motion,
                                   max_evals=cfg.silhouette_evals)[: cfg.silhouette_hypothesis_cells]
            screened = []
            for _, tilt in cells:
                cand = ball.copy()
                cand.tilts[b] = tilt
                if cfg.detect_hinges:
                    cand.axes = vsil.detect_hinges(scene, cand, root_motion=root_motion, parts=[b],
                                                   frames=cfg.silhouette_tilt_frames, max_evals=cfg.silhouette_evals,
                                                   min_ratio=cfg.hinge_min_ratio)
                _, scores = vsil.track(scene, cand, None, root_motion=root_motion, max_evals=cfg.silhouette_evals)
                screened.append((float(scores.mean()), cand))
            screened.sort(key=lambda c: -c[0])
            for first, cand in screened[: cfg.silhouette_hypotheses]:
                tilt = cand.tilts[b].copy()
                cand, value = vsil.search_joint_and_tilt(scene, cand, root_motion=root_motion,
                                                         max_evals=cfg.silhouette_evals,
                                                         tilt_step_deg=cfg.silhouette_tilt_refine_deg,
                                                         pivot_step=cfg.silhouette_pivot_step,
                                                         search_evals=cfg.silhouette_search_evals, parts=[b])
                log.info("recon=video: hypothesis for bone %d from tilt %s deg (score %.4f): tilt %s deg, score "
                         "%.4f (best so far %.4f)", b, np.round(np.degrees(tilt), 1).tolist(), first,
                         np.round(np.degrees(cand.tilts[b]), 1).tolist(), value, score)
                if value > score:
                    art, score = cand, value
        return art, score

    def _fit(self, frames: np.ndarray, masks: np.ndarray, camera: Camera) -> dict[str, Any]:
        cfg = self.cfg
        rng = np.random.default_rng(cfg.seed)
        torch.manual_seed(cfg.seed)
        n_frames, height, width = masks.shape
        fwd, bwd = optical_flow(frames, cfg.flow)
        valid = flow_consistency(fwd, bwd, tol_px=cfg.flow_check_px) & masks[:-1]
        init = self._init_shape(frames, masks, camera, fwd, valid, rng)
        silhouette_j = None
        if cfg.silhouette_rounds > 0 and cfg.bones > 1:
            silhouette_j, init = self._silhouette_starts(frames, masks, camera, fwd, valid, init)
        scale = init["width"]
        centre = init["points"].mean(0)
        n_bones = cfg.bones

        # Normalised object units: x_n = (x - centre) / scale.
        pts_n = (init["points"] - centre) / scale
        centers0 = np.zeros((n_bones, 3))
        rots0 = np.tile(np.eye(3), (n_bones, 1, 1))
        scales0 = np.full((n_bones, 3), 0.05)
        for b in range(n_bones):
            p = pts_n[init["labels"] == b]
            centers0[b] = p.mean(0)
            if len(p) >= 4:
                evals, evecs = np.linalg.eigh(np.cov(p.T))
                if np.linalg.det(evecs) < 0:
                    evecs[:, 0] = -evecs[:, 0]
                rots0[b], scales0[b] = evecs, np.sqrt(np.maximum(evals, 0.05**2))
        init_j = np.tile(np.eye(4), (n_frames, n_bones, 1, 1))
        if silhouette_j is not None:  # world-frame transforms -> normalised units (J_n = S J S^-1)
            init_j = silhouette_j.copy()
            init_j[..., :3, 3] = (silhouette_j[..., :3, 3] + silhouette_j[..., :3, :3] @ centre - centre) / scale
        elif cfg.init_pnp:
            for b in range(n_bones):
                members = init["labels"] == b
                world = pnp_transforms(init["points"][members], init["tracks"][:, members],
                                       init["track_ok"][:, members], camera)
                # to normalised units: J_n = S J S^-1 with S: x -> (x - centre) / scale
                jn = world.copy()
                jn[:, :3, 3] = (world[:, :3, 3] + world[:, :3, :3] @ centre - centre) / scale
                init_j[:, b] = jn
            log.info("recon=video: PnP initial bone rotations at the last frame [deg]: %s",
                     np.round(rotation_angle_deg(init_j[-1, :, :3, :3]), 1).tolist())

        dt = torch.float32
        K = torch.as_tensor(camera.K, dtype=dt)
        w2c_n = np.eye(4)  # camera acting on normalised points: x = scale x_n + centre
        w2c_n[:3, :3] = camera.world_to_cam[:3, :3] * scale
        w2c_n[:3, 3] = camera.world_to_cam[:3, :3] @ centre + camera.world_to_cam[:3, 3]
        W2C = torch.as_tensor(w2c_n, dtype=dt)  # note: rotation part scaled; project_points only multiplies

        # Canonical means live on their frame-0 viewing rays: x_i = c + d_i r_i (normalised units), plus a
        # small free offset. The first frame's projection is then right by construction and the depths
        # d_i, which a single view leaves open, are learned from the motion (flow and silhouettes).
        cam_c = sk.rigid_inverse(camera.world_to_cam)[:3, 3]
        rays = init["points"] - cam_c
        depth0 = np.linalg.norm(rays, axis=1)
        ray_dir = torch.as_tensor(rays / depth0[:, None], dtype=dt)
        cam_c_n = torch.as_tensor((cam_c - centre) / scale, dtype=dt)
        log_depth = torch.nn.Parameter(torch.as_tensor(np.log(depth0 / scale), dtype=dt))
        offset = torch.nn.Parameter(torch.zeros(len(pts_n), 3, dtype=dt))

        def canonical() -> torch.Tensor:
            """(N, 3) canonical means in normalised units."""
            return cam_c_n + torch.exp(log_depth)[:, None] * ray_dir + offset
        log_sigma = torch.nn.Parameter(torch.full((len(pts_n),), math.log(init["sigma"] / scale), dtype=dt))
        opacity_logit = torch.nn.Parameter(torch.full((len(pts_n),), math.log(cfg.opacity / (1 - cfg.opacity)), dtype=dt))
        bone_c = torch.nn.Parameter(torch.as_tensor(centers0, dtype=dt))
        bone_r = torch.nn.Parameter(torch.as_tensor(sk.matrix_to_rot6d(rots0), dtype=dt))
        bone_s = torch.nn.Parameter(torch.as_tensor(np.log(scales0), dtype=dt))
        pivots = torch.as_tensor(centers0, dtype=dt)
        rot6 = torch.nn.Parameter(torch.as_tensor(sk.matrix_to_rot6d(init_j[1:, :, :3, :3]), dtype=dt))
        tau0 = (np.einsum("tbij,bj->tbi", init_j[1:, :, :3, :3], centers0) + init_j[1:, :, :3, 3] - centers0)
        tau = torch.nn.Parameter(torch.as_tensor(tau0, dtype=dt))
        mlp = sk.SkinningDelta(n_bones, center=np.zeros(3), scale=1.0, width=32, layers=2, frequencies=3)
        optim = torch.optim.Adam([
            {"params": [log_depth, offset, log_sigma, opacity_logit, bone_c, bone_r, bone_s], "lr": cfg.lr},
            {"params": [rot6, tau], "lr": cfg.lr_motion},
            {"params": list(mlp.parameters()), "lr": cfg.lr * 0.5},
        ])

        def transforms() -> torch.Tensor:
            """(T, B, 3, 4) J in normalised units, J_0 = identity."""
            rot = sk.rot6d_to_matrix(rot6)
            trans = pivots + tau - torch.einsum("tbij,bj->tbi", rot, pivots)
            moving = torch.cat([rot, trans[..., None]], -1)
            ident = torch.eye(4, dtype=dt)[:3].expand(1, n_bones, 3, 4)
            return torch.cat([ident, moving], 0)

        def skin(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            logits = -sk.mahalanobis_sq_torch(x, bone_c, sk.rot6d_to_matrix(bone_r), bone_s)
            delta = mlp(x)
            return torch.softmax(logits + delta, -1), delta

        def posed(frames_idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            means = canonical()
            w, delta = skin(means)
            j = transforms()[frames_idx]  # (F, B, 3, 4)
            blended = torch.einsum("nb,fbij->fnij", w, j)
            x = torch.einsum("fnij,nj->fni", blended[..., :3], means) + blended[..., 3]
            return x, w, delta

        history: list[dict[str, float]] = []
        ys, xs = np.nonzero(masks.any(0))
        pad = int(0.15 * max(ys.max() - ys.min(), xs.max() - xs.min())) + 4
        box = (max(xs.min() - pad, 0), min(xs.max() + pad, width - 1), max(ys.min() - pad, 0), min(ys.max() + pad, height - 1))
        flow_pix = [np.argwhere(valid[t]) for t in range(n_frames - 1)]
        tau_z = cfg.depth_softness * scale  # soft z-buffer temperature [m]
        blurred = {s: box_blur(masks, s) for s in set(cfg.levels)}
        identity6 = torch.as_tensor(sk.matrix_to_rot6d(np.tile(np.eye(3), (1, n_bones, 1, 1))), dtype=dt)

        def render_terms(fidx: np.ndarray, stride: int, n_pix: int, n_flow: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
            """Silhouette and flow losses on frames ``fidx``; flow compares t -> t+1 for t in fidx (t < T-1)."""
            fidx = np.asarray(fidx)
            x, w, delta = posed(torch.as_tensor(fidx))
            uv, z = project_points(x, K, W2C)
            sig_px = (K[0, 0] * torch.exp(log_sigma)[None] * scale / z.clamp_min(1e-4)).clamp_min(0.5 * stride)
            opac = torch.sigmoid(opacity_logit)
            # silhouette pixels: a stride grid inside the padded bounding box
            pu = rng.integers(box[0] // stride, box[1] // stride + 1, (len(fidx), n_pix)) * stride
            pv = rng.integers(box[2] // stride, box[3] // stride + 1, (len(fidx), n_pix)) * stride
            pu, pv = np.clip(pu, 0, width - 1), np.clip(pv, 0, height - 1)
            target = torch.as_tensor(blurred[stride][fidx[:, None], pv, pu], dtype=dt)
            pix = torch.as_tensor(np.stack([pu + 0.5, pv + 0.5], -1), dtype=dt)
            sil = soft_silhouette(splat_alpha(uv, sig_px, opac, pix))
            loss_sil = ((sil - target) ** 2).mean()
            loss_flow = torch.zeros((), dtype=dt)
            has_next = fidx < n_frames - 1
            fsel = fidx[has_next]
            if cfg.flow_weight > 0 and len(fsel) and all(len(flow_pix[t]) for t in fsel):
                x1, _, _ = posed(torch.as_tensor(fsel + 1))
                uv1, _ = project_points(x1, K, W2C)
                sel = np.stack([flow_pix[t][rng.integers(0, len(flow_pix[t]), n_flow)] for t in fsel])  # (row, col)
                fpix = torch.as_tensor(np.stack([sel[..., 1] + 0.5, sel[..., 0] + 0.5], -1), dtype=dt)
                target_flow = torch.as_tensor(fwd[fsel[:, None], sel[..., 0], sel[..., 1]], dtype=dt)
                wts = front_weights(splat_alpha(uv[has_next], sig_px[has_next], opac, fpix), z[has_next], tau_z)
                rendered = torch.einsum("fnp,fnc->fpc", wts, uv1 - uv[has_next])
                err = ((rendered - target_flow) ** 2).sum(-1)
                loss_flow = (torch.sqrt(err + 1.0) - 1.0).mean()  # robust (Charbonnier) error [px]
            return loss_sil, loss_flow, w, delta

        def record(stage: str, step: int, loss_sil: torch.Tensor, loss_flow: torch.Tensor, extra: float = 0.0) -> None:
            history.append({"stage": stage, "step": step, "silhouette": float(loss_sil.detach()),
                            "flow": float(loss_flow.detach()), "smooth": extra})
            log.debug("recon=video %s", history[-1])

        if silhouette_j is not None and cfg.skin_fit_steps > 0:
            # The silhouette stage decided each Gaussian's part; fit the bones and the skinning delta so that
            # W = softmax(-d_M + delta) reproduces it (cross-entropy on the canonical means).
            target = torch.as_tensor(init["labels"], dtype=torch.long)
            skin_opt = torch.optim.Adam([{"params": [bone_c, bone_r, bone_s], "lr": cfg.lr * 3},
                                         {"params": list(mlp.parameters()), "lr": cfg.lr}])
            with torch.no_grad():
                means_fixed = canonical()
            for it in range(cfg.skin_fit_steps):
                skin_opt.zero_grad(set_to_none=True)
                w, _ = skin(means_fixed)
                loss = torch.nn.functional.nll_loss(torch.log(w + 1e-8), target)
                loss.backward()
                skin_opt.step()
            with torch.no_grad():
                agree = float((torch.argmax(skin(means_fixed)[0], 1) == target).double().mean())
            log.info("recon=video: skinning fitted to the silhouette labels: cross-entropy %.3f, argmax agreement %.3f",
                     float(loss.detach()), agree)

        # Stage 1: track frame by frame with the canonical shape fixed: J_t starts from J_{t-1} and is fitted
        # to frame t's silhouette and to the flow (t-1 -> t). Cheap (only B transforms move) and it keeps
        # large motions (e.g. a lid folding shut) out of the local minima a joint fit from rest falls into.
        # Stage 0: fit opacities and sizes to the first frame's silhouette (J_0 is the identity).
        first_opt = torch.optim.Adam([log_sigma, opacity_logit], lr=cfg.lr * 3)
        for it in range(cfg.first_frame_steps):
            first_opt.zero_grad(set_to_none=True)
            l_sil, _, _, _ = render_terms(np.array([0]), cfg.levels[-1], cfg.pixels_per_frame, 0)
            l_sil.backward()
            first_opt.step()
        if cfg.first_frame_steps:
            record("first_frame", cfg.first_frame_steps, l_sil, torch.zeros(()))

        # Stage 1: track frame by frame: J_t starts from J_{t-1} and is fitted, together with the canonical
        # depths, to frame t's silhouette and the flow t-1 -> t, plus a few earlier frames so that the
        # depths stay consistent with them. Only frame t's transforms move; this keeps large motions (a
        # lid folding shut) out of the local minima of a joint fit started from the rest pose.
        if cfg.track_steps > 0 and silhouette_j is None:  # the silhouette stage tracked already
            stride = cfg.levels[0]
            for t in range(1, n_frames):
                with torch.no_grad():  # constant-velocity prediction from the two previous frames
                    prev6 = rot6[t - 2] if t >= 2 else identity6[0]
                    prev2 = rot6[t - 3] if t >= 3 else identity6[0]
                    rot6[t - 1] = prev6 + (prev6 - prev2) if t >= 2 else prev6
                    prev_t = tau[t - 2] if t >= 2 else torch.zeros_like(tau[0])
                    prev2_t = tau[t - 3] if t >= 3 else torch.zeros_like(tau[0])
                    tau[t - 1] = prev_t + (prev_t - prev2_t) if t >= 2 else prev_t
                track_opt = torch.optim.Adam([{"params": [rot6, tau], "lr": cfg.lr_track},
                                              {"params": [log_depth, offset], "lr": cfg.lr_track * 0.25}])
                for it in range(cfg.track_steps):
                    track_opt.zero_grad(set_to_none=True)
                    past = rng.choice(t, size=min(2, t), replace=False) if t > 1 else np.zeros(0, int)
                    l_sil, _, _, _ = render_terms(np.append(past, t), stride, cfg.pixels_per_frame, 0)
                    _, l_flow, _, _ = render_terms(np.append(past[past < t - 1], t - 1), stride, 8,
                                                   cfg.flow_pixels_per_frame)
                    loss = cfg.silhouette_weight * l_sil + cfg.flow_weight * l_flow
                    loss.backward()
                    for p in (rot6, tau):  # only frame t's transforms move in this stage
                        keep = torch.zeros_like(p.grad)
                        keep[t - 1] = 1.0
                        p.grad *= keep
                    track_opt.step()
                record("track", t, l_sil, l_flow)
                if t % 10 == 0:
                    log.info("recon=video: tracked frame %d/%d (silhouette %.4f, flow %.3f px)", t, n_frames - 1,
                             float(l_sil.detach()), float(l_flow.detach()))
            log.info("recon=video: tracked %d frames (%d steps each)", n_frames - 1, cfg.track_steps)

        # Stage 2: joint refinement of shape, bones, skinning and motion, coarse to fine.
        step = 0
        for level, (stride, iters) in enumerate(zip(cfg.levels, cfg.iterations)):
            if silhouette_j is not None and not cfg.refine_after_silhouette:
                break
            for it in range(iters):
                optim.zero_grad(set_to_none=True)
                fidx = np.sort(rng.choice(n_frames, size=min(cfg.frames_per_step, n_frames), replace=False))
                loss_sil, loss_flow, w, delta = render_terms(fidx, stride, cfg.pixels_per_frame, cfg.flow_pixels_per_frame)
                r6 = torch.cat([identity6, rot6], 0)
                tt = torch.cat([torch.zeros(1, n_bones, 3, dtype=dt), tau], 0)
                loss_smooth = ((r6[1:] - r6[:-1]) ** 2).mean() + ((tt[1:] - tt[:-1]) ** 2).mean()
                loss = (cfg.silhouette_weight * loss_sil + cfg.flow_weight * loss_flow + cfg.smooth_weight * loss_smooth
                        + cfg.delta_weight * (delta**2).mean()
                        + cfg.entropy_weight * (-(w * torch.log(w + 1e-8)).sum(-1).mean()))
                loss.backward()
                optim.step()
                step += 1
                if it % 50 == 0 or it == iters - 1:
                    record(f"refine{level}", step, loss_sil, loss_flow, float(loss_smooth.detach()))
                    log.info("recon=video: refine level %d (stride %d) step %d/%d: silhouette %.4f, flow %.3f px",
                             level, stride, it + 1, iters, float(loss_sil.detach()), float(loss_flow.detach()))

        with torch.no_grad():
            means = canonical()
            w_all, _ = skin(means)
            j_n = np.tile(np.eye(4), (n_frames, n_bones, 1, 1))
            j_n[..., :3, :] = transforms().double().numpy()
            means_n = means.double().numpy()
            cov_n = sk.bone_covariances(sk.rot6d_to_matrix(bone_r).double().numpy(), np.exp(bone_s.double().numpy()))
            out = {
                "means": means_n * scale + centre,
                "sigma": np.exp(log_sigma.double().numpy()) * scale,
                "opacity": torch.sigmoid(opacity_logit).double().numpy(),
                "weights": w_all.double().numpy(),
                "bone_centers": bone_c.double().numpy() * scale + centre,
                "bone_covariances": cov_n * scale**2,
            }
        j = j_n.copy()
        j[..., :3, 3] = scale * j_n[..., :3, 3] + centre - np.einsum("tbij,j->tbi", j_n[..., :3, :3], centre)
        out["bone_transforms"] = j
        out["camera"] = camera
        out["masks"] = masks
        out["report"] = {"history": history, "init_depth_m": init["depth"], "object_width_m": scale,
                         "gaussians": int(len(means_n)), "bones": n_bones,
                         "init_labels_count": np.bincount(init["labels"], minlength=n_bones).tolist(),
                         "silhouette_start": init.get("silhouette_start", 0),
                         "silhouette_starts": init.get("silhouette_starts", [])}
        return out

    def _reference(self, fit: dict[str, Any], clip: VideoClip, camera: Camera, source: ReferenceInput) -> Reference:
        weights = fit["weights"] / fit["weights"].sum(1, keepdims=True)
        bones = fit["bone_transforms"]
        n_frames = bones.shape[0]
        glob = np.tile(np.eye(4), (n_frames, 1, 1))
        if self.cfg.global_from == "root_bone":
            root = int(np.argmax(weights.sum(0)))
            glob = bones[:, root].copy()
            bones = np.einsum("tij,tbjk->tbik", sk.rigid_inverse(glob), bones)
        # colours: sample the first frame where each canonical Gaussian projects
        uv, _ = project_points(torch.as_tensor(fit["means"]), torch.as_tensor(camera.K), torch.as_tensor(camera.world_to_cam))
        colors = sample_image(clip.frames[0], uv.numpy()) / 255.0
        return Reference(
            rest_vertices=fit["means"], rest_faces=None, bone_centers=fit["bone_centers"],
            bone_covariances=0.5 * (fit["bone_covariances"] + np.swapaxes(fit["bone_covariances"], 1, 2)),
            skinning=weights, bone_transforms=bones, global_transforms=sk.project_to_rigid(glob), fps=clip.fps,
            vertex_colors=np.clip(colors, 0.0, 1.0), name=source.name,
        ).validate()
