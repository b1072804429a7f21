"""``run(cfg)``: wires the stages through the registries. No algorithm lives here.

reference -> recon -> target -> features/match -> driving motion -> sim + velocity -> metrics ->
render/export. Every completed frame is written as it is produced (``frames/%06d.ply``) so an
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
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from sync4d import cache
from sync4d.errors import ConfigError, Sync4DError
from sync4d.io.atomic import atomic_write_json
from sync4d.io.ply import write_gaussians_ply
from sync4d.registry import available, build, effective_config, lookup
from sync4d.scenes.targets import check_target_extent
from sync4d.types import PartMap, Reference, TargetGaussians

log = logging.getLogger("sync4d")
ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("torch", "warp-lang", "hydra-core", "omegaconf", "numpy", "trimesh", "scipy")


@dataclass
class RunContext:
    """What the stages share during one run."""

    cfg: DictConfig
    run_dir: Path
    cache_root: Path
    logger: Any


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (the one ``seed`` of the config)."""
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def environment_record(device: str) -> dict[str, Any]:
    """Git SHA, package versions, python, platform and device, for ``env.json``."""
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, timeout=10, check=False
        ).stdout.strip() or None
        dirty = bool(subprocess.run(
            ["git", "status", "--porcelain"], cwd=ROOT, capture_output=True, text=True, timeout=10, check=False
        ).stdout.strip())
    except OSError:
        sha, dirty = None, None
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "git_sha": sha,
        "git_dirty": dirty,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "device": device,
        "packages": versions,
        "argv": sys.argv,
    }


def run_dir_of(cfg: DictConfig) -> Path:
    """The run folder: Hydra's output dir when under Hydra, else ``cfg.run_dir``."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    return Path(cfg.get("run_dir") or ROOT / "outputs" / cfg.name / time.strftime("%Y-%m-%d_%H-%M-%S"))


def overrides_of(cfg: DictConfig) -> dict[str, str]:
    """The command-line overrides of this run as a dict (for hparams and reports)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return {}
    out = {}
    for item in HydraConfig.get().overrides.task:
        key, _, value = item.partition("=")
        out[key.lstrip("+~")] = value
    return out


def group_cfg(cfg: DictConfig, group: str) -> dict[str, Any]:
    """A component group's config with the ``shrink`` values (``debug=smoke``) its component knows."""
    shrink = cfg.get("shrink") or {}
    return effective_config(group, cfg[group], shrink.get(group))


def stage_reference(ctx: RunContext) -> tuple[Reference, str]:
    """Load the reference input and reconstruct it (cached). Returns the reference and its cache key."""
    cfg = ctx.cfg
    reference_cfg = bound_reference_frames(group_cfg(cfg, "reference"), int(cfg.frames))
    recon_cfg = group_cfg(cfg, "recon")
    source = build("reference", reference_cfg, device=cfg.device, seed=cfg.seed)
    code = cache.code_hash(type(source), lookup("recon", str(recon_cfg["type"])))
    key = cache.stage_key("recon", reference_cfg, recon_cfg, cfg.seed, code)
    built: list[Any] = []

    def compute() -> Reference:
        reconstructor = build("recon", recon_cfg, device=cfg.device)
        built.append(reconstructor)
        started = time.perf_counter()
        reference = reconstructor.reconstruct(source.load()).validate()
        log.info("recon=%s: %d bones, %d frames, %d vertices in %.1f s", cfg.recon.type, reference.num_bones,
                 reference.num_frames, len(reference.rest_vertices), time.perf_counter() - started)
        return reference

    reference = cache.cached(ctx.cache_root, "recon", key, Reference, compute, enabled=cfg.cache)
    for reconstructor in built:  # pictures after the cache write: a failed picture never costs the fit
        if hasattr(reconstructor, "write_figures"):
            optional_step("recon pictures", reconstructor.write_figures, ctx.run_dir / "recon")
    return reference.validate(), key


def bound_reference_frames(reference_cfg: dict[str, Any], frames: int) -> dict[str, Any]:
    """A video reference reads (and so reconstructs) only the ``frames`` frames the run uses unless its
    ``max_frames`` is set; the log says which key bounds it."""
    if reference_cfg.get("type") != "video" or int(reference_cfg.get("max_frames", 0) or 0) > 0:
        return reference_cfg
    log.info("reference=video: reconstructing the first %d frames, the ones the run uses (frames=%d); "
             "set reference.max_frames to reconstruct more", frames, frames)
    return {**reference_cfg, "max_frames": frames}


