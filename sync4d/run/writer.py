"""Everything a run writes as it goes: frames, per-frame metrics, checkpoints, and the final files.

Each completed frame is written at once (``frames/%06d.ply``, after the global transform G_t), logged
to TensorBoard, and checkpointed (``checkpoint.pt``: the simulator's state plus the frames so far), so a
killed run can resume from its last complete frame. All files are written atomically.

A run simulated on control points hands each frame over as the points' x and F (P of them) with the
points (``control``); the writer carries the Gaussians one frame at a time, and keeps, stores
(``state/``, ``trajectory.npz``) and returns only per-point arrays plus the Gaussian-to-point index, so
its memory does not grow with frames x Gaussians. Metrics use at most ``METRIC_GAUSSIANS`` Gaussians
(evenly by stride; all of them below that).

A frame's ``.ply`` (carrying, SH rotation, the 3DGS table: seconds for millions of Gaussians) is made in
a second thread while the simulator computes the next frame, one frame in flight at most; its state
and the checkpoint are written before ``on_frame`` returns, so a resume never depends on it.
"""

from __future__ import annotations

import io
import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from sync4d.geometry import bbox_diagonal, skinned_positions
from sync4d.run import metrics as M
from sync4d.run.plan import flatten
from sync4d.sim.deform import deform_gaussians
from sync4d.sim.mpm_warp import MPMWarp
from sync4d.sim.physics import fit_grid
from sync4d.errors import ConfigError
from sync4d.io.atomic import atomic_save_npz, atomic_write_bytes, atomic_write_json
from sync4d.io.ply import write_gaussians_ply
from sync4d.sim.control import ControlPoints, bounded_subset, gaussian_trajectory, with_control
from sync4d.types import DrivingMotion, PartMap, Reference, TargetGaussians, Trajectory

log = logging.getLogger(__name__)
CHECKPOINT = "checkpoint.pt"
#: The control points of a run simulated through them (``state/control.npz``: rest points and index).
CONTROL = "control.npz"
#: Most Gaussians the metrics follow over every frame (evenly by stride beyond it): bounds their memory.
METRIC_GAUSSIANS = 100_000


