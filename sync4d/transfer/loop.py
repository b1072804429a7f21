"""The transfer loop (paper Sec. 3.4): frame-pair training of a delta-velocity field through a simulator.

The transfer owns the loop; the simulator only steps (:class:`sync4d.interfaces.Simulator`). For each frame
pair t -> t+1:
  1. every simulated particle (a control point or a Gaussian) of part b starts with the reference velocity
     v0 plus the field's delta dv(x) (``transfer.init``: the bone's rigid velocity field, or the paper's one
     velocity per part);
  2. the simulator rolls out N substeps of dt (N dt = the simulated time of one frame), given the parts'
     poses at t and t+1 (point-wise simulators follow them; the MPM follows its initial velocities);
  3. the loss compares each part's end positions with the reference's motion (``transfer.loss_points``,
     ``transfer.target_mode``) plus the field's own regulariser (the triplane's total variation);
  4. Adam updates the field until the loss stops improving; the best field advances the state (x, F, C; v
     is re-initialised at the next pair), and the frame is handed to ``on_frame``.
"""

from __future__ import annotations

import logging
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from sync4d.geometry import skew_matrices
from sync4d.interfaces import GridModel, Simulator, VelocityField
from sync4d.rng import deterministic_torch
from sync4d.sim.control import ControlPoints, with_control
from sync4d.transfer.budget import SPEED_HEADROOM
from sync4d.transfer.config import TransferConfig
from sync4d.transfer.loss import PartLoss, anchor_targets, anchor_weights, initial_velocity
from sync4d.transfer.particles import Particles, make_particles
from sync4d.types import DrivingMotion, FramePose, PartMap, TargetGaussians, Trajectory

log = logging.getLogger(__name__)

#: ``on_frame(t, x, F, stats, checkpoint, control=...)``: a finished frame (see :class:`sync4d.run.writer.FrameWriter`).
FrameCallback = Callable[..., None]
#: Builds the velocity field of a transfer: ``(num_parts=B, bounds=(lo, hi), seed=...)``.
FieldFactory = Callable[..., VelocityField]


@dataclass
class ParticleState:
    """The simulated particles between frame pairs (float32): x (P, 3) [m], F (P, 3, 3), C (P, 3, 3) [1/s], and the
    velocities v (P, 3) [m/s] the last frame ended with (None at rest)."""

    x: torch.Tensor
    F: torch.Tensor
    C: torch.Tensor
    v: torch.Tensor | None = None


@dataclass
class Transfer:
    """What stays fixed through one transfer: the simulator and its model, the particles, the field and its
    optimiser, the options and the driving motion."""

    simulator: Simulator
    model: Any
    particles: Particles
    velocity_field: VelocityField
    optimizer: torch.optim.Optimizer | None
    options: TransferConfig
    motion: DrivingMotion
    control: ControlPoints | None
    initial_field: dict[str, torch.Tensor] = field(default_factory=dict)

    @property
    def num_parts(self) -> int:
        return int(self.motion.part_transforms.shape[1])

    @property
    def trains(self) -> bool:
        return self.optimizer is not None and self.options.iterations > 0


def setup_transfer(simulator: Simulator, make_field: FieldFactory, options: TransferConfig, target: TargetGaussians,
                   part_map: PartMap, motion: DrivingMotion, *, seed: int) -> Transfer:
    """The particles (control points split by part), the simulator's model, the velocity field over the
    simulated box and its optimiser."""
    particles = make_particles(target, part_map, options.control_grid)
    model = simulator.prepare(particles.points, volume=particles.volume, part=particles.part,
                              parent=motion.part_parent)
    num_parts = part_map.num_parts
    velocity = make_field(num_parts=num_parts, bounds=simulator.domain(model), seed=seed)
    trains = velocity.trainable and options.iterations > 0
    if trains and not simulator.differentiable:
        log.info("transfer: this simulator carries no gradient; the velocity field is not trained")
        trains = False
    optimizer = torch.optim.Adam(velocity.parameters(), lr=options.lr) if trains else None
    control = None if options.control_grid is None else ControlPoints(particles.points, particles.gaussian_to_point)
    return Transfer(simulator, model, particles, velocity, optimizer, options, motion, control,
                    {k: v.clone() for k, v in velocity.state_dict().items()})


def rest_state(transfer: Transfer) -> ParticleState:
    """Every particle at rest: x the rest points, F = I, C = 0, in the simulator's float type."""
    n, dtype = len(transfer.particles.points), transfer.simulator.dtype
    return ParticleState(torch.as_tensor(transfer.particles.points, dtype=dtype),
                         torch.eye(3, dtype=dtype).expand(n, 3, 3).clone(), torch.zeros(n, 3, 3, dtype=dtype))


def frame_pose(transfer: Transfer, t: int) -> FramePose:
    """The parts' rest -> t and rest -> t+1 poses in the target's frame."""
    P = transfer.motion.part_transforms
    rest_inverse = np.linalg.inv(P[0])
    return FramePose(start=P[t] @ rest_inverse, end=P[t + 1] @ rest_inverse)


