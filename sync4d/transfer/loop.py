"""The transfer loop (paper Sec. 3.4): frame-pair training of a delta-velocity field through the simulator.

For each frame pair t -> t+1:
  1. every simulated particle (a control point or a Gaussian) of part b starts with the reference
     velocity v0 plus the field's delta dv(x);
  2. the differentiable MPM rollout runs N substeps of dt (N dt = the simulated time of one frame);
  3. the loss compares each part's end positions with the reference's motion: the paper's L1 on part
     mass-centroid displacements (``loss_points: centroid``), or, because a centroid cannot tell a
     rotation from a translation (see docs), L1 on a few affine anchors per part (``loss_points:
     anchors``: the centroid and the centroids of the half-spaces along the part's principal axes);
     plus total variation on the triplane;
  4. Adam updates the field until the loss stops improving; the best field advances the state
     (x, F, C; v is re-initialised at the next pair), and the frame is handed to ``on_frame``.

Initial velocities (``transfer.init``): ``centroid`` is the paper's v0 = (b_{t+1} - b_t) / (N dt) per part;
``rigid`` uses the whole rigid motion of the part's bone, v0(x) = (T_rel x - x) / (N dt) with
T_rel = P_{t+1} P_t^{-1}, and the matching APIC matrix C = (R_rel - I) / (N dt).

Targets (``transfer.target_mode``): ``relative`` moves the current anchors by the reference's step (the paper:
errors accumulate), ``absolute`` moves the rest anchors by the reference's pose at t+1 (drift is
corrected at every pair).
"""

from __future__ import annotations

import logging
import random
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from sync4d.registry import build
from sync4d.sim.control import ControlPoints, make_control_points, with_control
from sync4d.transfer.config import TransferConfig
from sync4d.types import DrivingMotion, PartMap, TargetGaussians, Trajectory

log = logging.getLogger(__name__)


@dataclass
class Particles:
    """The simulated set: control points (or the Gaussians themselves) and their parts.

    Attributes:
        points: (P, 3) rest positions [m].
        part: (P,) part of each particle (majority of its Gaussians).
        gaussian_to_point: (N,) particle of each Gaussian.
        counts: (P,) Gaussians per particle.
        volume: (P,) rest volume of each particle [m^3], from geometry: every occupied control cell holds
            one cell volume (side^3), shared among the cell's per-part particles by their Gaussians; so
            neighbouring particles weigh the same however unevenly the Gaussians are spread. None when
            every Gaussian is simulated (the simulator then estimates the volume from occupancy).
    """

    points: np.ndarray
    part: np.ndarray
    gaussian_to_point: np.ndarray
    counts: np.ndarray
    volume: np.ndarray | None = None


def make_particles(target: TargetGaussians, part_map: PartMap, control_grid: int | None) -> Particles:
    """Downsample to control points when ``control_grid`` is set; each point takes its Gaussians' majority part.

    Control cells straddling two parts are split per part so that a particle never mixes parts.
    """
    means = target.means.astype(np.float64)
    if control_grid is None:
        n = len(means)
        return Particles(means, part_map.tgt_part.copy(), np.arange(n), np.ones(n, dtype=np.int64))
    points, g2p, counts = make_control_points(means, control_grid)
    # Split cells by part: key = (cell, part).
    key = g2p * part_map.num_parts + part_map.tgt_part
    _, g2p_split, counts_split = np.unique(key, return_inverse=True, return_counts=True)
    g2p_split = g2p_split.reshape(-1)
    sums = np.zeros((len(counts_split), 3))
    np.add.at(sums, g2p_split, means)
    part = np.zeros(len(counts_split), dtype=np.int64)
    part[g2p_split] = part_map.tgt_part
    cell_of = np.zeros(len(counts_split), dtype=np.int64)
    cell_of[g2p_split] = g2p
    side = float(np.ptp(means, axis=0).max()) / int(control_grid)
    share = counts_split / np.bincount(cell_of, weights=counts_split)[cell_of]
    return Particles(sums / counts_split[:, None], part, g2p_split.astype(np.int64), counts_split.astype(np.int64),
                     volume=share * side**3)


def anchor_weights(x: np.ndarray, part: np.ndarray, num_parts: int, mode: str) -> list[np.ndarray | None]:
    """Per part, a (K, P_b) matrix of affine weights (rows sum to 1) defining K anchors of its particles.

    ``particles``: None per part, meaning every particle is its own anchor (identity weights).
    ``centroid``: K = 1, the part's centroid. ``anchors``: K = 7, the centroid and the centroids of the
    particles on either side of each principal axis. Any affine combination of a body's points moves
    with the body, so the anchors follow rotation as well as translation.
    """
    if mode == "particles":
        return [None] * num_parts
    out: list[np.ndarray | None] = []
    for b in range(num_parts):
        idx = np.flatnonzero(part == b)
        n = len(idx)
        rows = [np.full(n, 1.0 / max(n, 1))]
        if mode == "anchors" and n >= 8:
            centred = x[idx] - x[idx].mean(axis=0)
            _, _, axes = np.linalg.svd(centred, full_matrices=False)
            for axis in axes:
                side = centred @ axis
                for mask in (side > 0, side <= 0):
                    if mask.sum() > 0:
                        rows.append(mask / mask.sum())
        out.append(np.stack(rows))
    return out


