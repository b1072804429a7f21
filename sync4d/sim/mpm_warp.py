"""Differentiable MLS-MPM in NVIDIA Warp (``sim=mpm_warp``): model, substep, checkpointed rollout.

Shape (after Newton): an immutable :class:`MPMModel` (grid, particle masses and volumes, material,
gravity, boundary) and :func:`step` ``(model, state_in, state_out, dt)``, which never writes its input.
:meth:`MPMWarp.rollout` runs ``substeps`` substeps as ONE ``torch.autograd.Function``:

* forward: ping-pong between two preallocated states (no per-substep allocation); when gradients are
  wanted it stores every ``checkpoint_every``-th particle state (x, v, C, F: 96 bytes per particle).
* backward: per segment, the stored state is advanced again to recover the segment's particle states;
  then for each substep in reverse the grid is rebuilt (P2G + grid update) and Warp's generated adjoint
  kernels of G2P, grid update and P2G are launched, exactly what ``wp.Tape.backward`` would launch for
  that substep, but without replaying G2P's forward and with one reused grid (never a copy per substep).

Memory of a forward+backward rollout is therefore O(P (substeps / k + k)) + one grid with its adjoint.

Both cores (CPU only): Warp's CPU backend runs a launch on one thread, and its ctypes call releases the
GIL. With ``cpu_threads`` T > 1 every particle kernel is launched as T contiguous chunks of the
(cell-sorted) particles from T Python threads, each P2G and each G2P adjoint scattering into its own
grid (the grid update and its adjoint sum the T grids, split into T slabs of nodes), so no two threads
ever write the same memory. Results equal the one-thread path up to float rounding (the node sums are
added in another order) and do not depend on thread timing. On CUDA nothing is split.

Guards: material and dt validation, the CFL bound (auto sub-stepping or :class:`SimulationUnstable`),
and a NaN/inf/off-grid check at the end of every rollout (one per frame), raised as
:class:`SimulationDiverged` naming the frame, the substep, the largest speed and what to change.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import warp as wp

from sync4d.device import torch_device, warp_device
from sync4d.errors import ConfigError, InputError, SimulationDiverged, SimulationUnstable
from sync4d.registry import register
from sync4d.sim import _kernels as K
from sync4d.sim import physics
from sync4d.sim.control import make_control_points
from sync4d.types import validate_material

log = logging.getLogger(__name__)

_STATUS_OK = 2147483647
# auto cpu_threads: a thread gets at least this many particles. Each extra chunk adds Python launch
# overhead (measured: splitting 9.4k particles on 32^3 in two costs 20-28 % more CPU per substep), which
# only larger chunks amortise (docs/scale.md, "Both cores for the simulator").
_MIN_PARTICLES_PER_THREAD = 8192


# ----------------------------------------------------------------------------------------------------
# Model and state
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MPMModel:
    """Everything a substep needs that does not change during a rollout.

    Attributes:
        grid: the background grid (origin [m], cell size dx [m], nodes per axis, wall thickness).
        rest_points: (P, 3) particle positions given to :meth:`MPMWarp.prepare` [m].
        mass: (P,) particle masses m_p = rho V_p^0 [kg].
        volume: (P,) initial particle volumes V_p^0 [m^3].
        E: Young's modulus [Pa].
        nu: Poisson's ratio.
        density: [kg/m^3].
        mu: shear modulus [Pa].
        lam: first Lame parameter [Pa].
        gravity: (3,) [m/s^2].
        sticky: walls stop every velocity component (True) or only the outward one (False, slip).
        fixed_box: (2, 3) world box [m] whose grid nodes are held still, or None.
        device: Warp device name.
    """

    grid: physics.GridSpec
    rest_points: np.ndarray
    mass: np.ndarray
    volume: np.ndarray
    E: float
    nu: float
    density: float
    mu: float
    lam: float
    gravity: np.ndarray
    sticky: bool
    fixed_box: np.ndarray | None
    device: str

    @property
    def num_particles(self) -> int:
        return int(self.mass.shape[0])

    @property
    def wave_speed(self) -> float:
        """p-wave speed sqrt((lam + 2 mu) / rho) [m/s]."""
        return math.sqrt((self.lam + 2.0 * self.mu) / self.density)

    def with_grid(self, grid: physics.GridSpec) -> MPMModel:
        """The same particles and material on another grid."""
        return dataclasses.replace(self, grid=grid)


@dataclass
class WarpState:
    """Particle state as Warp arrays, (P,) each: x [m], v [m/s] (vec3); C [1/s], F (mat33)."""

    x: wp.array
    v: wp.array
    C: wp.array
    F: wp.array
    _parts: dict = field(default_factory=dict, repr=False, compare=False)

    def parts(self, bounds: tuple[tuple[int, int], ...]) -> list[WarpState]:
        """The state as views of the particle ranges ``bounds`` (itself for one range; views are cached)."""
        if len(bounds) == 1:
            return [self]
        views = self._parts.get(bounds)
        if views is None:
            views = [WarpState(*(a[lo:hi] for a in self.arrays())) for lo, hi in bounds]
            self._parts[bounds] = views
        return views

    @staticmethod
    def empty(n: int, device: str) -> WarpState:
        return WarpState(
            wp.empty(n, dtype=wp.vec3, device=device),
            wp.empty(n, dtype=wp.vec3, device=device),
            wp.empty(n, dtype=wp.mat33, device=device),
            wp.empty(n, dtype=wp.mat33, device=device),
        )

    def zero_(self) -> None:
        for a in self.arrays():
            a.zero_()

    def arrays(self) -> tuple[wp.array, wp.array, wp.array, wp.array]:
        return self.x, self.v, self.C, self.F

    def assign(self, other: WarpState) -> None:
        for dst, src in zip(self.arrays(), other.arrays()):
            wp.copy(dst, src)


def _split(n: int, parts: int) -> tuple[tuple[int, int], ...]:
    """``parts`` contiguous ranges [lo, hi) covering 0..n, as equal as possible."""
    edges = [n * t // parts for t in range(parts + 1)]
    return tuple((edges[t], edges[t + 1]) for t in range(parts))


class _Workspace:
    """Preallocated scratch of one (particle count, grid shape, device, threads): reused by every rollout.

    With ``threads`` T > 1 (CPU), thread t handles particles ``bounds[t]`` and node slab ``slabs[t]``,
    and owns P2G grid ``grids[t]``, G2P-adjoint grid ``adj_grid_v[t]`` and failure record ``status_of[t]``.
    Not thread-safe: one simulator object runs one rollout (forward or backward) at a time.
    """

    def __init__(
        self, n: int, dims: tuple[int, int, int], device: str, threads: int = 1, pool: ThreadPoolExecutor | None = None
    ) -> None:
        self.n, self.dims, self.device, self.threads, self.pool = n, dims, device, threads, pool
        if threads > 1 and pool is None:
            raise ValueError("_Workspace: a thread pool is needed for threads > 1")
        self.bounds = _split(n, threads)
        self.slabs = _split(dims[0], threads)
        self.grids = wp.zeros((threads, *dims), dtype=wp.vec4, device=device)
        self.grid_of = [self.grids[t] for t in range(threads)]
        self.grid = self.grid_of[0]
        self.grid_v = wp.zeros(dims, dtype=wp.vec3, device=device)
        self.status_all = wp.full(threads, _STATUS_OK, dtype=wp.int32, device=device)
        self.status_of = [self.status_all[t : t + 1] for t in range(threads)]
        self.status = self.status_of[0]
        # polar rotations of the substep being reversed: written by the P2G that rebuilds its grid,
        # read by the P2G adjoint (one substep at a time, so one buffer)
        self.rotation = wp.zeros(n, dtype=wp.mat33, device=device)
        self.rotation_of = [self.rotation[lo:hi] for lo, hi in self.bounds] if threads > 1 else [self.rotation]
        self.ping = WarpState.empty(n, device)
        self.pong = WarpState.empty(n, device)
        # backward-only buffers, allocated on first use
        self.adj_grid: wp.array | None = None
        self.adj_grid_v: wp.array | None = None  # (T, nx, ny, nz)
        self.adj_grid_v_of: list[wp.array] = []
        self.adj_a: WarpState | None = None
        self.adj_b: WarpState | None = None

        self.segment: list[WarpState] = []

    def ensure_backward(self, k: int) -> None:
        if self.adj_grid is None:
            self.adj_grid = wp.zeros(self.dims, dtype=wp.vec4, device=self.device)
            self.adj_grid_v = wp.zeros((self.threads, *self.dims), dtype=wp.vec3, device=self.device)
            self.adj_grid_v_of = [self.adj_grid_v[t] for t in range(self.threads)]
            self.adj_a = WarpState.empty(self.n, self.device)
            self.adj_b = WarpState.empty(self.n, self.device)
        while len(self.segment) < k:
            self.segment.append(WarpState.empty(self.n, self.device))

    def status_value(self) -> int:
        """The earliest substep any thread recorded a failure at (``_STATUS_OK`` when none did)."""
        return int(self.status_all.numpy().min())

    def run(self, task: Callable[[int], None]) -> None:
        """``task(t)`` for every thread t: t = 0 here, the others on the pool; returns when all are done."""
        if self.threads == 1:
            task(0)
            return
        assert self.pool is not None
        futures = [self.pool.submit(task, t) for t in range(1, self.threads)]
        try:
            task(0)
        finally:
            for f in futures:
                f.result()


@dataclass
class _Launch:
    """Per-rollout constants of the three kernels (model in sorted particle order, workspace)."""

    model: MPMModel
    ws: _Workspace
    mass: wp.array
    volume: wp.array
    dt: float
    mass_eps: float
    _mass_of: list[wp.array] = field(default_factory=list, repr=False)
    _volume_of: list[wp.array] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        if self.ws.threads > 1:
            self._mass_of = [self.mass[lo:hi] for lo, hi in self.ws.bounds]
            self._volume_of = [self.volume[lo:hi] for lo, hi in self.ws.bounds]
        else:
            self._mass_of, self._volume_of = [self.mass], [self.volume]

    def p2g_args(
        self, s: WarpState, substep: int, *, store_rotation: bool = False, t: int = 0
    ) -> tuple[list[Any], list[Any]]:
        """P2G of thread t's particles (``s`` is that thread's view of the state) into its own grid."""
        g = self.model.grid
        inputs = [
            s.x, s.v, s.C, s.F, self._mass_of[t], self._volume_of[t],
            float(self.model.mu), float(self.model.lam),
            wp.vec3(*g.origin), float(g.dx), float(1.0 / g.dx), float(self.dt),
            int(g.dims[0]), int(g.dims[1]), int(g.dims[2]), int(substep), int(store_rotation),
        ]  # fmt: skip
        return inputs, [self.ws.grid_of[t], self.ws.status_of[t], self.ws.rotation_of[t]]

    def grid_args(self, t: int = 0) -> tuple[list[Any], list[Any]]:
        """Grid update of thread t's slab of nodes (the launch dimension is :meth:`slab_dim`)."""
        m, g = self.model, self.model.grid
        box = m.fixed_box if m.fixed_box is not None else np.zeros((2, 3))
        inputs = [
            self.ws.grids, int(self.ws.slabs[t][0]), wp.vec3(*m.gravity), float(self.dt), float(self.mass_eps), int(g.wall),
            int(m.sticky), wp.vec3(*g.origin), float(g.dx), wp.vec3(*box[0]), wp.vec3(*box[1]),
            int(m.fixed_box is not None),
        ]  # fmt: skip
        return inputs, [self.ws.grid_v]

    def slab_dim(self, t: int) -> tuple[int, int, int]:
        lo, hi = self.ws.slabs[t]
        return (hi - lo, self.ws.dims[1], self.ws.dims[2])

    def g2p_args(self, s: WarpState, out: WarpState, substep: int, t: int = 0) -> tuple[list[Any], list[Any]]:
        g = self.model.grid
        inputs = [s.x, s.F, self.ws.grid_v, wp.vec3(*g.origin), float(1.0 / g.dx), float(self.dt), int(substep)]
        return inputs, [out.x, out.v, out.C, out.F, self.ws.status_of[t]]

    def count(self, t: int) -> int:
        lo, hi = self.ws.bounds[t]
        return hi - lo

    def p2g(self, s: WarpState, substep: int, t: int, *, store_rotation: bool = False) -> None:
        """Zero thread t's grid and scatter its particles (``s`` the whole state) into it."""
        ws = self.ws
        ws.grid_of[t].zero_()
        i, o = self.p2g_args(s.parts(ws.bounds)[t], substep, store_rotation=store_rotation, t=t)
        wp.launch(K.p2g, dim=self.count(t), inputs=i, outputs=o, device=ws.device)

    def grid_update(self, t: int) -> None:
        i, o = self.grid_args(t)
        wp.launch(K.grid_update, dim=self.slab_dim(t), inputs=i, outputs=o, device=self.ws.device)

    def g2p(self, s: WarpState, out: WarpState, substep: int, t: int) -> None:
        ws = self.ws
        i, o = self.g2p_args(s.parts(ws.bounds)[t], out.parts(ws.bounds)[t], substep, t)
        wp.launch(K.g2p, dim=self.count(t), inputs=i, outputs=o, device=ws.device)


