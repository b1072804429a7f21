"""``recon_suite``: ``recon=video`` (one configuration) on the articulated-object suite, scored against exact truth.

    python -m sync4d.evaluate recon_suite [--seeds 0 1 2] [--only mw_drawer chest_lid] [--no-laptops]

Cases: every clip of the suite (eight objects x two views, rendered by MuJoCo into
``outputs/cache/articulated/clips`` by :mod:`sync4d_tools.articulated.render` when missing), plus the
Meta-World laptop-hinge renders (shared data) and the default scene's filmed laptop, each at every seed.
The configuration is ``conf/recon/video.yaml``; per clip only the number of parts (``recon.bones``, as the
paper gives B per category) and the seed change.

Scores per case (all frames):
    * part labels: fraction of the ground-truth foreground pixels whose rendered bone (front-to-back
      compositing, bones mapped to gt parts by majority) is the gt part;
    * hinge: mean |recovered angle - gt angle| [deg], the recovered angle being the rotation of the part's
      bone relative to the base bone since frame 0;
    * slide: mean |recovered travel - gt travel| as % of the gt travel's range, the recovered travel being
      the displacement of the part's point centroid relative to the base, times the one scale a single
      view cannot see (gt / recovered mean camera depth of the part's frame-0 pixels, ``part_depth_m``);
    * pass: every joint within 3 deg (or 3 % of travel) and labels >= 0.95.

Writes ``outputs/recon_suite/results.json`` and ``table.md``; the last stdout line is the summary JSON.
Data: Meta-World (MIT) models rendered with MuJoCo; ``rendered/metaworld_laptop_hinge`` (shared data).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from sync4d.sources.references import VideoSource, resolve_path
from sync4d.recon.video import VideoFit, rotation_angle_deg
from sync4d_tools.evaluate.recon_hinge import render_bone_labels

log = logging.getLogger(__name__)
LAPTOP_RENDERS = "../shared/data/rendered/metaworld_laptop_hinge"


def build_recon(bones: int, seed: int) -> Any:
    """``recon=video`` from ``conf/recon/video.yaml`` with only the part count and the seed set."""
    from omegaconf import OmegaConf

    from sync4d.registry import make_config

    conf = OmegaConf.load(Path(__file__).resolve().parents[2] / "conf" / "recon" / "video.yaml")
    conf.pop("defaults", None)  # the Hydra schema entry; the typed Config holds the defaults
    conf.bones, conf.seed = bones, seed
    cls, cfg = make_config("recon", conf)
    return cls(cfg)


def rendered_labels(fit: VideoFit, gt_labels: np.ndarray) -> list[np.ndarray]:
    """Per frame, the bone rendered at each gt foreground pixel."""
    out = []
    for t in range(fit.reference.num_frames):
        pix = np.argwhere(gt_labels[t] > 0)[:, ::-1].astype(np.float64)
        out.append(render_bone_labels(fit.reference, fit.means, fit.sigma, fit.opacity, fit.camera, t, pix,
                                      tau=0.02 * fit.object_width))
    return out


def part_mapping(rendered: list[np.ndarray], gt_labels: np.ndarray, n_bones: int, n_parts: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(bone -> gt part (B,), votes (B, P + 1), label agreement) by majority over the rendered pixels."""
    votes = np.zeros((n_bones, n_parts + 1))
    for t, lab in enumerate(rendered):
        np.add.at(votes, (lab, gt_labels[t][gt_labels[t] > 0]), 1)
    mapping = np.argmax(votes[:, 1:], 1) + 1
    agree = sum(int((mapping[lab] == gt_labels[t][gt_labels[t] > 0]).sum()) for t, lab in enumerate(rendered))
    return mapping, votes, agree / max(int((gt_labels > 0).sum()), 1)


