"""One MLS-MPM substep forward (:func:`step`) and in reverse (:func:`step_adjoint`), and a rollout of many
(:class:`RolloutPlan`): the orchestration of :mod:`sync4d.sim.mpm_warp.kernels` over a :class:`Workspace`.

Forward: ping-pong between two preallocated states (no per-substep allocation); when gradients are wanted
every ``checkpoint_every``-th particle state is stored (x, v, C, F: 96 bytes per particle). Backward: per
segment, the stored state is advanced again to recover the segment's states; then for each substep in
reverse the grid is rebuilt (P2G + grid update) and the hand-written adjoint kernels of G2P, the grid
update and P2G run, with one reused grid (never a copy per substep). Memory of a forward+backward rollout
is O(P (substeps / k + k)) plus one grid with its adjoint.

Both cores (CPU only): Warp's CPU backend runs a launch on one thread and its ctypes call releases the GIL.
With T > 1 threads every particle kernel is launched as T contiguous chunks of the (cell-sorted) particles
from T Python threads, each P2G and each G2P adjoint scattering into its own grid (the grid update and its
adjoint sum the T grids, split into T slabs of nodes), so no two threads ever write the same memory.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import warp as wp

from sync4d.errors import SimulationDiverged
from sync4d.sim.mpm_warp import kernels as K
from sync4d.sim.mpm_warp.drive import DriveArrays
from sync4d.sim.mpm_warp.fields import BOND_SHARE
from sync4d.sim.mpm_warp.model import STATUS_OK, MPMModel, WarpState, Workspace


@dataclass
class Launch:
    """Per-rollout constants of the kernels (model in sorted particle order, workspace). ``field_id`` and
    ``bond_flag``: (P,) each particle's velocity field (int32) and bond flag (float) in that order, zeros when None."""

    model: MPMModel
    ws: Workspace
    mass: wp.array
    volume: wp.array
    dt: float
    mass_eps: float
    drive: DriveArrays | None = None
    field_id: wp.array | None = None
    bond_flag: wp.array | None = None
    mass_of: list[wp.array] = field(default_factory=list, repr=False)
    volume_of: list[wp.array] = field(default_factory=list, repr=False)
    field_id_of: list[wp.array] = field(default_factory=list, repr=False)
    bond_flag_of: list[wp.array] = field(default_factory=list, repr=False)
    slot_part_of: list[wp.array] = field(default_factory=list, repr=False)
    slot_weight_of: list[wp.array] = field(default_factory=list, repr=False)
    slot_offset_of: list[wp.array] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        bounds = self.ws.bounds
        one = self.ws.threads == 1
        n, dev = self.mass.shape[0], self.ws.device
        if self.field_id is None:
            self.field_id = wp.zeros(n, dtype=wp.int32, device=dev)
        if self.bond_flag is None:
            self.bond_flag = wp.zeros(n, dtype=float, device=dev)
        self.mass_of = [self.mass] if one else [self.mass[lo:hi] for lo, hi in bounds]
        self.volume_of = [self.volume] if one else [self.volume[lo:hi] for lo, hi in bounds]
        self.field_id_of = [self.field_id] if one else [self.field_id[lo:hi] for lo, hi in bounds]
        self.bond_flag_of = [self.bond_flag] if one else [self.bond_flag[lo:hi] for lo, hi in bounds]
        if self.drive is not None:
            d = self.drive
            self.slot_part_of = [d.slot_part] if one else [d.slot_part[lo:hi] for lo, hi in bounds]
            self.slot_weight_of = [d.slot_weight] if one else [d.slot_weight[lo:hi] for lo, hi in bounds]
            self.slot_offset_of = [d.slot_offset] if one else [d.slot_offset[lo:hi] for lo, hi in bounds]
            self.ws.ensure_drive(d.num_parts)

    def p2g_args(
        self, s: WarpState, substep: int, *, store_rotation: bool = False, t: int = 0
    ) -> tuple[list[Any], list[Any]]:
        """P2G of thread t's particles (``s`` is that thread's view of the state) into its own grid."""
        g = self.model.grid
        inputs = [
            s.x, s.v, s.C, s.F, self.mass_of[t], self.volume_of[t], self.field_id_of[t],
            float(self.model.mu), float(self.model.lam),
            wp.vec3(*g.origin), float(g.dx), float(1.0 / g.dx), float(self.dt),
            int(g.dims[0]), int(g.dims[1]), int(g.dims[2]), int(substep), int(store_rotation),
            self.bond_flag_of[t], int(self.ws.bonding),
        ]  # fmt: skip
        return inputs, [self.ws.grid_of[t], self.ws.status_of[t], self.ws.rotation_of[t], self.ws.bond_of[t]]

    def grid_args(self, t: int = 0) -> tuple[list[Any], list[Any]]:
        """Grid update of thread t's slab of nodes (the launch dimension is :meth:`slab_dim`)."""
        m, g = self.model, self.model.grid
        box = m.fixed_box if m.fixed_box is not None else np.zeros((2, 3))
        ws = self.ws
        inputs = [
            ws.grids, ws.bonds, int(ws.slabs[t][0]), int(ws.dims[0]), int(ws.fields), int(ws.bonding),
            float(BOND_SHARE), wp.vec3(*m.gravity), float(self.dt), float(self.mass_eps),
            int(g.wall), int(m.sticky), wp.vec3(*g.origin), float(g.dx), wp.vec3(*box[0]), wp.vec3(*box[1]),
            int(m.fixed_box is not None),
        ]  # fmt: skip
        return inputs, [self.ws.grid_v]

    def slab_dim(self, t: int) -> tuple[int, int, int]:
        lo, hi = self.ws.slabs[t]
        return (hi - lo, self.ws.dims[1], self.ws.dims[2])

    def g2p_args(self, s: WarpState, out: WarpState, substep: int, t: int = 0) -> tuple[list[Any], list[Any]]:
        g = self.model.grid
        inputs = [s.x, s.F, self.ws.grid_v, self.field_id_of[t], int(self.ws.dims[0]), wp.vec3(*g.origin),
                  float(1.0 / g.dx), float(self.dt), int(substep)]
        return inputs, [out.x, out.v, out.C, out.F, self.ws.status_of[t]]

    def count(self, t: int) -> int:
        lo, hi = self.ws.bounds[t]
        return hi - lo

    def p2g(self, s: WarpState, substep: int, t: int, *, store_rotation: bool = False) -> None:
        """Zero thread t's grid and scatter its particles (``s`` the whole state) into it."""
        ws = self.ws
        ws.grid_of[t].zero_()
        if ws.bonding:
            ws.bond_of[t].zero_()
        i, o = self.p2g_args(s.parts(ws.bounds)[t], substep, store_rotation=store_rotation, t=t)
        wp.launch(K.p2g, dim=self.count(t), inputs=i, outputs=o, device=ws.device)

    def grid_update(self, t: int) -> None:
        i, o = self.grid_args(t)
        wp.launch(K.grid_update, dim=self.slab_dim(t), inputs=i, outputs=o, device=self.ws.device)

    def g2p(self, s: WarpState, out: WarpState, substep: int, t: int) -> None:
        ws = self.ws
        i, o = self.g2p_args(s.parts(ws.bounds)[t], out.parts(ws.bounds)[t], substep, t)
        wp.launch(K.g2p, dim=self.count(t), inputs=i, outputs=o, device=ws.device)

    # -- the drive held through the frame (sync4d.sim.mpm_warp.drive) --------------------------------------

    def drive_sums_args(self, s: WarpState, substep: int, t: int) -> tuple[list[Any], list[Any]]:
        d = self.drive
        assert d is not None
        inputs = [s.x, s.v, self.slot_part_of[t], self.slot_weight_of[t], self.slot_offset_of[t], self.mass_of[t],
                  d.turn[substep], d.centre[substep], d.linear, d.angular]
        return inputs, [self.ws.drive_sums_of[t]]

    def drive_apply_args(self, s: WarpState, out: WarpState, substep: int, t: int) -> tuple[list[Any], list[Any]]:
        d = self.drive
        assert d is not None
        inputs = [s.x, s.v, s.C, s.F, self.slot_part_of[t], self.slot_weight_of[t], self.slot_offset_of[t],
                  d.turn[substep], self.ws.drive_theta]
        return inputs, [out.x, out.v, out.C, out.F]

    def drive_sums(self, s: WarpState, substep: int, t: int) -> None:
        """Thread t's share of every part's rigid deviation moments (``s`` is the whole state)."""
        ws = self.ws
        ws.drive_sums_of[t].zero_()
        i, o = self.drive_sums_args(s.parts(ws.bounds)[t], substep, t)
        wp.launch(K.drive_sums, dim=self.count(t), inputs=i, outputs=o, device=ws.device)

    def g2p_and_sums(self, s: WarpState, mid: WarpState, substep: int, t: int) -> None:
        """Thread t's G2P of ``s`` into ``mid`` and its share of the drive's moments of ``mid``."""
        self.g2p(s, mid, substep, t)
        self.drive_sums(mid, substep, t)

    def drive_total(self, substep: int) -> None:
        """The threads' partial moments summed (``ws.drive_total``) and the rig's fit of them (``ws.drive_theta``)."""
        ws = self.ws
        assert self.drive is not None
        wp.launch(K.sum_slices, dim=ws.drive_total.shape, inputs=[ws.drive_sums_all], outputs=[ws.drive_total],
                  device=ws.device)
        wp.launch(K.drive_solve, dim=ws.drive_theta.shape, inputs=[self.drive.solve, self.drive.turn[substep],
                  ws.drive_total], outputs=[ws.drive_theta], device=ws.device)

    def drive_apply(self, s: WarpState, out: WarpState, substep: int, t: int) -> None:
        """Thread t's particles with their part's rigid deviation removed: ``s`` -> ``out``."""
        ws = self.ws
        i, o = self.drive_apply_args(s.parts(ws.bounds)[t], out.parts(ws.bounds)[t], substep, t)
        wp.launch(K.drive_apply, dim=self.count(t), inputs=i, outputs=o, device=ws.device)

    def drive_adjoint(self, out: WarpState, adj_out: WarpState, adj_mid: WarpState, substep: int) -> None:
        """dL/d(state after G2P) into ``adj_mid`` from dL/d(state after the drive) ``adj_out``, by the hand-written
        adjoints of :func:`K.drive_apply`, the solve (its own adjoint) and :func:`K.drive_sums`. ``out`` is the
        corrected state and ``ws.drive_theta`` the fit that corrected it."""
        ws = self.ws
        d = self.drive
        assert d is not None
        ep, op, mp = out.parts(ws.bounds), adj_out.parts(ws.bounds), adj_mid.parts(ws.bounds)

        def apply_adjoint(t: int) -> None:
            ws.adj_drive_sums_of[t].zero_()
            wp.launch(K.drive_apply_adjoint, dim=self.count(t),
                      inputs=[ep[t].F, self.slot_part_of[t], self.slot_weight_of[t], self.slot_offset_of[t],
                              d.turn[substep], ws.drive_theta, *op[t].arrays()],
                      outputs=[*mp[t].arrays(), ws.adj_drive_sums_of[t]], device=ws.device)

        def sums_adjoint(t: int) -> None:
            wp.launch(K.drive_sums_adjoint, dim=self.count(t),
                      inputs=[self.slot_part_of[t], self.slot_weight_of[t], self.slot_offset_of[t], self.mass_of[t],
                              d.turn[substep], ws.adj_drive_total],
                      outputs=[mp[t].x, mp[t].v], device=ws.device)

        ws.run(apply_adjoint)
        wp.launch(K.sum_slices, dim=ws.adj_drive_theta.shape, inputs=[ws.adj_drive_sums_all],
                  outputs=[ws.adj_drive_theta], device=ws.device)
        wp.launch(K.drive_solve, dim=ws.adj_drive_total.shape, inputs=[d.solve, d.turn[substep],
                  ws.adj_drive_theta], outputs=[ws.adj_drive_total], device=ws.device)
        ws.run(sums_adjoint)


