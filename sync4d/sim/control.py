"""Control points (paper, Implementation details): simulate a downsampled set, carry the Gaussians.

A Gaussian object with millions of Gaussians is simulated through its control points: the mean of the
Gaussians in each occupied cell of a ``control_grid``^3 lattice (41 in the paper). After simulation every
Gaussian follows its control point with the point's displacement and deformation gradient F:

    mu_g(t) = x_c(t) + F_c(t) (mu_g(0) - x_c(0)),     Sigma_g(t) = F_c(t) Sigma_g(0) F_c(t)^T.

The offset term is the first-order (affine) motion around the control point; the offset is smaller than
one lattice cell, and for a rigid motion F is a rotation, so Gaussians in a cell move rigidly with it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from sync4d.errors import ConfigError, InputError
from sync4d.types import TargetGaussians, Trajectory


def make_control_points(means: np.ndarray, control_grid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Downsample Gaussians to the mean of each occupied cell of a cubic lattice.

    The lattice spans the bounding cube of ``means`` (its longest extent) with ``control_grid`` cells per
    axis, so cells are cubes of side extent / control_grid.

    Args:
        means: (N, 3) Gaussian centres [m].
        control_grid: cells per axis of the lattice (41 in the paper), >= 1.

    Returns:
        points: (P, 3) control points [m], P <= N, ordered by lattice cell index.
        gaussian_to_point: (N,) int64 index of each Gaussian's control point.
        counts: (P,) int64 number of Gaussians per control point.
    """
    pts = np.asarray(means, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise InputError(f"make_control_points: expected means of shape (N, 3) with N > 0, got {pts.shape}")
    if not np.isfinite(pts).all():
        raise InputError("make_control_points: means contain NaN/inf")
    if int(control_grid) < 1:
        raise ConfigError(f"sim.control_grid={control_grid}: must be >= 1 (or null to simulate every Gaussian)")
    n = int(control_grid)
    lo = pts.min(0)
    extent = float((pts.max(0) - lo).max())
    cell = extent / n if extent > 0 else 1.0
    idx = np.clip(np.floor((pts - lo) / cell).astype(np.int64), 0, n - 1)
    key = (idx[:, 0] * n + idx[:, 1]) * n + idx[:, 2]
    _, gaussian_to_point, counts = np.unique(key, return_inverse=True, return_counts=True)
    gaussian_to_point = gaussian_to_point.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, gaussian_to_point, pts)
    points = sums / counts[:, None]
    return points, gaussian_to_point.astype(np.int64), counts.astype(np.int64)


def carry_gaussians(
    means0: Any,
    covariances0: Any,
    gaussian_to_point: Any,
    points0: Any,
    points_t: Any,
    F_t: Any,
) -> tuple[Any, Any]:
    """Move Gaussians with their control points' displacement and deformation gradient.

    Works on NumPy arrays and on torch tensors alike (differentiable in torch).

    Args:
        means0: (N, 3) Gaussian centres at rest [m].
        covariances0: (N, 3, 3) Gaussian covariances at rest [m^2].
        gaussian_to_point: (N,) int index of each Gaussian's control point.
        points0: (P, 3) control points at rest [m].
        points_t: (P, 3) control points at time t [m].
        F_t: (P, 3, 3) control points' deformation gradients at time t (rest -> t).

    Returns:
        means_t: (N, 3) x_c(t) + F_c(t) (mu_g - x_c(0)) [m].
        covariances_t: (N, 3, 3) F_c Sigma_g F_c^T [m^2].
    """
    Fg = F_t[gaussian_to_point]
    offset = means0 - points0[gaussian_to_point]
    means_t = points_t[gaussian_to_point] + (Fg @ offset[..., None])[..., 0]
    covariances_t = Fg @ covariances0 @ Fg.swapaxes(-1, -2)
    return means_t, covariances_t


def carry_frame(
    target: TargetGaussians,
    gaussian_to_point: np.ndarray,
    points0: np.ndarray,
    points_t: np.ndarray,
    F_t: np.ndarray,
    global_transform: np.ndarray | None = None,
) -> TargetGaussians:
    """Every Gaussian of one output frame, carried by its control point (one frame at a time, so a run of
    millions of Gaussians streams its frames to disk instead of holding them).

    Positions follow :func:`carry_gaussians`; covariances F_c Sigma F_c^T and the SH colours turned by the
    polar rotation of F_c (then the global transform) come from :func:`sync4d.sim.deform.deform_gaussians`,
    whose rotations are built once per control point.

    Args:
        target: the rest Gaussians (N).
        gaussian_to_point: (N,) int control point of each Gaussian.
        points0: (P, 3) control points at rest [m]; points_t: (P, 3) at time t [m].
        F_t: (P, 3, 3) their deformation gradients (rest -> t).
        global_transform: (4, 4) rigid G_t applied last, or None.

    Returns:
        The frame's Gaussians (float32, world frame).
    """
    from sync4d.sim.deform import deform_gaussians

    g2p = np.asarray(gaussian_to_point, dtype=np.int64)
    F = np.asarray(F_t, dtype=np.float64)
    offset = target.means.astype(np.float64) - np.asarray(points0, dtype=np.float64)[g2p]
    means_t = np.asarray(points_t, dtype=np.float64)[g2p] + (F[g2p] @ offset[..., None])[..., 0]
    return deform_gaussians(target, means_t, F, global_transform, index=g2p)