def step(
    launch: _Launch,
    state_in: WarpState,
    state_out: WarpState,
    substep: int,
    *,
    p2g_done: bool = False,
    prefetch: bool = False,
    prefetch_rotation: bool = False,
    timers: dict | None = None,
) -> None:
    """One MLS-MPM substep ``state_in -> state_out`` (``state_in`` is only read).

    Args:
        launch: model, workspace, dt [s] of this rollout.
        state_in: particle state at the start of the substep.
        state_out: receives the state at the end of the substep (must not alias ``state_in``).
        substep: global substep index (recorded if a particle leaves the grid or turns non-finite).
        p2g_done: the grids already hold this substep's P2G (a previous call's ``prefetch``).
        prefetch: also run the next substep's P2G of ``state_out`` (each thread right after its own G2P,
            whose chunk it reads: one hand-over between threads fewer per substep).
        prefetch_rotation: the prefetched P2G stores the polar rotations (for the backward pass).
        timers: when given, accumulates wall time [s] per kernel under 'p2g', 'grid', 'g2p' (synchronises
            after each launch, so only for profiling; no prefetching then).
    """
    ws, dev = launch.ws, launch.ws.device
    if timers is not None:
        import time

        wp.synchronize_device(dev)
        t0 = time.perf_counter()
        p2g_done = prefetch = False
    if not p2g_done:
        ws.run(lambda t: launch.p2g(state_in, substep, t))
    if timers is not None:
        wp.synchronize_device(dev)
        t1 = time.perf_counter()
    ws.run(launch.grid_update)
    if timers is not None:
        wp.synchronize_device(dev)
        t2 = time.perf_counter()

    def g2p(t: int) -> None:
        launch.g2p(state_in, state_out, substep, t)
        if prefetch:
            launch.p2g(state_out, substep + 1, t, store_rotation=prefetch_rotation)

    ws.run(g2p)
    if timers is not None:
        wp.synchronize_device(dev)
        t3 = time.perf_counter()
        timers["p2g"] = timers.get("p2g", 0.0) + (t1 - t0)
        timers["grid"] = timers.get("grid", 0.0) + (t2 - t1)
        timers["g2p"] = timers.get("g2p", 0.0) + (t3 - t2)


