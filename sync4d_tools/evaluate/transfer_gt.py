"""``transfer_gt``: motion transfer onto targets of other proportions, against a truth the transfer never sees.

    python -m sync4d.evaluate transfer_gt [--pairs laptop,cmu_walk,deepmimic_walk,dog_trot]
        [--methods lbs_hard,lbs_smooth,kinematic,mpm_none,mpm_triplane,paper] [--frames 8] --json out.json

Each pair is a reference and a target built from the SAME joint motion on two skeletons of different
proportions: the target's correct motion is that joint motion applied to the target's own skeleton and
skinning (its own kinematic model), never anything the transfer computes. The transfer only sees the
reference, the target's rest Gaussians and the part correspondence (the target's own bone labels: the
matching is taken as perfect, so what is measured is the transfer alone).

* ``laptop``: the procedural laptop (34 x 24 cm, 2 cm base, 12 mm lid) drives a laptop of 42 x 18 cm with
  a 3 cm base and an 8 mm lid; its hinge sits at its own back edge and height.
* ``cmu_walk``: CMU 131_01 (start walk stop) drives a body with 20% longer legs, 20% shorter arms and
  capsules 35% thicker.
* ``deepmimic_walk``: the DeepMimic humanoid walk drives the same kind of body change.
* ``dog_trot``: the AI4Animation dog trot drives a quadruped with 30% shorter legs, a 25% longer body and
  neck, and 45% thicker capsules (cow-like).

Methods (all share the driving motion and the part map): ``lbs_hard`` (each Gaussian moved by its part's
transform: the point-wise deformation the paper argues against), ``lbs_smooth`` (16-neighbour blended
weights), ``kinematic`` (the MPM's particles in free flight: each moved by its part's rigid motion, no grid),
``mpm_none`` (the default MPM, no velocity training), ``mpm_triplane`` (the default MPM with the trained
triplane field), ``paper`` (centroid init, centroid loss, relative targets, trained triplane).

Prints one JSON object on the last line: ``pairs`` -> pair -> method -> ``pose_error_pct`` (mean over frames
1..T of the mean distance to the truth, % of the target's bounding-box diagonal), ``pose_error_max_pct``,
``torn_pairs_pct``, ``torn_seam_pairs_pct``, ``strain_p99_pct``, ``strain_p99_max_pct``, ``fragments``,
``volume_change_pct``, ``jitter_ratio`` (against the truth's own), ``seconds_per_frame``; plus the settings.
Charts (fidelity vs integrity vs seconds per frame) go to ``--charts`` (docs/charts/transfer_gt/).

Data (attribution): CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu; "The database was created
with funding from NSF EIA-0196217"), via yuki-koyama/bvh11; DeepMimic humanoid walk clip and URDF
(DeepMimic, MIT) from the pybullet 3.2.7 wheel (zlib); AI4Animation dog mocap via
erwincoumans/motion_imitation (CC BY-NC 4.0).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from sync4d.transfer import PAPER, TransferConfig, run_transfer
from sync4d.errors import ConfigError
from sync4d.io.mesh import mesh_to_gaussians
from sync4d.io.mocap import SkeletonMotion
from sync4d.geometry import skinned_positions
from sync4d.geometry import part_centroids
from sync4d.transfer.motion import driving_motion
from sync4d.run.writer import compute_metrics
from sync4d.registry import build, component
from sync4d.types import PartMap, Reference, TargetGaussians

log = logging.getLogger(__name__)

DATA = "../shared/data/motion"
PAIRS = ("laptop", "cmu_walk", "deepmimic_walk", "dog_trot")
METHODS = ("lbs_hard", "lbs_smooth", "kinematic", "mpm_none", "mpm_triplane", "paper")
#: velocity training kept short (PhysDreamer's authors: early stopping; here it also bounds the run time)
TRAIN = {"iterations": 6, "patience": 2}


@dataclass(frozen=True)
class GTPair:
    """A reference, a target of other proportions, and the target's true motion.

    Attributes:
        name: pair name.
        reference: the driving reference (its articulation in ``bone_transforms``).
        target: the target's rest Gaussians (N).
        target_vertices, target_faces: the target's rest surface (for the coverage ratio) [m].
        part_map: reference bone -> the target's own bone labels (argmax of its skinning).
        truth: (T, N, 3) the target's Gaussians posed by its own bones and skinning [m] (no G_t).
    """

    name: str
    reference: Reference
    target: TargetGaussians
    target_vertices: np.ndarray
    target_faces: np.ndarray
    part_map: PartMap
    truth: np.ndarray


def posed_by_own_model(model: Reference, points: np.ndarray, num_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Points posed by a kinematic model's own bones and skinning: ((T, N, 3) [m], (N,) hard bone labels).

    Each point takes the blend weights of its nearest rest vertex of ``model``.
    """
    _, nearest = cKDTree(model.rest_vertices).query(points)
    weights = model.skinning[nearest]
    bones = model.bone_transforms[:num_frames] @ np.linalg.inv(model.bone_transforms[0])[None]
    truth = np.stack([skinned_positions(points, weights, bones[t]) for t in range(num_frames)])
    return truth, weights.argmax(axis=1)


