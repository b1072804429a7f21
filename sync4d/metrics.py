"""Transfer metrics (pure functions). Lengths are reported in % of the target's bounding-box diagonal.

``metrics.json`` keys: ``pose_error_pct`` (null without ground truth), ``displacement_error_pct``,
``drift_pct``, ``rigidity_residual_pct``, ``det_f_deviation``, ``jitter_ratio``, ``seconds_per_frame``,
``peak_memory_mb``, ``frames``, and ``per_frame`` with the same per frame.
"""

from __future__ import annotations

import resource
import sys

import numpy as np


def bbox_diagonal(points: np.ndarray) -> float:
    """Length of the axis-aligned bounding-box diagonal of (N, 3) points [m]."""
    return float(np.linalg.norm(np.ptp(points, axis=0)))


def part_centroids(x: np.ndarray, parts: np.ndarray, num_parts: int, mass: np.ndarray | None = None) -> np.ndarray:
    """(B, 3) mass centroids of each part of (N, 3) points (NaN rows for empty parts)."""
    w = np.ones(len(x)) if mass is None else np.asarray(mass, dtype=np.float64)
    sums = np.zeros((num_parts, 3))
    np.add.at(sums, parts, x * w[:, None])
    totals = np.bincount(parts, weights=w, minlength=num_parts)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums / totals[:, None]


def displacement_error(
    x_start: np.ndarray, x_end: np.ndarray, parts: np.ndarray, target_displacement: np.ndarray, diagonal: float
) -> float:
    """Mean over parts of |delta_b - (s_t/s_o) delta_hat_b| in % of ``diagonal`` (one frame pair).

    Args:
        x_start, x_end: (N, 3) positions before and after the step [m].
        parts: (N,) part of each point.
        target_displacement: (B, 3) scaled reference displacement per part [m].
    """
    b = len(target_displacement)
    delta = part_centroids(x_end, parts, b) - part_centroids(x_start, parts, b)
    err = np.linalg.norm(delta - target_displacement, axis=1)
    return float(np.nanmean(err) / diagonal * 100.0)


def drift(x_t: np.ndarray, x_0: np.ndarray, parts: np.ndarray, accumulated_target: np.ndarray, diagonal: float) -> float:
    """Mean over parts of |(c_b(t) - c_b(0)) - sum_{s<t} delta_hat_b(s)| in % of ``diagonal``."""
    b = len(accumulated_target)
    moved = part_centroids(x_t, parts, b) - part_centroids(x_0, parts, b)
    return float(np.nanmean(np.linalg.norm(moved - accumulated_target, axis=1)) / diagonal * 100.0)


def pose_error(x_t: np.ndarray, x_true: np.ndarray, diagonal: float) -> float:
    """Mean distance of each point to its ground-truth position, in % of ``diagonal``."""
    return float(np.linalg.norm(x_t - x_true, axis=1).mean() / diagonal * 100.0)


def procrustes_residual(source: np.ndarray, moved: np.ndarray) -> float:
    """RMS residual [m] of the best rigid fit (rotation + translation, Kabsch) of ``source`` onto ``moved``."""
    if len(source) < 3:
        return 0.0
    a = source - source.mean(axis=0)
    b = moved - moved.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    rot = (u @ np.diag([1.0, 1.0, d]) @ vt).T
    residual = b - a @ rot.T
    return float(np.sqrt((residual**2).sum(axis=1).mean()))


def rigidity_residual(x_0: np.ndarray, x_t: np.ndarray, parts: np.ndarray, num_parts: int, diagonal: float) -> float:
    """Mean over parts of the Procrustes residual from rest to frame t, in % of ``diagonal``."""
    values = [procrustes_residual(x_0[parts == b], x_t[parts == b]) for b in range(num_parts) if (parts == b).sum() >= 3]
    return float(np.mean(values) / diagonal * 100.0) if values else 0.0


def det_f_deviation(F: np.ndarray | None) -> float:
    """Mean |det F - 1| over (N, 3, 3) deformation gradients (0 when F is not tracked)."""
    return 0.0 if F is None else float(np.abs(np.linalg.det(F) - 1.0).mean())


def second_difference(x: np.ndarray) -> np.ndarray:
    """(T-2,) mean |x_{t+1} - 2 x_t + x_{t-1}| over points of a (T, N, 3) sequence [m]."""
    if len(x) < 3:
        return np.zeros(0)
    return np.linalg.norm(x[2:] - 2 * x[1:-1] + x[:-2], axis=2).mean(axis=1)


def jitter_ratio(x_target: np.ndarray, x_reference: np.ndarray, coverage_ratio: float) -> float:
    """Mean second difference of the target against the reference's own (scaled to the target's size).

    1 means as smooth as the reference; much more than 1 means added jitter. NaN for fewer than 3 frames.
    """
    tgt, ref = second_difference(x_target), second_difference(x_reference) * coverage_ratio
    if len(tgt) == 0:
        return float("nan")
    return float(tgt.mean() / max(ref.mean(), 1e-12))


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far [MB]."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1024.0 if sys.platform != "darwin" else peak / (1024.0 * 1024.0)


def skinned_positions(rest: np.ndarray, skinning: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """(N, 3) linear blend skinning of rest points [m] with (N, B) weights and (B, 4, 4) transforms."""
    blended = np.einsum("nb,bij->nij", skinning, transforms)
    return np.einsum("nij,nj->ni", blended[:, :3, :3], rest) + blended[:, :3, 3]
