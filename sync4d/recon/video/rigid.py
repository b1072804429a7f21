"""First part labels under a known moving camera: tracks grouped by the rigid motion that explains them.

The root is the rigid set that stands still in the world (the identity motion); each further part is the
rigid motion, fitted by PnP to a small patch of tracks, that explains most of what the identity leaves
unexplained. Every hypothesis reads a track at the best depth within a narrow band about the still surface
next to it (the depth the root's neighbouring tracks triangulate to), not at any depth: with a free depth a
part's motion along the camera's epipolar lines is read as parallax, and the identity explains it.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from sync4d.recon.video.images import static_depths

STILL_PX = 1.0  # a track whose still reading leaves less [px RMS] starts on the root (the tracks' ~1 px noise)
DEPTH_BAND = np.geomspace(1.0 / 1.3, 1.3, 7)  # depths tried about the still surface (a part within 30 % of it)
HYPOTHESES = 30  # patches a motion is fitted to, per clip
PATCH = 16  # tracks in a patch (nearest in the image to a track the identity leaves unexplained)
ROOT_MARGIN_PX = 0.2  # a track goes to a moving part only if it explains it this much better than the root
GAIN_CAP_PX = 5.0  # a drifted track's residual counts at most this much [px] (choosing a motion, assigning)
NEIGHBOURS = 9  # the labels are smoothed by a majority over this many nearest tracks in the image, twice
MIN_PNP = 6  # fewest trusted tracks a frame's PnP uses (fewer: the previous frame's motion is kept)
SPATIAL_PX = 0.5  # a track a spread (RMS) from its part's centroid in the image costs this much [px] more
REFITS = 2  # rounds of refitting the moving parts' motions on their tracks
MIN_MEMBERS = 3  # fewest tracks a part keeps (the joint fit needs every part)


def frame0_points(uv0: np.ndarray, K: np.ndarray, world_to_cam0: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(N, 3) world points at frame-0 camera depths ``depth`` (N,) [m] along the rays of pixels ``uv0`` (N, 2)
    [px] of a camera with intrinsics ``K`` (3, 3) and world-to-camera ``world_to_cam0`` (4, 4)."""
    c2w = np.linalg.inv(world_to_cam0)
    rays = (np.linalg.inv(K) @ np.concatenate([uv0, np.ones((len(uv0), 1))], 1).T).T
    return (rays * depth[:, None]) @ c2w[:3, :3].T + c2w[:3, 3]