def make_pair(name: str, reference: Reference, model: Reference, *, num_frames: int, gaussians: int,
              seed: int = 0) -> GTPair:
    """Sample the target model's rest surface into Gaussians and pose them by the model itself."""
    target = mesh_to_gaussians(model.rest_vertices, model.rest_faces, num_surface=int(gaussians * 0.6),
                               num_interior=int(gaussians * 0.4), seed=seed, name=f"{name}_target")
    truth, labels = posed_by_own_model(model, target.means.astype(np.float64), num_frames)
    part_map = PartMap(reference.part_labels(), labels, np.ones(target.num), reference.num_bones).validate()
    return GTPair(name, reference, target, model.rest_vertices, model.rest_faces, part_map, truth)


def laptop_pair(num_frames: int, gaussians: int) -> GTPair:
    """Laptop -> a wider, shallower laptop with a thicker base and a thinner lid (hinge at its own edge)."""
    from sync4d.scenes.laptop import laptop_reference

    kw = dict(rest_angle_deg=110.0, min_angle_deg=40.0, period_frames=24, subdivisions=2)
    ref = laptop_reference(num_frames, **kw)
    model = laptop_reference(num_frames, width=0.42, depth=0.18, base_thickness=0.03, lid_thickness=0.008, **kw)
    return make_pair("laptop", ref, model, num_frames=num_frames, gaussians=gaussians)


def rescale_segments(motion: SkeletonMotion, factors: np.ndarray) -> SkeletonMotion:
    """The same joint motion on a skeleton whose segment ``parents[j] -> j`` is ``factors[j]`` times as long.

    Every segment keeps its direction in every frame (so every joint rotation is unchanged); the root
    keeps its path. Parents precede children in the joint order.
    """
    pos = motion.positions
    out = pos.copy()
    for j, p in enumerate(motion.parents):
        if p >= 0:
            out[:, j] = out[:, p] + factors[j] * (pos[:, j] - pos[:, p])
    return dataclasses.replace(motion, positions=out)


def limb_factors(names: tuple[str, ...], legs: float, arms: float) -> np.ndarray:
    """(J,) segment factors of a humanoid by the child joint's name: legs (knee/ankle/toe), arms (elbow/wrist/hand)."""
    out = np.ones(len(names))
    for j, n in enumerate(names):
        low = n.lower()
        if any(k in low for k in ("knee", "ankle", "toe")):
            out[j] = legs
        elif any(k in low for k in ("elbow", "wrist", "hand", "finger", "thumb")):
            out[j] = arms
    return out


def quadruped_factors(parents: np.ndarray, toes: tuple[int, ...], hips: tuple[int, ...], legs: float,
                      body: float) -> np.ndarray:
    """(J,) segment factors of a quadruped: the chain from each toe up to (not including) its hip is a leg."""
    out = np.full(len(parents), body)
    for toe in toes:
        j = toe
        while j >= 0 and j not in hips:
            out[j] = legs
            j = int(parents[j])
    return out


def window(motion: SkeletonMotion, start: int, num_frames: int) -> SkeletonMotion:
    """Frames start .. start + num_frames - 1 of a motion."""
    sl = slice(start, start + num_frames)
    return dataclasses.replace(motion, positions=motion.positions[sl],
                               rotations=None if motion.rotations is None else motion.rotations[sl])


