"""``budget=auto``: model no more than a scene needs.

Instead of fixed numbers, the simulation's size is read off the scene:

* control points: the coarsest control lattice that still gives about ``target_particles`` particles
  (PhysDreamer's authors found ~10 particles per grid cell enough; the paper downsamples to a 41^3
  lattice for millions of Gaussians);
* grid: the finest of the candidate resolutions that still holds ``particles_per_cell`` particles in
  every occupied cell on average (finer grids cost time and leave cells empty, which makes MPM brittle);
* substeps: the fewest that satisfy the CFL bound for the chosen cell size, the material and the fastest
  particle the reference motion implies (its largest per-frame displacement over the frame time).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from sync4d.sim import physics
from sync4d.sim.control import make_control_points
from sync4d.types import DrivingMotion

log = logging.getLogger(__name__)

GRID_CANDIDATES = (16, 20, 24, 32, 40, 48, 64)


@dataclass(frozen=True)
class Budget:
    """What ``budget=auto`` chose (all logged and written to metrics)."""

    control_grid: int | None
    particles: int
    n_grid: int
    particles_per_cell: float
    substeps: int
    v_max: float


def choose_control_grid(means: np.ndarray, target_particles: int) -> tuple[int | None, int]:
    """Coarsest control lattice with at least ``target_particles`` points; None when the Gaussians are fewer."""
    if len(means) <= target_particles:
        return None, len(means)
    for grid in range(4, 129):
        points, _, _ = make_control_points(means, grid)
        if len(points) >= target_particles:
            return grid, len(points)
    return None, len(means)


def occupied_cells(points: np.ndarray, dx: float) -> int:
    """Number of grid cells of size ``dx`` holding at least one point."""
    keys = np.floor((points - points.min(axis=0)) / dx).astype(np.int64)
    return len(np.unique(keys, axis=0))


def choose_grid(points: np.ndarray, *, padding: float, wall: int, particles_per_cell: float) -> tuple[int, float, float]:
    """Finest candidate ``n_grid`` whose occupied cells hold >= ``particles_per_cell`` points on average.

    Returns:
        (n_grid, dx [m], particles per occupied cell).
    """
    chosen = None
    for n in GRID_CANDIDATES:
        spec = physics.fit_grid(points, n_grid=n, padding=padding, wall=wall)
        ppc = len(points) / max(occupied_cells(points, spec.dx), 1)
        if chosen is None or ppc >= particles_per_cell:
            chosen = (n, spec.dx, ppc)
        if ppc < particles_per_cell:
            break
    assert chosen is not None
    return chosen


def motion_speed(motion: DrivingMotion, points: np.ndarray, frame_time: float) -> float:
    """Largest particle speed the reference motion implies [m/s]: the biggest per-frame move of any
    point under its part transforms (all parts applied to all points: an upper bound) over ``frame_time``."""
    homo = np.concatenate([points, np.ones((len(points), 1))], axis=1)
    step = motion.part_transforms[1:] @ np.linalg.inv(motion.part_transforms[:-1])  # (T-1, B, 4, 4)
    moved = np.einsum("tbij,pj->tbpi", step[..., :3, :], homo)
    return float(np.linalg.norm(moved - points[None, None], axis=-1).max() / frame_time) if len(step) else 0.0


def choose_budget(
    means: np.ndarray,
    motion: DrivingMotion,
    *,
    E: float,
    nu: float,
    density: float,
    frame_time: float,
    padding: float,
    wall: int,
    cfl_safety: float,
    target_particles: int = 1500,
    particles_per_cell: float = 8.0,
) -> Budget:
    """Pick control points, grid resolution and substeps for a scene (see the module docstring)."""
    control_grid, count = choose_control_grid(np.asarray(means, dtype=np.float64), target_particles)
    points = means if control_grid is None else make_control_points(means, control_grid)[0]
    n_grid, dx, ppc = choose_grid(np.asarray(points, dtype=np.float64), padding=padding, wall=wall,
                                  particles_per_cell=particles_per_cell)
    sample = points[:: max(1, len(points) // 500)]
    v_max = motion_speed(motion, np.asarray(sample, dtype=np.float64), frame_time)
    dt = physics.cfl_dt(dx, E, nu, density, v_max=v_max, safety=cfl_safety)
    substeps = max(1, math.ceil(frame_time / dt))
    budget = Budget(control_grid, count, n_grid, ppc, substeps, v_max)
    log.info("budget=auto: control_grid=%s (%d particles), n_grid=%d (%.1f particles/cell), %d substeps "
             "(|v|max %.3g m/s)", control_grid, count, n_grid, ppc, substeps, v_max)
    return budget