class FrameWriter:
    """Receives frames from a simulator (``on_frame``) and writes the run's outputs."""

    def __init__(self, run_dir: Path, target: TargetGaussians, motion: DrivingMotion, *, logger: Any = None,
                 run_config: dict[str, Any] | None = None) -> None:
        """Args:
        run_dir: the run folder (``frames/``, ``checkpoint.pt``, ``metrics.json`` go there).
        target: the target Gaussians at rest; motion: the driving motion (for G_t).
        logger: a ``logger`` component, or None.
        run_config: the settings that determine the results (stored in checkpoints; a resume must match).
        """
        self.run_dir = Path(run_dir)
        self.target = target
        self.motion = motion
        self.logger = logger
        self.run_config = run_config
        self.frames_x: list[np.ndarray] = []
        self.frames_F: list[np.ndarray | None] = []
        self.frame_stats: list[dict[str, float]] = []
        self.frame_seconds: list[float] = []
        self.control: ControlPoints | None = None
        self._last = time.perf_counter()
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="frame-writer")
        self._pending: Future | None = None

    # ----------------------------------------------------------------------------------------- frames
    def on_frame(self, t: int, x: np.ndarray, F: np.ndarray | None, stats: dict[str, float],
                 checkpoint: dict[str, Any] | None = None, control: ControlPoints | None = None) -> None:
        """Write frame ``t``: positions (N, 3) and deformation gradients (N, 3, 3) of every Gaussian, or,
        with ``control``, of its P control points ((P, 3) and (P, 3, 3)), which carry the Gaussians."""
        now = time.perf_counter()
        seconds = stats.get("time/frame_s", now - self._last)
        self._last = now
        if t != len(self.frames_x):
            raise RuntimeError(f"frames must arrive in order: got {t}, expected {len(self.frames_x)}")
        self.frames_x.append(np.asarray(x, dtype=np.float64))
        self.frames_F.append(None if F is None else np.asarray(F, dtype=np.float64))
        self.frame_stats.append({k: float(v) for k, v in stats.items()})
        self.frame_seconds.append(float(seconds))
        if control is not None and self.control is None:
            self.control = control
            atomic_save_npz(self.run_dir / "state" / CONTROL, rest=control.rest,
                            gaussian_to_point=control.gaussian_to_point)
        self.wait_for_frames()  # one frame in flight: memory stays one frame's
        self._pending = self._writer.submit(self.write_frame, t)
        # Exact per-frame state beside the .ply (which holds float32 world Gaussians): a resume reads it
        # back, so the checkpoint itself stays one frame's size however long the run.
        atomic_save_npz(state_path(self.run_dir, t), x=self.frames_x[-1],
                        F=np.zeros(0) if self.frames_F[-1] is None else self.frames_F[-1])
        if self.logger is not None:
            for key, value in stats.items():
                self.logger.scalar(key if "/" in key else f"loss/{key}", value, t)
        if checkpoint is not None:
            self.save_checkpoint(t, checkpoint)

    def write_frame(self, t: int) -> None:
        """``frames/%06d.ply`` of received frame ``t``."""
        write_gaussians_ply(self.run_dir / "frames" / f"{t:06d}.ply", self.gaussians_at(t))

    def wait_for_frames(self) -> None:
        """Block until the frame being written is on disk (re-raising its error, if any)."""
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()

    def gaussians_at(self, t: int) -> TargetGaussians:
        """Every Gaussian of received frame ``t`` in the world (carried by the control points if any)."""
        x, F, G = self.frames_x[t], self.frames_F[t], self.motion.global_transforms[t]
        if self.control is not None:
            assert F is not None, "control points are carried by their deformation gradients"
            return self.control.carry(self.target, x, F, G)
        return deform_gaussians(self.target, x, F, G)

    def save_checkpoint(self, t: int, state: dict[str, Any]) -> None:
        """Atomically store the simulator's state after frame ``t`` (the frames themselves are in ``state/``)."""
        import torch

        payload = {
            "frame": t,
            "config": self.run_config,
            "sim": state,
            "frame_stats": self.frame_stats,
            "frame_seconds": self.frame_seconds,
        }
        buffer = io.BytesIO()
        torch.save(payload, buffer)
        atomic_write_bytes(self.run_dir / CHECKPOINT, buffer.getvalue())

    def resume_state(self, resume: str | None) -> dict[str, Any] | None:
        """Load ``<resume>/checkpoint.pt`` (if ``resume`` is set) and restore the frames it holds.

        The restored frames are written again into this run's folder (a resumed run never writes into
        the interrupted run's folder) and re-logged.

        Returns:
            The simulator's saved state (``sim``) with ``frame`` = the last complete frame, or None.

        Raises:
            ConfigError: no readable checkpoint there, or it was made with different settings.
        """
        if not resume:
            return None
        folder = Path(resume).expanduser()
        payload = load_checkpoint(folder, resume)
        check_same_config(payload.get("config"), self.run_config, resume)
        last = int(payload["frame"])
        self.frames_x, self.frames_F = read_frame_states(folder, last, resume)
        self.control = read_control(folder, resume)
        if self.control is not None:
            atomic_save_npz(self.run_dir / "state" / CONTROL, rest=self.control.rest,
                            gaussian_to_point=self.control.gaussian_to_point)
        self.frame_stats = list(payload["frame_stats"])
        self.frame_seconds = list(payload["frame_seconds"])
        if len(self.frame_stats) != last + 1:
            raise ConfigError(f"resume={resume}: {CHECKPOINT} holds {len(self.frame_stats)} frame records for frame "
                              f"{last}; it is damaged, start the run again")
        for t, (x, F) in enumerate(zip(self.frames_x, self.frames_F)):
            self.write_frame(t)
            atomic_save_npz(state_path(self.run_dir, t), x=x, F=np.zeros(0) if F is None else F)
            if self.logger is not None:
                for key, value in self.frame_stats[t].items():
                    self.logger.scalar(key if "/" in key else f"loss/{key}", value, t)
        log.info("resuming from %s after frame %d", resume, payload["frame"])
        return {**payload["sim"], "frame": int(payload["frame"])}

    # ------------------------------------------------------------------------------------------ final
    def finish(self, trajectory: Trajectory, *, reference: Reference, part_map: PartMap, self_transfer: bool,
               loop: bool, run_name: str, overrides: dict[str, str], wall_seconds: float,
               extra: dict[str, Any] | None = None) -> tuple[dict[str, Any], Trajectory]:
        """Write ``trajectory.npz`` and ``metrics.json`` (with ``extra`` merged in) and log the metrics and hparams.

        The trajectory is rebuilt from the frames this writer received (all of them, including those
        restored on resume); the simulator's own ``trajectory`` supplies the frame interval and velocities.
        Returns the metrics and that whole trajectory (what the renders and exports are made from): per
        control point, marked with them (:func:`sync4d.sim.control.control_of`), when the run had them.

        ``trajectory.npz`` holds x, F (and v) of what was simulated with its ``part``; with control
        points also ``gaussian_to_point`` (N,), ``control_rest`` (P, 3) and ``gaussian_part`` (N,).
        """
        self.wait_for_frames()
        self._writer.shutdown(wait=True)  # every frame is on disk; no idle thread outlives the run
        known_F = [F for F in self.frames_F if F is not None]
        full_F = np.stack(known_F) if len(known_F) == len(self.frames_F) else None
        trajectory = with_control(Trajectory(
            x=np.stack(self.frames_x), F=full_F, frame_dt=trajectory.frame_dt,
            v=trajectory.v if trajectory.v is not None and len(trajectory.v) == len(self.frames_x) else None,
            global_transforms=self.motion.global_transforms[: len(self.frames_x)],
        ).validate(), self.control)
        control = {} if self.control is None else {
            "gaussian_to_point": self.control.gaussian_to_point, "control_rest": self.control.rest,
            "gaussian_part": part_map.tgt_part}
        atomic_save_npz(
            self.run_dir / "trajectory.npz",
            x=trajectory.x.astype(np.float32),
            v=np.zeros(0) if trajectory.v is None else trajectory.v.astype(np.float32),
            F=np.zeros(0) if trajectory.F is None else trajectory.F.astype(np.float32),
            global_transforms=self.motion.global_transforms[: trajectory.num_frames],
            part=part_map.tgt_part if self.control is None else self.control.point_parts(part_map.tgt_part),
            frame_dt=np.float64(trajectory.frame_dt),
            **control,
        )
        result = compute_metrics(
            trajectory, self.target, part_map, self.motion, reference,
            self_transfer=self_transfer,
            frame_seconds=self.frame_seconds,
            loop=loop,
            dx=next((row["sim/dx"] for row in self.frame_stats if "sim/dx" in row), None),
        )
        result["wall_seconds"] = wall_seconds
        result["status"] = "ok"
        result["overrides"] = overrides
        result["frame_stats"] = self.frame_stats
        dx = [row["sim/dx"] for row in self.frame_stats if "sim/dx" in row]
        result["dx"] = dx[0] if dx else None
        result.update(extra or {})
        atomic_write_json(self.run_dir / "metrics.json", result)
        if self.logger is not None:
            for t, row in enumerate(result["per_frame"]):
                for key, value in row.items():
                    if value is not None and np.isfinite(value):
                        self.logger.scalar(f"metric/{key}", value, t)
            self.logger.hparams(overrides or {"config": run_name},
                                {k: v for k, v in result.items() if isinstance(v, (int, float))})
        log.info("metrics: %s", {k: v for k, v in result.items() if k.endswith(("_pct", "_ratio", "deviation", "per_frame_s"))})
        return result, trajectory