def joint_errors(fit: VideoFit, gt: dict[str, np.ndarray], mapping: np.ndarray, votes: np.ndarray) -> list[dict[str, Any]]:
    """Per gt joint: its kind, the bone that carries it and the error (deg, or % of travel)."""
    ref = fit.reference
    world = np.einsum("tij,tbjk->tbik", ref.global_transforms, ref.bone_transforms)
    n_frames = ref.num_frames
    bones_of = {p: np.flatnonzero(mapping == p) for p in range(1, votes.shape[1])}
    base = bones_of[1][np.argmax(votes[bones_of[1], 1])] if len(bones_of[1]) else None
    out = []
    for j, kind in enumerate(gt["joint_type"]):
        part = j + 2
        value = gt["joint_value"][:n_frames, j]
        row: dict[str, Any] = {"joint": str(kind), "found": None, "error": float("inf")}
        if base is None or not len(bones_of[part]):
            out.append(row)
            continue
        bone = bones_of[part][np.argmax(votes[bones_of[part], part])]
        row["found"] = fit.joints.kinds[bone]
        rel = np.einsum("tij,tjk->tik", np.linalg.inv(world[:, base]), world[:, bone])
        rel = np.einsum("ij,tjk->tik", np.linalg.inv(rel[0]), rel)  # since frame 0
        if kind == "hinge":
            err = np.abs(rotation_angle_deg(rel[:, :3, :3]) - np.degrees(np.abs(value - value[0])))
            row["error"] = float(err.mean())
        else:
            own = ref.part_labels() == bone
            centroid = fit.means[own].mean(0)
            travel = np.linalg.norm(rel[:, :3, :3] @ centroid + rel[:, :3, 3] - centroid, axis=1)
            depth = (fit.means[own] @ fit.camera.world_to_cam[2, :3] + fit.camera.world_to_cam[2, 3]).mean()
            scale = float(gt["part_depth_m"][part - 1]) / float(depth)
            span = float(np.ptp(value))
            row["error"] = float(np.abs(scale * travel - np.abs(value - value[0])).mean() / max(span, 1e-9) * 100.0)
            row["scale"] = round(scale, 3)
        out.append(row)
    return out


def passes(joints: list[dict[str, Any]], labels: float) -> bool:
    return labels >= 0.95 and all(r["error"] <= 3.0 for r in joints)


def suite_cases(cache: Path, only: list[str], laptops: bool) -> list[tuple[str, Path | None]]:
    """(name, clip folder) of every case; the filmed laptop has no folder."""
    clips = cache / "clips"
    if not clips.exists() or not any(clips.glob("*/gt.npz")):
        from sync4d_tools.articulated.render import main as render

        render(["--out", str(cache)])
    cases: list[tuple[str, Path | None]] = [(p.name, p) for p in sorted(clips.iterdir()) if (p / "gt.npz").exists()]
    if laptops:
        cases += [("laptop_hinge_renders", resolve_path(LAPTOP_RENDERS, what="laptop render folder")),
                  ("laptop_filmed", None)]
    return [c for c in cases if not only or any(c[0].startswith(o) for o in only)]


def load_case(folder: Path | None) -> tuple[Any, dict[str, np.ndarray]]:
    """(ReferenceInput, gt) of a clip folder, or of the filmed laptop (``None``)."""
    if folder is None:
        from sync4d.scenes.laptop import filmed_laptop_case

        source, gt = filmed_laptop_case()
    else:
        source = VideoSource(VideoSource.Config(video=str(folder / "rgb.mp4"), masks=str(folder / "masks"),
                                                camera=str(folder / "gt.npz"))).load()
        gt = dict(np.load(folder / "gt.npz"))
    if "joint_type" not in gt:  # the laptop layout: one hinge
        gt["joint_type"] = np.array(["hinge"])
        gt["joint_value"] = np.asarray(gt["hinge_angle_rad"], np.float64)[:, None]
    return source, gt


