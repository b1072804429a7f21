"""Surfaces the first frame never saw (a keyboard under a lid, a drawer's sides): added after the joint fit.

The joint fit reconstructs the frame-0 surface only. Once the joints are known, every later frame's mask
pixels that no posed point covers are surface revealed by the motion. Each is given to the part whose
fitted motion best predicts the optical flow at that pixel (the image-nearest part where the flow is not
trusted), placed at the camera depth of that part's nearest posed point, and carried back to the rest pose
by the inverse of the part's motion in that frame. Frames are visited in order, so a surface revealed once
is not added again.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from sync4d.recon.video.images import backproject, sample_image
from sync4d.recon.video.stages import Tracks
from sync4d.types import Camera


def project_np(x: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """((..., 2) pixels [px], (...,) camera depths [m]) of world points (..., 3) [m]."""
    pc = x @ camera.world_to_cam[:3, :3].T + camera.world_to_cam[:3, 3]
    uvw = pc @ camera.K.T
    return uvw[..., :2] / np.maximum(uvw[..., 2:3], 1e-9), pc[..., 2]


def _flow_cost(q: np.ndarray, x0: np.ndarray, motion: np.ndarray, t: int, tracks: Tracks, cameras: list[Camera]) -> np.ndarray:
    """(M,) image distance [px] between the flow from frame t at pixels q (M, 2) and the displacement that
    ``motion`` (T, 4, 4) predicts for rest points x0 (M, 3) (frame t + 1 seen by its camera); NaN where the
    flow is not consistent."""
    if tracks.flow is None or tracks.flow_ok is None or t >= len(tracks.flow):
        return np.full(len(q), np.nan)
    nxt = x0 @ motion[t + 1, :3, :3].T + motion[t + 1, :3, 3]
    pred = project_np(nxt, cameras[t + 1])[0] - q
    flow = sample_image(tracks.flow[t], q - 0.5)
    ok = sample_image(tracks.flow_ok[t].astype(np.float32)[..., None], q - 0.5)[:, 0] > 0.99
    return np.where(ok, np.linalg.norm(pred - flow, axis=1), np.nan)


def behind_first_frame(
    q: np.ndarray,
    depth: np.ndarray,
    motion: np.ndarray,
    first: tuple[cKDTree, np.ndarray],
    camera: Camera,
    stride: float,
    *,
    rounds: int = 3,
    first_camera: Camera | None = None,
) -> np.ndarray:
    """(M, 3) rest points of a part seen at pixels q (M, 2) of a frame where its motion is ``motion`` (4, 4),
    at camera depths (M,) [m] pushed back along their rays until they lie behind the frame-0 surface where it
    covers them (``first``: k-d tree of its pixels, its depths): a surface revealed later was hidden in frame
    0 (pushing behind every frame's posed surface measured worse). ``camera`` sees the frame, ``first_camera``
    frame 0 (the same when None)."""
    tree, z_first = first
    inv = np.linalg.inv(motion)
    depth = depth.copy()
    for _ in range(rounds):
        uv0, z0 = project_np(backproject(q, depth, camera) @ inv[:3, :3].T + inv[:3, 3], first_camera or camera)
        dist, near = tree.query(uv0)
        ahead = (dist <= stride) & (z0 < z_first[near] * 1.02)
        if not ahead.any():
            break
        depth = np.where(ahead, depth + z_first[near] * 1.04 - z0, depth)
    return backproject(q, depth, camera) @ inv[:3, :3].T + inv[:3, 3]


def reveal(
    means: np.ndarray, labels: np.ndarray, motions: np.ndarray, masks: np.ndarray, tracks: Tracks,
    camera: Camera | list[Camera],
) -> tuple[np.ndarray, np.ndarray]:
    """Rest points (M, 3) [m] and their parts (M,) for the mask pixels no posed point covers.

    Args:
        means: (N, 3) rest (frame-0) points [m]; labels: (N,) their parts.
        motions: (T, B, 4, 4) rest -> frame t world motion of every part.
        masks: (T, H, W) bool; tracks: the grid stride and the forward flow.
        camera: the static camera, or each frame's camera (a list of T).
    """
    cameras = camera if isinstance(camera, list) else [camera] * len(masks)
    camera = cameras[0]
    stride = tracks.stride
    pts, labs = means.copy(), labels.copy()
    n_parts = motions.shape[1]
    new_x, new_l = [], []
    uv_first, z_first = project_np(means, camera)
    first = (cKDTree(uv_first), z_first)
    for t in range(1, len(masks)):
        vv, uu = np.nonzero(masks[t])
        grid = (vv % stride == 0) & (uu % stride == 0)
        q = np.stack([uu[grid], vv[grid]], 1).astype(np.float64) + 0.5
        posed = np.einsum("nij,nj->ni", motions[t, labs, :3, :3], pts) + motions[t, labs, :3, 3]
        uv, z = project_np(posed, cameras[t])
        far = cKDTree(uv).query(q)[0] > stride
        q = q[far]
        if not len(q):
            continue
        cost = np.full((len(q), n_parts), np.inf)
        flow_cost = np.full((len(q), n_parts), np.nan)
        depth = np.zeros((n_parts, len(q)))
        for b in range(n_parts):
            own = np.flatnonzero(labs == b)
            if not len(own):
                continue
            dist, near = cKDTree(uv[own]).query(q)
            cost[:, b] = dist
            depth[b] = z[own[near]]
            inv = np.linalg.inv(motions[t, b])
            flow_cost[:, b] = _flow_cost(
                q, backproject(q, depth[b], cameras[t]) @ inv[:3, :3].T + inv[:3, 3], motions[:, b], t, tracks, cameras
            )
        use_flow = np.isfinite(flow_cost).all(1)
        best = np.where(use_flow, np.argmin(np.where(use_flow[:, None], flow_cost, 0.0), 1), np.argmin(cost, 1))
        x0 = np.zeros((len(q), 3))
        for b in np.unique(best):
            sel = best == b
            x0[sel] = behind_first_frame(q[sel], depth[b, sel], motions[t, b], first, cameras[t], stride,
                                         first_camera=camera)
        new_x.append(x0)
        new_l.append(best)
        pts, labs = np.concatenate([pts, x0]), np.concatenate([labs, best])
    if not new_x:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    return np.concatenate(new_x), np.concatenate(new_l).astype(np.int64)
