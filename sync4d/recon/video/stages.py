"""The first stages of ``recon=video``: masks, flow and tracks, part initialisation; their typed results."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np

from sync4d.errors import InputError
from sync4d.recon import skinning as sk
from sync4d.recon.video.images import (
    background_masks, flow_consistency, optical_flow, patch_agreement, trusted_tracks,
)
from sync4d.types import Camera, VideoClip

log = logging.getLogger(__name__)
# the flow is the subject's alone (outside its masks blanked), on frames enlarged 2x: DIS's support (patches of
# 8 px) is wider than a thin part, and the background's motion bled into it (docs/results/articulated.md)
FLOW_UPSAMPLE = 2
FLOW_MASKED = True
MIN_PATCH_CONTRAST = 0.02  # grey std-dev (0-1) of a frame-0 patch under which its track cannot be verified


@dataclass
class MaskConfig:
    """Attributes:
    source: ``auto`` (the input's masks if any pixel is set, else a background model), ``input`` or
        ``background`` (median background model, static camera).
    background_threshold: colour distance (0-255 RGB) from the median frame counted as foreground.
    """

    source: Literal["auto", "input", "background"] = "auto"
    background_threshold: float = 30.0


@dataclass
class TrackConfig:
    """Attributes:
    flow: dense optical flow: ``dis`` or ``farneback`` (OpenCV).
    check_px: forward-backward consistency tolerance of a flow vector [px].
    points: about this many first-frame mask pixels are tracked (a regular grid).
    patch_ncc: a trusted track is also verified while its 7x7 grey patch correlates with its frame-0 patch
        at least this much (in [-1, 1]), and only where the frame-0 patch has contrast
        (``MIN_PATCH_CONTRAST``): flow on a plain face is near zero and still forward-backward consistent,
        so unverified tracks stick.
    """

    flow: Literal["dis", "farneback"] = "dis"
    check_px: float = 1.0
    points: int = 1200
    patch_ncc: float = 0.8


@dataclass
class InitConfig:
    """Attributes:
    motion_weight: weight of the track displacements against the positions in the part clustering.
    fov_deg: horizontal field of view assumed when the video has no intrinsics [deg].
    """

    motion_weight: float = 2.0
    fov_deg: float = 60.0


@dataclass(frozen=True)
class Tracks:
    """Frame-0 points tracked through the video by chained optical flow.

    Attributes:
        uv0: (N, 2) frame-0 pixel centres of the tracked points [px] (pixel k covers [k, k + 1)).
        uv: (T, N, 2) their tracks [px].
        trusted: (T, N) bool, the track is still forward-backward consistent and inside the masks.
        verified: (T, N) bool, trusted and its patch still matches its frame-0 patch (``patch_ncc``).
        stride: grid spacing of the points [px].
        flow: (T-1, H, W, 2) forward flow between consecutive frames [px] (None when not kept).
        flow_ok: (T-1, H, W) bool, the forward flow is forward-backward consistent.
    """

    uv0: np.ndarray
    uv: np.ndarray
    trusted: np.ndarray
    verified: np.ndarray
    stride: int
    flow: np.ndarray | None = None
    flow_ok: np.ndarray | None = None


@dataclass(frozen=True)
class PartInit:
    """The first part labels.

    Attributes:
        labels: (N,) int part of each tracked point in [0, B).
        root: the part whose tracks move least (the base).
        root_static: whether the root stays still (median track motion below ``static_px``).
        motion_px: (B,) median track displacement of each part [px].
    """

    labels: np.ndarray
    root: int
    root_static: bool
    motion_px: np.ndarray


def video_masks(clip: VideoClip, config: MaskConfig) -> np.ndarray:
    """(T, H, W) bool masks: the input's or a median background model's (logged)."""
    mode = config.source
    if mode == "auto":
        mode = "input" if clip.masks.any() else "background"
    if mode == "input":
        if not clip.masks.any():
            raise InputError(f"recon.masks.source=input but the video '{clip.source}' has empty masks; supply masks")
        return clip.masks
    log.info("recon=video: masks from a median background model (static camera; threshold %.0f)",
             config.background_threshold)
    masks = background_masks(clip.frames, threshold=config.background_threshold)
    if not masks[0].any():
        raise InputError(f"recon=video: the background model finds no foreground in the first frame of "
                         f"'{clip.source}'; supply masks")
    return masks


def track_grid(frames: np.ndarray, masks: np.ndarray, config: TrackConfig) -> Tracks:
    """Track a regular grid of frame-0 mask pixels (about ``config.points``) through the dense flow."""
    area = int(masks[0].sum())
    if area < 4:
        raise InputError(f"recon=video: the first mask has {area} pixels; the object must be visible in frame 0")
    stride = max(1, int(np.round(np.sqrt(area / config.points))))
    vv, uu = np.nonzero(masks[0])
    keep = (vv % stride == 0) & (uu % stride == 0)
    uv0 = np.stack([uu[keep], vv[keep]], 1).astype(np.float64) + 0.5
    source = np.where(masks[..., None], frames, 0).astype(np.uint8) if FLOW_MASKED else frames
    fwd, bwd = optical_flow(source, config.flow, FLOW_UPSAMPLE)
    valid = flow_consistency(fwd, bwd, tol_px=config.check_px)
    uv, ok = trusted_tracks(uv0, fwd, valid, masks)
    ncc, contrast = patch_agreement(frames, uv0, uv)
    verified = ok & np.logical_and.accumulate((ncc >= config.patch_ncc) & (contrast >= MIN_PATCH_CONTRAST)[None], axis=0)
    verified[0] = True  # frame 0 is where the tracks start
    return Tracks(uv0=uv0, uv=uv, trusted=ok, verified=verified, stride=stride, flow=fwd, flow_ok=valid & masks[:-1])


def affine_labels(tracks: Tracks, labels: np.ndarray, *, iterations: int = 8) -> np.ndarray:
    """Re-assign points to the part whose per-frame 2D affine motion explains their track best.

    Displacement k-means puts points near a joint (which barely move) with the static part; a rigid
    part's image motion is close to affine, and such a point still follows its part's map.
    """
    n_parts = int(labels.max()) + 1
    uv0 = tracks.uv0
    spread2 = float(((uv0 - uv0.mean(0)) ** 2).sum(1).mean()) + 1e-9
    homo = np.concatenate([uv0, np.ones((len(uv0), 1))], 1)
    labels = labels.copy()
    for _ in range(iterations):
        cost = np.full((len(uv0), n_parts), np.inf)
        for b in range(n_parts):
            members = labels == b
            if members.sum() < 3:
                continue
            err, count = np.zeros(len(uv0)), np.zeros(len(uv0))
            for t in range(1, len(tracks.uv)):
                sel = members & tracks.trusted[t]
                if sel.sum() < 3:
                    continue
                affine, *_ = np.linalg.lstsq(homo[sel], tracks.uv[t, sel], rcond=None)
                res = ((homo @ affine - tracks.uv[t]) ** 2).sum(1)
                err += np.where(tracks.trusted[t], res, 0.0)
                count += tracks.trusted[t]
            centroid = uv0[members].mean(0)
            # ~1 px residuals against a spread of tens of px: x1e3 brings them to order 1
            cost[:, b] = err / np.maximum(count, 1) / spread2 * 1e3 + 0.1 * ((uv0 - centroid) ** 2).sum(1) / spread2
        new = np.argmin(cost, 1)
        if any((new == b).sum() < 3 for b in range(n_parts)) or np.array_equal(new, labels):
            break
        labels = new
    return labels


def init_parts(tracks: Tracks, n_parts: int, config: InitConfig, *, static_px: float) -> PartInit:
    """Part labels by k-means over image position and track displacement, refined by affine motion.

    The clustering uses the trusted tracks, not only the verified ones: on plain parts almost no track is
    verified, and a sticking track's direction still separates the parts (clustering on verified tracks
    alone: the closed laptops' label scores fell to 0.52 / 0.60, one lid bone lost; docs/results/articulated.md)."""
    ok = tracks.trusted
    disp = np.where(ok[..., None], tracks.uv - tracks.uv[:1], 0.0)
    pos = tracks.uv0 - tracks.uv0.mean(0)
    motion = disp.transpose(1, 0, 2).reshape(len(pos), -1)
    # drifted tracks are outliers that would each take a centre: clip their norm at the 90th percentile
    med = np.median(motion, axis=0)
    norm = np.linalg.norm(motion - med, axis=1)
    cap = float(np.quantile(norm, 0.9)) + 1e-12
    motion = med + (motion - med) * np.minimum(1.0, cap / np.maximum(norm, 1e-12))[:, None]
    m_spread = float(np.sqrt(((motion - motion.mean(0)) ** 2).sum(1).mean()))
    p_spread = float(np.sqrt((pos**2).sum(1).mean())) + 1e-9
    if m_spread > 1e-9:  # scale-free: trajectories get motion_weight x the spread of the positions
        motion = motion * (config.motion_weight * p_spread / m_spread)
    feats = np.concatenate([pos, motion], 1)
    labels = sk.kmeans(np.zeros((len(pos), 3)), n_parts, features=feats) if n_parts > 1 else np.zeros(len(pos), int)
    if n_parts > 1:
        labels = affine_labels(tracks, labels)
    step = np.linalg.norm(tracks.uv - tracks.uv[:1], axis=-1)
    moves = np.array([np.median(step[:, labels == b][ok[:, labels == b]]) if (labels == b).any() else np.inf
                      for b in range(n_parts)])
    root = int(np.argmin(moves))
    return PartInit(labels=labels, root=root, root_static=bool(moves[root] <= static_px), motion_px=moves)


def reference_depth(camera: Camera) -> float:
    """Depth [m] that fixes the monocular scale: the world origin's camera depth when the camera is known."""
    z = float(camera.world_to_cam[2, 3])
    return z if z > 1e-3 and not np.allclose(camera.world_to_cam, np.eye(4)) else 1.0