def state_path(run_dir: Path, t: int) -> Path:
    """Where frame ``t``'s exact state (Gaussian centres and deformation gradients, float64) is kept."""
    return Path(run_dir) / "state" / f"{t:06d}.npz"


def read_frame_states(folder: Path, last: int, resume: str) -> tuple[list[np.ndarray], list[np.ndarray | None]]:
    """Frames 0..last of an interrupted run: x (N, 3) and F (N, 3, 3) or None each, from ``state/``.

    Raises:
        ConfigError: a frame's state file is missing or unreadable (names it and what to do).
    """
    xs: list[np.ndarray] = []
    Fs: list[np.ndarray | None] = []
    for t in range(last + 1):
        path = state_path(folder, t)
        try:
            with np.load(path) as data:
                xs.append(np.asarray(data["x"], dtype=np.float64))
                F = np.asarray(data["F"], dtype=np.float64)
        except (OSError, KeyError, ValueError) as err:
            raise ConfigError(
                f"resume={resume}: frame {t}'s state {path} is missing or unreadable ({type(err).__name__}); "
                "the checkpoint needs every frame up to it: start the run again"
            ) from None
        Fs.append(None if F.size == 0 else F)
    return xs, Fs


def read_control(folder: Path, resume: str) -> ControlPoints | None:
    """The control points of an interrupted run (``state/control.npz``), or None if it had none.

    Raises:
        ConfigError: the file is there but unreadable.
    """
    path = Path(folder) / "state" / CONTROL
    if not path.is_file():
        return None
    try:
        with np.load(path) as data:
            return ControlPoints(np.asarray(data["rest"], dtype=np.float64),
                                 np.asarray(data["gaussian_to_point"], dtype=np.int64))
    except (OSError, KeyError, ValueError) as err:
        raise ConfigError(f"resume={resume}: {path} is unreadable ({type(err).__name__}); start the run again") from None