def _step_adjoint(
    launch: _Launch,
    s: WarpState,
    adj_out: WarpState,
    adj_in: WarpState,
    substep: int,
    *,
    p2g_done: bool = False,
    prefetch: WarpState | None = None,
) -> None:
    """Reverse one substep: given dL/d(state_out) in ``adj_out``, write dL/d(state_in) into ``adj_in``.

    ``p2g_done``: the grids and rotations already hold this substep's P2G of ``s``; ``prefetch``: the
    state of the substep reversed next, whose P2G (with rotations) each thread runs right after its P2G
    adjoint.

    Rebuilds the substep's grid from ``s`` (P2G + grid update), then runs the adjoints in reverse order:
    G2P, grid update, and P2G fused with the fixed-corotated stress, all by hand-written kernels (checked
    against finite differences and against Warp's generated adjoints in the tests; the generated ones
    were 3-6x slower). The grid mass is differentiated like every other input. No buffer needs zeroing
    except the scattered node-velocity adjoint.
    """
    ws, dev = launch.ws, launch.ws.device
    assert ws.adj_grid is not None and ws.adj_grid_v is not None
    g = launch.model.grid
    # forward part: the grid this substep saw
    if not p2g_done:
        ws.run(lambda t: launch.p2g(s, substep, t, store_rotation=True))
    ws.run(launch.grid_update)

    origin, inv_dx, dt = wp.vec3(*g.origin), float(1.0 / g.dx), float(launch.dt)
    sp, op, ip = s.parts(ws.bounds), adj_out.parts(ws.bounds), adj_in.parts(ws.bounds)

    def g2p_adjoint(t: int) -> None:
        ws.adj_grid_v_of[t].zero_()
        wp.launch(
            K.g2p_adjoint, dim=launch.count(t),
            inputs=[sp[t].x, sp[t].F, ws.grid_v, origin, inv_dx, dt, op[t].x, op[t].v, op[t].C, op[t].F],
            outputs=[ws.adj_grid_v_of[t], ip[t].x, ip[t].F], device=dev,
        )  # fmt: skip

    def grid_update_adjoint(t: int) -> None:
        grid_in, _ = launch.grid_args(t)
        wp.launch(
            K.grid_update_adjoint, dim=launch.slab_dim(t), inputs=grid_in + [ws.adj_grid_v], outputs=[ws.adj_grid],
            device=dev,
        )  # fmt: skip

    def p2g_adjoint(t: int) -> None:
        p2g_in, _ = launch.p2g_args(sp[t], substep, t=t)
        wp.launch(
            K.p2g_adjoint, dim=launch.count(t),
            inputs=p2g_in[:15] + [ws.rotation_of[t], ws.adj_grid],
            outputs=[ip[t].x, ip[t].v, ip[t].C, ip[t].F], device=dev,
        )  # fmt: skip
        if prefetch is not None:  # after this thread's adjoint has read its chunk's rotations
            launch.p2g(prefetch, substep - 1, t, store_rotation=True)

    ws.run(g2p_adjoint)
    ws.run(grid_update_adjoint)
    ws.run(p2g_adjoint)


