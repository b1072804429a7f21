"""Depth of a static root part from occlusion ordering (NumPy, static camera).

Why: a static part's silhouette is the same at every depth, so the silhouette stage leaves its surface
at a fronto-parallel stand-in. Its depth still matters for anything rendered with a z-buffer: a moving
part that passes over it in the image must be in front exactly where it hides it. With a static camera
and a static root the video tells which: a root pixel whose colour changes from the first frame is
hidden by a moving part (it is still inside the mask), one whose colour stays is visible. The root's
surface is then the plane through its joints (joints are shared with the children, so the root reaches
their depth) whose tilt best honours those orderings against the tracked children's depths.
"""

from __future__ import annotations

import numpy as np

from sync4d.recon import _video_silhouette as vsil


def cell_colors(frames: np.ndarray, stride: int) -> np.ndarray:
    """(T, H // stride, W // stride, 3) float32 mean colour of each raster cell of (T, H, W, 3) frames."""
    t, h, w = frames.shape[0], frames.shape[1] // stride * stride, frames.shape[2] // stride * stride
    f = frames[:, :h, :w].astype(np.float32)
    return f.reshape(t, h // stride, stride, w // stride, stride, 3).mean((2, 4))


def child_depth_buffer(cells: np.ndarray, z: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) nearest camera depth per raster cell (inf where no point falls).

    Args:
        cells: (N, 2) integer cell coordinates (iu, iv); out-of-range cells are ignored.
        z: (N,) camera depths [m].
    """
    h, w = shape
    out = np.full(h * w, np.inf)
    keep = (cells[:, 0] >= 0) & (cells[:, 0] < w) & (cells[:, 1] >= 0) & (cells[:, 1] < h)
    np.minimum.at(out, cells[keep, 1] * w + cells[keep, 0], z[keep])
    return out.reshape(h, w)


def ordering_loss(z_root: np.ndarray, z_child: np.ndarray, hidden: np.ndarray, *, slack: float = 0.01) -> float:
    """Mean violation [m] of the depth orderings, plus ``slack`` x the mean gap of hidden points.

    Args:
        z_root: (M,) camera depths of the root points [m].
        z_child: (T, M) nearest child depth over each root point's cell per frame (inf = no child there).
        hidden: (T, M) bool: the root point's colour changed (a child hides it) at that frame.

    A hidden root point must be behind the child (z_root >= z_child), a visible one in front
    (z_root <= z_child). The slack term prefers, among planes that satisfy everything, the one that
    lies closest behind the occluder (parts in contact), so a root with only hidden constraints does
    not drift to infinity.
    """
    covered = np.isfinite(z_child)
    if not covered.any():
        return 0.0
    gap = np.where(covered, z_root[None] - np.where(covered, z_child, 0.0), 0.0)  # > 0: root behind
    viol = np.where(hidden, np.maximum(-gap, 0.0), np.maximum(gap, 0.0))
    behind = np.where(hidden & covered, np.maximum(gap, 0.0), 0.0)
    n = covered.sum()
    return float(viol[covered].sum() / n + slack * behind.sum() / max((hidden & covered).sum(), 1))


def root_plane_depths(
    scene: vsil.SilhouetteScene, art: vsil.Articulation, params: np.ndarray, frames: np.ndarray, root: int, *,
    color_threshold: float = 30.0, contact: bool = False, grid_deg: tuple[float, ...] = tuple(range(-80, 81, 10)),
) -> tuple[np.ndarray | None, dict[str, float]]:
    """(M,) depths along the rays of the scene's points with the static root's points on the plane through
    its joints that best honours the occlusion orderings (others unchanged), or None without evidence.

    Args:
        scene, art: the silhouette stage's scene and articulation (root static).
        params: (T, D) its per-frame pose parameters.
        frames: (T, H, W, 3) uint8 video frames.
        root: the root part.
        color_threshold: RGB distance (0-255) from the first frame above which a root cell counts as hidden.
        contact: ignore the colours and treat every covered root point as hidden: the root is the surface
            closest behind everything its children sweep over (non-penetration and contact, e.g. a lid that
            closes onto its base), for videos whose shading changes the visible root's colours too.
        grid_deg: tilt grid [deg] (both angles) of the root plane about the camera's x and y axes.

    Returns:
        (depths or None, report with the loss of the fronto-parallel stand-in and of the chosen plane).
    """
    points = vsil.canonical_points(scene, art)
    depth0 = np.linalg.norm(points - scene.cam_center, axis=1)
    is_root = art.labels == root
    children = np.flatnonzero(art.parent == root)
    if not is_root.any() or len(children) == 0 or (~is_root).sum() == 0:
        return None, {}
    h, w = scene.masks.shape[1:]
    colors = cell_colors(frames, scene.stride)[:, :h, :w]
    r_cells = np.floor(scene.uv0[is_root] / scene.stride).astype(int)
    r_cells = np.clip(r_cells, 0, [w - 1, h - 1])
    forward = scene.cam_rot[:, 2]
    n_frames = len(params)
    z_child = np.full((n_frames, int(is_root.sum())), np.inf)
    hidden = np.zeros_like(z_child, dtype=bool)
    c0 = colors[0][r_cells[:, 1], r_cells[:, 0]]
    for t in range(1, n_frames):
        tf = vsil.pose_transforms(params[t], art, scene.width)
        moved = vsil.posed_points(points[~is_root], art.labels[~is_root], tf)
        cells = np.floor(scene.project(moved) / scene.stride).astype(int)
        zc = (moved - scene.cam_center) @ forward
        buf = child_depth_buffer(cells, zc, (h, w))
        z_child[t] = buf[r_cells[:, 1], r_cells[:, 0]]
        ct = colors[t][r_cells[:, 1], r_cells[:, 0]]
        hidden[t] = True if contact else np.linalg.norm(ct - c0, axis=1) > color_threshold
    rays = scene.rays[is_root]
    cos_f = rays @ forward
    pivot = art.pivots[children].mean(0)
    view = pivot - scene.cam_center
    pivot_depth = float(np.linalg.norm(view))

    def depths(tilt: np.ndarray) -> np.ndarray:
        normal = vsil.tilted_normal(view / pivot_depth, tilt, scene.cam_rot)
        return np.clip(vsil.ray_plane_depths(rays, scene.cam_center, pivot, normal), 0.5 * pivot_depth, 2.0 * pivot_depth)

    def loss(tilt: np.ndarray) -> float:
        return ordering_loss(depths(tilt) * cos_f, z_child, hidden)

    base = ordering_loss(depth0[is_root] * cos_f, z_child, hidden)
    grid = [np.radians([a, b]) for a in grid_deg for b in grid_deg]
    scores = [loss(g) for g in grid]
    best = grid[int(np.argmin(scores))]
    step = np.radians(max(abs(grid_deg[1] - grid_deg[0]), 1.0) if len(grid_deg) > 1 else 5.0) / 2
    tilt, neg = vsil.pattern_search(lambda x: -loss(x), best, np.array([step, step]), min_scale=1 / 16, max_evals=200)
    out = depth0.copy()
    out[is_root] = depths(tilt)
    report = {"stand_in_loss_m": base, "plane_loss_m": -neg, "tilt_x_deg": float(np.degrees(tilt[0])),
              "tilt_y_deg": float(np.degrees(tilt[1])), "covered_pairs": int(np.isfinite(z_child).sum()),
              "hidden_share": float(hidden[np.isfinite(z_child)].mean()) if np.isfinite(z_child).any() else 0.0}
    return out, report
