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

The cost of a run is known before it starts (:func:`estimate_cost`, the same CFL model ``budget=auto``
uses): substeps per frame, particles, grid nodes, seconds per frame and peak memory, from the scene and
the config. :func:`check_cost` refuses a run whose substeps exceed ``sim.max_substeps``, naming the
cause (the stiffness E, the motion's speed, or the cell size) and the fix, in milliseconds rather than
after hours of sub-stepping (E = 1e12 needs ~10^5 substeps per frame).

Time model (fitted to ``benchmarks/mpm.py`` on this machine, Warp 1.19 CPU, one core per launch): a
forward substep costs ``PARTICLE_SUBSTEP_S`` per particle plus ``NODE_SUBSTEP_S`` per grid node; an
optimisation iteration (forward + backward) ``BACKWARD_FACTOR`` times a forward plus the velocity
field's own cost (``FIELD_ITERATION_S`` + ``FIELD_PARTICLE_S`` per particle). The velocity field's
``iterations`` is an upper bound (early stopping usually ends sooner), so the estimate is an upper bound
too; ``benchmarks/scale.py`` prints it beside the measured time.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from sync4d.errors import ConfigError
from sync4d.interfaces import GridSimulatorConfig
from sync4d.sim import physics
from sync4d.sim.mpm_warp import MPMWarp
from sync4d.sim.control import make_control_points
from sync4d.transfer.config import TransferConfig
from sync4d.types import DrivingMotion, TargetGaussians

log = logging.getLogger(__name__)

#: Forward cost of one substep per particle [s] and per grid node [s] (10k-50k particles, 32^3-64^3).
PARTICLE_SUBSTEP_S = 2.1e-7
NODE_SUBSTEP_S = 1.0e-8
#: Forward + backward over forward alone (3.5 measured at 10k and 50k particles).
BACKWARD_FACTOR = 3.5
#: The velocity field's share of one optimisation iteration (triplane + MLP forward and backward, its
#: total-variation term, Adam): a fixed part [s] and a part per particle [s]. CPU seconds measured in the
#: transfer itself (``benchmarks/scale.py``: 0.5 s per iteration at 1.7 k particles, 0.77 s at 5.9 k,
#: where the MPM kernels take 0.04-0.1 s): at these sizes the field, not the simulator, costs most.
FIELD_ITERATION_S = 0.4
FIELD_PARTICLE_S = 6.0e-5
#: Bytes of one stored particle state (x, v, C, F in float32) and of one grid node with its adjoint.
STATE_BYTES = 96
NODE_BYTES = 2 * (16 + 12)
#: Resident memory of the process before any scene is loaded (torch, Warp, Hydra) [MB].
BASE_MB = 450.0
#: While simulating: the simulator's and the transfer's working memory (Warp arrays, torch autograd of
#: a rollout, the velocity field) [MB], and the bytes per Gaussian of the frame being carried and written
#: (float64 positions, F Sigma F^T and its eigendecomposition, rotated SH, the .ply table: one frame in
#: flight, ``outputs.FrameWriter``). Fitted to ``train.py``'s peak while simulating in
#: ``benchmarks/scale.py`` at 50 k and 500 k Gaussians (828 MB and 1,436 MB; docs/results/scale.md).
SIM_WORKING_MB = 260.0
CARRY_BYTES = 1400
#: Headroom the transfer gives the reference speed for the optimised delta velocities (sync4d.transfer).
SPEED_HEADROOM = 2.0


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
    """Pick control points, grid resolution and substeps for a scene (see the module docstring).

    The substeps come from :func:`estimate_cost`, the model that checks every run's cost.
    """
    control_grid, count = choose_control_grid(np.asarray(means, dtype=np.float64), target_particles)
    points = simulated_points(means, control_grid)
    n_grid = grid_for_cells(cells_across, padding=padding, wall=wall)
    dx = physics.fit_grid(points, n_grid=n_grid, padding=padding, wall=wall).dx
    ppc = len(points) / max(occupied_cells(points, dx), 1)
    settings = SimSettings(E=E, nu=nu, density=density, n_grid=n_grid, grid_padding=padding, wall_cells=wall,
                           frame_time=frame_time, substeps=1, cfl_safety=cfl_safety, control_grid=control_grid)
    cost = estimate_cost(means, motion, settings, frames=1, iterations=0)
    budget = Budget(control_grid, count, n_grid, ppc, cost.substeps, cost.v_max)
    log.info("budget=auto: control_grid=%s (%d particles), n_grid=%d (%.1f particles/cell), %d substeps "
             "(|v|max %.3g m/s)", control_grid, count, n_grid, ppc, cost.substeps, cost.v_max)
    return budget


@dataclass(frozen=True)
class SimSettings:
    """The simulator settings the cost model reads (the fields of ``MPMWarp.Config`` of the same names)."""

    E: float
    nu: float
    density: float
    n_grid: int
    grid_padding: float
    wall_cells: int
    frame_time: float | None  # null: the reference's frame interval 1 / fps
    substeps: int
    cfl_safety: float
    control_grid: int | None
    checkpoint_budget_mb: float = MPMWarp.Config.checkpoint_budget_mb  # its one owner: the simulator's Config

    @staticmethod
    def fields() -> tuple[str, ...]:
        return tuple(f for f in SimSettings.__dataclass_fields__ if f != "control_grid")

    @staticmethod
    def of(config: object, control_grid: int | None) -> SimSettings:
        """The settings of a simulator config holding these fields (e.g. ``MPMWarp.Config``) with the
        transfer's control lattice."""
        return SimSettings(**{f: getattr(config, f) for f in SimSettings.fields()}, control_grid=control_grid)


@dataclass(frozen=True)
class CostEstimate:
    """What a simulation will cost, estimated before it starts (logged; see the module docstring).

    Attributes:
        particles: simulated particles P (control points or Gaussians).
        gaussians: Gaussians carried N.
        grid_dims: (3,) grid nodes per axis.
        dx: grid cell [m].
        wave_speed: p-wave speed c = sqrt((lambda + 2 mu) / rho) [m/s].
        v_max: largest particle speed expected [m/s] (reference motion with the transfer's headroom).
        substeps: substeps per frame N (CFL bound, at least ``sim.substeps``).
        dt: substep [s].
        iterations: optimisation iterations per frame (upper bound).
        seconds_per_frame: estimated wall time of one frame [s] (upper bound over early stopping).
        total_seconds: for all frames [s].
        peak_memory_mb: estimated peak resident memory [MB].
        cause: what sets the substeps: ``E`` (the stiffness), ``motion`` (the particle speed) or
            ``substeps`` (the configured minimum).
    """

    particles: int
    gaussians: int
    grid_dims: tuple[int, int, int]
    dx: float
    wave_speed: float
    v_max: float
    substeps: int
    dt: float
    iterations: int
    seconds_per_frame: float
    total_seconds: float
    peak_memory_mb: float
    cause: str

    def summary(self) -> str:
        """One log line."""
        return (f"cost estimate: {self.substeps} substeps/frame of dt={self.dt:.3g} s (set by {self.cause}; "
                f"c={self.wave_speed:.3g} m/s, |v|max={self.v_max:.3g} m/s, dx={self.dx:.3g} m), {self.particles} "
                f"particles for {self.gaussians} Gaussians, grid {'x'.join(map(str, self.grid_dims))}, "
                f"<= {self.seconds_per_frame:.3g} s/frame ({self.total_seconds / 60:.3g} min in all), "
                f"peak ~{self.peak_memory_mb:.0f} MB")


def simulated_points(means: np.ndarray, control_grid: int | None) -> np.ndarray:
    """(P, 3) what the simulator will simulate: control points of ``control_grid``, or the means [m]."""
    pts = np.asarray(means, dtype=np.float64)
    return pts if control_grid is None else make_control_points(pts, control_grid)[0]


def estimate_cost(
    means: np.ndarray,
    motion: DrivingMotion,
    sim: SimSettings,
    *,
    frames: int,
    iterations: int,
    sh_coeffs: int = 1,
) -> CostEstimate:
    """Estimate substeps, time and memory of a ``sim=mpm_warp`` run from the scene and the config.

    Args:
        means: (N, 3) Gaussian centres [m] (after floater removal).
        motion: the driving motion in the target's frame (its speed enters the CFL bound).
        sim: the simulator's settings (``SimSettings.of(MPMWarp.Config)``).
        frames: output frames T.
        iterations: the velocity field's optimisation iterations per frame (0 for none).
        sh_coeffs: SH coefficients per colour channel K (memory of the Gaussians).

    Returns:
        The estimate (no simulation is run; costs milliseconds to a second for millions of Gaussians).
    """
    n = len(means)
    points = simulated_points(means, sim.control_grid)
    p = len(points)
    grid = physics.fit_grid(points, n_grid=sim.n_grid, padding=sim.grid_padding, wall=sim.wall_cells)
    nodes = int(np.prod(grid.dims))
    frame_time = physics.frame_time(sim.frame_time, motion.fps)
    sample = points[:: max(1, p // 500)]
    v_max = SPEED_HEADROOM * motion_speed(motion, sample, frame_time)
    mu, lam = physics.lame_parameters(sim.E, sim.nu)
    c = math.sqrt((lam + 2.0 * mu) / sim.density)
    dt_max = physics.cfl_dt(grid.dx, sim.E, sim.nu, sim.density, v_max=v_max, safety=sim.cfl_safety)
    substeps, dt = physics.substeps_for(frame_time, dt_max, min_substeps=sim.substeps)
    cause = "substeps" if substeps == sim.substeps else ("E" if c >= v_max else "motion")
    forward = substeps * (PARTICLE_SUBSTEP_S * p + NODE_SUBSTEP_S * nodes)
    per_iteration = BACKWARD_FACTOR * forward + FIELD_ITERATION_S + FIELD_PARTICLE_S * p
    per_frame = forward + max(int(iterations), 0) * per_iteration
    stored = min(STATE_BYTES * p * (substeps + 1), sim.checkpoint_budget_mb * 2**20 + 2 * STATE_BYTES * p)
    gaussian_bytes = 4 * (3 + 4 + 3 + 1 + 3 * sh_coeffs)
    # The rest Gaussians, one frame being carried and written, and every frame's simulated x and F in
    # float64, held twice (the transfer's trajectory and the run writer's): per control point, not per
    # Gaussian, when the run has control points (P = N without).
    memory = ((BASE_MB + SIM_WORKING_MB) * 2**20 + stored + NODE_BYTES * nodes + (gaussian_bytes + CARRY_BYTES) * n
              + 2 * frames * p * 8 * (3 + 9))
    return CostEstimate(
        particles=p, gaussians=n, grid_dims=(int(grid.dims[0]), int(grid.dims[1]), int(grid.dims[2])), dx=float(grid.dx), wave_speed=c,
        v_max=float(v_max), substeps=int(substeps), dt=float(dt), iterations=int(iterations),
        seconds_per_frame=float(per_frame), total_seconds=float(per_frame * max(frames - 1, 0)),
        peak_memory_mb=float(memory / 2**20), cause=cause,
    )  # fmt: skip


def check_cost(estimate: CostEstimate, *, max_substeps: int, E: float) -> None:
    """Refuse a run whose estimated substeps per frame exceed ``max_substeps`` (one line: cause and fix).

    Raises:
        ConfigError: naming the cause (``sim.E``, the motion's speed or the grid) and what to change.
    """
    if estimate.substeps <= max_substeps:
        return
    e = estimate
    if e.cause == "E":
        # c scales as sqrt(E): the E that fits max_substeps at this dx and speed
        fits = E * ((e.substeps / max_substeps) ** -2)
        cause = (f"sim.E={E:g} Pa: its p-wave speed c={e.wave_speed:.3g} m/s allows dt <= {e.dt:.3g} s at "
                 f"dx={e.dx:.3g} m")
        fix = f"lower sim.E (about {fits:.2g} Pa or less fits), coarsen the grid (sim.n_grid) or shorten sim.frame_time"
    elif e.cause == "motion":
        cause = f"the reference motion's speed |v|max={e.v_max:.3g} m/s allows dt <= {e.dt:.3g} s at dx={e.dx:.3g} m"
        fix = "shorten sim.frame_time or coarsen the grid (sim.n_grid)"
    else:
        cause = f"sim.substeps={e.substeps}"
        fix = "lower sim.substeps"
    raise ConfigError(
        f"{cause}: {e.substeps} substeps per frame exceed sim.max_substeps={max_substeps} (estimated "
        f"{e.seconds_per_frame:.3g} s per frame, {e.total_seconds / 3600:.3g} h for the run); {fix}, "
        "or raise sim.max_substeps to run it anyway"
    )


def check_run_cost(
    sim_config: object, transfer: TransferConfig, trainable: bool, target: TargetGaussians, motion: DrivingMotion, *,
    frames: int,
) -> CostEstimate | None:
    """Estimate and log a run's cost before it simulates; refuse it when it exceeds ``sim.max_substeps``.

    Args:
        sim_config: the simulator's typed Config; only grid simulators (with the :class:`SimSettings` fields
            and ``max_substeps``) have a cost model.
        transfer: the transfer's options (control lattice, optimisation iterations per frame).
        trainable: the velocity field trains (its iterations count).
        target: the Gaussians (after floater removal); motion: the driving motion; frames: T.

    Returns:
        The estimate, or None for simulators without a cost model.

    Raises:
        ConfigError: the estimate exceeds ``sim.max_substeps`` (see :func:`check_cost`).
    """
    if not isinstance(sim_config, GridSimulatorConfig):
        return None
    iterations = transfer.iterations if trainable else 0
    estimate = estimate_cost(target.means, motion, SimSettings.of(sim_config, transfer.control_grid),
                             frames=frames, iterations=iterations, sh_coeffs=target.sh.shape[1])
    log.info("%s", estimate.summary())
    check_cost(estimate, max_substeps=int(sim_config.max_substeps), E=float(sim_config.E))
    return estimate