@dataclass(frozen=True)
class ControlPoints:
    """The simulated control points at rest and the point each Gaussian follows.

    A simulator that runs on control points hands these to ``on_frame`` (``control=``) with the points'
    positions and deformation gradients, so the Gaussians are carried one frame at a time and nothing
    per Gaussian is held across frames.

    Attributes:
        rest: (P, 3) control points at rest [m], float64.
        gaussian_to_point: (N,) int64 control point of each Gaussian.
    """

    rest: np.ndarray
    gaussian_to_point: np.ndarray

    def carry(self, target: TargetGaussians, points_t: np.ndarray, F_t: np.ndarray,
              global_transform: np.ndarray | None = None) -> TargetGaussians:
        """Every Gaussian of one frame carried by its point (:func:`carry_frame`)."""
        return carry_frame(target, self.gaussian_to_point, self.rest, points_t, F_t, global_transform)

    def point_parts(self, gaussian_parts: np.ndarray) -> np.ndarray:
        """(P,) part of each point from its Gaussians' (N,) parts (a point never mixes parts)."""
        parts = np.zeros(len(self.rest), dtype=np.asarray(gaussian_parts).dtype)
        parts[self.gaussian_to_point] = gaussian_parts
        return parts


#: ``Trajectory.extras`` keys of a trajectory simulated on control points (x and F are then (T, P, ...)).
CONTROL_REST, GAUSSIAN_TO_POINT = "control_rest", "gaussian_to_point"


def with_control(trajectory: Trajectory, control: ControlPoints | None) -> Trajectory:
    """``trajectory`` (x and F per control point) marked with the points it moves (in its extras)."""
    if control is None:
        return trajectory
    trajectory.extras[CONTROL_REST] = control.rest
    trajectory.extras[GAUSSIAN_TO_POINT] = control.gaussian_to_point
    return trajectory


def control_of(trajectory: Trajectory) -> ControlPoints | None:
    """The control points a trajectory was simulated on, or None when its x and F are per Gaussian."""
    extras = trajectory.extras or {}
    if GAUSSIAN_TO_POINT not in extras:
        return None
    return ControlPoints(np.asarray(extras[CONTROL_REST], dtype=np.float64),
                         np.asarray(extras[GAUSSIAN_TO_POINT], dtype=np.int64))


def bounded_subset(n: int, limit: int) -> np.ndarray | None:
    """Indices of at most ``limit`` of ``n`` Gaussians, evenly by stride (file order); None: all of them.

    Used where every Gaussian of every frame would be held at once (metrics, renders, exports).
    """
    if n <= limit:
        return None
    return np.arange(0, n, -(-n // int(limit)), dtype=np.int64)


def gaussian_trajectory(trajectory: Trajectory, means0: np.ndarray, index: np.ndarray | None = None) -> Trajectory:
    """The trajectory of the Gaussians ``index`` (all when None): x (T, n, 3) [m] and F (T, n, 3, 3).

    A control-point trajectory is carried (:func:`carry_gaussians`: x_c + F_c (mu_g - x_c(0)), F_c) for
    those Gaussians only; a per-Gaussian one is sliced. Args: ``means0`` (N, 3) rest centres [m].
    """
    control = control_of(trajectory)
    if control is None:
        if index is None:
            return trajectory
        return dataclasses.replace(
            trajectory, x=trajectory.x[:, index], F=None if trajectory.F is None else trajectory.F[:, index],
            v=None if trajectory.v is None else trajectory.v[:, index], extras={})
    assert trajectory.F is not None, "a trajectory through control points carries F"
    g2p = control.gaussian_to_point if index is None else control.gaussian_to_point[index]
    mu = np.asarray(means0, dtype=np.float64)
    offset = (mu if index is None else mu[index]) - control.rest[g2p]
    x = np.stack([xt[g2p] + (Ft[g2p] @ offset[..., None])[..., 0] for xt, Ft in zip(trajectory.x, trajectory.F)])
    return dataclasses.replace(trajectory, x=x, F=trajectory.F[:, g2p], v=None, extras={})
