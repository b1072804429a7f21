"""``transfer_gt``: motion transfer onto targets of other proportions, against two truths the transfer never sees.

    python -m sync4d.evaluate transfer_gt [--pairs laptop,cmu_walk,...] [--methods default,mpm_none,...]
        [--frames 10] [--gaussians 4000] [--quick] --json out.json [--table out.md] [--charts folder]

Each pair (:mod:`sync4d_tools.truth.pairs`) is a reference and a target built from the SAME joint motion on
two skeletons of different proportions. The target has two truths, named in the JSON: ``skinning`` (that
joint motion applied to the target's own skeleton and skinning) and ``elastic`` (the target as an ARAP
solid whose bone cores follow the same bones, solved by libigl: :mod:`sync4d_tools.truth.elastic`). The
transfer only sees the reference, the target's rest Gaussians and the part correspondence (the target's own
bone labels: matching is taken as perfect, so what is measured is the transfer alone).

Methods are configurations by name (:data:`METHODS`: sim, velocity and transfer groups exactly as
``python train.py`` takes them; adding one is one line there). ``default`` is what ``python train.py``
runs (composed from conf/config.yaml); rows whose configuration is the same are run once. Beside them:
``frozen`` (the rest pose every frame: the floor) and ``rigid_oracle`` (each truth part's best rigid fit to
that truth: the ceiling of any part-wise rigid transfer), and ``truth`` (the truth scored like a method).

Prints one JSON object on the last line: ``pairs`` -> pair -> truth -> method -> the row (:data:`KEYS`,
``tear_curve``: torn pairs and fragments at 5/10/20/30%), ``criteria`` -> pair -> truth -> the issue's bars
for ``--candidate`` (:func:`criteria`), plus the settings.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sync4d.errors import ConfigError
from sync4d.geometry import part_centroids, rigid_fit
from sync4d.registry import build, component, make_config
from sync4d.run.writer import compute_metrics
from sync4d.transfer import PAPER, TransferConfig, run_transfer
from sync4d.transfer.motion import driving_motion
from sync4d.types import DrivingMotion, PartMap, TargetGaussians, Trajectory
from sync4d_tools.truth.pairs import PAIRS, TRUTHS, GTPair, load_pair

log = logging.getLogger(__name__)
ROOT = Path(__file__).resolve().parents[2]
NONE = {"type": "none"}


@dataclass(frozen=True)
class Method:
    """A transfer configuration by name: the ``sim``, ``velocity`` and ``transfer`` groups as ``train.py`` takes them
    (dicts of the keys that differ from each component's defaults)."""

    sim: dict[str, Any]
    velocity: dict[str, Any] = field(default_factory=lambda: dict(NONE))
    transfer: dict[str, Any] = field(default_factory=dict)


#: Every simulated method; ``default`` is filled from conf/config.yaml (what ``python train.py`` runs).
METHODS: dict[str, Method | None] = {
    "default": None,
    "mpm_none": Method({"type": "mpm_warp"}),
    # the held drive with a part-wise rigid rig (no blend at the seams): the former default
    "mpm_rigid": Method({"type": "mpm_warp", "blend_band": 0.0}),
    # the former default: launched once a frame towards its pose, then free through the frame (no held drive)
    "mpm_launch": Method({"type": "mpm_warp", "drive": "launch"}, transfer={"init": "pose"}),
    "mpm_triplane": Method({"type": "mpm_warp"}, {"type": "triplane"}),
    # the paper's form: launched once per frame, a trained triplane, centroid loss, relative targets
    "paper": Method({"type": "mpm_warp", "drive": "launch"}, {"type": "triplane"}, dataclasses.asdict(PAPER)),
    # point-wise deformation of every Gaussian (no control points), as the paper's baseline
    "lbs_hard": Method({"type": "lbs", "neighbours": 1}, transfer={"control_grid": None}),
    "lbs_smooth": Method({"type": "lbs", "neighbours": 16}, transfer={"control_grid": None}),
    "kinematic": Method({"type": "kinematic"}),
}
#: Computed rows beside the methods: the floor and the ceiling.
BOUNDS = ("frozen", "rigid_oracle")
#: Methods without physics (the pose bar on the skinning truth is against the best of these).
NON_PHYSICS = ("lbs_hard", "lbs_smooth", "kinematic")
QUICK = dict(pairs="laptop", methods="lbs_hard,lbs_smooth,kinematic,mpm_none,frozen,rigid_oracle", candidate="mpm_none",
             frames=4, gaussians=600)
KEYS = ("pose_error_pct", "pose_error_max_pct", "follow_rotation_deg", "follow_rotation_max_deg",
        "follow_translation_pct", "follow_translation_max_pct", "torn_pairs_pct", "torn_seam_pairs_pct", "strain_p99_pct", "strain_p99_max_pct",
        "fragments", "volume_change_pct", "jitter_ratio", "seconds_per_frame")
THRESHOLDS = ("10", "20", "30")


def default_method() -> Method:
    """What ``python train.py`` runs: the sim, velocity and transfer groups of conf/config.yaml."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from sync4d.config_schemas import register_schemas

    register_schemas()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="config")
    groups = {g: OmegaConf.to_container(cfg[g], resolve=True) for g in ("sim", "velocity", "transfer")}
    return Method(groups["sim"], groups["velocity"], groups["transfer"])  # type: ignore[arg-type]


def resolve_methods(names: list[str]) -> dict[str, Method]:
    """The named methods' configurations; raises a one-line :class:`ConfigError` for an unknown name."""
    out = {}
    for name in names:
        if name not in METHODS and name not in BOUNDS:
            raise ConfigError(f"transfer_gt --methods: unknown method '{name}'; use {', '.join([*METHODS, *BOUNDS])}")
        if name in METHODS:
            out[name] = METHODS[name] or default_method()
    return out


def method_key(method: Method) -> str:
    """Every setting of a method, defaults filled in: two names with the same key run the same thing."""
    _, sim = make_config("sim", dict(method.sim))
    _, vel = make_config("velocity", dict(method.velocity))
    transfer = TransferConfig(**method.transfer)
    return json.dumps([method.sim["type"], dataclasses.asdict(sim), method.velocity["type"],
                       dataclasses.asdict(vel), dataclasses.asdict(transfer)], sort_keys=True, default=str)


def pair_motion(pair: GTPair, num_frames: int) -> DrivingMotion:
    """The driving motion of a pair (what every method is given), as ``python train.py`` builds it: each target
    part turns about its joint with its parent part (``pivot=joint``)."""
    means, parts, B = pair.target.means.astype(np.float64), pair.part_map.tgt_part, pair.part_map.num_parts
    return driving_motion(
        pair.reference, target_points=pair.target_vertices, target_faces=pair.target_faces, num_frames=num_frames,
        loop=False, part_centroids=part_centroids(means, parts, B), joints_of=(means, parts),
    )


def run_method(target: TargetGaussians, part_map: PartMap, method: Method, motion: DrivingMotion, num_frames: int
               ) -> tuple[Trajectory, list[float]]:
    """One method's trajectory of a target and its CPU seconds per frame (the whole process's)."""
    sim = build("sim", dict(method.sim), device="cpu")
    seconds: list[float] = []
    last = [time.process_time()]

    def on_frame(t: int, x: Any, F: Any, stats: dict[str, float], checkpoint: Any = None, **_: Any) -> None:
        now = time.process_time()
        seconds.append(now - last[0])
        last[0] = now

    traj = run_transfer(sim, component("velocity", dict(method.velocity)).build, TransferConfig(**method.transfer),
                        target, part_map, motion, num_frames=num_frames, seed=0, on_frame=on_frame)
    return traj, seconds


def frozen_trajectory(rest: np.ndarray, num_frames: int, fps: float) -> Trajectory:
    """The floor: the rest pose in every frame."""
    return Trajectory(x=np.repeat(rest[None], num_frames, axis=0), F=None, frame_dt=1.0 / fps)


def rigid_oracle(truth: np.ndarray, parts: np.ndarray, fps: float) -> Trajectory:
    """The ceiling of part-wise rigid motion: each part moved by its best rigid fit (rest -> t) to the truth."""
    rest = truth[0]
    x = np.repeat(rest[None], len(truth), axis=0)
    for b in np.unique(parts):
        idx = np.flatnonzero(parts == b)
        for t in range(1, len(truth)):
            if len(idx) >= 3:
                fit = rigid_fit(rest[idx], truth[t, idx])
                x[t, idx] = rest[idx] @ fit[:3, :3].T + fit[:3, 3]
            else:
                x[t, idx] = truth[t, idx]
    return Trajectory(x=x, F=None, frame_dt=1.0 / fps)


def score(pair: GTPair, traj: Trajectory, motion: DrivingMotion, seconds: list[float], truth: str) -> dict[str, Any]:
    """The reported numbers of one trajectory against one of the pair's truths (frames 1..T)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # parts too small for a hull volume are NaN
        m = compute_metrics(traj, pair.target, pair.part_map, motion, pair.reference, self_transfer=False,
                            frame_seconds=seconds, truth=pair.truths[truth])
    row = {k: (round(float(m[k]), 4) if isinstance(m[k], float) else m[k]) for k in KEYS}
    row["tear_curve"] = m["tear_curve"]
    return row


def score_pair(pair: GTPair, methods: dict[str, Method], bounds: list[str], num_frames: int
               ) -> dict[str, dict[str, dict[str, Any]]]:
    """truth -> row name -> row, for every method (identical configurations run once) and bound."""
    motion = pair_motion(pair, num_frames)
    rest, fps = pair.target.means.astype(np.float64), motion.fps
    rows: dict[str, dict[str, dict[str, Any]]] = {t: {} for t in TRUTHS}
    for truth in TRUTHS:
        rows[truth]["truth"] = score(pair, Trajectory(x=pair.truths[truth], F=None, frame_dt=1 / fps), motion,
                                     [0.0] * num_frames, truth)
    ran: dict[str, str] = {}
    for name, method in methods.items():
        key = method_key(method)
        if key in ran:
            for truth in TRUTHS:
                rows[truth][name] = {**rows[truth][ran[key]], "same_as": ran[key]}
            continue
        started = time.process_time()
        traj, seconds = run_method(pair.target, pair.part_map, method, motion, num_frames)
        ran[key] = name
        for truth in TRUTHS:
            rows[truth][name] = score(pair, traj, motion, seconds, truth)
        log.info("transfer_gt %s / %s: %.1f s CPU", pair.name, name, time.process_time() - started)
    for truth in TRUTHS:
        if "frozen" in bounds:
            rows[truth]["frozen"] = score(pair, frozen_trajectory(rest, num_frames, fps), motion, [0.0] * num_frames,
                                          truth)
        if "rigid_oracle" in bounds:
            oracle = rigid_oracle(pair.truths[truth], pair.part_map.tgt_part, fps)
            rows[truth]["rigid_oracle"] = score(pair, oracle, motion, [0.0] * num_frames, truth)
    return rows


def torn_at(row: dict[str, Any], threshold: str) -> float:
    """Torn pairs [%] of a row at a tear threshold ("10", "20", "30")."""
    return float(row["tear_curve"]["torn_pairs_pct"][threshold])


def fewer_torn(row: dict[str, Any], hard: dict[str, Any], threshold: str) -> bool:
    """Fewer torn pairs than ``hard`` at ``threshold``; tearing none where ``hard`` tears none also counts."""
    mine, theirs = torn_at(row, threshold), torn_at(hard, threshold)
    return mine < theirs or mine == 0.0


def criteria(rows: dict[str, dict[str, Any]], truth: str, candidate: str = "default") -> dict[str, Any]:
    """Issue 30's bars for ``candidate`` on one pair and one truth: each check as pass/fail, and ``passed``.

    0 fragments; fewer torn pairs than ``lbs_hard`` at 10, 20 and 30%; worst-frame p99 strain at most half of
    lbs_hard's wherever lbs_hard's exceeds 5%; pose error within 0.25% of the diagonal of the best method
    without physics (skinning truth), or the lowest of all methods (elastic truth; the bounds and the truth
    itself are not methods).
    """
    m, hard = rows[candidate], rows["lbs_hard"]
    out: dict[str, Any] = {"fragments_zero": m["fragments"] == 0}
    for th in THRESHOLDS:
        out[f"torn_below_lbs_hard_at_{th}"] = fewer_torn(m, hard, th)
    strained = hard["strain_p99_max_pct"] > 5.0
    out["strain_half_of_lbs_hard"] = (not strained) or m["strain_p99_max_pct"] <= 0.5 * hard["strain_p99_max_pct"]
    if truth == "skinning":
        best = min(rows[b]["pose_error_pct"] for b in NON_PHYSICS if b in rows)
        out["pose_within_0.25_of_best_non_physics"] = m["pose_error_pct"] <= best + 0.25
    else:
        others = [r["pose_error_pct"] for k, r in rows.items()
                  if k not in (candidate, "truth", *BOUNDS) and r.get("same_as") != candidate]
        best = min(others) if others else float("inf")
        out["pose_lowest_of_all_methods"] = m["pose_error_pct"] <= best
    out["passed"] = all(v for v in out.values() if isinstance(v, bool))
    out["best_other_pose_error_pct"] = best
    return out


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m sync4d.evaluate transfer_gt", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pairs", default=",".join(PAIRS))
    parser.add_argument("--methods", default=",".join([*METHODS, *BOUNDS]))
    parser.add_argument("--candidate", default="default", help="the method the criteria judge")
    parser.add_argument("--frames", type=int, default=10, help="frames per pair (frame 0 = rest)")
    parser.add_argument("--gaussians", type=int, default=4000, help="target Gaussians per pair")
    parser.add_argument("--quick", action="store_true", help=f"a small run for tests: {QUICK} unless given")
    parser.add_argument("--json", default="", help="write the result here too")
    parser.add_argument("--charts", default="", help="chart folder ('' = none)")
    parser.add_argument("--table", default="", help="write the Markdown tables here too")
    parser.add_argument("--from-json", default="", help="comma-separated result files to merge instead of running")
    args = parser.parse_args(argv)
    if args.quick:
        given = set(a.split("=")[0].lstrip("-") for a in (argv or []))
        for key, value in QUICK.items():
            if key not in given:
                setattr(args, key, value)
    if args.frames < 3:
        raise ConfigError(f"transfer_gt --frames={args.frames}: need >= 3 (frame 0 is the rest pose)")
    return args


def merge_rows(into: dict[str, Any], rows: dict[str, Any], depth: int) -> None:
    """Join nested result rows: ``depth`` levels of keys (pair, truth, ...) above the method rows, a later row wins."""
    if depth == 0:
        into.update(rows)
        return
    for key, inner in rows.items():
        merge_rows(into.setdefault(key, {}), inner, depth - 1)


def joined(paths: list[str], rows_key: str, depth: int) -> dict[str, Any]:
    """Several saved results as one: the rows under ``rows_key`` joined (:func:`merge_rows`), the methods merged,
    the CPU seconds summed; the first file's settings."""
    out: dict[str, Any] = {}
    for path in paths:
        part = json.loads(Path(path).read_text())
        if not out:
            out = part
            continue
        merge_rows(out[rows_key], part[rows_key], depth)
        out["methods"].update(part["methods"])
        out["cpu_seconds"] = round(out["cpu_seconds"] + part["cpu_seconds"], 1)
    return out


def merged(paths: list[str], candidate: str) -> dict[str, Any]:
    """Several saved results as one, rows joined per pair, truth and method, the criteria computed again."""
    out = joined(paths, "pairs", 2)
    out["candidate"] = candidate
    out["criteria"] = {p: {t: criteria(rows, t, candidate) for t, rows in r.items()}
                       for p, r in out["pairs"].items() if all({candidate, "lbs_hard"} <= set(rows) for rows in r.values())}
    return out


def write_outputs(out: dict[str, Any], args: argparse.Namespace) -> None:
    """The charts, tables and JSON a run was asked for."""
    from sync4d_tools.truth.report import follow_strain_chart, markdown_tables, write_charts

    if args.charts:
        out["charts"] = write_charts(out["pairs"], Path(args.charts), prefix="physics_")
        skinning = {p: r["skinning"] for p, r in out["pairs"].items() if "skinning" in r}
        out["charts"].append(follow_strain_chart(skinning, Path(args.charts) / "physics_gt_follow_strain.png",
                                                 "the pairs with a truth (strain against the skinning truth)"))
    if args.table:
        Path(args.table).parent.mkdir(parents=True, exist_ok=True)
        Path(args.table).write_text(markdown_tables(out))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=1, default=str))


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    if args.from_json:
        out = merged([p for p in args.from_json.split(",") if p], args.candidate)
        write_outputs(out, args)
        return out
    names = [m for m in args.methods.split(",") if m]
    methods, bounds = resolve_methods(names), [b for b in BOUNDS if b in names]
    pairs = [p for p in args.pairs.split(",") if p]
    started = time.process_time()
    results: dict[str, dict[str, dict[str, dict[str, Any]]]] = {}
    for name in pairs:
        t0 = time.process_time()
        pair = load_pair(name, args.frames, args.gaussians)
        log.info("transfer_gt %s: both truths in %.1f s CPU", name, time.process_time() - t0)
        results[name] = score_pair(pair, methods, bounds, args.frames)
    judged = args.candidate in methods and "lbs_hard" in methods
    out = {
        "pairs": results,
        "criteria": {p: {t: criteria(r[t], t, args.candidate) for t in TRUTHS} for p, r in results.items()}
        if judged else {},
        "candidate": args.candidate,
        "methods": {k: dataclasses.asdict(v) for k, v in methods.items()},
        "frames": args.frames,
        "gaussians": args.gaussians,
        "cpu_seconds": round(time.process_time() - started, 1),
    }
    write_outputs(out, args)
    print(json.dumps(out, default=str))
    return out
