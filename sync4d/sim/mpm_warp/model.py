"""The MPM model (what does not change during a rollout), the particle state as Warp arrays, and the
preallocated scratch a rollout reuses."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import cast

import numpy as np
import torch
import warp as wp

from sync4d.sim import physics
from sync4d.sim.mpm_warp.drive import PartRig
from sync4d.sim.mpm_warp.fields import MAX_FIELDS, FieldSplit

#: The status record's value when no substep failed (a failing substep writes its index with atomic_min).
STATUS_OK = 2147483647


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
        rig: the parts' rest centroids, inertias and masses (:mod:`drive`), or None when no parts were given
            (the drive is then off).
        fields: each particle's velocity field and bond flag (:mod:`fields`), or None: one field (no parts or part
            tree given, or no touching parts that are not joined).
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
    rig: PartRig | None = None
    fields: FieldSplit | None = None

    @property
    def num_fields(self) -> int:
        """Velocity fields of the grid (1 without a split)."""
        return 1 if self.fields is None else self.fields.num_fields

    @property
    def bonding(self) -> bool:
        """Whether fields are bonded at joints (some particle flagged)."""
        return self.fields is not None and self.fields.bonding

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
    views: dict = field(default_factory=dict, repr=False, compare=False)

    def parts(self, bounds: tuple[tuple[int, int], ...]) -> list[WarpState]:
        """The state as views of the particle ranges ``bounds`` (itself for one range; views are cached)."""
        if len(bounds) == 1:
            return [self]
        views = self.views.get(bounds)
        if views is None:
            views = [WarpState(*(a[lo:hi] for a in self.arrays())) for lo, hi in bounds]
            self.views[bounds] = views
        return views

    @staticmethod
    def empty(n: int, device: str) -> WarpState:
        return WarpState(
            wp.empty(n, dtype=wp.vec3, device=device),
            wp.empty(n, dtype=wp.vec3, device=device),
            wp.empty(n, dtype=wp.mat33, device=device),
            wp.empty(n, dtype=wp.mat33, device=device),
        )

    def arrays(self) -> tuple[wp.array, wp.array, wp.array, wp.array]:
        return self.x, self.v, self.C, self.F

    def clone(self) -> WarpState:
        return WarpState(wp.clone(self.x), wp.clone(self.v), wp.clone(self.C), wp.clone(self.F))

    def load(self, x: torch.Tensor, v: torch.Tensor, F: torch.Tensor, C: torch.Tensor) -> None:
        """Copy torch tensors (any float dtype, any device) into this state."""
        wp.copy(self.x, to_warp(x, wp.vec3))
        wp.copy(self.v, to_warp(v, wp.vec3))
        wp.copy(self.C, to_warp(C, wp.mat33))
        wp.copy(self.F, to_warp(F, wp.mat33))

    def to_torch(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(x, v, F, C) as new float32 torch tensors: (P, 3), (P, 3), (P, 3, 3), (P, 3, 3)."""
        n = self.x.shape[0]
        x = wp.to_torch(self.x).clone()
        v = wp.to_torch(self.v).clone()
        C = wp.to_torch(self.C).clone().reshape(n, 3, 3)
        F = wp.to_torch(self.F).clone().reshape(n, 3, 3)
        return x, v, F, C


def to_warp(t: torch.Tensor, dtype: type) -> wp.array:
    """A float32 Warp view of a torch tensor (detached, made contiguous)."""
    return cast(wp.array, wp.from_torch(t.detach().to(torch.float32).contiguous(), dtype=dtype))