def label_diagnosis(fit: VideoFit, gt_labels: np.ndarray, rendered: list[np.ndarray], mapping: np.ndarray) -> dict[str, float]:
    """Where the labels are lost: agreement of the tracked points' initial and fitted labels with the gt part
    under their frame-0 pixel (bones mapped as for the score), the rendered score in frame 0 and in the
    later frames, and the share of wrongly rendered pixels within 2 px of a gt part border."""
    import cv2

    uv = np.floor(fit.tracks.uv0).astype(int)
    truth = gt_labels[0][uv[:, 1], uv[:, 0]]
    fg = truth > 0
    out = {"points_init": float((mapping[fit.init.labels] == truth)[fg].mean()) if fg.any() else 0.0,
           "points_fit": float((mapping[fit.joints.labels] == truth)[fg].mean()) if fg.any() else 0.0}
    wrong_border = wrong = 0
    per_frame = []
    for t, lab in enumerate(rendered):
        g = gt_labels[t]
        ok = mapping[lab] == g[g > 0]
        per_frame.append(ok.mean() if len(ok) else 1.0)
        border = np.zeros(g.shape, bool)
        for p in np.unique(g[g > 0]):
            near = cv2.dilate((g == p).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
            border |= near & (g > 0) & (g != p)
        wrong += int((~ok).sum())
        wrong_border += int((~ok & border[g > 0]).sum())
    out["render_f0"] = float(per_frame[0])
    out["render_later"] = float(np.mean(per_frame[1:])) if len(per_frame) > 1 else float(per_frame[0])
    out["wrong_at_border"] = wrong_border / max(wrong, 1)
    return {k: round(v, 4) for k, v in out.items()}


def run_case(name: str, folder: Path | None, seed: int) -> dict[str, Any]:
    source, gt = load_case(folder)
    n_parts = len(gt["joint_type"]) + 1
    fit = build_recon(n_parts, seed).reconstruct_detailed(source)
    rendered = rendered_labels(fit, gt["part_labels"])
    mapping, votes, labels = part_mapping(rendered, gt["part_labels"], fit.reference.num_bones, n_parts)
    joints = joint_errors(fit, gt, mapping, votes)
    return {"case": name, "seed": seed, "joints": joints, "labels": round(labels, 4),
            "seconds": round(fit.seconds, 1), "cpu_seconds": round(fit.cpu_seconds, 1), "frames": fit.reference.num_frames,
            "size": list(fit.masks.shape[1:][::-1]), "pass": passes(joints, labels),
            "label_diagnosis": label_diagnosis(fit, gt["part_labels"], rendered, mapping)}


def table(rows: list[dict[str, Any]]) -> str:
    lines = ["| case | seed | joints (gt -> found) | error (deg or % travel) | labels | s | pass |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        kinds = ", ".join(f"{j['joint']}->{j['found']}" for j in r["joints"])
        errs = ", ".join(f"{j['error']:.2f}{'' if j['joint'] == 'hinge' else '%'}" for j in r["joints"])
        lines.append(f"| {r['case']} | {r['seed']} | {kinds} | {errs} | {r['labels']:.3f} | {r['seconds']} | "
                     f"{'yes' if r['pass'] else 'no'} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m sync4d.evaluate recon_suite", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--only", nargs="*", default=[], help="case name prefixes")
    parser.add_argument("--no-laptops", action="store_true", help="leave out the two laptop cases")
    parser.add_argument("--cache", default="outputs/cache/articulated")
    parser.add_argument("--out", default="outputs/recon_suite")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    rows = []
    for name, folder in suite_cases(Path(args.cache), args.only, not args.no_laptops):
        for seed in args.seeds:
            rows.append(run_case(name, folder, seed))
            print(json.dumps(rows[-1]), flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(rows, indent=1))
    (out / "table.md").write_text(table(rows) + "\n")
    print(table(rows))
    summary = {"cases": len(rows), "passed": sum(r["pass"] for r in rows),
               "pass_rate": round(sum(r["pass"] for r in rows) / max(len(rows), 1), 3),
               "median_seconds": float(np.median([r["seconds"] for r in rows])) if rows else 0.0,
               "wall_seconds": round(time.perf_counter() - start, 1), "table": str(out / "table.md")}
    print(json.dumps(summary))
    return summary
