"""Global search for hinge starts of ``recon=video``: every axis direction, every angle, every frame.

The joint fit (:mod:`sync4d.recon.video.joints`) is local: from a poor axis start Adam settles in a basin
whose loss is several times the truth's (measured on the suite: a lever at 6.3 found against 1.7 refined
from the true hinge with the method's own labels). This module scores a moving part turned about each of
a set of axis directions through its pivot start, by each angle of a grid, against each frame's image
terms (the fit's inside, cover and verified-track terms, on a coarse grid), and finds for every axis the
best angle track by dynamic programming (frame 0 is the rest pose; at most ``max_step_deg`` per frame). The
axes with the lowest totals start the fit.

The parts' surfaces are taken on the fronto-parallel plane at the reference depth (the fit's own start);
the other parts stay at rest while one part is searched.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from sync4d.recon.video.stages import Tracks


@dataclass(frozen=True)
class HingeStart:
    """One hinge hypothesis for one part.

    Attributes:
        part: the part index.
        axis: (3,) unit world axis.
        angles: (T,) angle per frame [rad], 0 at frame 0.
        loss: the search's mean cost over frames 1.. (lower is better).
        depth: (N_b,) camera depths of the part's points in frame 0 [m] (the surface the search assumed).
    """

    part: int
    axis: np.ndarray
    angles: np.ndarray
    loss: float
    depth: np.ndarray


def hemisphere_directions(count: int) -> np.ndarray:
    """(count, 3) unit directions spread evenly over the upper hemisphere (Fibonacci lattice); a hinge axis
    and its opposite give the same motions with the angles negated, so a hemisphere covers every axis."""
    k = np.arange(count) + 0.5
    z = 1.0 - k / count  # uniform in (0, 1]: equal areas on the hemisphere
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(np.maximum(1.0 - z**2, 0.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def rotations(axes: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(A, K, 3, 3) rotations about unit axes (A, 3) by angles (K,) [rad] (Rodrigues)."""
    k = np.zeros((len(axes), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axes[:, 2], axes[:, 1], -axes[:, 0]
    k = k - k.transpose(0, 2, 1)
    s, c = np.sin(angles)[None, :, None, None], np.cos(angles)[None, :, None, None]
    return np.eye(3) + s * k[:, None] + (1 - c) * (k @ k)[:, None]


def project(x: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """(..., 2) pixels of world points (..., 3)."""
    pc = x @ w2c[:3, :3].T + w2c[:3, 3]
    uvw = pc @ K.T
    return uvw[..., :2] / np.maximum(uvw[..., 2:3], 1e-6)


@dataclass(frozen=True)
class ImageTargets:
    """What a posed part is scored against, on the search's grid of one stride.

    Attributes:
        outside: (T, H, W) distance to each frame's mask [px].
        cover_cells: (P,) flat grid cell of every mask pixel only moving parts can reach, all frames.
        cover_frame: (P,) its frame; cover_count: (T,) such pixels per frame.
        grid: (rows, columns) of the grid; stride: its cell size [px].
    """

    outside: np.ndarray
    cover_cells: np.ndarray
    cover_frame: np.ndarray
    cover_count: np.ndarray
    grid: tuple[int, int]
    stride: float

    def every(self, step: int) -> "ImageTargets":
        """The same targets on every ``step``-th frame (frame 0 kept)."""
        keep = np.isin(self.cover_frame, np.arange(0, len(self.outside), step))
        return ImageTargets(outside=self.outside[::step], cover_cells=self.cover_cells[keep],
                            cover_frame=self.cover_frame[keep] // step, cover_count=self.cover_count[::step],
                            grid=self.grid, stride=self.stride)

    @staticmethod
    def make(outside: np.ndarray, cover_px: list[np.ndarray], stride: float) -> "ImageTargets":
        _, h, w = outside.shape
        grid = (int(np.ceil(h / stride)), int(np.ceil(w / stride)))
        cells = [cell_index(px, grid, stride) for px in cover_px]
        frame = np.concatenate([np.full(len(c), f) for f, c in enumerate(cells)]).astype(int)
        return ImageTargets(outside=outside, cover_cells=np.concatenate(cells).astype(int), cover_frame=frame,
                            cover_count=np.array([len(c) for c in cells]), grid=grid, stride=stride)


def cell_index(px: np.ndarray, grid: tuple[int, int], stride: float) -> np.ndarray:
    """(P,) flat cell of pixels (P, 2) [px] on a grid of ``stride`` cells (clipped to the grid)."""
    col = np.clip((px[:, 0] / stride).astype(int), 0, grid[1] - 1)
    row = np.clip((px[:, 1] / stride).astype(int), 0, grid[0] - 1)
    return row * grid[1] + col


def pose_costs(uv: np.ndarray, static_uv: np.ndarray, targets: ImageTargets, tracks: np.ndarray,
               verified: np.ndarray, *, cover_weight: float, inside_weight: float) -> np.ndarray:
    """(T, K) image cost of each frame for each of K poses of one part, in strides: the fit's verified-track,
    inside and cover terms.

    Args:
        uv: (K, N, 2) pixels of the part's points in each pose.
        static_uv: (M, 2) pixels of the other parts' points (at rest).
        targets: the frames' masks and cover pixels.
        tracks: (T, N, 2) the part's tracks [px]; verified: (T, N) bool.
    """
    n_frames, h, w = targets.outside.shape
    stride = targets.stride
    ui = np.clip(uv[..., 0].astype(int), 0, w - 1)
    vi = np.clip(uv[..., 1].astype(int), 0, h - 1)
    off = (uv[..., 0] < 0) | (uv[..., 0] >= w) | (uv[..., 1] < 0) | (uv[..., 1] >= h)
    inside = np.minimum(targets.outside[:, vi, ui] / stride + 10.0 * off, 10.0).mean(-1)  # (T, K)
    static_cells = cell_index(static_uv, targets.grid, stride)
    cover = np.zeros((n_frames, len(uv)))
    for k in range(len(uv)):
        # distance from every grid cell to the nearest point, in strides (the cover term's scale)
        cells = np.ones(targets.grid[0] * targets.grid[1], np.uint8)
        cells[static_cells] = 0
        cells[cell_index(uv[k][~off[k]], targets.grid, stride)] = 0
        dist = cv2.distanceTransform(cells.reshape(targets.grid), cv2.DIST_L2, 3).ravel()
        near = np.minimum(dist[targets.cover_cells], 4.0)
        cover[:, k] = np.bincount(targets.cover_frame, near, minlength=n_frames) / np.maximum(targets.cover_count, 1)
    err = ((uv[None] - tracks[:, None]) ** 2).sum(-1) / stride**2  # (T, K, N)
    track = ((np.sqrt(err + 1.0) - 1.0) * verified[:, None]).sum(-1)
    track = track / np.maximum(verified.sum(1), 1)[:, None]
    return track + inside_weight * inside + cover_weight * cover


def best_track(costs: np.ndarray, angles: np.ndarray, max_step: float) -> tuple[float, np.ndarray]:
    """The angle track through (T, K) per-frame costs over the angle grid (K,) [rad] with the least total,
    starting at angle 0 in frame 0 and moving at most ``max_step`` [rad] between frames (Viterbi); ties go
    to the smaller steps (a 1e-3 penalty per squared radian)."""
    n_frames, n_angles = costs.shape
    step = np.abs(angles[:, None] - angles[None, :])
    step = np.minimum(step, 2 * np.pi - step)
    trans = np.where(step <= max_step + 1e-9, 1e-3 * step**2, np.inf)
    total = np.where(np.isclose(angles, 0.0), 0.0, np.inf)
    back = np.zeros((n_frames, n_angles), int)
    for t in range(1, n_frames):
        cand = total[:, None] + trans  # from j (rows) to k (columns)
        back[t] = np.argmin(cand, 0)
        total = cand[back[t], np.arange(n_angles)] + costs[t]
    path = [int(np.argmin(total))]
    for t in range(n_frames - 1, 0, -1):
        path.append(back[t, path[-1]])
    return float(total.min()), angles[np.array(path[::-1])]


def tilt_normals(tilts_deg: tuple[float, ...] = (0.0, 35.0, 65.0), headings: int = 6) -> np.ndarray:
    """(M, 3) camera-frame unit normals of the surface planes tried: facing the camera (-z), then tilted by
    each angle towards ``headings`` directions around the view axis."""
    out = [np.array([0.0, 0.0, -1.0])]
    for tilt in np.radians([t for t in tilts_deg if t > 0]):
        for h in np.arange(headings) * 2 * np.pi / headings:
            out.append(np.array([np.sin(tilt) * np.cos(h), np.sin(tilt) * np.sin(h), -np.cos(tilt)]))
    return np.stack(out)


def plane_points(rays_cam: np.ndarray, through: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(N,) camera depths [m] of the plane with camera-frame ``normal`` through ``through`` (3,) along rays
    (N, 3) of unit camera depth (clipped to a quarter and four times the point's depth)."""
    depth = (normal @ through) / np.minimum(rays_cam @ normal, -1e-3)
    return np.clip(depth, 0.25 * through[2], 4.0 * through[2])


def search_part(rest: np.ndarray, pivot: np.ndarray, static_uv: np.ndarray, axes: np.ndarray, angles: np.ndarray,
                targets: ImageTargets, uv: np.ndarray, verified: np.ndarray, K: np.ndarray, w2c: np.ndarray, *,
                max_step: float, weights: dict[str, float]) -> list[tuple[float, int, np.ndarray]]:
    """(loss, axis index, angle track (T,)) of every axis for one part with rest points (N, 3) [m]."""
    posed = np.einsum("akij,nj->akni", rotations(axes, angles), rest - pivot) + pivot
    pix = project(posed, K, w2c)  # (A, K, N, 2)
    out = []
    for a in range(len(axes)):
        costs = pose_costs(pix[a], static_uv, targets, uv, verified, **weights)
        loss, track = best_track(costs, angles, max_step)
        out.append((loss / max(len(costs) - 1, 1), a, track))
    return out


def search_hinges(rays: np.ndarray, centre: np.ndarray, z_ref: float, labels: np.ndarray, root: int,
                  pivots: np.ndarray, extra_axes: np.ndarray, scene_arrays: dict, tracks: Tracks, *,
                  directions: int = 32, step_deg: float = 7.5, max_step_deg: float = 30.0,
                  cover_weight: float = 3.0, inside_weight: float = 3.0, keep_surfaces: int = 2,
                  coarse_points: int = 80, fine_points: int = 200) -> list[list[HingeStart]]:
    """Per part (the root's list empty), hinge hypotheses sorted by loss, each with its surface.

    The part's frame-0 surface is a plane through its pivot start; the plane's tilt is searched coarsely
    (every tilt of :func:`tilt_normals`, 24 axes, 15-degree angles, every other frame, ``coarse_points``
    points), then the best ``keep_surfaces`` tilts finely (``directions`` axes and the part's border,
    ``step_deg`` angles, all frames, ``fine_points`` points).

    Args:
        rays: (N, 3) world directions of the points' frame-0 pixels with unit camera depth.
        centre: (3,) camera centre [m]; z_ref: the reference depth [m] (others at rest lie there).
        labels: (N,) parts; root: the base part.
        pivots: (B, 3) pivot start of each part [m]; extra_axes: (B, 3) one more axis per part.
        scene_arrays: ``K`` (3, 3), ``w2c`` (4, 4), ``outside`` (T, H, W), ``cover_px`` (T arrays (P, 2)),
            ``stride``.
        tracks: the tracks (``uv`` and ``verified`` are used).
    """
    K, w2c = scene_arrays["K"], scene_arrays["w2c"]
    targets = ImageTargets.make(scene_arrays["outside"], scene_arrays["cover_px"], float(scene_arrays["stride"]))
    weights = {"cover_weight": cover_weight, "inside_weight": inside_weight}
    rays_cam = rays @ w2c[:3, :3].T
    normals = tilt_normals()
    out: list[list[HingeStart]] = []
    for b in range(int(labels.max()) + 1):
        own = np.flatnonzero(labels == b)
        if b == root or len(own) < 3:
            out.append([])
            continue
        static_uv = project(centre + z_ref * rays[labels != b], K, w2c)
        through = pivots[b] @ w2c[:3, :3].T + w2c[:3, 3]
        depths = [plane_points(rays_cam[own], through, n) for n in normals]
        few = own[:: max(1, len(own) // coarse_points)]
        some = np.arange(len(own))[:: max(1, len(own) // fine_points)]
        half = targets.every(2)
        coarse = []
        for m, n in enumerate(normals):
            rest = centre + plane_points(rays_cam[few], through, n)[:, None] * rays[few]
            scored = search_part(rest, pivots[b], static_uv, hemisphere_directions(24), np.radians(np.arange(-180.0, 180.0, 15.0)),
                                 half, tracks.uv[::2, few], tracks.verified[::2, few], K, w2c,
                                 max_step=2 * np.radians(max_step_deg), weights=weights)
            coarse.append((min(x[0] for x in scored), m))
        axes = np.concatenate([hemisphere_directions(directions), extra_axes[b:b + 1] / np.linalg.norm(extra_axes[b])])
        hyps = []
        for _, m in sorted(coarse)[:keep_surfaces]:
            rest = centre + depths[m][some, None] * rays[own[some]]
            for loss, a, track in search_part(rest, pivots[b], static_uv, axes, np.radians(np.arange(-180.0, 180.0, step_deg)),
                                              targets, tracks.uv[:, own[some]], tracks.verified[:, own[some]], K, w2c,
                                              max_step=np.radians(max_step_deg), weights=weights):
                hyps.append(HingeStart(part=b, axis=axes[a], angles=track, loss=loss, depth=depths[m]))
        out.append(sorted(hyps, key=lambda h: h.loss))
    return out