def load_checkpoint(folder: Path, resume: str) -> dict[str, Any]:
    """Read ``<folder>/checkpoint.pt``; any failure is a :class:`ConfigError` naming ``resume``."""
    import torch

    path = folder / CHECKPOINT
    if not folder.is_dir():
        raise ConfigError(f"resume={resume}: no such folder; pass the folder of an interrupted run")
    if not path.is_file():
        done = " (that run finished: it has metrics.json)" if (folder / "metrics.json").is_file() else ""
        raise ConfigError(f"resume={resume}: no {CHECKPOINT} there{done}; pass the folder of an interrupted run")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # noqa: BLE001 - torch/pickle raise many types for a bad file
        raise ConfigError(f"resume={resume}: {CHECKPOINT} is unreadable ({type(err).__name__}: {err}); "
                          "start the run again") from None
    if not isinstance(payload, dict) or not {"frame", "sim", "frame_stats"} <= set(payload):
        raise ConfigError(f"resume={resume}: {CHECKPOINT} is not a sync4d run checkpoint")
    return payload


def check_same_config(saved: dict[str, Any] | None, current: dict[str, Any] | None, resume: str) -> None:
    """Raise :class:`ConfigError` naming the first settings that differ between a checkpoint and this run."""
    if saved is None or current is None:
        return
    old, new = flatten(saved), flatten(current)
    differ = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))
    if differ:
        shown = ", ".join(f"{k}={old.get(k)!r} (now {new.get(k)!r})" for k in differ[:3])
        more = f" and {len(differ) - 3} more" if len(differ) > 3 else ""
        raise ConfigError(f"resume={resume}: that run used {shown}{more}; resume with the same overrides")


def fragment_gap(rest: np.ndarray, dx: float | None) -> float:
    """Distance [m] beyond which a piece counts as detached: two cells of the run's grid (``dx`` [m]), or
    without one (``sim=lbs``, ``sim=kinematic``) of the grid the default ``sim=mpm_warp`` fits to the same rest
    shape (its Config's ``n_grid``, ``grid_padding`` and ``wall_cells``), so every method is judged alike."""
    if dx is None:
        defaults = MPMWarp.Config()
        dx = fit_grid(np.asarray(rest, dtype=np.float64), n_grid=defaults.n_grid, padding=defaults.grid_padding,
                      wall=defaults.wall_cells).dx
    return 2.0 * float(dx)


def self_transfer_truth(reference: Reference, rest: np.ndarray, num_frames: int, *, loop: bool) -> np.ndarray:
    """(T, N, 3) the truth of a self-transfer: ``rest`` points posed by the reference's own bones and skinning.

    Each point takes the blend weights of its nearest reference rest vertex and moves by
    ``reference.bone_transforms[t] @ inv(bone_transforms[0])`` (articulation only; G_t is applied after
    the simulation). Neither the part map nor the driving motion enters, so an error in either shows.
    """
    from scipy.spatial import cKDTree

    from sync4d.transfer.motion import frame_indices

    _, nearest = cKDTree(reference.rest_vertices).query(rest)
    weights = reference.skinning[nearest]
    idx = frame_indices(reference.num_frames, num_frames, loop=loop)
    bones = reference.bone_transforms[idx] @ np.linalg.inv(reference.bone_transforms[idx[0]])[None]
    return np.stack([skinned_positions(rest, weights, bones[t]) for t in range(num_frames)])