def mocap_pair(name: str, motion: SkeletonMotion, factors: np.ndarray, *, radius_scale: float, girth: float,
               num_frames: int, gaussians: int) -> GTPair:
    """Reference and target from one joint motion: target segments x ``factors``, capsules x ``girth``."""
    from sync4d.recon.mocap import MocapReconstructor

    cfg = MocapReconstructor.Config(radius_scale=radius_scale)
    ref = MocapReconstructor(cfg).from_motion(motion, name=name)
    tcfg = MocapReconstructor.Config(radius_scale=radius_scale * girth, min_radius=cfg.min_radius * girth)
    model = MocapReconstructor(tcfg).from_motion(rescale_segments(motion, factors), name=f"{name}_target")
    if model.num_bones != ref.num_bones:
        raise ConfigError(f"transfer_gt {name}: the rescaled skeleton has {model.num_bones} bones, not {ref.num_bones}")
    return make_pair(name, ref, model, num_frames=num_frames, gaussians=gaussians)


def load_pair(name: str, num_frames: int, gaussians: int) -> GTPair:
    """Build one of :data:`PAIRS` with ``num_frames`` frames (30 fps for the mocap pairs)."""
    from sync4d.io.deepmimic import read_deepmimic
    from sync4d.io.mocap import CMU_UNIT_SCALE, read_bvh, read_joint_position_motion
    from sync4d.sources.references import resolve_path

    def data(rel: str) -> Path:
        return resolve_path(f"{DATA}/{rel}", what="transfer_gt motion file")

    if name == "laptop":
        return laptop_pair(num_frames, gaussians)
    if name == "cmu_walk":
        m = read_bvh(data("cmu_bvh/131_01.bvh"), unit_scale=CMU_UNIT_SCALE).subsample(4)  # 120 -> 30 fps
        m = window(m, int(0.4 * m.num_frames), num_frames)  # mid-stride
        return mocap_pair(name, m, limb_factors(m.names, 1.2, 0.8), radius_scale=0.18, girth=1.35,
                          num_frames=num_frames, gaussians=gaussians)
    if name == "deepmimic_walk":
        clip, urdf = data("deepmimic/humanoid3d_walk.txt"), data("deepmimic/humanoid.urdf")
        m = window(read_deepmimic(clip, urdf, urdf_scale=0.25), 0, num_frames)
        return mocap_pair(name, m, limb_factors(m.names, 1.2, 0.8), radius_scale=0.18, girth=1.35,
                          num_frames=num_frames, gaussians=gaussians)
    if name == "dog_trot":
        m = read_joint_position_motion(data("dog_mocap/dog_trot_joint_pos.txt"), fps=60.0, unit_scale=1.0,
                                       root=0, parents=None).subsample(2)  # 60 -> 30 fps
        m = window(m, 0, num_frames)
        factors = quadruped_factors(m.parents, toes=(10, 19, 15, 23), hips=(6, 16, 11, 20), legs=0.7, body=1.25)
        return mocap_pair(name, m, factors, radius_scale=0.18, girth=1.45, num_frames=num_frames, gaussians=gaussians)
    raise ConfigError(f"transfer_gt --pairs: unknown pair '{name}'; use {', '.join(PAIRS)}")


def method_configs(name: str, mpm: dict[str, Any] | None = None
                   ) -> tuple[dict[str, Any], dict[str, Any], TransferConfig]:
    """(sim config, velocity config, transfer options) of a method; MPM methods use the simulator's
    defaults otherwise.

    ``mpm`` overrides keys of every ``sim=mpm_warp`` method (one setting for the whole suite); the paper's
    form keeps its own transfer options (:data:`sync4d.transfer.PAPER`).
    """
    triplane = {"type": "triplane"}
    trained = dataclasses.replace(TransferConfig(), **TRAIN)
    pointwise = TransferConfig(control_grid=None)  # point-wise deformation of every Gaussian
    table: dict[str, tuple[dict[str, Any], dict[str, Any], TransferConfig]] = {
        "lbs_hard": ({"type": "lbs", "neighbours": 1}, {"type": "none"}, pointwise),
        "lbs_smooth": ({"type": "lbs", "neighbours": 16}, {"type": "none"}, pointwise),
        "kinematic": ({"type": "kinematic"}, {"type": "none"}, TransferConfig()),
        "mpm_none": ({"type": "mpm_warp"}, {"type": "none"}, TransferConfig()),
        "mpm_triplane": ({"type": "mpm_warp"}, triplane, trained),
        "paper": ({"type": "mpm_warp"}, triplane, dataclasses.replace(PAPER, **TRAIN)),
    }
    if name not in table:
        raise ConfigError(f"transfer_gt --methods: unknown method '{name}'; use {', '.join(METHODS)}")
    sim_cfg, vel_cfg, transfer = table[name]
    if mpm and sim_cfg["type"] == "mpm_warp":
        sim_cfg = {**sim_cfg, **mpm}
    return sim_cfg, vel_cfg, transfer