def project_frames(points: np.ndarray, world_to_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(T, N, 2) pixels [px] of world points (N, 3) [m] in cameras ``world_to_cam`` (T, 4, 4), intrinsics K."""
    pc = np.einsum("tij,nj->tni", world_to_cam[:, :3, :3], points) + world_to_cam[:, None, :3, 3]
    pix = pc @ K.T
    return pix[..., :2] / np.maximum(pix[..., 2:3], 1e-9)


def banded_residual(uv0: np.ndarray, uv: np.ndarray, ok: np.ndarray, K: np.ndarray, extrinsics: np.ndarray,
                    motion: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(N,) RMS reprojection error [px] over each track's trusted frames after frame 0, of the point at the best
    depth within ``DEPTH_BAND`` x ``depth`` (N,) [m] moved rigidly by ``motion`` (T, 4, 4; world, frame 0 ->
    t) and seen by ``extrinsics`` (T, 4, 4; world-to-camera). uv0 (N, 2), uv (T, N, 2) [px], ok (T, N)."""
    cams = np.einsum("tij,tjk->tik", extrinsics, motion)
    weight = ok.astype(np.float64)
    weight[0] = 0.0
    count = np.maximum(weight.sum(0), 1.0)
    best = np.full(len(uv0), np.inf)
    for scale in DEPTH_BAND:
        pix = project_frames(frame0_points(uv0, K, extrinsics[0], depth * scale), cams, K)
        best = np.minimum(best, (((pix - uv) ** 2).sum(-1) * weight).sum(0) / count)
    return np.sqrt(best)


def part_motion(points: np.ndarray, uv: np.ndarray, ok: np.ndarray, K: np.ndarray,
                extrinsics: np.ndarray) -> np.ndarray:
    """(T, 4, 4) world motion (frame 0 -> t) of a rigid set with frame-0 world points (n, 3) [m] from its
    tracks uv (T, n, 2) [px] trusted where ok (T, n), by PnP in each frame's known camera (T, 4, 4)."""
    motion = np.tile(np.eye(4), (len(extrinsics), 1, 1))
    for t in range(1, len(extrinsics)):
        sel = ok[t]
        if sel.sum() < MIN_PNP:
            motion[t] = motion[t - 1]
            continue
        guess = extrinsics[t] @ motion[t - 1]
        found, rv, tv = cv2.solvePnP(points[sel], uv[t, sel].astype(np.float64), K, None,
                                     cv2.Rodrigues(guess[:3, :3])[0], guess[:3, 3].reshape(3, 1).copy(),
                                     useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        if not found or not np.isfinite(rv).all() or not np.isfinite(tv).all():
            motion[t] = motion[t - 1]
            continue
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = cv2.Rodrigues(rv)[0], tv.ravel()
        motion[t] = np.linalg.inv(extrinsics[t]) @ pose
    return motion


def surface_depth(uv0: np.ndarray, depth: np.ndarray, still: np.ndarray, k: int = 8) -> np.ndarray:
    """(N,) the still surface's depth [m] at every track: the median triangulated depth (N,) of its ``k``
    nearest still tracks (``still`` (N,) bool) in the image (uv0 (N, 2) [px])."""
    idx = cKDTree(uv0[still]).query(uv0, k=min(k, int(still.sum())))[1]
    return np.median(depth[still][idx.reshape(len(uv0), -1)], axis=1)


def smooth_labels(uv0: np.ndarray, labels: np.ndarray, k: int = NEIGHBOURS, rounds: int = 2) -> np.ndarray:
    """(N,) labels after ``rounds`` majority votes over each track's ``k`` nearest tracks in the image."""
    k = min(k, len(labels))
    idx = cKDTree(uv0).query(uv0, k=k)[1].reshape(len(labels), k)
    for _ in range(rounds):
        votes = np.zeros((len(labels), int(labels.max()) + 1))
        np.add.at(votes, (np.repeat(np.arange(len(labels)), k), labels[idx].ravel()), 1)
        labels = np.argmax(votes, 1)
    return labels


def choose_motions(pool: list[tuple[np.ndarray, np.ndarray]], root_res: np.ndarray, seen: np.ndarray,
                   n_moving: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Greedy: ``n_moving`` hypotheses (motion (T, 4, 4), residual (N,) [px]) from ``pool``, each the one that
    lowers the seen tracks' best residual (starting from the root's ``root_res``) most, each track's gain
    capped at ``GAIN_CAP_PX``; returns their motions and residuals."""
    motions: list[np.ndarray] = []
    residuals: list[np.ndarray] = []
    best = root_res.copy()
    for _ in range(n_moving):
        gains = [float(np.clip(best - res, 0.0, GAIN_CAP_PX)[seen].sum()) for _, res in pool]
        j = int(np.argmax(gains))
        motions.append(pool[j][0])
        residuals.append(pool[j][1])
        best = np.minimum(best, pool[j][1])
    return motions, residuals


def assign_parts(cost: np.ndarray, uv0: np.ndarray, rounds: int = 5) -> np.ndarray:
    """(N,) labels minimising ``cost`` (B, N) [px] plus ``SPATIAL_PX`` x each track's squared image distance
    (uv0 (N, 2) [px]) from its part's centroid over the tracks' mean squared spread, alternated ``rounds``
    times with the centroids (k-means with the motions' residuals added)."""
    labels = np.argmin(cost, 0)
    spread2 = float(((uv0 - uv0.mean(0)) ** 2).sum(1).mean()) + 1e-9
    for _ in range(rounds):
        centres = np.stack([uv0[labels == b].mean(0) if (labels == b).any() else uv0.mean(0)
                            for b in range(len(cost))])
        labels = np.argmin(cost + SPATIAL_PX * ((uv0[None] - centres[:, None]) ** 2).sum(-1) / spread2, 0)
    return labels


def motion_pool(uv0: np.ndarray, uv: np.ndarray, ok: np.ndarray, K: np.ndarray, extrinsics: np.ndarray,
                surface: np.ndarray, seeds: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Hypotheses (motion (T, 4, 4), residual (N,) [px]): a rigid motion fitted by PnP to the ``PATCH`` tracks
    nearest each seed track (indices) in the image, its points on the still surface (depths (N,) [m])."""
    points = frame0_points(uv0, K, extrinsics[0], surface)
    tree = cKDTree(uv0)
    pool = []
    for s in seeds:
        patch = tree.query(uv0[s], k=min(PATCH, len(uv0)))[1]
        motion = part_motion(points[patch], uv[:, patch], ok[:, patch], K, extrinsics)
        pool.append((motion, banded_residual(uv0, uv, ok, K, extrinsics, motion, surface)))
    return pool


def rigid_labels(uv0: np.ndarray, uv: np.ndarray, ok: np.ndarray, K: np.ndarray, extrinsics: np.ndarray,
                 n_parts: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First labels of tracks seen by a known moving camera, part 0 the root (still in the world).

    The root's hypothesis is the identity, each moving part's a rigid motion chosen greedily from
    ``HYPOTHESES`` patch fits (:func:`choose_motions`); tracks go to the part whose motion explains them best,
    with a pull toward its centroid in the image (:func:`assign_parts`), and each moving part's motion is
    refitted on its tracks (``REFITS`` times).

    Args:
        uv0: (N, 2) frame-0 pixels [px]; uv: (T, N, 2) tracks [px]; ok: (T, N) bool, trusted.
        K: (3, 3) intrinsics; extrinsics: (T, 4, 4) world-to-camera per frame [m].
        n_parts: parts B, the root included; rng: draws the tracks whose patches seed the hypotheses.

    Returns:
        (labels (N,) in [0, B), part 0 still; still depth (N,) each track's frame-0 depth read as a still point
        [m]; still pixels (T, N, 2) where that still point projects [px]), as :func:`static_depths`.
    """
    depth, still_res, still_uv = static_depths(uv0, uv, ok, K, extrinsics)
    seen = ok[1:].any(0)
    still = (still_res < STILL_PX) & seen
    if still.sum() < MIN_PNP:
        still = seen if seen.sum() >= MIN_PNP else np.ones(len(uv0), bool)
    surface = surface_depth(uv0, depth, still)
    eye = np.tile(np.eye(4), (len(extrinsics), 1, 1))
    residuals = [banded_residual(uv0, uv, ok, K, extrinsics, eye, surface)]
    unexplained = np.flatnonzero(seen & (residuals[0] > STILL_PX))
    if n_parts > 1 and len(unexplained) >= MIN_PNP:
        seeds = rng.choice(unexplained, size=min(HYPOTHESES, len(unexplained)), replace=False)
        moving = choose_motions(motion_pool(uv0, uv, ok, K, extrinsics, surface, seeds), residuals[0], seen,
                                n_parts - 1)[1]
    else:  # nothing to fit a motion to: the tracks the still reading explains least
        moving = [-residuals[0]] * (n_parts - 1)
    margin = np.array([ROOT_MARGIN_PX] + [0.0] * (n_parts - 1))[:, None]
    points = frame0_points(uv0, K, extrinsics[0], surface)
    for refit in range(REFITS + 1):
        # a track lost after frame 0 carries no motion: the centroids alone place it
        cost = np.where(seen[None], np.minimum(np.stack(residuals + moving) - margin, GAIN_CAP_PX), 0.0)
        labels = assign_parts(cost, uv0)
        for b in range(1, n_parts if refit < REFITS else 1):
            if (labels == b).sum() >= MIN_PNP:
                motion = part_motion(points[labels == b], uv[:, labels == b], ok[:, labels == b], K, extrinsics)
                moving[b - 1] = banded_residual(uv0, uv, ok, K, extrinsics, motion, surface)
    return fill_parts(smooth_labels(uv0, labels), cost), depth, still_uv


def fill_parts(labels: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """(N,) labels where every part of ``cost`` (B, N) keeps at least ``MIN_MEMBERS`` tracks: a part with fewer
    takes the tracks it explains best relative to their own part (the root's never go below it either)."""
    labels = labels.copy()
    for b in range(len(cost)):
        short = MIN_MEMBERS - int((labels == b).sum())
        if short <= 0:
            continue
        own = cost[labels, np.arange(len(labels))]
        counts = np.bincount(labels, minlength=len(cost))
        gain = np.where((labels != b) & (counts[labels] > MIN_MEMBERS), cost[b] - own, np.inf)
        labels[np.argsort(gain, kind="stable")[:short]] = b
    return labels