def split_range(n: int, parts: int) -> tuple[tuple[int, int], ...]:
    """``parts`` contiguous ranges [lo, hi) covering 0..n, as equal as possible."""
    edges = [n * t // parts for t in range(parts + 1)]
    return tuple((edges[t], edges[t + 1]) for t in range(parts))


class Workspace:
    """Preallocated scratch of one (particle count, grid shape, device, threads): reused by every rollout.

    With ``threads`` T > 1 (CPU), thread t handles particles ``bounds[t]`` and node slab ``slabs[t]``,
    and owns P2G grid ``grids[t]``, G2P-adjoint grid ``adj_grid_v[t]`` and failure record ``status_of[t]``.
    With ``fields`` F > 1 every grid holds the F fields stacked along x (``field_dims``: F nx, ny, nz); with
    ``bonding`` each thread also owns a grid of flagged mass ``bonds[t]`` (else ``bonds`` is a dummy).
    Not thread-safe: one simulator object runs one rollout (forward or backward) at a time.
    """

    def __init__(
        self, n: int, dims: tuple[int, int, int], device: str, threads: int = 1, pool: ThreadPoolExecutor | None = None,
        *, fields: int = 1, bonding: bool = False,
    ) -> None:
        self.n, self.dims, self.device, self.threads, self.pool = n, dims, device, threads, pool
        self.fields, self.bonding = fields, bonding
        if not 1 <= fields <= MAX_FIELDS:
            raise ValueError(f"Workspace: {fields} velocity fields, the kernels handle 1 to {MAX_FIELDS}")
        if threads > 1 and pool is None:
            raise ValueError("Workspace: a thread pool is needed for threads > 1")
        self.bounds = split_range(n, threads)
        self.slabs = split_range(dims[0], threads)
        self.field_dims = (fields * dims[0], dims[1], dims[2])
        self.grids = wp.zeros((threads, *self.field_dims), dtype=wp.vec4, device=device)
        self.grid_of = [self.grids[t] for t in range(threads)]
        self.grid = self.grid_of[0]
        self.bonds = wp.zeros((threads, *(self.field_dims if bonding else (1, 1, 1))), dtype=float, device=device)
        self.bond_of = [self.bonds[t] for t in range(threads)]
        self.grid_v = wp.zeros(self.field_dims, dtype=wp.vec3, device=device)
        self.status_all = wp.full(threads, STATUS_OK, dtype=wp.int32, device=device)
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
        self.drive_parts = -1  # the part count the drive's scratch is allocated for (none yet)

    def ensure_drive(self, num_parts: int) -> None:
        """Allocate the drive's scratch for ``num_parts`` parts (once per part count): the state after G2P
        and its adjoint, the threads' partial moments (T, B, 4), their totals and the rig's fit of them (B, 4),
        forward and adjoint."""
        if self.drive_parts == num_parts:
            return
        self.drive_parts = num_parts
        shape = (self.threads, num_parts, 4)
        self.drive_mid = WarpState.empty(self.n, self.device)
        self.adj_drive_mid = WarpState.empty(self.n, self.device)
        self.drive_sums_all = wp.zeros(shape, dtype=wp.vec3, device=self.device)
        self.adj_drive_sums_all = wp.zeros(shape, dtype=wp.vec3, device=self.device)
        self.drive_sums_of = [self.drive_sums_all[t] for t in range(self.threads)]
        self.adj_drive_sums_of = [self.adj_drive_sums_all[t] for t in range(self.threads)]
        self.drive_total = wp.zeros(shape[1:], dtype=wp.vec3, device=self.device)
        self.adj_drive_total = wp.zeros(shape[1:], dtype=wp.vec3, device=self.device)
        self.drive_theta = wp.zeros(shape[1:], dtype=wp.vec3, device=self.device)
        self.adj_drive_theta = wp.zeros(shape[1:], dtype=wp.vec3, device=self.device)

    def ensure_backward(self, k: int) -> None:
        """Allocate the adjoint buffers and ``k`` segment states (once)."""
        if self.adj_grid is None:
            self.adj_grid = wp.zeros(self.field_dims, dtype=wp.vec4, device=self.device)
            self.adj_grid_v = wp.zeros((self.threads, *self.field_dims), dtype=wp.vec3, device=self.device)
            self.adj_grid_v_of = [self.adj_grid_v[t] for t in range(self.threads)]
            self.adj_a = WarpState.empty(self.n, self.device)
            self.adj_b = WarpState.empty(self.n, self.device)
        while len(self.segment) < k:
            self.segment.append(WarpState.empty(self.n, self.device))

    def status_value(self) -> int:
        """The earliest substep any thread recorded a failure at (``STATUS_OK`` when none did)."""
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