def step(
    launch: Launch,
    state_in: WarpState,
    state_out: WarpState,
    substep: int,
    *,
    p2g_done: bool = False,
    prefetch: bool = False,
    prefetch_rotation: bool = False,
    timers: dict[str, float] | None = None,
) -> None:
    """One MLS-MPM substep ``state_in -> state_out`` (``state_in`` is only read).

    Args:
        launch: model, workspace, dt [s] of this rollout.
        state_in: particle state at the start of the substep.
        state_out: receives the state at the end of the substep (must not alias ``state_in``).
        substep: substep index in the rollout (recorded if a particle leaves the grid or turns non-finite).
        p2g_done: the grids already hold this substep's P2G (a previous call's ``prefetch``).
        prefetch: also run the next substep's P2G of ``state_out`` (each thread right after its own G2P,
            whose chunk it reads: one hand-over between threads fewer per substep).
        prefetch_rotation: the prefetched P2G stores the polar rotations (for the backward pass).
        timers: when given, accumulates wall time [s] per kernel under 'p2g', 'grid', 'g2p', 'drive' (synchronises
            after each launch, so only for profiling; no prefetching then).
    """
    ws, dev = launch.ws, launch.ws.device
    marks: list[float] = []

    def mark() -> None:
        if timers is not None:
            wp.synchronize_device(dev)
            marks.append(time.perf_counter())

    if timers is not None:
        p2g_done = prefetch = False
    mark()
    if not p2g_done:
        ws.run(lambda t: launch.p2g(state_in, substep, t))
    mark()
    ws.run(launch.grid_update)
    mark()

    def next_p2g(t: int) -> None:
        if prefetch:
            launch.p2g(state_out, substep + 1, t, store_rotation=prefetch_rotation)

    def g2p(t: int) -> None:
        launch.g2p(state_in, state_out, substep, t)
        next_p2g(t)

    def held(t: int) -> None:
        launch.drive_apply(ws.drive_mid, state_out, substep, t)
        next_p2g(t)

    if launch.drive is None:
        ws.run(g2p)
        mark()
    else:  # G2P into the scratch state, then each part's rigid deviation from its drive taken off
        ws.run(lambda t: launch.g2p_and_sums(state_in, ws.drive_mid, substep, t))
        mark()
        launch.drive_total(substep)
        ws.run(held)
        mark()
    if timers is not None:
        for name, lo, hi in zip(("p2g", "grid", "g2p", "drive"), marks, marks[1:]):
            timers[name] = timers.get(name, 0.0) + (hi - lo)