def optional_step(what: str, step: Any, *args: Any, **kwargs: Any) -> Any:
    """Run a step after the main work (a picture, an export); a failure is one warning and the run goes on
    (``HYDRA_FULL_ERROR=1`` raises it instead, for debugging)."""
    try:
        return step(*args, **kwargs)
    except Exception as err:  # noqa: BLE001 -- an optional output must never end a run that has its results
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        log.warning("%s failed and was skipped: %s", what, one_line(f"{type(err).__name__}: {err}"))
        return None


def stage_target(ctx: RunContext) -> tuple[TargetGaussians, Any]:
    """Load the target Gaussians; returns them and the source (which may offer a surface mesh)."""
    source = build("target", group_cfg(ctx.cfg, "target"), device=ctx.cfg.device, seed=ctx.cfg.seed)
    load_checked = getattr(source, "load_checked", None)  # splat targets: floaters removed, with a report
    target, floaters = load_checked() if load_checked is not None else (source.load(), None)
    target = target.validate()
    if floaters is not None:  # merged into metrics.json at the end of the run
        atomic_write_json(ctx.run_dir / FLOATERS, floaters.as_dict())
    check_target_extent(target.means, target_label(ctx.cfg))
    log.info("target=%s: %d Gaussians (SH degree %d)", ctx.cfg.target.type, target.num, target.sh_degree)
    return target, source


def target_label(cfg: DictConfig) -> str:
    """How an error names the target: its file when it has one, else its component."""
    path = cfg.target.get("path")
    return f"target.path={path}" if path else f"target={cfg.target.type}"


