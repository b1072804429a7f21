"""``run(cfg)``: the stages wired in order from one :class:`RunPlan`. No algorithm lives here.

reference -> recon -> target -> features/match -> driving motion -> transfer (simulator + velocity field) ->
metrics -> render/export. Every completed frame is written as it is produced (``frames/%06d.ply``) so an
interrupted run loses nothing; reconstruction and matching are cached by :mod:`sync4d.cache`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import platform
import random
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Any, cast

import numpy as np
from omegaconf import DictConfig

from sync4d import cache
from sync4d.errors import ConfigError, Sync4DError
from sync4d.sim import physics
from sync4d.frontend.outputs import write_video_inputs
from sync4d.geometry import part_centroids
from sync4d.interfaces import (CheckedTarget, FigureWriter, FileSourceConfig, GridSimulatorConfig, Logger,
                               Reconstructor, ReferenceSource, TargetSource, VelocityField)
from sync4d.io.atomic import atomic_write_json
from sync4d.io.ply import write_gaussians_ply
from sync4d.match import match_parts
from sync4d.paths import PROJECT_ROOT
from sync4d.run import figures
from sync4d.run.plan import RunPlan, build_plan, run_dir_of
from sync4d.run.writer import FrameWriter
from sync4d.sources.targets import check_target_extent
from sync4d.surface import target_surface
from sync4d.transfer.budget import check_run_cost, choose_budget
from sync4d.transfer.loop import run_transfer
from sync4d.transfer.motion import driving_motion
from sync4d.types import DrivingMotion, PartMap, Reference, ReferenceInput, TargetGaussians, Trajectory

log = logging.getLogger("sync4d")

PACKAGES = ("torch", "warp-lang", "hydra-core", "omegaconf", "numpy", "trimesh", "scipy")
#: What floater removal did to a splat target (counts, removed and kept boxes), also in metrics.json.
FLOATERS = "floaters.json"
#: Files whose presence marks a folder as another run's.
RUN_MARKERS = ("metrics.json", "checkpoint.pt")


class RunFolderInUse(ConfigError):
    """The run folder already holds another run's outputs; nothing is written into it."""


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (the one ``seed`` of the config)."""
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def git(*args: str) -> str | None:
    """The output of a git command in the project, or None when git is not there."""
    try:
        return subprocess.run(["git", *args], cwd=PROJECT_ROOT, capture_output=True, text=True, timeout=10,
                              check=False).stdout.strip()
    except OSError:
        return None


def environment_record(device: str) -> dict[str, Any]:
    """Git SHA, package versions, python, platform and device, for ``env.json``."""
    status = git("status", "--porcelain")
    versions: dict[str, str | None] = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "git_sha": git("rev-parse", "HEAD") or None, "git_dirty": None if status is None else bool(status),
        "python": sys.version.split()[0], "platform": platform.platform(), "device": device, "packages": versions,
        "argv": sys.argv,
    }  # fmt: skip


def claim_run_dir(run_dir: Path, resume: str | None) -> None:
    """Refuse a run folder that holds another run's outputs, or that is the folder being resumed.

    A run never overwrites another run's folder: a resumed run writes a new folder (Hydra's default
    ``outputs/<name>/<timestamp>``), copying the frames it restores from the checkpoint.
    """
    if resume and Path(resume).expanduser().resolve() == run_dir.resolve():
        raise RunFolderInUse(
            f"resume={resume} is also this run's folder (hydra.run.dir); a resumed run writes a new folder: "
            "drop hydra.run.dir or point it elsewhere"
        )
    taken = [name for name in RUN_MARKERS if (run_dir / name).exists()]
    frames = run_dir / "frames"
    if frames.is_dir() and any(frames.glob("*.ply")):
        taken.append("frames/")
    if taken:
        raise RunFolderInUse(
            f"hydra.run.dir={run_dir} already holds another run's {', '.join(taken)}; a run never overwrites "
            f"another: choose a new folder, or continue that run with resume={run_dir} (into a new folder)"
        )


# ---------------------------------------------------------------------------------------------- stages


def stage_target(plan: RunPlan) -> tuple[TargetGaussians, TargetSource]:
    """Load the target Gaussians; returns them and the source (which may offer a surface mesh)."""
    source = plan["target"].build(device=plan.device, seed=plan.seed)
    # splat targets: floaters removed, with a report
    target, floaters = source.load_checked() if isinstance(source, CheckedTarget) else (source.load(), None)
    target = target.validate()
    if floaters is not None:  # merged into metrics.json at the end of the run
        atomic_write_json(plan.run_dir / FLOATERS, floaters.as_dict())
    config = plan["target"].config
    path = config.path if isinstance(config, FileSourceConfig) else None
    check_target_extent(target.means, f"target.path={path}" if path else f"target={plan['target'].name}")
    log.info("target=%s: %d Gaussians (SH degree %d)", plan["target"].name, target.num, target.sh_degree)
    return target, source


def stage_reference(plan: RunPlan) -> tuple[Reference, str, ReferenceInput]:
    """Load the reference input once and reconstruct it (cached). Returns the reference, its cache key and
    the input (whose video the final renders show)."""
    reference_c, recon_c = plan["reference"], plan["recon"]
    source: ReferenceSource = reference_c.build(device=plan.device, seed=plan.seed)
    loaded = source.load()
    key = cache.stage_key("recon", reference_c.values(), recon_c.values(), plan.seed,
                          cache.code_hash(type(source), recon_c.cls))

    built: list[Reconstructor] = []

    def compute() -> Reference:
        started = time.perf_counter()
        reconstructor: Reconstructor = recon_c.build(device=plan.device)
        built.append(reconstructor)
        reference = reconstructor.reconstruct(loaded).validate()
        log.info("recon=%s: %d bones, %d frames, %d vertices in %.1f s", recon_c.name, reference.num_bones,
                 reference.num_frames, len(reference.rest_vertices), time.perf_counter() - started)
        return reference

    reference = cache.cached(plan.cache_root, "recon", key, Reference, compute, enabled=plan.cache)
    for reconstructor in built:  # pictures after the cache write: a failed picture never costs the fit
        if isinstance(reconstructor, FigureWriter):
            optional_step("recon pictures", reconstructor.write_figures, plan.run_dir / "recon")
    return reference.validate(), key, loaded


def stage_match(plan: RunPlan, reference: Reference, recon_key: str, target: TargetGaussians,
                surface: tuple[np.ndarray, np.ndarray | None]) -> PartMap:
    """Features and part matching (cached)."""
    points, faces = surface
    features_c = plan["features"]
    key = cache.stage_key("match", recon_key, features_c.values(), dataclasses.asdict(plan.match),
                          plan["target"].values(), plan.seed,
                          cache.code_hash(match_parts, plan["target"].cls, features_c.cls))

    def compute() -> PartMap:
        extractor = features_c.build(device=plan.device)
        result = match_parts(reference, target, extractor, plan.match, target_vertices=points, target_faces=faces,
                             seed=plan.seed)
        return dataclasses.replace(result.part_map, alignment_rotation=result.alignment.rotation)

    part_map = cache.cached(plan.cache_root, "match", key, PartMap, compute, enabled=plan.cache).validate()
    counts = np.bincount(part_map.tgt_part, minlength=part_map.num_parts)
    log.info("match: target Gaussians per part %s, mean confidence %.2f", counts.tolist(), part_map.confidence.mean())
    return part_map


def reference_to_target_rotation(part_map: PartMap) -> np.ndarray:
    """(3, 3) rotation taking the reference's frame to the target's: the one matching aligned them with.

    The reference's motion must turn with the target when the alignment turned it (e.g. ``pca_icp`` on a
    target lying on its side, or the structure match's turn about the up axis).
    """
    if part_map.alignment_rotation is None:
        return np.eye(3)
    return np.asarray(part_map.alignment_rotation, dtype=np.float64).T


def stage_motion(plan: RunPlan, reference: Reference, target: TargetGaussians, part_map: PartMap,
                 surface: tuple[np.ndarray, np.ndarray | None]) -> DrivingMotion:
    """The reference's motion in the target's frame, part by part (paper: matched parts inherit the motion)."""
    means = target.means.astype(np.float64)
    anchor = part_centroids(means, part_map.tgt_part, part_map.num_parts) if plan.pivot != "bone" else None
    joints_of = (means, part_map.tgt_part) if plan.pivot == "joint" else None
    motion = driving_motion(reference, target_points=surface[0], target_faces=surface[1], num_frames=plan.frames,
                            loop=plan.loop_reference, part_centroids=anchor, joints_of=joints_of,
                            rotation=reference_to_target_rotation(part_map))
    log.info("driving motion: %d frames, coverage ratio s_t/s_o = %.4f", motion.num_frames, motion.coverage_ratio)
    return motion


def sized_plan(plan: RunPlan, target: TargetGaussians, motion: DrivingMotion) -> RunPlan:
    """With ``budget=auto``, the simulator and the control points sized from the scene; else ``plan``."""
    sim = plan["sim"]
    if plan.budget == "off":
        return plan
    if not isinstance(sim.config, GridSimulatorConfig):
        log.info("budget=auto sizes grid simulators only; sim=%s unchanged", sim.name)
        return plan
    c = sim.config
    chosen = choose_budget(target.means.astype(np.float64), motion, E=c.E, nu=c.nu, density=c.density,
                           frame_time=physics.frame_time(c.frame_time, motion.fps), padding=c.grid_padding, wall=c.wall_cells,
                           cfl_safety=c.cfl_safety)
    atomic_write_json(plan.run_dir / "budget.json", dataclasses.asdict(chosen))
    sized = plan.with_component(sim.with_values(n_grid=chosen.n_grid, substeps=chosen.substeps))
    return dataclasses.replace(sized, transfer=dataclasses.replace(plan.transfer, control_grid=chosen.control_grid))


def stage_transfer(plan: RunPlan, target: TargetGaussians, part_map: PartMap, motion: DrivingMotion,
                   writer: FrameWriter) -> Trajectory:
    """Animate the target frame pair by frame pair (the transfer owns the loop; the simulator steps)."""
    trainable = bool(cast("type[VelocityField]", plan["velocity"].cls).trainable)
    cost = check_run_cost(plan["sim"].config, plan.transfer, trainable, target, motion, frames=plan.frames)
    if cost is not None:
        atomic_write_json(plan.run_dir / "cost_estimate.json", dataclasses.asdict(cost))
    return run_transfer(
        plan["sim"].build(device=plan.device), plan["velocity"].build, plan.transfer, target, part_map, motion,
        num_frames=plan.frames, seed=plan.seed, on_frame=writer.on_frame, resume=writer.resume_state(plan.resume),
    )


# ---------------------------------------------------------------------------------------------- the run


def run(cfg: DictConfig) -> dict[str, Any]:
    """Run the whole pipeline for one configuration; returns the final metrics."""
    from sync4d.plugins import load_all

    load_all()
    plan = build_plan(cfg)
    claim_run_dir(plan.run_dir, plan.resume)
    return run_plan(plan)


def run_plan(plan: RunPlan) -> dict[str, Any]:
    """Run a built plan into ``plan.run_dir``; returns the final metrics."""
    plan.run_dir.mkdir(parents=True, exist_ok=True)
    seed_everything(plan.seed)
    atomic_write_json(plan.run_dir / "env.json", environment_record(plan.device))
    logger: Logger = plan["logger"].build(run_dir=plan.run_dir)
    try:
        return run_stages(plan, logger, time.perf_counter())
    finally:
        logger.close()


def run_stages(plan: RunPlan, logger: Logger, started: float) -> dict[str, Any]:
    """Every stage in order; optional pictures and exports never end the run (one warning each)."""
    target, source = stage_target(plan)  # before the reconstruction: a bad target file fails in seconds
    reference, recon_key, loaded = stage_reference(plan)
    write_gaussians_ply(plan.run_dir / "frames" / f"{0:06d}.ply", target)
    if loaded.video is not None:  # what the reconstruction was given: recon/masks.mp4, recon/camera.json
        optional_step("recon/masks.mp4", write_video_inputs, plan.run_dir / "recon", loaded.video, loaded.camera)
    optional_step("reference_parts.png", figures.save_reference_parts, reference, plan.run_dir / "reference_parts.png",
             logger=logger)
    surface = target_surface(target, source)
    part_map = stage_match(plan, reference, recon_key, target, surface)
    optional_step("match.png", figures.save_match_figure, reference, target, part_map, plan.run_dir / "match.png",
             logger=logger)
    motion = stage_motion(plan, reference, target, part_map, surface)
    plan = sized_plan(plan, target, motion)
    writer = FrameWriter(plan.run_dir, target, motion, logger=logger, run_config=dict(plan.record))
    trajectory = stage_transfer(plan, target, part_map, motion, writer)
    floaters = plan.run_dir / FLOATERS
    result, trajectory = writer.finish(
        trajectory, reference=reference, part_map=part_map, self_transfer=plan.self_transfer,
        loop=plan.loop_reference, run_name=plan.name, overrides=dict(plan.overrides),
        wall_seconds=time.perf_counter() - started,
        extra={"floaters": json.loads(floaters.read_text())} if floaters.is_file() else None,
    )
    if plan.render_video:
        from sync4d.run.exports import render_run_outputs

        optional_step("renders and exports", render_run_outputs, plan.run_dir, plan["render"], plan.device, target,
                 trajectory, motion, reference, clip=loaded.video, part_map=part_map, logger=logger)
    return result


def optional_step(what: str, step: Any, *args: Any, **kwargs: Any) -> Any:
    """``step(*args, **kwargs)`` after the main work (a picture, an export): a failure is one warning and the run
    goes on, its results already written (``HYDRA_FULL_ERROR=1`` raises it instead, for debugging)."""
    try:
        return step(*args, **kwargs)
    except Exception as err:  # noqa: BLE001 - an optional output must never end a run that has its results
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        log.warning("%s failed and was skipped: %s", what, one_line(f"{type(err).__name__}: {err}")[:300])
        return None


def run_guarded(cfg: DictConfig) -> dict[str, Any] | None:
    """Run, turning user errors into one line (exit code 2), or, in a multirun, a recorded failure.

    In a multirun one failing job (bad config, diverged simulation) must not stop the sweep: the job's
    folder gets ``metrics.json`` with ``status: failed`` and the reason, and the sweep goes on.
    """
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from sync4d.run.plan import overrides_of

    multirun = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    try:
        return run(cfg)
    except Sync4DError as err:
        message = one_line(f"{type(err).__name__}: {err}")
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        if multirun:
            log.error("job failed: %s", message)
            if not isinstance(err, RunFolderInUse):  # never write into another run's folder
                atomic_write_json(run_dir_of(cfg) / "metrics.json", {"status": "failed", "error": message,
                                                                    "overrides": overrides_of(cfg)})
            return None
        print(f"sync4d: {message}", file=sys.stderr)
        raise SystemExit(2) from None


def one_line(message: str) -> str:
    """``message`` with its lines joined by ``"; "`` (an error must print as exactly one line)."""
    return "; ".join(line.strip() for line in message.splitlines() if line.strip())