# ----------------------------------------------------------------------------------------------------
# torch bridge
# ----------------------------------------------------------------------------------------------------


def _to_warp(t: torch.Tensor, dtype: Any) -> wp.array:
    return wp.from_torch(t.detach().to(torch.float32).contiguous(), dtype=dtype)


def _load(dst: WarpState, x: torch.Tensor, v: torch.Tensor, F: torch.Tensor, C: torch.Tensor) -> None:
    wp.copy(dst.x, _to_warp(x, wp.vec3))
    wp.copy(dst.v, _to_warp(v, wp.vec3))
    wp.copy(dst.C, _to_warp(C, wp.mat33))
    wp.copy(dst.F, _to_warp(F, wp.mat33))


def _clone_state(s: WarpState) -> WarpState:
    return WarpState(wp.clone(s.x), wp.clone(s.v), wp.clone(s.C), wp.clone(s.F))


def _state_to_torch(s: WarpState) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    n = s.x.shape[0]
    x = wp.to_torch(s.x).clone()
    v = wp.to_torch(s.v).clone()
    C = wp.to_torch(s.C).clone().reshape(n, 3, 3)
    F = wp.to_torch(s.F).clone().reshape(n, 3, 3)
    return x, v, F, C


@dataclass
class _RolloutPlan:
    """What one rollout call runs; kept on the autograd context for its backward."""

    launch: _Launch
    substeps: int
    checkpoint_every: int
    frame_index: int
    first_substep: int = 0
    checkpoints: list[WarpState] = field(default_factory=list)

    def forward(
        self,
        x: torch.Tensor,
        v: torch.Tensor,
        F: torch.Tensor,
        C: torch.Tensor,
        *,
        store: bool,
        timers: dict | None = None,
    ) -> WarpState:
        ws = self.launch.ws
        ws.status_all.fill_(_STATUS_OK)
        _load(ws.ping, x, v, F, C)
        cur, nxt = ws.ping, ws.pong
        k = self.checkpoint_every
        p2g_done = False
        for s in range(self.substeps):
            if s % k == 0:
                if s > 0 and ws.status_value() != _STATUS_OK:
                    break  # diverged: stop early, the caller raises SimulationDiverged
                if store:
                    self.checkpoints.append(_clone_state(cur))
            prefetch = s + 1 < self.substeps
            step(self.launch, cur, nxt, self.first_substep + s, p2g_done=p2g_done, prefetch=prefetch, timers=timers)
            p2g_done = prefetch and timers is None
            cur, nxt = nxt, cur
        return cur

    def backward(self, grads: list[torch.Tensor | None], like: torch.Tensor) -> list[torch.Tensor]:
        ws, n = self.launch.ws, self.launch.model.num_particles
        k = self.checkpoint_every
        ws.ensure_backward(k)
        assert ws.adj_a is not None and ws.adj_b is not None
        adj_next, adj_cur = ws.adj_a, ws.adj_b
        zeros = {
            "x": torch.zeros(n, 3), "v": torch.zeros(n, 3), "F": torch.zeros(n, 3, 3), "C": torch.zeros(n, 3, 3),
        }  # fmt: skip
        gx, gv, gF, gC = (g if g is not None else zeros[name] for g, name in zip(grads, ("x", "v", "F", "C")))
        _load(adj_next, gx, gv, gF, gC)
        # Every P2G is run ahead, by the threads that finish the step before it: the grids (and rotations)
        # then hold the P2G of the state used next, and p2g_done says so.
        p2g_done = False
        for seg_id in reversed(range(len(self.checkpoints))):
            s0 = seg_id * k
            s1 = min(s0 + k, self.substeps)
            # particle states s0 .. s1-1 of this segment
            states = [self.checkpoints[seg_id]]
            for j in range(1, s1 - s0):
                out = ws.segment[j]
                step(
                    self.launch, states[-1], out, self.first_substep + s0 + j - 1, p2g_done=p2g_done, prefetch=True,
                    prefetch_rotation=True,
                )  # fmt: skip
                p2g_done = True
                states.append(out)
            for j in reversed(range(s1 - s0)):
                nxt = states[j - 1] if j > 0 else (self.checkpoints[seg_id - 1] if seg_id > 0 else None)
                _step_adjoint(
                    self.launch, states[j], adj_next, adj_cur, self.first_substep + s0 + j, p2g_done=p2g_done,
                    prefetch=nxt,
                )  # fmt: skip
                p2g_done = nxt is not None
                adj_next, adj_cur = adj_cur, adj_next
        gx, gv, gF, gC = _state_to_torch(adj_next)
        out = [g.to(like.device) for g in (gx, gv, gF, gC)]
        if not all(bool(torch.isfinite(g).all()) for g in out):
            raise SimulationDiverged(
                f"frame {self.frame_index}: the rollout's gradient is NaN/inf although its forward pass was "
                "finite; lower dt (sim.cfl_safety) or the learning rate of the velocities"
            )
        return out


