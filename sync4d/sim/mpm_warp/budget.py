"""The time-step policy of ``sim=mpm_warp``: the CFL bound, substeps per frame, checkpoint spacing and the
threads a rollout runs on. Pure functions of the simulator's Config and the model."""

from __future__ import annotations

import logging
import math
import os
from typing import Protocol

from sync4d.errors import SimulationUnstable
from sync4d.sim import physics
from sync4d.sim.mpm_warp.model import MPMModel

log = logging.getLogger(__name__)

#: Automatic ``cpu_threads``: a thread gets at least this many particles. Each extra chunk adds Python
#: launch overhead (splitting 9.4k particles on 32^3 in two cost 20-28 % more CPU per substep), which only
#: larger chunks amortise (docs/results/scale.md).
MIN_PARTICLES_PER_THREAD = 8192


class StepSettings(Protocol):
    """The simulator settings the policy reads (``MPMWarp.Config``)."""

    cfl_safety: float
    frame_time: float | None
    substeps: int
    auto_substep: bool
    checkpoint_every: int | None
    checkpoint_budget_mb: float
    cpu_threads: int | None


def max_stable_dt(settings: StepSettings, model: MPMModel, v_max: float = 0.0) -> float:
    """CFL bound cfl_safety dx / (c + v_max) [s] for this model."""
    return physics.cfl_dt(model.grid.dx, model.E, model.nu, model.density, v_max=v_max, safety=settings.cfl_safety)


def frame_time_for(settings: StepSettings, fps: float | None) -> float:
    """Simulated time of one frame [s]: ``sim.frame_time``, or 1 / ``fps`` when it is null."""
    return physics.frame_time(settings.frame_time, fps)


def unstable(settings: StepSettings, model: MPMModel, dt: float, v_max: float, substeps: int) -> SimulationUnstable:
    """The error for a dt over the CFL bound, naming the substeps that would fit."""
    dt_max = max_stable_dt(settings, model, v_max)
    need = int(math.ceil(substeps * dt / dt_max))
    return SimulationUnstable(
        f"sim: dt={dt:.3g} s breaks the CFL bound dt <= {settings.cfl_safety} dx / (c + |v|max) = {dt_max:.3g} s "
        f"(dx={model.grid.dx:.3g} m, p-wave speed c={model.wave_speed:.3g} m/s, |v|max={v_max:.3g} m/s); "
        f"use dt <= {dt_max:.3g} s (>= {need} substeps for this frame) or set sim.auto_substep=true"
    )


def substeps_for(settings: StepSettings, model: MPMModel, v_max: float, fps: float | None) -> tuple[int, float]:
    """Substeps N and dt [s] for one frame of :func:`frame_time_for` that respect the CFL bound.

    Raises:
        SimulationUnstable: frame_time / substeps breaks the bound and auto_substep is off.
    """
    dt_max = max_stable_dt(settings, model, v_max)
    frame_time = frame_time_for(settings, fps)
    if settings.auto_substep:
        n, dt = physics.substeps_for(frame_time, dt_max, min_substeps=settings.substeps)
        if n > settings.substeps:
            log.info("sim: %d substeps of dt=%.3g s per frame (CFL bound %.3g s; sim.substeps=%d)",
                     n, dt, dt_max, settings.substeps)
        return n, dt
    dt = frame_time / settings.substeps
    if dt > dt_max:
        raise unstable(settings, model, dt, v_max, settings.substeps)
    return settings.substeps, dt


def split_for_cfl(settings: StepSettings, model: MPMModel, substeps: int, dt: float, v_max: float,
                  frame_index: int) -> tuple[int, float]:
    """(substeps, dt) of a rollout after the CFL guard: split further when dt is over the bound (logged), or
    :class:`SimulationUnstable` when ``auto_substep`` is off."""
    dt_max = max_stable_dt(settings, model, v_max)
    if dt <= dt_max * (1.0 + 1e-6):
        return substeps, dt
    if not settings.auto_substep:
        raise unstable(settings, model, dt, v_max, substeps)
    split = int(math.ceil(dt / dt_max))
    log.info("sim: frame %d: dt=%.3g s over the CFL bound %.3g s; running %d x %d substeps of %.3g s",
             frame_index, dt, dt_max, substeps, split, dt / split)
    return substeps * split, dt / split


def checkpoint_interval(settings: StepSettings, n_particles: int, substeps: int) -> int:
    """k: the backward pass stores every k-th substep state (``checkpoint_every`` or from the budget).

    Stored: ceil(N / k) states plus k - 1 recomputed ones, 96 bytes per particle each (x, v, C, F).
    """
    if settings.checkpoint_every is not None:
        return int(settings.checkpoint_every)
    state_mb = 96.0 * n_particles / 2**20
    for k in range(1, substeps + 1):
        if (math.ceil(substeps / k) + k - 1) * state_mb <= settings.checkpoint_budget_mb:
            return k
    k = max(1, int(math.ceil(math.sqrt(substeps))))  # minimises N/k + k when nothing fits
    log.warning(
        "sim: %d substeps of %d particles need %.0f MB of stored states (> sim.checkpoint_budget_mb=%g)",
        substeps, n_particles, (math.ceil(substeps / k) + k - 1) * state_mb, settings.checkpoint_budget_mb,
    )  # fmt: skip
    return k


def threads_for(settings: StepSettings, device: str, n_particles: int) -> int:
    """Threads a rollout of ``n_particles`` runs on: 1 on CUDA, else ``cpu_threads`` or the usable cores.

    Automatic (``cpu_threads`` null): the cores this process may run on, but at most one thread per
    :data:`MIN_PARTICLES_PER_THREAD` particles (tiny scenes stay on one thread).
    """
    if not device.startswith("cpu"):
        return 1
    if settings.cpu_threads is not None:
        return max(1, min(int(settings.cpu_threads), n_particles))
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cores, n_particles // MIN_PARTICLES_PER_THREAD))