def parse_overrides(text: str) -> dict[str, Any]:
    """``"E=1e5 loss_points=anchors"`` -> {"E": 100000.0, "loss_points": "anchors"} (YAML values)."""
    import yaml

    out: dict[str, Any] = {}
    for item in text.split():
        if "=" not in item:
            raise ConfigError(f"transfer_gt --mpm: '{item}' is not KEY=VALUE")
        key, value = item.split("=", 1)
        parsed = yaml.safe_load(value)
        if isinstance(parsed, str):
            try:  # YAML 1.1 reads 1e5 (no dot) as a string
                parsed = float(parsed)
            except ValueError:
                pass
        out[key] = parsed
    return out


KEYS = ("pose_error_pct", "pose_error_max_pct", "torn_pairs_pct", "torn_seam_pairs_pct", "strain_p99_pct",
        "strain_p99_max_pct", "fragments", "volume_change_pct", "jitter_ratio", "seconds_per_frame")


def pair_motion(pair: GTPair, num_frames: int) -> Any:
    """The driving motion of a pair (what every method is given), pivoted on the target's part centroids."""
    return driving_motion(
        pair.reference, target_points=pair.target_vertices, target_faces=pair.target_faces, num_frames=num_frames,
        loop=False, part_centroids=part_centroids(pair.target.means.astype(np.float64), pair.part_map.tgt_part,
                                                  pair.part_map.num_parts),
    )


def score(pair: GTPair, traj: Any, motion: Any, seconds: list[float]) -> dict[str, Any]:
    """The reported numbers of one trajectory against the pair's truth (frames 1..T)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # parts too small for a hull volume are NaN
        m = compute_metrics(traj, pair.target, pair.part_map, motion, pair.reference, self_transfer=False,
                            frame_seconds=seconds, truth=pair.truth)
    return {k: (round(float(m[k]), 4) if isinstance(m[k], float) else m[k]) for k in KEYS}


def score_truth(pair: GTPair, num_frames: int) -> dict[str, Any]:
    """The truth scored like a method: its own strain and volume change are what a correct motion does."""
    from sync4d.types import Trajectory

    motion = pair_motion(pair, num_frames)
    traj = Trajectory(x=pair.truth, F=None, frame_dt=1.0 / motion.fps)
    return score(pair, traj, motion, [0.0] * num_frames)


def run_method(pair: GTPair, method: str, num_frames: int, mpm: dict[str, Any] | None = None) -> dict[str, Any]:
    """Run one method on one pair and score it against the pair's truth (frames 1..T)."""
    motion = pair_motion(pair, num_frames)
    sim_cfg, vel_cfg, transfer = method_configs(method, mpm)
    sim = build("sim", sim_cfg, device="cpu")
    seconds: list[float] = []
    last = [time.perf_counter()]

    def on_frame(t: int, x: Any, F: Any, stats: dict[str, float], checkpoint: Any = None, **_: Any) -> None:
        now = time.perf_counter()
        seconds.append(now - last[0])
        last[0] = now

    traj = run_transfer(sim, component("velocity", vel_cfg).build, transfer, pair.target, pair.part_map, motion,
                        num_frames=num_frames, seed=0, on_frame=on_frame)
    return score(pair, traj, motion, seconds)