def frame_loss(transfer: Transfer, x_np: np.ndarray, t: int) -> PartLoss:
    """The displacement loss of frame pair t -> t+1 (``transfer.loss_points``, ``transfer.target_mode``)."""
    options, particles, P = transfer.options, transfer.particles, transfer.motion.part_transforms
    B = transfer.num_parts
    if options.target_mode == "absolute":
        weights = anchor_weights(particles.points, particles.part, B, options.loss_points)
        targets = anchor_targets(particles.points, particles.part, weights, P[t + 1] @ np.linalg.inv(P[0]))
    else:
        weights = anchor_weights(x_np, particles.part, B, options.loss_points)
        targets = anchor_targets(x_np, particles.part, weights, P[t + 1] @ np.linalg.inv(P[t]))
    return PartLoss(particles.part, weights, targets)


def optimise_field(transfer: Transfer, rollout: Callable[[bool], tuple[torch.Tensor, ...]],
                   loss_fn: PartLoss) -> list[float]:
    """Adam steps on the field until the data loss stops improving; the best field is kept. Returns the
    data loss of every step."""
    options, velocity, optimizer = transfer.options, transfer.velocity_field, transfer.optimizer
    assert optimizer is not None
    losses: list[float] = []
    best, best_state, stale = np.inf, None, 0
    for _ in range(options.iterations):
        optimizer.zero_grad()
        x1, *_ = rollout(True)
        data = loss_fn(x1)
        (data + velocity.regularizer()).backward()
        value = float(data.detach())
        losses.append(value)
        if value < best * (1.0 - options.min_improvement):
            best, stale = value, 0
            best_state = {k: v.detach().clone() for k, v in velocity.state_dict().items()}
        else:
            stale += 1
            if stale >= options.patience:
                break
        optimizer.step()
    if best_state is not None:
        velocity.load_state_dict(best_state)
    return losses


def advance(transfer: Transfer, state: ParticleState, t: int) -> tuple[ParticleState, dict[str, float]]:
    """Frame pair t -> t+1: initial velocities, the field trained through the simulator, the state advanced."""
    started = time.perf_counter()
    sim, motion, velocity, particles = transfer.simulator, transfer.motion, transfer.velocity_field, transfer.particles
    x_np = state.x.double().numpy()
    P = motion.part_transforms
    frame_time = sim.frame_time_for(motion.fps)
    v0, C0 = initial_velocity(x_np, particles.part, P[t + 1] @ np.linalg.inv(P[t]), motion.part_displacements[t],
                              frame_time, transfer.options.init, rest=particles.points,
                              pose=P[t + 1] @ np.linalg.inv(P[0]))
    if transfer.options.init == "drive" and state.v is not None:
        # the drive sets each part's rigid motion anew; what the material was doing besides carries on
        dv, dC = complementary_motion(x_np, state.v.double().numpy(), state.C.double().numpy(), particles.part,
                                      transfer.num_parts)
        v0, C0 = v0 + dv, C0 + dC
    dtype = sim.dtype
    v0_t, C0_t = torch.as_tensor(v0, dtype=dtype), torch.as_tensor(C0, dtype=dtype)
    part_t = torch.as_tensor(particles.part)
    # Headroom for the delta velocities the optimiser may add on top of the reference's.
    v_expected = float(np.linalg.norm(v0, axis=1).max()) * max(abs(velocity.velocity_scale), 1.0) * SPEED_HEADROOM
    substeps, dt = sim.substeps_for(transfer.model, v_expected, fps=motion.fps)
    pose = frame_pose(transfer, t)
    loss_fn = frame_loss(transfer, x_np, t)
    if transfer.trains and transfer.options.reset_each_frame:
        velocity.load_state_dict(transfer.initial_field)

    def rollout(with_grad: bool) -> tuple[torch.Tensor, ...]:
        with torch.set_grad_enabled(with_grad):
            v_init = velocity.velocity_scale * v0_t + velocity(state.x.float(), part_t).to(dtype)
            return sim.rollout(transfer.model, state.x, v_init, state.F, C0_t * velocity.velocity_scale,
                               substeps=substeps, dt=dt, frame_index=t + 1, pose=pose)

    with deterministic_torch():  # the field's grid_sample backward accumulates from several threads
        losses = optimise_field(transfer, rollout, loss_fn) if transfer.trains else []
    x1, v1, F1, C1 = (a.detach() for a in rollout(False))
    final = float(loss_fn(x1))
    stats = {
        "loss/displacement": final, "loss/initial": losses[0] if losses else final,
        "loss/iterations": float(len(losses)), "time/frame_s": time.perf_counter() - started,
        "time/substeps": float(substeps), **({"sim/dx": float(transfer.model.grid.dx)}
                                             if isinstance(transfer.model, GridModel) else {}),
    }  # fmt: skip
    log.info("frame %d/%d: loss %.3e -> %.3e in %d iterations, %d substeps, %.1f s", t + 1,
             motion.num_frames - 1, stats["loss/initial"], final, len(losses), substeps, stats["time/frame_s"])
    return ParticleState(x1, F1, C1, v1), stats