def target_surface(target: TargetGaussians, source: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """The target's surface mesh when its source has one, else a bounded, evenly spread sample of its
    opaque Gaussian centres (at most ``surface_sample.SURFACE_POINTS``, however many Gaussians)."""
    from sync4d.surface_sample import splat_surface

    surface = source.surface() if hasattr(source, "surface") else None
    if surface is None:
        return splat_surface(target.means, target.opacities), None
    return surface


def stage_match(ctx: RunContext, reference: Reference, recon_key: str, target: TargetGaussians,
                source: Any) -> PartMap:
    """Features and part matching (cached)."""
    from sync4d.match import match_parts

    cfg = ctx.cfg
    points, faces = target_surface(target, source)
    features_cfg = group_cfg(cfg, "features")
    key = cache.stage_key(
        "match", recon_key, features_cfg, OmegaConf.to_container(cfg.match, resolve=True),
        group_cfg(cfg, "target"), cfg.seed,
        cache.code_hash(match_parts, type(source), lookup("features", str(features_cfg["type"]))),
    )

    def compute() -> PartMap:
        extractor = build("features", features_cfg, device=cfg.device)
        result = match_parts(reference, target, extractor, match_config(cfg), target_vertices=points,
                             target_faces=faces, seed=int(cfg.seed))
        return dataclasses.replace(result.part_map, alignment_rotation=result.alignment.rotation)

    part_map = cache.cached(ctx.cache_root, "match", key, PartMap, compute, enabled=cfg.cache).validate()
    counts = np.bincount(part_map.tgt_part, minlength=part_map.num_parts)
    log.info("match: target Gaussians per part %s, mean confidence %.2f", counts.tolist(), part_map.confidence.mean())
    return part_map


def match_config(cfg: DictConfig) -> Any:
    """The run's typed :class:`sync4d.match.MatchConfig` (defaults from the code, ``match.*`` deviations)."""
    from sync4d.match import MatchConfig
    from sync4d.registry import typed_config

    return typed_config(MatchConfig, OmegaConf.to_container(cfg.match, resolve=True), where="match",
                        label="match").validate()


def transfer_config(cfg: DictConfig) -> Any:
    """The run's typed :class:`sync4d.transfer.TransferConfig` (defaults from the code, ``transfer.*``)."""
    from sync4d.registry import typed_config
    from sync4d.transfer import TransferConfig

    return typed_config(TransferConfig, OmegaConf.to_container(cfg.transfer, resolve=True), where="transfer",
                        label="transfer")


def reference_to_target_rotation(part_map: PartMap) -> np.ndarray:
    """(3, 3) rotation taking the reference's frame to the target's: the one matching aligned them with.

    The reference's motion must turn with the target when the alignment turned it (e.g. ``pca_icp`` on a
    target lying on its side, or the structure match's turn about the up axis).
    """
    if part_map.alignment_rotation is None:
        return np.eye(3)
    return np.asarray(part_map.alignment_rotation, dtype=np.float64).T


def apply_budget(ctx: RunContext, sim_cfg: dict[str, Any], target: TargetGaussians, motion: Any) -> dict[str, Any]:
    """With ``budget=auto``, size the simulation from the scene (:mod:`sync4d.budget`); else unchanged."""
    if str(ctx.cfg.budget) == "off":
        return sim_cfg
    if sim_cfg.get("type") != "mpm_warp":
        log.info("budget=auto applies to sim=mpm_warp only; sim=%s unchanged", sim_cfg.get("type"))
        return sim_cfg
    from sync4d.budget import choose_budget
    from sync4d.registry import make_config

    _, sim = make_config("sim", sim_cfg)  # every field, defaults from the simulator's own Config
    chosen = choose_budget(
        target.means.astype(np.float64), motion, E=sim.E, nu=sim.nu, density=sim.density,
        frame_time=sim.frame_time or 1.0 / motion.fps, padding=sim.grid_padding, wall=sim.wall_cells,
        cfl_safety=sim.cfl_safety,
    )
    atomic_write_json(ctx.run_dir / "budget.json", dataclasses.asdict(chosen))
    return {**sim_cfg, "control_grid": chosen.control_grid, "n_grid": chosen.n_grid, "substeps": chosen.substeps}


def write_frame(run_dir: Path, index: int, gaussians: TargetGaussians) -> Path:
    """Write one output frame as ``frames/%06d.ply`` (atomically)."""
    return write_gaussians_ply(run_dir / "frames" / f"{index:06d}.ply", gaussians)


#: What floater removal did to a splat target (counts, removed and kept boxes), also in metrics.json.
FLOATERS = "floaters.json"


class RunFolderInUse(ConfigError):
    """The run folder already holds another run's outputs; nothing is written into it."""


#: Top-level keys that do not change a run's results (excluded from the resume fingerprint).
NOT_RESULTS = ("resume", "name", "cache", "cache_dir", "render", "logger", "hydra")
#: Files whose presence marks a folder as another run's.
RUN_MARKERS = ("metrics.json", "checkpoint.pt")


def check_run_config(cfg: DictConfig) -> None:
    """Reject missing mandatory values (``???``) and malformed top-level values with one line each."""
    missing = sorted(OmegaConf.missing_keys(cfg))
    if missing:
        key = missing[0]
        raise ConfigError(f"{key}: a value is required (it is ??? in the config); set it, e.g. {key}=<value>"
                          + (f" (also missing: {', '.join(missing[1:])})" if len(missing) > 1 else ""))
    for key, minimum in (("frames", 1), ("seed", 0)):
        value = cfg.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise ConfigError(f"{key}={value!r}: must be an integer >= {minimum}")
    resume = cfg.get("resume")
    if resume is not None and not isinstance(resume, str):
        raise ConfigError(f"resume={resume!r}: must be the folder of an interrupted run")


#: Top-level run options whose value must be one of a fixed set.
RUN_CHOICES = {"pivot": ("part_centroid", "bone"), "budget": ("off", "auto")}


def check_components(cfg: DictConfig) -> dict[str, Any]:
    """Build every component's typed Config before any stage runs; returns them by group.

    A bad value of any group (``sim.E=0``, ``sim.n_grid=1``, an unknown option) fails here, in
    milliseconds, with the key's name, instead of after reconstruction and matching have run.
    """
    from sync4d.registry import GROUPS, make_config

    check_device(str(cfg.device))
    for key, allowed in RUN_CHOICES.items():
        if str(cfg.get(key)) not in allowed:
            raise ConfigError(f"{key}={cfg.get(key)!r}: must be one of {', '.join(allowed)}")
    shrink = cfg.get("shrink") or {}
    built = {group: make_config(group, cfg[group], shrink=shrink.get(group))[1] for group in GROUPS if group in cfg}
    return {**built, "match": match_config(cfg), "transfer": transfer_config(cfg)}


def check_device(device: str) -> None:
    """Refuse a ``device`` that is not ``cpu``, ``cuda`` or ``cuda:N``, or a CUDA device this machine lacks."""
    import re

    if device == "cpu":
        return
    if not re.fullmatch(r"cuda(:\d+)?", device):
        raise ConfigError(f"device={device}: unknown device; use device=cpu, or device=cuda / cuda:N on a CUDA machine")
    import torch

    index = int(device.partition(":")[2] or 0)
    if not torch.cuda.is_available() or index >= torch.cuda.device_count():
        found = torch.cuda.device_count() if torch.cuda.is_available() else 0
        raise ConfigError(f"device={device}: this machine has {found} CUDA device(s); use device=cpu")


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


def run_config_record(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config minus keys that do not change results: what a resume must match."""
    values = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(values, dict)
    return {k: v for k, v in values.items() if k not in NOT_RESULTS}


def run(cfg: DictConfig) -> dict[str, Any]:
    """Run the whole pipeline for one configuration; returns the final metrics."""
    from sync4d.plugins import load_all

    load_all()
    check_run_config(cfg)
    check_components(cfg)
    run_dir = run_dir_of(cfg)
    claim_run_dir(run_dir, cfg.get("resume"))
    run_dir.mkdir(parents=True, exist_ok=True)
    seed_everything(int(cfg.seed))
    atomic_write_json(run_dir / "env.json", environment_record(str(cfg.device)))
    logger = build("logger", group_cfg(cfg, "logger"), run_dir=run_dir)
    cache_root = Path(cfg.cache_dir) if cfg.get("cache_dir") else ROOT / "outputs" / "cache"
    ctx = RunContext(cfg=cfg, run_dir=run_dir, cache_root=cache_root, logger=logger)
    started = time.perf_counter()
    try:
        return _run_stages(ctx, started)
    finally:
        logger.close()


def _run_stages(ctx: RunContext, started: float) -> dict[str, Any]:
    from sync4d import report_figures
    from sync4d.motion import driving_motion

    cfg = ctx.cfg
    target, source = stage_target(ctx)  # before the reconstruction: a bad target file fails in seconds
    reference, recon_key = stage_reference(ctx)
    write_frame(ctx.run_dir, 0, target)
    optional_step("reference_parts.png", report_figures.save_reference_parts, reference,
                  ctx.run_dir / "reference_parts.png", logger=ctx.logger)

    if not available("features"):
        log.warning("no feature extractor is registered yet: the run ends after loading the target")
        return {}
    part_map = stage_match(ctx, reference, recon_key, target, source)
    optional_step("match.png", report_figures.save_match_figure, reference, target, part_map,
                  ctx.run_dir / "match.png", logger=ctx.logger)

    points, faces = target_surface(target, source)
    from sync4d.metrics import part_centroids

    anchor = part_centroids(target.means.astype(np.float64), part_map.tgt_part, part_map.num_parts) \
        if cfg.get("pivot", "part_centroid") == "part_centroid" else None
    motion = driving_motion(reference, target_points=points, target_faces=faces, num_frames=int(cfg.frames),
                            loop=bool(cfg.loop_reference), part_centroids=anchor,
                            rotation=reference_to_target_rotation(part_map))
    log.info("driving motion: %d frames, coverage ratio s_t/s_o = %.4f", motion.num_frames, motion.coverage_ratio)

    from sync4d.outputs import FrameWriter

    writer = FrameWriter(ctx.run_dir, target, motion, logger=ctx.logger, run_config=run_config_record(cfg))
    sim_cfg = apply_budget(ctx, group_cfg(cfg, "sim"), target, motion)
    from sync4d.budget import check_run_cost

    cost = check_run_cost(sim_cfg, group_cfg(cfg, "velocity"), target, motion, frames=int(cfg.frames))
    if cost is not None:
        atomic_write_json(ctx.run_dir / "cost_estimate.json", dataclasses.asdict(cost))
    simulator = build("sim", sim_cfg, device=cfg.device)
    trajectory = simulator.run(
        target, part_map, motion,
        velocity_cfg=group_cfg(cfg, "velocity"), num_frames=int(cfg.frames), transfer=transfer_config(cfg),
        seed=int(cfg.seed), on_frame=writer.on_frame,
        resume=writer.resume_state(cfg.get("resume")),
    )
    floaters = ctx.run_dir / FLOATERS
    result, trajectory = writer.finish(
        trajectory, reference=reference, part_map=part_map, self_transfer=bool(cfg.self_transfer),
        loop=bool(cfg.loop_reference), run_name=str(cfg.name), overrides=overrides_of(cfg),
        wall_seconds=time.perf_counter() - started,
        extra={"floaters": load_json(floaters)} if floaters.is_file() else None,
    )
    if cfg.render_video:
        from sync4d.render_outputs import render_run_outputs

        optional_step("renders and exports", render_run_outputs, ctx.run_dir, cfg, target, trajectory, motion,
                      reference, part_map=part_map, logger=ctx.logger)
    return result


def run_guarded(cfg: DictConfig) -> dict[str, Any] | None:
    """Run, turning user errors into one line (exit code 2) — or, in a multirun, a recorded failure.

    In a multirun one failing job (bad config, diverged simulation) must not stop the sweep: the job's
    folder gets ``metrics.json`` with ``status: failed`` and the reason, and the sweep goes on.
    """
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

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


def load_json(path: Path) -> Any:
    return json.loads(Path(path).read_text())
