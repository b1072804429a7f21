"""``sim=mpm_warp``: differentiable MLS-MPM of the target (paper Sec. 3.1, appendix A.1) on NVIDIA Warp.

The registered simulator: it builds an immutable :class:`MPMModel` of a particle set (:meth:`MPMWarp.prepare`)
and advances a state by one frame's substeps (:meth:`MPMWarp.rollout`, differentiable in x, v, F and C through
one ``torch.autograd.Function``). It only steps: the transfer stage (:mod:`sync4d.transfer`) owns the
frame-pair loop, the initial velocities and the optimiser. Substeps follow the CFL bound
(:mod:`sync4d.sim.mpm_warp.budget`); the substep itself is :mod:`sync4d.sim.mpm_warp.solver`.

Guards: material and dt validation, the CFL bound (auto sub-stepping or :class:`SimulationUnstable`),
and a NaN/inf/off-grid check at the end of every rollout (one per frame), raised as
:class:`SimulationDiverged` naming the frame, the substep, the largest speed and what to change.
"""

from __future__ import annotations

import logging
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
import warp as wp

from sync4d.device import torch_device, warp_device
from sync4d.errors import ConfigError, InputError, SimulationDiverged
from sync4d.geometry import SEAM_BAND_OF_DIAGONAL
from sync4d.registry import register
from sync4d.sim import physics
from sync4d.sim.mpm_warp import budget
from sync4d.sim.mpm_warp.bridge import run_rollout
from sync4d.sim.mpm_warp.drive import DriveArrays, blend_weights, part_rig, substep_drive
from sync4d.sim.mpm_warp.fields import FieldSplit, field_split
from sync4d.sim.mpm_warp.model import STATUS_OK, MPMModel, WarpState, Workspace
from sync4d.sim.mpm_warp.solver import Launch, RolloutPlan
from sync4d.types import FramePose, validate_material

log = logging.getLogger(__name__)