class _RolloutFunction(torch.autograd.Function):
    """(x, v, F, C) -> (x, v, F, C) after ``plan.substeps`` substeps; differentiable in all four inputs."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, x: torch.Tensor, v: torch.Tensor, F: torch.Tensor, C: torch.Tensor, plan: _RolloutPlan, sim: MPMWarp
    ) -> tuple[torch.Tensor, ...]:
        store = any(ctx.needs_input_grad[:4])
        final = plan.forward(x, v, F, C, store=store)
        sim._check_status(plan, final)
        xo, vo, Fo, Co = (t.to(x.device) for t in _state_to_torch(final))
        ctx.plan = plan
        ctx.device = x.device
        return xo, vo, Fo, Co

    @staticmethod
    def backward(ctx: Any, gx: torch.Tensor, gv: torch.Tensor, gF: torch.Tensor, gC: torch.Tensor):  # type: ignore[override]
        plan: _RolloutPlan = ctx.plan
        grads = plan.backward([gx, gv, gF, gC], like=gx if gx is not None else torch.empty(0, device=ctx.device))
        ctx.plan = None  # free the checkpoints
        return grads[0], grads[1], grads[2], grads[3], None, None


# ----------------------------------------------------------------------------------------------------
# The registered component
# ----------------------------------------------------------------------------------------------------


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
                (:func:`sync4d.budget.check_cost`), naming the cause (e.g. E) and the fix.
            control_grid: cells per axis of the control-point lattice (paper: 41), or null to simulate
                every Gaussian. 40 against n_grid 32 gives ~2.5 lattice cells per grid cell along the
                object's longest axis (up to ~15 particles per filled grid cell; 3-6 measured on the
                transfer_gt bodies, where thin limbs and lids are one or two cells thick); cells that
                straddle a part boundary are split per part, so seams get more particles.
            gravity: (3,) acceleration [m/s^2]; off for motion transfer.
            checkpoint_every: store every k-th substep state for the backward pass, which recomputes the
                other (k-1)/k substeps once (memory ~ N/k + k states of 96 bytes per particle); null picks
                the smallest k whose states fit ``checkpoint_budget_mb`` (k = 1: no recomputation).
            checkpoint_budget_mb: memory for stored states of one rollout when checkpoint_every is null [MB].
            sort_particles: order particles by grid cell inside each rollout (cache locality; no effect on
                results beyond float rounding).
            refit_grid: when particles come near the walls, re-centre and grow the grid (same dx) before
                a rollout instead of letting the walls act on them.
            cpu_threads: threads of a rollout on the CPU (each launch split into particle chunks that
                scatter into their own grids; equal to one thread up to float rounding); null = the usable
                cores, one per 8192 particles at most. Ignored on CUDA.
        """

        E: float = 1e4
        nu: float = 0.3
        density: float = 1000.0
        n_grid: int = 32
        grid_padding: float = 0.25
        wall_cells: int = 3
        boundary: str = "slip"
        fixed_box: list[float] | None = None
        frame_time: float | None = None
        substeps: int = 20
        auto_substep: bool = True
        cfl_safety: float = 0.3
        max_substeps: int = 2000
        control_grid: int | None = 40
        gravity: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
        checkpoint_every: int | None = None
        checkpoint_budget_mb: float = 512.0
        sort_particles: bool = True
        refit_grid: bool = True
        cpu_threads: int | None = None

        def validate(self) -> None:
            """Raise :class:`ConfigError` naming the offending ``sim.*`` key."""
            validate_material(self.E, self.nu, self.density, where="sim")
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
            if self.control_grid is not None and self.control_grid < 1:
                raise ConfigError(
                    f"sim.control_grid={self.control_grid}: must be >= 1, or null to simulate every Gaussian"
                )
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

    def __init__(self, cfg: Config, *, device: str) -> None:
        cfg.validate()
        self.cfg = cfg
        self.device = device
        self.wp_device = warp_device(device)
        self.torch_device = torch_device(device)
        self._ws: _Workspace | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._pool_size = 0

    # -- building ---------------------------------------------------------------------------------

    def prepare(
        self,
        points: np.ndarray,
        *,
        volume: float | np.ndarray | None = None,
        weights: np.ndarray | None = None,
    ) -> MPMModel:
        """Build the model of a particle set: fitted grid, masses and volumes, material.

        Args:
            points: (P, 3) particle rest positions [m].
            volume: the object's total volume [m^3] shared among particles, or (P,) per-particle volumes
                [m^3], or None to estimate the total from the points' voxel occupancy (cells of side
                max(dx, (8 bbox volume / P)^(1/3)), i.e. ~8 points per cell for a filled box).
            weights: (P,) shares of the total volume (e.g. Gaussians per control point); uniform if None.

        Returns:
            The immutable model.
        """
        cfg = self.cfg
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
            raise InputError(f"sim.prepare: points must have shape (P, 3) with P > 0, got {pts.shape}")
        if not np.isfinite(pts).all():
            raise InputError("sim.prepare: points contain NaN/inf")
        grid = physics.fit_grid(pts, n_grid=cfg.n_grid, padding=cfg.grid_padding, wall=cfg.wall_cells)
        n = len(pts)
        if volume is None:
            box = np.prod(np.maximum(pts.max(0) - pts.min(0), grid.dx))
            cell = max(grid.dx, (8.0 * box / n) ** (1.0 / 3.0))
            vols = physics.particle_volumes(n, total_volume=physics.voxel_volume(pts, cell), weights=weights)
        elif np.ndim(volume) == 0:
            vols = physics.particle_volumes(n, total_volume=float(volume), weights=weights)  # type: ignore[arg-type]
        else:
            vols = np.asarray(volume, dtype=np.float64)
            if vols.shape != (n,) or not np.all(vols > 0) or not np.isfinite(vols).all():
                raise InputError(f"sim.prepare: per-particle volumes must be ({n},) and > 0, got {vols.shape}")
        mu, lam = physics.lame_parameters(cfg.E, cfg.nu)
        box = None if cfg.fixed_box is None else np.asarray(cfg.fixed_box, dtype=np.float64).reshape(2, 3)
        return MPMModel(
            grid=grid, rest_points=pts, mass=cfg.density * vols, volume=vols, E=cfg.E, nu=cfg.nu,
            density=cfg.density, mu=mu, lam=lam, gravity=np.asarray(cfg.gravity, dtype=np.float64),
            sticky=cfg.boundary == "sticky", fixed_box=box, device=self.wp_device,
        )  # fmt: skip

    def prepare_gaussians(self, means: np.ndarray, *, volume: float | None = None) -> tuple[MPMModel, np.ndarray]:
        """Model of a Gaussian object, through control points when ``control_grid`` is set.

        Args:
            means: (N, 3) Gaussian centres [m].
            volume: the object's volume [m^3], or None to estimate it from the Gaussians' occupancy.

        Returns:
            model: simulates the control points (or every Gaussian when ``control_grid`` is null).
            gaussian_to_point: (N,) index of each Gaussian's simulated particle
                (use :func:`sync4d.sim.control.carry_gaussians`).
        """
        means = np.asarray(means, dtype=np.float64)
        if self.cfg.control_grid is None:
            return self.prepare(means, volume=volume), np.arange(len(means), dtype=np.int64)
        points, g2p, counts = make_control_points(means, self.cfg.control_grid)
        if volume is None:
            probe = physics.fit_grid(
                means, n_grid=self.cfg.n_grid, padding=self.cfg.grid_padding, wall=self.cfg.wall_cells
            )
            box = np.prod(np.maximum(means.max(0) - means.min(0), probe.dx))
            volume = physics.voxel_volume(means, max(probe.dx, (8.0 * box / len(means)) ** (1.0 / 3.0)))
        model = self.prepare(points, volume=volume, weights=counts.astype(np.float64))
        log.info(
            "sim: %d Gaussians -> %d control points (control_grid=%d)", len(means), len(points), self.cfg.control_grid
        )
        return model, g2p

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

    # -- stability ---------------------------------------------------------------------------------

    def max_stable_dt(self, model: MPMModel, v_max: float = 0.0) -> float:
        """CFL bound cfl_safety dx / (c + v_max) [s] for this model."""
        return physics.cfl_dt(model.grid.dx, model.E, model.nu, model.density, v_max=v_max, safety=self.cfg.cfl_safety)

    def frame_time_for(self, fps: float | None) -> float:
        """Simulated time of one frame [s]: ``sim.frame_time``, or 1 / ``fps`` when it is null."""
        if self.cfg.frame_time is not None:
            return float(self.cfg.frame_time)
        if fps is None or not fps > 0:
            raise ConfigError(
                "sim.frame_time is null (the reference's frame interval) but no frame rate is known; "
                "set sim.frame_time=<seconds>"
            )
        return 1.0 / float(fps)

    def substeps_for(self, model: MPMModel, v_max: float = 0.0, *, fps: float | None = None) -> tuple[int, float]:
        """Substeps N and dt [s] for one frame of :meth:`frame_time_for` that respect the CFL bound.

        Args:
            model: the prepared model (its dx and material set the bound).
            v_max: the largest particle speed expected in the frame [m/s].
            fps: the reference's frame rate [1/s] (used when ``sim.frame_time`` is null).

        Raises:
            SimulationUnstable: frame_time / substeps breaks the bound and auto_substep is off.
        """
        cfg = self.cfg
        dt_max = self.max_stable_dt(model, v_max)
        frame_time = self.frame_time_for(fps)
        if cfg.auto_substep:
            n, dt = physics.substeps_for(frame_time, dt_max, min_substeps=cfg.substeps)
            if n > cfg.substeps:
                log.info(
                    "sim: %d substeps of dt=%.3g s per frame (CFL bound %.3g s; sim.substeps=%d)",
                    n,
                    dt,
                    dt_max,
                    cfg.substeps,
                )
            return n, dt
        dt = frame_time / cfg.substeps
        if dt > dt_max:
            raise self._unstable(model, dt, dt_max, v_max, cfg.substeps)
        return cfg.substeps, dt

    def _unstable(self, model: MPMModel, dt: float, dt_max: float, v_max: float, substeps: int) -> SimulationUnstable:
        need = int(math.ceil(substeps * dt / dt_max))
        return SimulationUnstable(
            f"sim: dt={dt:.3g} s breaks the CFL bound dt <= {self.cfg.cfl_safety} dx / (c + |v|max) = {dt_max:.3g} s "
            f"(dx={model.grid.dx:.3g} m, p-wave speed c={model.wave_speed:.3g} m/s, |v|max={v_max:.3g} m/s); "
            f"use dt <= {dt_max:.3g} s (>= {need} substeps for this frame) or set sim.auto_substep=true"
        )

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
        check_cfl: bool = True,
        timers: dict | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Advance the particles ``substeps`` substeps of ``dt``; differentiable in x, v, F and C.

        Args:
            model: from :meth:`prepare`.
            x, v: (P, 3) float32 positions [m] and velocities [m/s].
            F, C: (P, 3, 3) float32 deformation gradients and APIC affine matrices [1/s].
            substeps: number of substeps N >= 1.
            dt: substep [s] > 0.
            frame_index: the output frame this rollout produces (for error messages).
            check_cfl: apply the CFL guard (auto sub-stepping or SimulationUnstable); False only for tests.
            timers: accumulate per-kernel wall time [s] (forward only, no gradients; profiling).

        Returns:
            (x, v, F, C) after N substeps, torch float32 on the input's device, carrying autograd history.

        Raises:
            SimulationUnstable: dt over the CFL bound with auto_substep off.
            SimulationDiverged: NaN/inf or a particle off the grid during the rollout.
        """
        n = model.num_particles
        for name, t, shape in (("x", x, (n, 3)), ("v", v, (n, 3)), ("F", F, (n, 3, 3)), ("C", C, (n, 3, 3))):
            if tuple(t.shape) != shape:
                raise InputError(f"sim.rollout: {name} must have shape {shape}, got {tuple(t.shape)}")
        if not (dt > 0 and math.isfinite(dt)):
            raise ConfigError(f"sim.rollout: dt={dt} must be > 0 s")
        if int(substeps) < 1:
            raise ConfigError(f"sim.rollout: substeps={substeps} must be >= 1")
        substeps = int(substeps)
        with torch.no_grad():
            if not all(bool(torch.isfinite(t).all()) for t in (x, v, F, C)):
                raise SimulationDiverged(
                    f"frame {frame_index}: the rollout's input state holds NaN/inf; check the initial velocities"
                )
            v_max = float(v.norm(dim=1).max()) if n else 0.0
        if check_cfl:
            dt_max = self.max_stable_dt(model, v_max)
            if dt > dt_max * (1.0 + 1e-6):
                if not self.cfg.auto_substep:
                    raise self._unstable(model, dt, dt_max, v_max, substeps)
                split = int(math.ceil(dt / dt_max))
                log.info(
                    "sim: frame %d: dt=%.3g s over the CFL bound %.3g s; running %d x %d substeps of %.3g s",
                    frame_index, dt, dt_max, substeps, split, dt / split,
                )  # fmt: skip
                substeps, dt = substeps * split, dt / split
        xn = x.detach().double().cpu().numpy()
        # how far a particle can travel in this rollout at its current speed under gravity, plus 2 cells
        horizon = substeps * dt
        reach = v_max * horizon + 0.5 * float(np.linalg.norm(model.gravity)) * horizon**2 + 2.0 * model.grid.dx
        lo, hi = xn.min(0) - reach, xn.max(0) + reach
        if not (model.grid.contains(lo[None]) and model.grid.contains(hi[None])):
            if not self.cfg.refit_grid:
                log.warning("sim: frame %d: particles may reach the grid walls (sim.refit_grid=false)", frame_index)
            else:
                longest = max(float((xn.max(0) - xn.min(0)).max()), model.grid.dx)
                # capped: a particle that would fly further than the object's size is a blow-up to report
                padding = min(max(self.cfg.grid_padding, reach / longest), max(self.cfg.grid_padding, 1.0))
                grid = physics.fit_grid(
                    xn,
                    n_grid=self.cfg.n_grid,
                    padding=padding,
                    wall=self.cfg.wall_cells,
                    dx=model.grid.dx,
                    anchor=model.grid.origin,
                )
                log.debug("sim: frame %d: grid re-fitted to %s nodes", frame_index, grid.dims)
                model = model.with_grid(grid)

        perm = None
        mass, volume = model.mass, model.volume
        if self.cfg.sort_particles and n > 1:
            g = model.grid
            cell = np.floor((xn - g.origin) / g.dx).astype(np.int64)
            cell = np.clip(cell, 0, np.asarray(g.dims) - 1)
            key = (cell[:, 0] * g.dims[1] + cell[:, 1]) * g.dims[2] + cell[:, 2]
            order = np.argsort(key, kind="stable")
            perm = torch.as_tensor(order, device=x.device)
            x, v, F, C = x[perm], v[perm], F[perm], C[perm]
            mass, volume = mass[order], volume[order]

        launch = _Launch(
            model=model, ws=self._workspace(n, model.grid.dims),
            mass=wp.array(mass.astype(np.float32), dtype=float, device=self.wp_device),
            volume=wp.array(volume.astype(np.float32), dtype=float, device=self.wp_device),
            dt=float(dt), mass_eps=float(1e-9 * mass.min()),
        )  # fmt: skip
        k = self.checkpoint_interval(n, substeps)
        plan = _RolloutPlan(launch=launch, substeps=substeps, checkpoint_every=k, frame_index=frame_index)
        if timers is not None:
            with torch.no_grad():
                final = plan.forward(x, v, F, C, store=False, timers=timers)
                self._check_status(plan, final)
                out = tuple(t.to(x.device) for t in _state_to_torch(final))
        else:
            out = _RolloutFunction.apply(x, v, F, C, plan, self)
        if perm is not None:
            inv = torch.empty_like(perm)
            inv[perm] = torch.arange(n, device=perm.device)
            out = tuple(t[inv] for t in out)
        return out  # type: ignore[return-value]

    def checkpoint_interval(self, n_particles: int, substeps: int) -> int:
        """k: the backward pass stores every k-th substep state (``checkpoint_every`` or from the budget).

        Stored: ceil(N / k) states plus k - 1 recomputed ones, 96 bytes per particle each (x, v, C, F).
        """
        if self.cfg.checkpoint_every is not None:
            return int(self.cfg.checkpoint_every)
        state_mb = 96.0 * n_particles / 2**20
        for k in range(1, substeps + 1):
            if (math.ceil(substeps / k) + k - 1) * state_mb <= self.cfg.checkpoint_budget_mb:
                return k
        k = max(1, int(math.ceil(math.sqrt(substeps))))  # minimises N/k + k when nothing fits
        log.warning(
            "sim: %d substeps of %d particles need %.0f MB of stored states (> sim.checkpoint_budget_mb=%g)",
            substeps, n_particles, (math.ceil(substeps / k) + k - 1) * state_mb, self.cfg.checkpoint_budget_mb,
        )  # fmt: skip
        return k

    def grid_totals(
        self, model: MPMModel, x: torch.Tensor, v: torch.Tensor, F: torch.Tensor, C: torch.Tensor, *, dt: float
    ) -> tuple[float, np.ndarray]:
        """Total mass [kg] and momentum [kg m/s] on the grid after one P2G of this state (diagnostics).

        MLS-MPM's P2G conserves both exactly (partition of unity, zero first moment of the weights), so
        these equal sum m_p and sum m_p v_p up to float rounding.
        """
        n = model.num_particles
        launch = _Launch(
            model=model, ws=self._workspace(n, model.grid.dims),
            mass=wp.array(model.mass.astype(np.float32), dtype=float, device=self.wp_device),
            volume=wp.array(model.volume.astype(np.float32), dtype=float, device=self.wp_device),
            dt=float(dt), mass_eps=float(1e-9 * model.mass.min()),
        )  # fmt: skip
        ws = launch.ws
        _load(ws.ping, x, v, F, C)
        ws.run(lambda t: launch.p2g(ws.ping, 0, t))
        g = ws.grids.numpy().astype(np.float64).reshape(-1, 4).sum(0)
        return float(g[3]), g[:3]

    def threads_for(self, n_particles: int) -> int:
        """Threads a rollout of ``n_particles`` runs on: 1 on CUDA, else ``cpu_threads`` or the usable cores.

        Automatic (``cpu_threads`` null): the cores this process may run on, but at most one thread per
        ``_MIN_PARTICLES_PER_THREAD`` particles (tiny scenes stay on one thread).
        """
        if not self.wp_device.startswith("cpu"):
            return 1
        if self.cfg.cpu_threads is not None:
            return max(1, min(int(self.cfg.cpu_threads), n_particles))
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        return max(1, min(cores, n_particles // _MIN_PARTICLES_PER_THREAD))

    def _workspace(self, n: int, dims: tuple[int, int, int]) -> _Workspace:
        ws = self._ws
        threads = self.threads_for(n)
        if ws is None or ws.n != n or ws.dims != tuple(dims) or ws.threads != threads:
            if threads > 1 and (self._pool is None or self._pool_size != threads - 1):
                if self._pool is not None:
                    self._pool.shutdown(wait=True)
                self._pool = ThreadPoolExecutor(max_workers=threads - 1, thread_name_prefix="sync4d-mpm")
                self._pool_size = threads - 1
            ws = _Workspace(n, tuple(dims), self.wp_device, threads, self._pool)  # type: ignore[arg-type]
            self._ws = ws
        return ws

    def _check_status(self, plan: _RolloutPlan, final: WarpState) -> None:
        """Raise SimulationDiverged if any substep recorded a NaN/inf or an off-grid particle."""
        first = plan.launch.ws.status_value()
        if first == _STATUS_OK:
            return
        v = final.v.numpy()
        speed = np.linalg.norm(v, axis=1)
        finite = np.isfinite(speed)
        vmax = float(speed[finite].max()) if finite.any() else float("nan")
        m = plan.launch.model
        raise SimulationDiverged(
            f"frame {plan.frame_index}, substep {first - plan.first_substep} of {plan.substeps}: particles left the grid "
            f"or turned NaN/inf (largest finite speed {vmax:.3g} m/s, {int((~finite).sum())} non-finite; "
            f"dt={plan.launch.dt:.3g} s, CFL bound {self.max_stable_dt(m, 0.0):.3g} s at rest); lower dt or sim.cfl_safety, "
            f"lower the initial velocities, or raise sim.grid_padding"
        )

    # -- the transfer loop (issue 5) ---------------------------------------------------------------

    def run(self, target: Any, part_map: Any, motion: Any, **kwargs: Any) -> Any:
        """The transfer stage's frame-pair loop through this simulator (:mod:`sync4d.transfer`)."""
        from sync4d.transfer import run_mpm_transfer

        return run_mpm_transfer(self, target, part_map, motion, **kwargs)
