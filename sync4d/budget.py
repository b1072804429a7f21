"""``budget=auto``: model no more than a scene needs.

Instead of fixed numbers, the simulation's size is read off the scene:

* control points: the coarsest control lattice that still gives about ``target_particles`` particles
  (PhysDreamer's authors found ~10 particles per grid cell enough; the paper downsamples to a 41^3
  lattice for millions of Gaussians);
* grid: ``cells_across`` cells over the object's longest extent (plus the padding and walls). The
  sweep ``experiment=ablate_budget`` on the laptop self-transfer showed accuracy set by the cell size,
  not by particles per cell: 271 control points at 1.5 particles per cell were as accurate as 4500
  Gaussians at 21 per cell on the same grid (thin slabs leave most cells sparsely filled whatever the
  count), while each halving of dx cost 2-4x time. PhysDreamer's "about 10 particles per cell" is
  therefore not used to pick the grid; it is logged;
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


def grid_for_cells(cells_across: int, *, padding: float, wall: int) -> int:
    """``n_grid`` giving ``cells_across`` cells over the object's longest extent (see ``physics.fit_grid``:
    the padded extent (1 + 2 padding) spans n_grid - 2 wall - 2 cells)."""
    return int(math.ceil(cells_across * (1.0 + 2.0 * padding))) + 2 * wall + 2


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
    target_particles: int = 300,
    cells_across: int = 12,
) -> Budget:
    """Pick control points, grid resolution and substeps for a scene (see the module docstring)."""
    control_grid, count = choose_control_grid(np.asarray(means, dtype=np.float64), target_particles)
    points = np.asarray(means if control_grid is None else make_control_points(means, control_grid)[0], dtype=np.float64)
    n_grid = grid_for_cells(cells_across, padding=padding, wall=wall)
    dx = physics.fit_grid(points, n_grid=n_grid, padding=padding, wall=wall).dx
    ppc = len(points) / max(occupied_cells(points, dx), 1)
    sample = points[:: max(1, len(points) // 500)]
    v_max = motion_speed(motion, np.asarray(sample, dtype=np.float64), frame_time)
    dt = physics.cfl_dt(dx, E, nu, density, v_max=v_max, safety=cfl_safety)
    substeps = max(1, math.ceil(frame_time / dt))
    budget = Budget(control_grid, count, n_grid, ppc, substeps, v_max)
    log.info("budget=auto: control_grid=%s (%d particles), n_grid=%d (%.1f particles/cell), %d substeps "
             "(|v|max %.3g m/s)", control_grid, count, n_grid, ppc, substeps, v_max)
    return budget