def write_charts(results: dict[str, dict[str, dict[str, Any]]], folder: Path) -> list[str]:
    """Per pair, pose error (fidelity) against p99 strain at the worst frame (integrity); marker area ~ s/frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    pairs = list(results)
    fig, axes = plt.subplots(1, len(pairs), figsize=(4.2 * len(pairs), 4.0), squeeze=False)
    for ax, pair in zip(axes[0], pairs):
        for i, (method, r) in enumerate(results[pair].items()):
            size = 30 + 200 * min(float(r["seconds_per_frame"]), 10.0) / 10.0
            ax.scatter(r["pose_error_pct"], r["strain_p99_max_pct"], s=size, color=f"C{i}", alpha=0.8,
                       edgecolors="k", label=f"{method} ({r['seconds_per_frame']:.2g} s/f, {r['fragments']} frag)")
        ax.set_title(pair)
        ax.set_xlabel("pose error vs truth [% diag]")
        ax.set_ylabel("p99 strain, worst frame [%]")
        ax.set_yscale("symlog", linthresh=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="best")
    fig.suptitle("transfer_gt: fidelity vs integrity (marker area ~ seconds per frame)")
    fig.tight_layout()
    path = folder / "fidelity_integrity.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(str(path))
    return written


BASELINES = ("lbs_hard", "lbs_smooth", "kinematic")


def criteria(rows: dict[str, dict[str, Any]], method: str = "mpm_none") -> dict[str, Any]:
    """Issue 18's bar for ``method`` on one pair, each as pass/fail with the numbers compared.

    fragments 0; strain_p99_max_pct <= half of lbs_hard's; torn_pairs_pct below lbs_hard's; pose error within
    1% of the diagonal of the best baseline (lbs hard / smooth, kinematic).
    """
    m, hard = rows[method], rows["lbs_hard"]
    best = min(rows[b]["pose_error_pct"] for b in BASELINES if b in rows)
    return {
        "fragments_zero": m["fragments"] == 0,
        "strain_p99_max_half_of_lbs_hard": m["strain_p99_max_pct"] <= 0.5 * hard["strain_p99_max_pct"],
        "torn_below_lbs_hard": m["torn_pairs_pct"] < hard["torn_pairs_pct"],
        "pose_within_1pct_of_best_baseline": m["pose_error_pct"] <= best + 1.0,
        "best_baseline_pose_error_pct": best,
    }


def markdown_table(results: dict[str, dict[str, dict[str, Any]]]) -> str:
    """The pairs x methods table of fidelity, integrity and cost, as Markdown."""
    cols = ("pose_error_pct", "pose_error_max_pct", "torn_pairs_pct", "torn_seam_pairs_pct", "strain_p99_pct",
            "strain_p99_max_pct", "fragments", "volume_change_pct", "jitter_ratio", "seconds_per_frame")
    lines = ["| pair | method | " + " | ".join(c.replace("_pct", " %") for c in cols) + " |",
             "|---|---|" + "---|" * len(cols)]
    for pair, rows in results.items():
        for method, r in rows.items():
            cells = [f"{r[c]:.3g}" if isinstance(r[c], float) else str(r[c]) for c in cols]
            lines.append(f"| {pair} | {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m sync4d.evaluate transfer_gt", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pairs", default=",".join(PAIRS))
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--frames", type=int, default=10, help="frames per pair (frame 0 = rest)")
    parser.add_argument("--gaussians", type=int, default=4000, help="target Gaussians per pair")
    parser.add_argument("--json", default="", help="write the result here too")
    parser.add_argument("--charts", default="docs/charts/transfer_gt", help="chart folder ('' = none)")
    parser.add_argument("--table", default="", help="write the Markdown table here too")
    parser.add_argument("--mpm", default="", help="overrides of every sim=mpm_warp method, e.g. 'E=1e5'")
    args = parser.parse_args(argv)
    if args.frames < 3:
        raise ConfigError(f"transfer_gt --frames={args.frames}: need >= 3 (frame 0 is the rest pose)")
    pairs = [p for p in args.pairs.split(",") if p]
    methods = [m for m in args.methods.split(",") if m]
    mpm = parse_overrides(args.mpm)
    for m in methods:
        method_configs(m, mpm)
    started = time.perf_counter()
    results: dict[str, dict[str, dict[str, Any]]] = {}
    for name in pairs:
        pair = load_pair(name, args.frames, args.gaussians)
        results[name] = {"truth": score_truth(pair, args.frames)}
        for method in methods:
            t0 = time.perf_counter()
            results[name][method] = run_method(pair, method, args.frames, mpm)
            log.info("transfer_gt %s / %s: %s (%.1f s)", name, method, results[name][method], time.perf_counter() - t0)
    out: dict[str, Any] = {
        "pairs": results,
        "criteria_mpm_none": {p: criteria(r) for p, r in results.items() if {"mpm_none", "lbs_hard"} <= set(r)},
        "frames": args.frames,
        "gaussians": args.gaussians,
        "training": TRAIN,
        "mpm_overrides": mpm,
        "seconds": round(time.perf_counter() - started, 1),
    }
    if args.charts:
        out["charts"] = write_charts(results, Path(args.charts))
    if args.table:
        Path(args.table).write_text(markdown_table(results))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=1))
    print(json.dumps(out))
    return out