def step_adjoint(
    launch: Launch,
    s: WarpState,
    adj_out: WarpState,
    adj_in: WarpState,
    substep: int,
    *,
    p2g_done: bool = False,
    prefetch: WarpState | None = None,
    held: tuple[WarpState, wp.array] | None = None,
) -> None:
    """Reverse one substep: given dL/d(state_out) in ``adj_out``, write dL/d(state_in) into ``adj_in``.

    ``p2g_done``: the grids and rotations already hold this substep's P2G of ``s``; ``prefetch``: the
    state of the substep reversed next, whose P2G (with rotations) each thread runs right after its P2G
    adjoint; ``held``: with a drive, the substep's end state and the drive's fit ``theta`` (B, 4) it applied.

    Rebuilds the substep's grid from ``s`` (P2G + grid update), then runs the adjoints in reverse order: the
    drive (from the end state and the fit it applied), G2P, grid update, and P2G fused with the
    fixed-corotated stress, all by hand-written kernels (checked
    against finite differences and against Warp's generated adjoints in the tests). The grid mass is
    differentiated like every other input.
    """
    ws, dev = launch.ws, launch.ws.device
    assert ws.adj_grid is not None and ws.adj_grid_v is not None
    g = launch.model.grid
    if not p2g_done:  # forward part: the grid this substep saw
        ws.run(lambda t: launch.p2g(s, substep, t, store_rotation=True))
    ws.run(launch.grid_update)

    origin, inv_dx, dt = wp.vec3(*g.origin), float(1.0 / g.dx), float(launch.dt)
    sp, op, ip = s.parts(ws.bounds), adj_out.parts(ws.bounds), adj_in.parts(ws.bounds)

    def g2p_adjoint(t: int) -> None:
        ws.adj_grid_v_of[t].zero_()
        wp.launch(
            K.g2p_adjoint, dim=launch.count(t),
            inputs=[sp[t].x, sp[t].F, ws.grid_v, launch.field_id_of[t], int(ws.dims[0]), origin, inv_dx, dt,
                    op[t].x, op[t].v, op[t].C, op[t].F],
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
            inputs=p2g_in[:16] + [ws.rotation_of[t], ws.adj_grid],
            outputs=[ip[t].x, ip[t].v, ip[t].C, ip[t].F], device=dev,
        )  # fmt: skip
        if prefetch is not None:  # after this thread's adjoint has read its chunk's rotations
            launch.p2g(prefetch, substep - 1, t, store_rotation=True)

    if held is not None:  # the drive's adjoint first: adj_out then stands for the state after G2P
        out, theta = held
        wp.copy(ws.drive_theta, theta)
        launch.drive_adjoint(out, adj_out, ws.adj_drive_mid, substep)
        op = ws.adj_drive_mid.parts(ws.bounds)
    ws.run(g2p_adjoint)
    ws.run(grid_update_adjoint)
    ws.run(p2g_adjoint)


