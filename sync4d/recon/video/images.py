"""Image-side helpers of ``recon=video`` (NumPy / OpenCV): optical flow, tracks, masks, camera, poses."""

from __future__ import annotations

import math

import cv2
import numpy as np

from sync4d.errors import ConfigError
from sync4d.recon import skinning as sk
from sync4d.types import Camera, VideoClip


def optical_flow(frames: np.ndarray, method: str = "dis", upsample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Dense forward and backward optical flow between consecutive frames.

    Args:
        frames: (T, H, W, 3) uint8 RGB.
        method: ``dis`` (OpenCV DIS, medium preset) or ``farneback``.
        upsample: the flow is computed on the frames enlarged this many times (bilinear) and brought back
            (area average): the flow's support (DIS patches of 8 px) shrinks in the image by that factor.

    Returns:
        (forward (T-1, H, W, 2), backward (T-1, H, W, 2)) displacements [px] as (du, dv);
        forward[t] maps frame t to t+1, backward[t] maps frame t+1 to t.
    """
    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]
    if upsample > 1:
        grey = [cv2.resize(g, None, fx=upsample, fy=upsample, interpolation=cv2.INTER_LINEAR) for g in grey]
    if method == "dis":
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)  # type: ignore[attr-defined]  # missing from OpenCV's stubs

        def flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return dis.calc(a, b, None)
    elif method == "farneback":

        def flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 4, 15, 5, 5, 1.2, 0)
    else:
        raise ConfigError(f"recon.flow={method!r}: use 'dis' or 'farneback'")
    size = (frames.shape[2], frames.shape[1])

    def back(f: np.ndarray) -> np.ndarray:
        return f if upsample <= 1 else cv2.resize(f, size, interpolation=cv2.INTER_AREA) / upsample

    fwd = np.stack([back(flow(grey[t], grey[t + 1])) for t in range(len(grey) - 1)]) if len(grey) > 1 else np.zeros((0,) + frames.shape[1:3] + (2,), np.float32)
    bwd = np.stack([back(flow(grey[t + 1], grey[t])) for t in range(len(grey) - 1)]) if len(grey) > 1 else fwd.copy()
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


def patch_agreement(frames: np.ndarray, uv0: np.ndarray, uv: np.ndarray, *, radius: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """How well each track's frame-t patch matches its frame-0 patch.

    Args:
        frames: (T, H, W, 3) uint8 RGB.
        uv0: (N, 2) frame-0 positions [px] (pixel k covers [k, k + 1)).
        uv: (T, N, 2) tracked positions [px].
        radius: the patches are (2 radius + 1)^2 pixels, bilinearly sampled.

    Returns:
        (ncc (T, N) normalised cross-correlation of the grey patches in [-1, 1], contrast (N,) standard
        deviation of the frame-0 patch in grey levels / 255).
    """
    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY).astype(np.float64)[..., None] / 255.0 for f in frames]
    offsets = np.stack(np.meshgrid(np.arange(-radius, radius + 1), np.arange(-radius, radius + 1)), -1).reshape(-1, 2)

    def centred(image: np.ndarray, centres: np.ndarray) -> np.ndarray:
        patch = np.stack([sample_image(image, centres - 0.5 + o)[:, 0] for o in offsets], 1)
        return patch - patch.mean(1, keepdims=True)

    first = centred(grey[0], uv0)
    contrast = np.sqrt((first**2).mean(1))
    ncc = np.empty(uv.shape[:2])
    for t, image in enumerate(grey):
        now = centred(image, uv[t])
        ncc[t] = (first * now).mean(1) / np.maximum(contrast * np.sqrt((now**2).mean(1)), 1e-9)
    return ncc, contrast


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


def camera_moves(extrinsics: np.ndarray | None, *, min_deg: float = 0.2) -> bool:
    """Whether per-frame world-to-camera poses (T, 4, 4) move: a turn over ``min_deg`` or a shift of the camera
    centre over 0.1 % of the first camera's distance to the world origin (None or equal poses: static)."""
    if extrinsics is None or len(extrinsics) < 2:
        return False
    turn = rotation_angle_deg(np.einsum("tij,kj->tik", extrinsics[:, :3, :3], extrinsics[0, :3, :3]))
    centres = -np.einsum("tji,tj->ti", extrinsics[:, :3, :3], extrinsics[:, :3, 3])
    scale = max(float(np.linalg.norm(centres[0])), 1.0)
    return bool(turn.max() > min_deg or np.linalg.norm(centres - centres[0], axis=1).max() > 1e-3 * scale)


def static_depths(uv0: np.ndarray, uv: np.ndarray, ok: np.ndarray, K: np.ndarray, extrinsics: np.ndarray,
                  *, samples: int = 96) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each tracked point read as standing still in the world, seen by a moving camera.

    Args:
        uv0: (N, 2) frame-0 pixels [px]; uv: (T, N, 2) their tracks [px]; ok: (T, N) bool, trusted.
        K: (3, 3) intrinsics; extrinsics: (T, 4, 4) world-to-camera per frame.
        samples: depths tried per point (log-spaced from 1/30 to 900 x the camera's median baseline from
            frame 0), then refined by a parabola through the best and its neighbours.

    Returns:
        (depth (N,) frame-0 camera depth of the still point that best explains each track [world units],
        residual (N,) its RMS reprojection error over the trusted frames [px], predicted (T, N, 2) where
        that still point projects in every frame [px]).
    """
    c2w0 = np.linalg.inv(extrinsics[0])
    rays = (np.linalg.inv(K) @ np.concatenate([uv0, np.ones((len(uv0), 1))], 1).T).T  # camera-0, unit depth
    centres = -np.einsum("tji,tj->ti", extrinsics[:, :3, :3], extrinsics[:, :3, 3])
    base = float(np.median(np.linalg.norm(centres - centres[0], axis=1)[1:])) if len(centres) > 1 else 0.0
    base = max(base, 1e-6)
    depths = base * np.geomspace(1.0 / 30.0, 30.0 * 30.0, samples)  # a baseline of 1/30 .. 1/900 of the depth

    def project(depth: np.ndarray) -> np.ndarray:
        """(T, N, 2) pixels of the still points at frame-0 depths (N,)."""
        world = (rays * depth[:, None]) @ c2w0[:3, :3].T + c2w0[:3, 3]
        pc = np.einsum("tij,nj->tni", extrinsics[:, :3, :3], world) + extrinsics[:, None, :3, 3]
        pix = pc @ K.T
        return pix[..., :2] / np.maximum(pix[..., 2:3], 1e-9)

    weight = ok.astype(np.float64)
    count = np.maximum(weight.sum(0), 1.0)
    idx = np.arange(len(uv0))

    def search(log_d: np.ndarray) -> np.ndarray:
        """(N,) the log depth of least cost among log_d (S, N), refined by a parabola through its neighbours."""
        cost = np.stack([(((project(np.exp(d)) - uv) ** 2).sum(-1) * weight).sum(0) / count for d in log_d])
        best = np.argmin(cost, 0)
        lo, hi = np.clip(best - 1, 0, len(log_d) - 1), np.clip(best + 1, 0, len(log_d) - 1)
        c0, c1, c2 = cost[lo, idx], cost[best, idx], cost[hi, idx]
        denom = c0 - 2 * c1 + c2
        inner = (denom > 1e-12) & (lo != best) & (hi != best)
        shift = np.where(inner, 0.5 * (c0 - c2) / np.maximum(denom, 1e-12), 0.0)
        step = log_d[1] - log_d[0]
        return log_d[best, idx] + np.clip(shift, -1.0, 1.0) * step

    coarse = np.log(depths)
    log_depth = search(np.repeat(coarse[:, None], len(uv0), 1))
    step = coarse[1] - coarse[0]  # then a fine grid of a tenth of the coarse step about each point's estimate
    log_depth = search(log_depth[None] + np.linspace(-step, step, 21)[:, None])
    depth = np.exp(log_depth)
    predicted = project(depth)
    residual = np.sqrt((((predicted - uv) ** 2).sum(-1) * weight).sum(0) / count)
    return depth, residual, predicted