def anchor_points(weights: np.ndarray | None, points: np.ndarray) -> np.ndarray:
    """(K, 3) anchors of a part's (P_b, 3) points: ``weights @ points``, or the points themselves."""
    return points if weights is None else weights @ points


def apply_rigid(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(K, 3) points moved by a (4, 4) transform."""
    return points @ transform[:3, :3].T + transform[:3, 3]


class PartLoss:
    """L1 between each part's anchors at the end of a rollout and their targets (paper Eq. L_x)."""

    def __init__(self, part: np.ndarray, weights: list[np.ndarray | None], targets: list[np.ndarray]) -> None:
        self.index = [torch.as_tensor(np.flatnonzero(part == b)) for b in range(len(weights))]
        self.weights = [None if w is None else torch.as_tensor(w, dtype=torch.float32) for w in weights]
        self.targets = [torch.as_tensor(t, dtype=torch.float32) for t in targets]

    def __call__(self, x_end: torch.Tensor) -> torch.Tensor:
        total = x_end.new_zeros(())
        for idx, w, target in zip(self.index, self.weights, self.targets):
            if len(idx):
                anchors = x_end[idx] if w is None else w @ x_end[idx]
                total = total + (anchors - target).abs().sum() / len(anchors)
        return total


def run_mpm_transfer(
    sim: Any,
    target: TargetGaussians,
    part_map: PartMap,
    motion: DrivingMotion,
    *,
    velocity_cfg: Any,
    num_frames: int,
    transfer: TransferConfig | None = None,
    seed: int = 0,
    on_frame: Callable[..., None] | None = None,
    resume: dict[str, Any] | None = None,
) -> Trajectory:
    """Frame-pair training through the differentiable simulator ``sim`` (``sim=mpm_warp``).

    ``transfer`` holds the stage's options (defaults when None); ``seed`` draws the velocity field's
    initial weights.
    """
    cfg = sim.cfg
    options = transfer if transfer is not None else TransferConfig()
    particles = make_particles(target, part_map, cfg.control_grid)
    B = part_map.num_parts
    model = sim.prepare(particles.points, volume=particles.volume)
    grid = model.grid
    lo, hi = grid.origin, grid.origin + (np.asarray(grid.dims) - 1) * grid.dx
    field = build("velocity", velocity_cfg, num_parts=B, bounds=(lo, hi), seed=seed)
    initial_field = {k: v.clone() for k, v in field.state_dict().items()}
    optimizer = torch.optim.Adam(field.parameters(), lr=float(getattr(field.cfg, "lr", 1e-2))) if field.trainable else None

    rest = particles.points
    x = torch.as_tensor(rest, dtype=torch.float32)
    F = torch.eye(3).expand(len(rest), 3, 3).clone()
    C = torch.zeros(len(rest), 3, 3)
    part_t = torch.as_tensor(particles.part)
    rest_anchor_w = anchor_weights(rest, particles.part, B, options.loss_points)
    # Through control points, on_frame gets the points' x and F with the points (control=) and carries
    # the Gaussians itself, one frame at a time; the returned trajectory is per point (with_control).
    control = None if cfg.control_grid is None else ControlPoints(rest, particles.gaussian_to_point)
    frames_x: list[np.ndarray] = []
    frames_F: list[np.ndarray] = []

    def emit(t: int, xp: torch.Tensor, Fp: torch.Tensor, stats: dict[str, float]) -> None:
        x_np, F_np = xp.double().numpy(), Fp.double().numpy()
        frames_x.append(x_np)
        frames_F.append(F_np)
        if on_frame is not None:
            checkpoint = {
                "x": xp.numpy().copy(), "F": Fp.numpy().copy(), "C": C.numpy().copy(),
                "field": {k: v.clone() for k, v in field.state_dict().items()},
                "optimizer": None if optimizer is None else optimizer.state_dict(),
                "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()},
            }
            on_frame(t, x_np, F_np, stats, checkpoint, **({} if control is None else {"control": control}))

    start = 0
    if resume is not None:
        start = int(resume["frame"])
        x, F, C = (torch.as_tensor(resume[k]) for k in ("x", "F", "C"))
        field.load_state_dict(resume["field"])
        if optimizer is not None and resume.get("optimizer") is not None:
            optimizer.load_state_dict(resume["optimizer"])
        torch.set_rng_state(resume["rng"]["torch"])
        np.random.set_state(resume["rng"]["numpy"])
        random.setstate(resume["rng"]["python"])
        # The restored frame (already written by the caller) opens the returned trajectory, so a run
        # resumed after its last frame still returns one.
        frames_x.append(x.double().numpy())
        frames_F.append(F.double().numpy())
        log.info("transfer: resumed after frame %d", start)
    else:
        emit(0, x, F, {"time/frame_s": 0.0})

    for t in range(start, num_frames - 1):
        started = time.perf_counter()
        x_np = x.double().numpy()
        P_t, P_next = motion.part_transforms[t], motion.part_transforms[t + 1]
        relative = P_next @ np.linalg.inv(P_t)  # (B, 4, 4) the reference's step, target space
        if options.target_mode == "absolute":
            weights = rest_anchor_w
            pose = P_next @ np.linalg.inv(motion.part_transforms[0])
            targets = [apply_rigid(pose[b], anchor_points(weights[b], rest[particles.part == b])) for b in range(B)]
        else:
            weights = anchor_weights(x_np, particles.part, B, options.loss_points)
            targets = [apply_rigid(relative[b], anchor_points(weights[b], x_np[particles.part == b])) for b in range(B)]
        loss_fn = PartLoss(particles.part, weights, targets)

        frame_time = sim.frame_time_for(motion.fps)
        v0, C0 = initial_velocity(x_np, particles.part, relative, motion.part_displacements[t], frame_time, options.init)
        v0_t = torch.as_tensor(v0, dtype=torch.float32)
        C0_t = torch.as_tensor(C0, dtype=torch.float32)
        # Headroom for the delta velocities the optimiser may add on top of the reference's.
        v_expected = float(np.linalg.norm(v0, axis=1).max()) * max(abs(field.velocity_scale), 1.0) * 2.0
        substeps, dt = sim.substeps_for(model, v_expected, fps=motion.fps)

        if field.trainable and getattr(field.cfg, "reset_each_frame", False):
            field.load_state_dict(initial_field)

        def rollout(with_grad: bool) -> tuple[torch.Tensor, ...]:
            with torch.set_grad_enabled(with_grad):
                v_init = field.velocity_scale * v0_t + field(x, part_t)
                return sim.rollout(model, x, v_init, F, C0_t * field.velocity_scale, substeps=substeps, dt=dt,
                                   frame_index=t + 1)

        losses: list[float] = []
        if field.trainable and field.cfg.iterations > 0:
            best, best_state, stale = np.inf, None, 0
            for _ in range(int(field.cfg.iterations)):
                optimizer.zero_grad()  # type: ignore[union-attr]
                x1, *_ = rollout(True)
                data = loss_fn(x1)
                loss = data + field.regularizer()
                loss.backward()
                value = float(data.detach())
                losses.append(value)
                if value < best * (1.0 - field.cfg.min_improvement):
                    best, stale = value, 0
                    best_state = {k: v.detach().clone() for k, v in field.state_dict().items()}
                else:
                    stale += 1
                    if stale >= field.cfg.patience:
                        break
                optimizer.step()  # type: ignore[union-attr]
            if best_state is not None:
                field.load_state_dict(best_state)
        x1, _, F1, C1 = (a.detach() for a in rollout(False))
        final = float(loss_fn(x1))
        x, F, C = x1, F1, C1
        stats = {
            "loss/displacement": final,
            "loss/initial": losses[0] if losses else final,
            "loss/iterations": float(len(losses)),
            "time/frame_s": time.perf_counter() - started,
            "time/substeps": float(substeps),
            "sim/dx": float(model.grid.dx),
        }
        log.info("frame %d/%d: loss %.3e -> %.3e in %d iterations, %d substeps, %.1f s", t + 1, num_frames - 1,
                 stats["loss/initial"], final, len(losses), substeps, stats["time/frame_s"])
        emit(t + 1, x, F, stats)

    # After a resume this holds the restored frame and the new ones; the pipeline's writer holds all of them.
    # Per control point: (T, P) arrays, however many Gaussians follow them.
    return with_control(Trajectory(x=np.stack(frames_x), F=np.stack(frames_F), frame_dt=1.0 / motion.fps), control)


def initial_velocity(
    x: np.ndarray, part: np.ndarray, relative: np.ndarray, displacement: np.ndarray, frame_time: float, mode: str
) -> tuple[np.ndarray, np.ndarray]:
    """Initial particle velocities (P, 3) [m/s] and APIC matrices (P, 3, 3) [1/s] for one frame pair.

    Args:
        x: (P, 3) current positions [m]; part: (P,) parts.
        relative: (B, 4, 4) the reference's rigid step P_{t+1} P_t^{-1} per part (target space).
        displacement: (B, 3) the scaled bone-centre displacement (s_t/s_o)(b_{t+1} - b_t) [m].
        frame_time: N dt [s].
        mode: ``centroid`` (paper: one velocity per part) or ``rigid`` (the bone's rigid velocity field).
    """
    if mode == "centroid":
        return displacement[part] / frame_time, np.zeros((len(x), 3, 3))
    rot, trans = relative[part, :3, :3], relative[part, :3, 3]
    moved = np.einsum("pij,pj->pi", rot, x) + trans
    return (moved - x) / frame_time, (rot - np.eye(3)) / frame_time