@dataclass
class RolloutPlan:
    """What one rollout call runs; kept on the autograd context for its backward."""

    launch: Launch
    substeps: int
    checkpoint_every: int
    frame_index: int
    checkpoints: list[WarpState] = field(default_factory=list)
    # with a drive and checkpoints: the fit theta (B, 4) of every substep and the rollout's end state (the backward
    # undoes each substep's correction instead of recomputing its G2P)
    thetas: list[wp.array] = field(default_factory=list)
    final: WarpState | None = None

    def forward(
        self,
        x: torch.Tensor,
        v: torch.Tensor,
        F: torch.Tensor,
        C: torch.Tensor,
        *,
        store: bool,
        timers: dict[str, float] | None = None,
    ) -> WarpState:
        """Run every substep; stores checkpoints when ``store``; stops early once a substep failed."""
        ws = self.launch.ws
        ws.status_all.fill_(STATUS_OK)
        ws.ping.load(x, v, F, C)
        cur, nxt = ws.ping, ws.pong
        k = self.checkpoint_every
        p2g_done = False
        for s in range(self.substeps):
            if s % k == 0:
                if s > 0 and ws.status_value() != STATUS_OK:
                    break  # diverged: stop early, the caller raises SimulationDiverged
                if store:
                    self.checkpoints.append(cur.clone())
            prefetch = s + 1 < self.substeps
            step(self.launch, cur, nxt, s, p2g_done=p2g_done, prefetch=prefetch, timers=timers)
            if store and self.launch.drive is not None:
                self.thetas.append(wp.clone(ws.drive_theta))
            p2g_done = prefetch and timers is None
            cur, nxt = nxt, cur
        if store and self.launch.drive is not None:
            self.final = cur.clone()
        return cur

    def segment_states(self, seg_id: int, p2g_done: bool) -> list[WarpState]:
        """The particle states at the start of each substep of segment ``seg_id``, recomputed from its
        checkpoint (every step prefetches the next P2G with rotations for the adjoint)."""
        ws, k = self.launch.ws, self.checkpoint_every
        s0 = seg_id * k
        s1 = min(s0 + k, self.substeps)
        states = [self.checkpoints[seg_id]]
        for j in range(1, s1 - s0):
            out = ws.segment[j]
            step(self.launch, states[-1], out, s0 + j - 1, p2g_done=p2g_done or j > 1, prefetch=True,
                 prefetch_rotation=True)
            states.append(out)
        return states

    def held_end(self, states: list[WarpState], seg_id: int, j: int) -> tuple[WarpState, wp.array] | None:
        """With a drive, substep ``j`` of segment ``seg_id``'s end state (the next substep's start: in ``states``,
        the next checkpoint or the rollout's end) and its fit; None without a drive."""
        if self.launch.drive is None:
            return None
        if j + 1 < len(states):
            end = states[j + 1]
        elif seg_id + 1 < len(self.checkpoints):
            end = self.checkpoints[seg_id + 1]
        else:
            assert self.final is not None
            end = self.final
        return end, self.thetas[seg_id * self.checkpoint_every + j]

    def backward(self, grads: list[torch.Tensor | None], like: torch.Tensor) -> list[torch.Tensor]:
        """dL/d(x, v, F, C) of the rollout's input from dL/d of its output (None = zero)."""
        ws, n = self.launch.ws, self.launch.model.num_particles
        k = self.checkpoint_every
        ws.ensure_backward(k)
        assert ws.adj_a is not None and ws.adj_b is not None
        adj_next, adj_cur = ws.adj_a, ws.adj_b
        shapes = ((n, 3), (n, 3), (n, 3, 3), (n, 3, 3))
        adj_next.load(*(g if g is not None else torch.zeros(shape) for g, shape in zip(grads, shapes)))
        # Every P2G is run ahead, by the threads that finish the step before it: the grids (and rotations)
        # then hold the P2G of the state used next, and p2g_done says so.
        p2g_done = False
        for seg_id in reversed(range(len(self.checkpoints))):
            states = self.segment_states(seg_id, p2g_done)
            p2g_done = p2g_done or len(states) > 1
            s0 = seg_id * k
            for j in reversed(range(len(states))):
                nxt = states[j - 1] if j > 0 else (self.checkpoints[seg_id - 1] if seg_id > 0 else None)
                step_adjoint(self.launch, states[j], adj_next, adj_cur, s0 + j, p2g_done=p2g_done, prefetch=nxt,
                             held=self.held_end(states, seg_id, j))
                p2g_done = nxt is not None
                adj_next, adj_cur = adj_cur, adj_next
        out = [g.to(like.device) for g in adj_next.to_torch()]
        if not all(bool(torch.isfinite(g).all()) for g in out):
            raise SimulationDiverged(
                f"frame {self.frame_index}: the rollout's gradient is NaN/inf although its forward pass was "
                "finite; lower dt (sim.cfl_safety) or the learning rate of the velocities"
            )
        return out