def complementary_motion(x: np.ndarray, v: np.ndarray, C: np.ndarray, part: np.ndarray, num_parts: int
                         ) -> tuple[np.ndarray, np.ndarray]:
    """What (P, 3) velocities [m/s] and (P, 3, 3) APIC matrices [1/s] hold besides each part's rigid motion.

    Per part, the least-squares rigid velocity field a + w x (x - c) (c the part's centroid) is taken off ``v``
    and its spin [w]x off ``C``: the elastic motion the drive does not control, which carries into the next frame.
    """
    dv, dC = v.copy(), C.copy()
    for b in range(num_parts):
        idx = np.flatnonzero(part == b)
        if len(idx) == 0:
            continue
        r = x[idx] - x[idx].mean(axis=0)
        a = v[idx].mean(axis=0)
        inertia = np.eye(3) * (r * r).sum() - r.T @ r
        w = np.linalg.lstsq(inertia, np.cross(r, v[idx] - a).sum(axis=0), rcond=1e-9)[0]
        dv[idx] -= a + np.cross(w, r)
        dC[idx] -= skew_matrices(w)
    return dv, dC


def checkpoint_of(transfer: Transfer, state: ParticleState) -> dict[str, Any]:
    """Everything a resume needs after a frame: the particles, the field and its optimiser, the RNG states."""
    return {
        "x": state.x.numpy().copy(), "F": state.F.numpy().copy(), "C": state.C.numpy().copy(),
        "v": None if state.v is None else state.v.numpy().copy(),
        "field": {k: v.clone() for k, v in transfer.velocity_field.state_dict().items()},
        "optimizer": None if transfer.optimizer is None else transfer.optimizer.state_dict(),
        "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()},
    }


def restore(transfer: Transfer, saved: dict[str, Any]) -> ParticleState:
    """The state, field, optimiser and RNG states of a checkpoint (:func:`checkpoint_of`)."""
    x, F, C = (torch.as_tensor(saved[k]) for k in ("x", "F", "C"))
    v = None if saved.get("v") is None else torch.as_tensor(saved["v"])
    transfer.velocity_field.load_state_dict(saved["field"])
    if transfer.optimizer is not None and saved.get("optimizer") is not None:
        transfer.optimizer.load_state_dict(saved["optimizer"])
    torch.set_rng_state(saved["rng"]["torch"])
    np.random.set_state(saved["rng"]["numpy"])
    random.setstate(saved["rng"]["python"])
    return ParticleState(x, F, C, v)


def run_transfer(
    simulator: Simulator,
    make_field: FieldFactory,
    options: TransferConfig,
    target: TargetGaussians,
    part_map: PartMap,
    motion: DrivingMotion,
    *,
    num_frames: int,
    seed: int = 0,
    on_frame: FrameCallback | None = None,
    resume: dict[str, Any] | None = None,
) -> Trajectory:
    """Animate ``target`` with ``motion`` frame pair by frame pair through ``simulator``.

    Args:
        simulator: a built ``sim`` component; make_field: builds the ``velocity`` component.
        options: the transfer's options; target, part_map, motion: the stages' results.
        num_frames: output frames T (frame 0 is the rest pose).
        seed: draws the velocity field's initial weights.
        on_frame: called after every frame with the particles' x and F, the frame's stats, a checkpoint and,
            through control points, ``control=`` the points the Gaussians follow.
        resume: a checkpoint (plus ``frame``, the last complete frame) to continue from.

    Returns:
        The trajectory per simulated particle (marked with its control points when it has them): after a
        resume it opens with the restored frame.
    """
    transfer = setup_transfer(simulator, make_field, options, target, part_map, motion, seed=seed)
    extra = {} if transfer.control is None else {"control": transfer.control}
    frames: list[ParticleState] = []

    def emit(t: int, state: ParticleState, stats: dict[str, float]) -> None:
        frames.append(state)
        if on_frame is not None:
            on_frame(t, state.x.double().numpy(), state.F.double().numpy(), stats, checkpoint_of(transfer, state),
                     **extra)

    start = 0
    if resume is not None:
        start = int(resume["frame"])
        frames.append(restore(transfer, resume))  # already written by the caller; opens the trajectory
        log.info("transfer: resumed after frame %d", start)
    else:
        emit(0, rest_state(transfer), {"time/frame_s": 0.0})
    for t in range(start, num_frames - 1):
        state, stats = advance(transfer, frames[-1], t)
        emit(t + 1, state, stats)
    trajectory = Trajectory(x=np.stack([s.x.double().numpy() for s in frames]),
                            F=np.stack([s.F.double().numpy() for s in frames]), frame_dt=1.0 / motion.fps)
    return with_control(trajectory, transfer.control)