def compute_metrics(
    trajectory: Trajectory,
    target: TargetGaussians,
    part_map: PartMap,
    motion: DrivingMotion,
    reference: Reference,
    *,
    self_transfer: bool,
    frame_seconds: list[float],
    truth: np.ndarray | None = None,
    loop: bool = True,
    dx: float | None = None,
) -> dict[str, Any]:
    """All metrics of a run, overall (frames 1..T) and per frame (see :mod:`sync4d.run.metrics`).

    A control-point trajectory is carried to the Gaussians first; beyond ``METRIC_GAUSSIANS`` Gaussians
    every metric but the bounding-box diagonal is computed on that many, evenly by stride.

    Args:
        truth: (T, N, 3) independent ground-truth positions, or None; with ``self_transfer`` and no
            ``truth`` it is :func:`self_transfer_truth`.
        loop: the driving motion loops the reference (for the self-transfer truth's frame indices).
        dx: the simulator's grid cell [m] (sets the fragment gap; None: the default grid's).
    """
    diagonal = bbox_diagonal(target.means)
    index = bounded_subset(target.num, METRIC_GAUSSIANS)
    trajectory = gaussian_trajectory(trajectory, target.means, index)
    if index is not None and truth is not None:
        truth = np.asarray(truth)[:, index]
    x = trajectory.x
    T = len(x)
    parts, B = part_map.tgt_part if index is None else part_map.tgt_part[index], part_map.num_parts
    accumulated = np.concatenate([np.zeros((1, B, 3)), np.cumsum(motion.part_displacements[: T - 1], axis=0)])
    if truth is None and self_transfer:
        truth = self_transfer_truth(reference, x[0], T, loop=loop)
    integrity = M.integrity_model(x[0], parts, B, gap=fragment_gap(x[0], dx), truth=truth)
    true_volumes = [None] * T if truth is None else [M.part_volumes(truth[t], parts, B) for t in range(T)]
    frames = [M.integrity_frame(integrity, x[t], true_volume=true_volumes[t]) for t in range(T)]
    follow = M.follow_error(x[0], x, parts, motion.part_transforms, diagonal)
    follow_rot, follow_trans = follow.frame_means()

    per_frame = []
    for t in range(T):
        per_frame.append({
            "displacement_error_pct": None if t == 0 else M.displacement_error(
                x[t - 1], x[t], parts, motion.part_displacements[t - 1], diagonal),
            "drift_pct": M.drift(x[t], x[0], parts, accumulated[t], diagonal),
            "rigidity_residual_pct": M.rigidity_residual(x[0], x[t], parts, B, diagonal),
            "det_f_deviation": M.det_f_deviation(None if trajectory.F is None else trajectory.F[t]),
            "pose_error_pct": None if truth is None else M.pose_error(x[t], truth[t], diagonal),
            "torn_pairs_pct": frames[t].torn_pairs_pct,
            "torn_seam_pairs_pct": frames[t].torn_seam_pairs_pct,
            "strain_p99_pct": frames[t].strain_p99_pct,
            "volume_change_pct": frames[t].body_volume_change_pct,
            "fragments": float(frames[t].fragments),
            "follow_rotation_deg": None if t == 0 else finite_or_none(follow_rot[t]),
            "follow_translation_pct": None if t == 0 else finite_or_none(follow_trans[t]),
            "seconds": frame_seconds[t] if t < len(frame_seconds) else None,
        })

    return {
        "pose_error_pct": mean_after_rest(per_frame, "pose_error_pct"),
        "pose_error_max_pct": None if truth is None else float(max(v for r in per_frame[1:] or per_frame if (v := r["pose_error_pct"]) is not None)),
        "displacement_error_pct": mean_after_rest(per_frame, "displacement_error_pct"),
        "drift_pct": mean_after_rest(per_frame, "drift_pct"),
        "drift_final_pct": per_frame[-1]["drift_pct"],
        "rigidity_residual_pct": mean_after_rest(per_frame, "rigidity_residual_pct"),
        "det_f_deviation": mean_after_rest(per_frame, "det_f_deviation"),
        **M.integrity_summary(frames),
        "tear_curve": M.tear_curve(x[0], x, integrity.gap, truth=truth),
        **M.follow_summary(follow),
        "jitter_ratio": jitter_of(x, truth, reference, motion),
        "seconds_per_frame": float(np.mean(frame_seconds[1:])) if len(frame_seconds) > 1 else float(np.mean(frame_seconds or [0.0])),
        "peak_memory_mb": M.peak_memory_mb(),
        "frames": T,
        "coverage_ratio": motion.coverage_ratio,
        "per_frame": per_frame,
    }


def mean_after_rest(per_frame: list[dict[str, Any]], key: str) -> float | None:
    """Mean of ``key`` over frames 1..T (frame 0 is the rest pose, exact by construction), None if unknown."""
    values = [r[key] for r in per_frame[1:] if r[key] is not None]
    return float(np.mean(values)) if values else None


def jitter_of(x: np.ndarray, truth: np.ndarray | None, reference: Reference, motion: DrivingMotion) -> float:
    """Jitter ratio of (T, N, 3) positions against the truth's own, else the reference's (scaled)."""
    if truth is not None:
        return M.jitter_ratio(x, truth, 1.0)
    ref_seq = np.stack([reference.posed_vertices(t % reference.num_frames) for t in range(len(x))])
    return M.jitter_ratio(x, ref_seq, motion.coverage_ratio)


def finite_or_none(value: float) -> float | None:
    """``value`` as a float, None when it is NaN or inf."""
    return float(value) if np.isfinite(value) else None