@register("sim", "mpm_warp")
class MPMWarp:
    """Differentiable MLS-MPM simulator of the target (paper Sec. 3.1, appendix A.1) on Warp."""

    @dataclass
    class Config:
        """Simulator settings.

        Attributes:
            E: Young's modulus [Pa], > 0 (paper: 1e3..1e5).
            nu: Poisson's ratio in [0, 0.5) (paper: 0.1..0.5; 0.5 is refused, lambda would be infinite).
            density: [kg/m^3], > 0.
            n_grid: grid nodes along the object's longest padded extent; shorter axes are cropped.
            grid_padding: free space around the object on each side, as a fraction of its longest extent.
            wall_cells: thickness of the boundary walls at the grid faces [nodes].
            boundary: 'slip' (walls stop the outward velocity) or 'sticky' (walls stop all of it).
            fixed_box: [xlo, ylo, zlo, xhi, yhi, zhi] world box [m] whose grid nodes are held still, or null.
            frame_time: simulated time of one output frame, N dt [s]; null (the default) = the reference's
                frame interval 1 / fps, so that E [Pa] and the elastic waves act over real time (a shorter
                frame lets waves cross only a few centimetres and the physics has no time to act).
            substeps: substeps N per frame (the minimum when auto_substep raises it for stability).
            auto_substep: split substeps that break the CFL bound (logged) instead of raising.
            cfl_safety: CFL number aimed for, dt <= cfl_safety dx / (c + |v|max) (stable to ~0.47 measured).
            max_substeps: a run whose estimated substeps per frame exceed this is refused before it starts
                (:func:`sync4d.transfer.budget.check_cost`), naming the cause (e.g. E) and the fix.
            gravity: (3,) acceleration [m/s^2]; off for motion transfer.
            checkpoint_every: store every k-th substep state for the backward pass, which recomputes the
                other (k-1)/k substeps once (memory ~ N/k + k states of 96 bytes per particle); null picks
                the smallest k whose states fit ``checkpoint_budget_mb`` (k = 1: no recomputation).
            checkpoint_budget_mb: memory for stored states of one rollout when checkpoint_every is null [MB].
            sort_particles: order particles by grid cell inside each rollout (cache locality; no effect on
                results beyond float rounding).
            refit_grid: when particles come near the walls, re-centre and grow the grid (same dx) before
                a rollout instead of letting the walls act on them.
            drive: how the parts' driving motion acts during a frame. ``complementary`` (the default): after every
                substep each part's rigid (6-DOF, mass-weighted) deviation from its drive, interpolated to that
                substep, is removed from the particles' positions and velocities (complementary dynamics, Zhang
                et al. 2020): the parts follow their drive by construction and the material is free only in what
                the rig does not control (closing the seams). ``launch`` (the paper's form): the material starts
                each frame with the velocities it is given and flies freely through the frame.
            blend_band: with ``drive=complementary``, the width of the band either side of a seam between joined
                parts over which each particle's rig blends the two parts' motions (equal shares on the seam, its
                own part's alone at the band's edge; :func:`drive.blend_weights`), as a share of the particles'
                bounding-box diagonal; 0 = part-wise rigid. The default is the seam band the follow error leaves
                out (:data:`sync4d.geometry.SEAM_BAND_OF_DIAGONAL`): a part's core is driven by its part alone.
            cpu_threads: threads of a rollout on the CPU (each launch split into particle chunks that
                scatter into their own grids; equal to one thread up to float rounding); null = the usable
                cores, one per 8192 particles at most. Ignored on CUDA.
        """

        E: float = 3e4
        nu: float = 0.3
        density: float = 1000.0
        n_grid: int = 48
        grid_padding: float = 0.25
        wall_cells: int = 3
        boundary: Literal["slip", "sticky"] = "slip"
        fixed_box: list[float] | None = None
        frame_time: float | None = None
        substeps: int = 20
        auto_substep: bool = True
        cfl_safety: float = 0.3
        max_substeps: int = 2000
        gravity: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
        checkpoint_every: int | None = None
        checkpoint_budget_mb: float = 512.0
        sort_particles: bool = True
        refit_grid: bool = True
        drive: Literal["complementary", "launch"] = "complementary"
        blend_band: float = SEAM_BAND_OF_DIAGONAL
        cpu_threads: int | None = None

        def validate(self) -> None:
            """Raise :class:`ConfigError` naming the offending ``sim.*`` key."""
            validate_material(self.E, self.nu, self.density, where="sim")
            if not (np.isfinite(self.blend_band) and self.blend_band >= 0.0):
                raise ConfigError(f"sim.blend_band must be a finite share of the diagonal >= 0, got {self.blend_band}")
            if self.n_grid < 2 * self.wall_cells + 4:
                raise ConfigError(
                    f"sim.n_grid={self.n_grid}: needs >= {2 * self.wall_cells + 4} (2 walls of sim.wall_cells + 4)"
                )
            if self.wall_cells < 1:
                raise ConfigError(f"sim.wall_cells={self.wall_cells}: must be >= 1 to keep particles on the grid")
            if not (self.grid_padding >= 0 and math.isfinite(self.grid_padding)):
                raise ConfigError(f"sim.grid_padding={self.grid_padding}: must be >= 0 (fraction of the object size)")
            if self.boundary not in ("slip", "sticky"):
                raise ConfigError(f"sim.boundary={self.boundary!r}: must be 'slip' or 'sticky'")
            if self.fixed_box is not None:
                box = np.asarray(self.fixed_box, dtype=float)
                if box.shape != (6,) or not np.all(box[:3] <= box[3:]):
                    raise ConfigError(
                        f"sim.fixed_box={self.fixed_box}: expected [xlo, ylo, zlo, xhi, yhi, zhi] with lo <= hi"
                    )
            if self.frame_time is not None and not (self.frame_time > 0 and math.isfinite(self.frame_time)):
                raise ConfigError(f"sim.frame_time={self.frame_time}: must be > 0 s, or null for the frame interval")
            if self.substeps < 1:
                raise ConfigError(f"sim.substeps={self.substeps}: must be >= 1")
            if not (0.0 < self.cfl_safety <= 1.0):
                raise ConfigError(f"sim.cfl_safety={self.cfl_safety}: must be in (0, 1]; 0.3 is safe (stable to ~0.47)")
            if self.max_substeps < self.substeps:
                raise ConfigError(f"sim.max_substeps={self.max_substeps}: must be >= sim.substeps={self.substeps}")
            if len(self.gravity) != 3:
                raise ConfigError(f"sim.gravity={self.gravity}: expected 3 values [m/s^2]")
            if self.checkpoint_every is not None and self.checkpoint_every < 1:
                raise ConfigError(
                    f"sim.checkpoint_every={self.checkpoint_every}: must be >= 1, or null (from the budget)"
                )
            if self.cpu_threads is not None and self.cpu_threads < 1:
                raise ConfigError(f"sim.cpu_threads={self.cpu_threads}: must be >= 1, or null (the usable cores)")
            if not self.checkpoint_budget_mb > 0:
                raise ConfigError(f"sim.checkpoint_budget_mb={self.checkpoint_budget_mb}: must be > 0 MB")

    differentiable = True
    dtype = torch.float32  # Warp's kernels are single precision

    def __init__(self, config: Config, *, device: str) -> None:
        config.validate()
        self.config = config
        self.device = device
        self.wp_device = warp_device(device)
        self.torch_device = torch_device(device)
        self.workspace: Workspace | None = None
        self.pool: ThreadPoolExecutor | None = None
        self.pool_size = 0

    # -- building ---------------------------------------------------------------------------------

    def prepare(
        self,
        points: np.ndarray,
        *,
        volume: float | np.ndarray | None = None,
        weights: np.ndarray | None = None,
        part: np.ndarray | None = None,
        parent: np.ndarray | None = None,
    ) -> MPMModel:
        """Build the model of a particle set: fitted grid, masses and volumes, material.

        Args:
            points: (P, 3) particle rest positions [m].
            volume: the object's total volume [m^3] shared among particles, or (P,) per-particle volumes
                [m^3], or None to estimate the total from the points' voxel occupancy (cells of side
                max(dx, (8 bbox volume / P)^(1/3)), i.e. ~8 points per cell for a filled box).
            weights: (P,) shares of the total volume (e.g. Gaussians per control point); uniform if None.
            part: (P,) part of each particle (-1: not driven), or None: the parts the drive holds (``drive``).
            parent: (B,) the part each part is joined to (-1 for a root), or None. With ``part`` it splits the grid
                into velocity fields (:mod:`fields`): parts that touch at rest but are not parent and child get
                different fields and do not glue; joined parts in different fields are bonded at their joint.
                None: the tree is unknown and the material is one continuum, whatever the parts (one field).

        Returns:
            The immutable model.
        """
        config = self.config
        pts = check_points(points)
        grid = physics.fit_grid(pts, n_grid=config.n_grid, padding=config.grid_padding, wall=config.wall_cells)
        vols = particle_volumes(pts, grid.dx, volume, weights)
        mu, lam = physics.lame_parameters(config.E, config.nu)
        box = None if config.fixed_box is None else np.asarray(config.fixed_box, dtype=np.float64).reshape(2, 3)
        mass = config.density * vols
        rig, fields = None, None
        if part is not None:
            labels = np.asarray(part, dtype=np.int64)
            if labels.shape != (len(pts),):
                raise InputError(f"sim.prepare: part must have shape ({len(pts)},), got {labels.shape}")
            if config.drive == "complementary":
                num_parts = int(labels.max()) + 1 if len(labels) else 0
                band = config.blend_band * float(np.linalg.norm(pts.max(0) - pts.min(0)))
                blend = blend_weights(pts, labels, num_parts, band, parent)
                rig = part_rig(pts, labels, mass, num_parts, blend)
            fields = self.fields_of(pts, labels, parent, grid.dx)
        return MPMModel(
            grid=grid, rest_points=pts, mass=mass, volume=vols, E=config.E, nu=config.nu,
            density=config.density, mu=mu, lam=lam, gravity=np.asarray(config.gravity, dtype=np.float64),
            sticky=config.boundary == "sticky", fixed_box=box, device=self.wp_device, rig=rig, fields=fields,
        )  # fmt: skip

    def fields_of(self, pts: np.ndarray, part: np.ndarray, parent: np.ndarray | None, dx: float) -> FieldSplit | None:
        """The velocity fields of particles ``pts`` labelled ``part`` with the part tree ``parent`` (None: one)."""
        if parent is None or len(pts) == 0:
            return None
        tree = np.asarray(parent, dtype=np.int64).reshape(-1)
        if np.any(tree >= len(tree)) or np.any(tree < -1):
            raise InputError(f"sim.prepare: parent must hold part indices in [-1, {len(tree)}), got {tree}")
        split = field_split(pts, part, tree, dx)
        if split is not None:
            log.info("sim: %d velocity fields (parts' fields %s), %d particles bonded at joints", split.num_fields,
                     split.part_field.tolist(), int(split.bond.sum()))
        return split

    def domain(self, model: MPMModel) -> tuple[np.ndarray, np.ndarray]:
        """The simulated box [m]: the grid's first and last node, (3,) each."""
        g = model.grid
        return g.origin.copy(), g.origin + (np.asarray(g.dims) - 1) * g.dx

    def initial_state(self, model: MPMModel) -> dict[str, torch.Tensor]:
        """Rest state as float32 torch tensors: x (P,3) [m], v (P,3) zeros [m/s], F (P,3,3) identity, C zeros."""
        n = model.num_particles
        dev = self.torch_device
        return {
            "x": torch.as_tensor(model.rest_points, dtype=torch.float32, device=dev).clone(),
            "v": torch.zeros(n, 3, dtype=torch.float32, device=dev),
            "F": torch.eye(3, dtype=torch.float32, device=dev).repeat(n, 1, 1),
            "C": torch.zeros(n, 3, 3, dtype=torch.float32, device=dev),
        }

    # -- time steps ---------------------------------------------------------------------------------

    def max_stable_dt(self, model: MPMModel, v_max: float = 0.0) -> float:
        """CFL bound cfl_safety dx / (c + v_max) [s] for this model."""
        return budget.max_stable_dt(self.config, model, v_max)

    def frame_time_for(self, fps: float | None) -> float:
        """Simulated time of one frame [s]: ``sim.frame_time``, or 1 / ``fps`` when it is null."""
        return budget.frame_time_for(self.config, fps)

    def substeps_for(self, model: MPMModel, v_max: float = 0.0, *, fps: float | None = None) -> tuple[int, float]:
        """Substeps N and dt [s] for one frame that respect the CFL bound (:func:`budget.substeps_for`)."""
        return budget.substeps_for(self.config, model, v_max, fps)

    def checkpoint_interval(self, n_particles: int, substeps: int) -> int:
        """k: the backward pass stores every k-th substep state (:func:`budget.checkpoint_interval`)."""
        return budget.checkpoint_interval(self.config, n_particles, substeps)

    def threads_for(self, n_particles: int) -> int:
        """Threads a rollout of ``n_particles`` runs on (:func:`budget.threads_for`)."""
        return budget.threads_for(self.config, self.wp_device, n_particles)

    # -- rollout -----------------------------------------------------------------------------------

    def rollout(
        self,
        model: MPMModel,
        x: torch.Tensor,
        v: torch.Tensor,
        F: torch.Tensor,
        C: torch.Tensor,
        *,
        substeps: int,
        dt: float,
        frame_index: int = 0,
        pose: FramePose | None = None,
        check_cfl: bool = True,
        timers: dict[str, float] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Advance the particles ``substeps`` substeps of ``dt``; differentiable in x, v, F and C.

        Args:
            model: from :meth:`prepare`.
            x, v: (P, 3) float32 positions [m] and velocities [m/s].
            F, C: (P, 3, 3) float32 deformation gradients and APIC affine matrices [1/s].
            substeps: number of substeps N >= 1.
            dt: substep [s] > 0.
            frame_index: the output frame this rollout produces (for error messages).
            pose: the parts' poses at the start and end of the rollout: held through every substep with
                ``drive=complementary`` (when the model has parts), else unused.
            check_cfl: apply the CFL guard (auto sub-stepping or SimulationUnstable); False only for tests.
            timers: accumulate per-kernel wall time [s] (forward only, no gradients; profiling).

        Returns:
            (x, v, F, C) after N substeps, torch float32 on the input's device, carrying autograd history.

        Raises:
            SimulationUnstable: dt over the CFL bound with auto_substep off.
            SimulationDiverged: NaN/inf or a particle off the grid during the rollout.
        """
        v_max = check_rollout_input(model, x, v, F, C, substeps=substeps, dt=dt, frame_index=frame_index)
        substeps = int(substeps)
        if check_cfl:
            substeps, dt = budget.split_for_cfl(self.config, model, substeps, dt, v_max, frame_index)
        xn = x.detach().double().cpu().numpy()
        model = self.grid_for(model, xn, reach_of(model, v_max, substeps * dt), frame_index)
        order = self.particle_order(model, xn)
        perm = None if order is None else torch.as_tensor(order, device=x.device)
        if perm is not None:
            x, v, F, C = x[perm], v[perm], F[perm], C[perm]
        plan = self.plan(model, order, substeps=substeps, dt=dt, frame_index=frame_index, pose=pose)
        out = run_rollout(plan, x, v, F, C, self.check_status, timers=timers)
        if perm is not None:
            inv = torch.empty_like(perm)
            inv[perm] = torch.arange(len(perm), device=perm.device)
            out = tuple(t[inv] for t in out)  # type: ignore[assignment]
        return out

    def plan(self, model: MPMModel, order: np.ndarray | None, *, substeps: int, dt: float,
             frame_index: int, pose: FramePose | None = None) -> RolloutPlan:
        """The rollout's kernels' constants in particle ``order`` (None = as given), with the drive of ``pose``
        when the model has parts."""
        n = model.num_particles
        mass, volume = (model.mass, model.volume) if order is None else (model.mass[order], model.volume[order])
        drive = None
        if pose is not None and model.rig is not None:
            if pose.num_parts < len(model.rig.mass):
                raise InputError(f"sim.rollout: the pose has {pose.num_parts} parts, the particles' labels "
                                 f"name {len(model.rig.mass)}")
            held = substep_drive(model.rig, pose, substeps=substeps, frame_time=substeps * dt)
            drive = DriveArrays.of(model.rig, held, order, self.wp_device)
        split = model.fields
        field_id: wp.array | None = None
        bond_flag: wp.array | None = None
        if split is not None:
            fid, flag = (split.field, split.bond) if order is None else (split.field[order], split.bond[order])
            field_id = wp.array(fid.astype(np.int32), dtype=wp.int32, device=self.wp_device)
            bond_flag = wp.array(flag.astype(np.float32), dtype=float, device=self.wp_device)
        launch = Launch(
            model=model, ws=self.workspace_for(n, model.grid.dims, fields=model.num_fields, bonding=model.bonding),
            mass=wp.array(mass.astype(np.float32), dtype=float, device=self.wp_device),
            volume=wp.array(volume.astype(np.float32), dtype=float, device=self.wp_device),
            dt=float(dt), mass_eps=float(1e-9 * mass.min()), drive=drive, field_id=field_id, bond_flag=bond_flag,
        )  # fmt: skip
        return RolloutPlan(launch=launch, substeps=substeps, checkpoint_every=self.checkpoint_interval(n, substeps),
                           frame_index=frame_index)

    def grid_for(self, model: MPMModel, x: np.ndarray, reach: float, frame_index: int) -> MPMModel:
        """``model`` on a grid that holds every particle within ``reach`` [m] of where it is now:
        re-centred and grown (same dx) when ``refit_grid``, else unchanged (with a warning)."""
        lo, hi = x.min(0) - reach, x.max(0) + reach
        if model.grid.contains(lo[None]) and model.grid.contains(hi[None]):
            return model
        if not self.config.refit_grid:
            log.warning("sim: frame %d: particles may reach the grid walls (sim.refit_grid=false)", frame_index)
            return model
        longest = max(float((x.max(0) - x.min(0)).max()), model.grid.dx)
        # capped: a particle that would fly further than the object's size is a blow-up to report
        padding = min(max(self.config.grid_padding, reach / longest), max(self.config.grid_padding, 1.0))
        grid = physics.fit_grid(x, n_grid=self.config.n_grid, padding=padding, wall=self.config.wall_cells,
                                dx=model.grid.dx, anchor=model.grid.origin)
        log.debug("sim: frame %d: grid re-fitted to %s nodes", frame_index, grid.dims)
        return model.with_grid(grid)

    def particle_order(self, model: MPMModel, x: np.ndarray) -> np.ndarray | None:
        """The particles sorted by grid cell (cache locality), or None when ``sort_particles`` is off."""
        if not self.config.sort_particles or model.num_particles < 2:
            return None
        g = model.grid
        cell = np.clip(np.floor((x - g.origin) / g.dx).astype(np.int64), 0, np.asarray(g.dims) - 1)
        key = (cell[:, 0] * g.dims[1] + cell[:, 1]) * g.dims[2] + cell[:, 2]
        return np.argsort(key, kind="stable")

    def grid_totals(
        self, model: MPMModel, x: torch.Tensor, v: torch.Tensor, F: torch.Tensor, C: torch.Tensor, *, dt: float
    ) -> tuple[float, np.ndarray]:
        """Total mass [kg] and momentum [kg m/s] on the grid after one P2G of this state (diagnostics).

        MLS-MPM's P2G conserves both exactly (partition of unity, zero first moment of the weights), so
        these equal sum m_p and sum m_p v_p up to float rounding.
        """
        launch = self.plan(model, None, substeps=1, dt=dt, frame_index=0).launch
        ws = launch.ws
        ws.ping.load(x, v, F, C)
        ws.run(lambda t: launch.p2g(ws.ping, 0, t))
        g = ws.grids.numpy().astype(np.float64).reshape(-1, 4).sum(0)
        return float(g[3]), g[:3]

    def workspace_for(self, n: int, dims: tuple[int, int, int], *, fields: int = 1, bonding: bool = False) -> Workspace:
        """The scratch of a rollout of ``n`` particles on ``dims`` nodes with ``fields`` velocity fields (bonded at
        joints with ``bonding``), reused while these stay the same."""
        ws = self.workspace
        threads = self.threads_for(n)
        same = ws is not None and ws.n == n and ws.dims == tuple(dims) and ws.threads == threads
        if not same or ws is None or ws.fields != fields or ws.bonding != bonding:
            if threads > 1 and (self.pool is None or self.pool_size != threads - 1):
                if self.pool is not None:
                    self.pool.shutdown(wait=True)
                self.pool = ThreadPoolExecutor(max_workers=threads - 1, thread_name_prefix="sync4d-mpm")
                self.pool_size = threads - 1
            ws = Workspace(n, tuple(dims), self.wp_device, threads, self.pool,  # type: ignore[arg-type]
                           fields=fields, bonding=bonding)
            self.workspace = ws
        return ws

    def check_status(self, plan: RolloutPlan, final: WarpState) -> None:
        """Raise SimulationDiverged if any substep recorded a NaN/inf or an off-grid particle."""
        first = plan.launch.ws.status_value()
        if first == STATUS_OK:
            return
        speed = np.linalg.norm(final.v.numpy(), axis=1)
        finite = np.isfinite(speed)
        vmax = float(speed[finite].max()) if finite.any() else float("nan")
        raise SimulationDiverged(
            f"frame {plan.frame_index}, substep {first} of {plan.substeps}: particles left the grid "
            f"or turned NaN/inf (largest finite speed {vmax:.3g} m/s, {int((~finite).sum())} non-finite; "
            f"dt={plan.launch.dt:.3g} s, CFL bound {self.max_stable_dt(plan.launch.model, 0.0):.3g} s at rest); "
            "lower dt or sim.cfl_safety, lower the initial velocities, or raise sim.grid_padding"
        )


def check_points(points: np.ndarray) -> np.ndarray:
    """``points`` as a finite (P, 3) float64 array with P > 0, else :class:`InputError`."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise InputError(f"sim.prepare: points must have shape (P, 3) with P > 0, got {pts.shape}")
    if not np.isfinite(pts).all():
        raise InputError("sim.prepare: points contain NaN/inf")
    return pts


def particle_volumes(pts: np.ndarray, dx: float, volume: float | np.ndarray | None,
                     weights: np.ndarray | None) -> np.ndarray:
    """(P,) particle volumes [m^3]: given per particle, a total shared by ``weights``, or a total estimated
    from the points' voxel occupancy (cells of side max(dx, (8 bbox volume / P)^(1/3)))."""
    n = len(pts)
    if volume is None:
        box = np.prod(np.maximum(pts.max(0) - pts.min(0), dx))
        cell = max(dx, (8.0 * box / n) ** (1.0 / 3.0))
        return physics.particle_volumes(n, total_volume=physics.voxel_volume(pts, cell), weights=weights)
    if np.ndim(volume) == 0:
        return physics.particle_volumes(n, total_volume=float(volume), weights=weights)
    vols = np.asarray(volume, dtype=np.float64)
    if vols.shape != (n,) or not np.all(vols > 0) or not np.isfinite(vols).all():
        raise InputError(f"sim.prepare: per-particle volumes must be ({n},) and > 0, got {vols.shape}")
    return vols


def check_rollout_input(model: MPMModel, x: torch.Tensor, v: torch.Tensor, F: torch.Tensor, C: torch.Tensor, *,
                        substeps: int, dt: float, frame_index: int) -> float:
    """Check shapes, dt, substeps and finiteness of a rollout's input; returns the largest speed [m/s]."""
    n = model.num_particles
    for name, t, shape in (("x", x, (n, 3)), ("v", v, (n, 3)), ("F", F, (n, 3, 3)), ("C", C, (n, 3, 3))):
        if tuple(t.shape) != shape:
            raise InputError(f"sim.rollout: {name} must have shape {shape}, got {tuple(t.shape)}")
    if not (dt > 0 and math.isfinite(dt)):
        raise ConfigError(f"sim.rollout: dt={dt} must be > 0 s")
    if int(substeps) < 1:
        raise ConfigError(f"sim.rollout: substeps={substeps} must be >= 1")
    with torch.no_grad():
        if not all(bool(torch.isfinite(t).all()) for t in (x, v, F, C)):
            raise SimulationDiverged(
                f"frame {frame_index}: the rollout's input state holds NaN/inf; check the initial velocities"
            )
        return float(v.norm(dim=1).max()) if n else 0.0


def reach_of(model: MPMModel, v_max: float, horizon: float) -> float:
    """How far [m] a particle can travel in ``horizon`` [s] at ``v_max`` under gravity, plus 2 cells."""
    return v_max * horizon + 0.5 * float(np.linalg.norm(model.gravity)) * horizon**2 + 2.0 * model.grid.dx
