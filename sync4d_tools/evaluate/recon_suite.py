"""``recon_suite``: ``recon=video`` (one configuration) on the articulated-object suite, every joint scored as a line.

    python -m sync4d.evaluate recon_suite [--seeds 0 1 2] [--only mw_drawer chest_lid] [--no-laptops] [--out DIR]
        [--frames N] [--set KEY=VALUE ...]     # the first N frames of every clip; recon=video overrides
        [--camera static|handheld]             # the MuJoCo clips filmed from static views or hand-held

Cases: the suite's eight objects x two views (MuJoCo clips, :mod:`sync4d_tools.articulated.render`; a seed other
than 0 samples another clip of each: camera placement, start state, colours and texture, floor, light), the
Meta-World laptop-hinge renders (shared data: one fixed clip, so its seeds change only the fit's random
choices) and the default scene's filmed laptop (a seed other than 0 moves the camera and scales the texture).
The configuration is ``conf/recon/video.yaml``; per clip only the number of parts (``recon.bones``, as the
paper gives B per category) and the seed change. The masks and the camera are the exact ones.
``--camera handheld`` runs the same MuJoCo clips filmed hand-held (the render's ``--camera handheld``: the
default scene's arc from each static view, ``-hh`` folders); the fit gets the exact per-frame camera and the
scores see each frame through its own camera (the laptop cases have no hand-held clip: ``--no-laptops``).

Scores per case (:mod:`sync4d_tools.articulated.score`): per joint the kind, the axis direction error [deg],
the pivot error [% of the object's size] and the motion error [deg, or % of travel]; a joint passes with the
right kind and each within 3. Labels: the fraction of gt object pixels (all frames) whose rendered bone
(front-to-back compositing, bones mapped to parts by majority) is the gt part, split into pixels showing
surface frame 0 sees (``first``) and surface revealed later (``revealed``), each beside its ceiling (the exact
truth rendered through the method's representation, :mod:`sync4d_tools.articulated.ceiling`) and its floor
(every pixel one constant part; no joint moving). A case's first-frame labels pass at >= 0.95 of the ceiling.

Rows that share a clip (the fixed laptop renders at several seeds) are one sample: the summary weighs each
by 1 / (rows of its clip). Writes ``results.json`` and ``table.md`` under ``--out``; the last stdout line is
the summary JSON. Data: Meta-World (MIT) models rendered with MuJoCo; ``rendered/metaworld_laptop_hinge``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from sync4d.errors import InputError
from sync4d.recon.video import VideoFit, VideoReconstructor
from sync4d.recon.video.reconstructor import upright_frame
from sync4d.sources.references import VideoSource, resolve_path
from sync4d.types import Camera, ReferenceInput
from sync4d_tools import camera_of, video_of
from sync4d_tools.articulated.ceiling import exact_splats, frame_cameras, rendered_labels
from sync4d_tools.articulated.score import constant_labels, joint_row, label_scores, missing_row
from sync4d_tools.articulated.truth import CaseTruth, clip_truth, filmed_laptop, first_frames, laptop_renders_truth
from sync4d_tools.evaluate import component_options, dotlist

log = logging.getLogger(__name__)
LAPTOP_RENDERS = "../shared/data/rendered/metaworld_laptop_hinge"
LABEL_BAR = 0.95  # first-frame labels against their ceiling
Loader = Callable[[], tuple[ReferenceInput, CaseTruth, str]]


def build_recon(bones: int, seed: int, overrides: dict[str, Any] | None = None) -> VideoReconstructor:
    """``recon=video`` from ``conf/recon/video.yaml`` with the part count and the seed set (and ``overrides``,
    the command line's ``--set``, merged first)."""
    from sync4d.registry import make_config

    _, cfg = make_config("recon", component_options("recon", "video", {**(overrides or {}), "bones": bones,
                                                                        "seed": seed}))
    return VideoReconstructor(cfg)


def part_mapping(rendered: list[np.ndarray], gt_labels: np.ndarray, n_bones: int, n_parts: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(bone -> gt part (B,), votes (B, P + 1), label agreement) by majority over the rendered pixels."""
    votes = np.zeros((n_bones, n_parts + 1))
    for t, lab in enumerate(rendered):
        np.add.at(votes, (lab, gt_labels[t][gt_labels[t] > 0]), 1)
    mapping = np.argmax(votes[:, 1:], 1) + 1
    agree = sum(int((mapping[lab] == gt_labels[t][gt_labels[t] > 0]).sum()) for t, lab in enumerate(rendered))
    return mapping, votes, agree / max(int((gt_labels > 0).sum()), 1)


def passes(joints: list[dict[str, Any]]) -> bool:
    """Every joint within the bar (right kind, axis, pivot, motion); a case with no joint row fails."""
    return bool(joints) and all(r["pass"] for r in joints)


def joint_rows(fit: VideoFit, truth: CaseTruth, mapping: np.ndarray, votes: np.ndarray,
               upright: np.ndarray | None = None) -> list[dict[str, Any]]:
    """Per gt joint, the scores of the bone that renders most of its part (:func:`score.joint_row`); ``upright``
    (4, 4): the fit's world is the truth's turned by it (a ``world_up`` given), so the fit is turned back."""
    ref = fit.reference
    world = np.einsum("tij,tbjk->tbik", ref.global_transforms, ref.bone_transforms)
    bones_of = {p: np.flatnonzero(mapping == p) for p in range(1, votes.shape[1])}
    base = bones_of[1][np.argmax(votes[bones_of[1], 1])] if len(bones_of[1]) else None
    tracked, camera = fit.means[: len(fit.joints.labels)], clip_camera(fit.camera, upright)
    if upright is not None:
        back = np.linalg.inv(upright)
        world = back @ world @ upright
        tracked = tracked @ back[:3, :3].T + back[:3, 3]
    out = []
    for j in range(len(truth.kinds)):
        part = j + 2
        if base is None or not len(bones_of[part]):
            out.append(missing_row(j, truth))
            continue
        bone = bones_of[part][np.argmax(votes[bones_of[part], part])]
        rel = np.einsum("tij,tjk->tik", np.linalg.inv(world[:, base]), world[:, bone])
        rel = np.einsum("ij,tjk->tik", np.linalg.inv(rel[0]), rel)  # since frame 0
        found = fit.joints.kinds[bone] if fit.joints.kinds[bone] != "root" else "none"
        out.append(joint_row(rel, found, j, truth, camera, tracked[fit.joints.labels == bone]))
    return out


def clip_camera(camera: Camera, upright: np.ndarray | None) -> Camera:
    """The fit's ``camera`` in the clip's world: the fit's world is the clip's turned by ``upright`` (4, 4) when
    a ``world_up`` was given (None: the same world)."""
    return camera if upright is None else replace(camera, world_to_cam=camera.world_to_cam @ upright)


def clip_extrinsics(fit: VideoFit, upright: np.ndarray | None) -> np.ndarray | None:
    """(T, 4, 4) the fit's per-frame world-to-camera in the clip's world (as :func:`clip_camera`); None when
    the camera is static."""
    if fit.extrinsics is None:
        return None
    return fit.extrinsics if upright is None else fit.extrinsics @ upright


def label_block(rendered: list[np.ndarray], mapping: np.ndarray, truth: CaseTruth, seen: np.ndarray) -> dict[str, float]:
    lab = truth.part_labels
    return label_scores([mapping[r] == lab[t][lab[t] > 0] for t, r in enumerate(rendered)], seen, lab)


def run_case(name: str, seed: int, load: Loader, overrides: dict[str, Any] | None = None,
             world_up: np.ndarray | None = None) -> dict[str, Any]:
    """Reconstruct one case (``recon=video`` with ``overrides``; the clip's world's up given when ``world_up``,
    (3,) in the clip's world) and score it, with its floor and ceiling."""
    source, truth, variant = load()
    if world_up is not None:
        source = replace(source, world_up=np.asarray(world_up, np.float64) / np.linalg.norm(world_up))
    clip = video_of(source)
    clip_id = hashlib.sha1(clip.frames.tobytes() + clip.masks.tobytes()).hexdigest()[:12]
    n_parts = len(truth.kinds) + 1
    fit = build_recon(n_parts, seed, overrides).reconstruct_detailed(source)
    upright = None if source.world_up is None else upright_frame(source.world_up)
    camera = clip_camera(fit.camera, upright)  # the truth lives in the clip's world
    extrinsics = clip_extrinsics(fit, upright)
    seen = truth.seen_first(frame_cameras(camera, extrinsics))
    rendered = rendered_labels(fit, truth.part_labels)
    mapping, votes, _ = part_mapping(rendered, truth.part_labels, fit.reference.num_bones, n_parts)
    joints = joint_rows(fit, truth, mapping, votes, upright)
    exact = exact_splats(fit.tracks, fit.masks, truth, clip, camera, fit.object_width, extrinsics)
    ex_rendered = rendered_labels(exact, truth.part_labels)
    ex_mapping = part_mapping(ex_rendered, truth.part_labels, exact.reference.num_bones, n_parts)[0]
    labels, ceiling = label_block(rendered, mapping, truth, seen), label_block(ex_rendered, ex_mapping, truth, seen)
    ratio = labels["first"] / ceiling["first"] if ceiling["first"] > 0 else float("nan")
    return {"case": name, "seed": seed, "clip_id": clip_id, "variant": variant,
            "camera": "static" if extrinsics is None else "moving", "joints": joints,
            "labels": labels, "ceiling": ceiling, "first_ratio": round(ratio, 4),
            "floor": {"labels": constant_labels(truth.part_labels, seen), "joints": [missing_row(j, truth) for j in range(len(truth.kinds))]},
            "seen_share": round(float(seen[truth.part_labels > 0].mean()), 4),
            "seconds": round(fit.seconds, 1), "cpu_seconds": round(fit.cpu_seconds, 1), "frames": fit.reference.num_frames,
            "size": list(fit.masks.shape[1:][::-1]), "pass_joints": passes(joints), "pass_labels": bool(ratio >= LABEL_BAR),
            "pass": passes(joints) and bool(ratio >= LABEL_BAR)}


def clip_loader(folder: Path, frames: int = 0) -> Loader:
    def load() -> tuple[ReferenceInput, CaseTruth, str]:
        source = VideoSource(VideoSource.Config(video=str(folder / "rgb.mp4"), masks=str(folder / "masks"),
                                                camera=str(folder / "gt.npz"), max_frames=frames)).load()
        gt = dict(np.load(folder / "gt.npz"))
        return source, first_frames(clip_truth(gt), frames), str(gt.get("variant", ""))
    return load


def renders_loader(cache: Path, frames: int = 0) -> Loader:
    def load() -> tuple[ReferenceInput, CaseTruth, str]:
        root = resolve_path(LAPTOP_RENDERS, what="laptop render folder")
        source = VideoSource(VideoSource.Config(video=str(root / "rgb.mp4"), masks=str(root / "masks"),
                                                camera=str(root / "gt.npz"), max_frames=frames)).load()
        truth = laptop_renders_truth(dict(np.load(root / "gt.npz")), camera_of(source), cache)
        return source, first_frames(truth, frames), "fixed clip (shared data)"
    return load


def filmed_loader(seed: int, frames: int) -> Loader:
    def load() -> tuple[ReferenceInput, CaseTruth, str]:
        return filmed_laptop(seed, frames)
    return load


def suite_cases(cache: Path, only: list[str], laptops: bool, seeds: list[int], frames: int = 0,
                camera: str = "static") -> list[tuple[str, int, Loader]]:
    """(name, seed, loader) of every case, the first ``frames`` frames of each (0: all), the MuJoCo clips
    filmed by ``camera`` (``static`` or ``handheld``); clips missing from the cache are rendered first."""
    from sync4d_tools.articulated.objects import suite_objects
    from sync4d_tools.articulated.render import VIEWS, clip_name

    names = [f"{o.name}-{v.name}" for o in suite_objects() for v in VIEWS]
    if laptops:
        names += ["laptop_hinge_renders", "laptop_filmed"]
    unknown = [o for o in only if not any(n.startswith(o) for n in names)]
    if unknown:
        raise InputError(f"--only {unknown[0]}: no case starts with it; cases: {', '.join(names)}")
    names = [n for n in names if not only or any(n.startswith(o) for o in only)]
    cases: list[tuple[str, int, Loader]] = []
    for name in names:
        for seed in seeds:
            if name == "laptop_filmed":
                cases.append((name, seed, filmed_loader(seed, frames or 24)))
            elif name == "laptop_hinge_renders":
                cases.append((name, seed, renders_loader(cache, frames)))
            else:
                obj, view = name.rsplit("-", 1)
                folder = cache / "clips" / clip_name(obj, view, seed, camera)
                if not (folder / "gt.npz").exists() or "depth_t" not in np.load(folder / "gt.npz").files:
                    from sync4d_tools.articulated.render import main as render

                    render(["--out", str(cache), "--seeds", str(seed), "--only", obj, "--camera", camera])
                cases.append((name, seed, clip_loader(folder, frames)))
    return cases


def _fmt(v: float | None, pct: bool = False) -> str:
    return "-" if v is None else ("inf" if not np.isfinite(v) else f"{v:.1f}{'%' if pct else ''}")


def table(rows: list[dict[str, Any]]) -> str:
    """Markdown: every case and seed, joints as kind / axis / pivot / motion, labels beside floor and ceiling."""
    lines = ["| case | seed | kind (gt->found) | axis [deg] | pivot [% size] | motion [deg or % travel] | joints pass | "
             "first-frame labels: floor / method / ceiling (ratio) | revealed labels: floor / method / ceiling | CPU s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        js = r["joints"]
        kinds = ", ".join(f"{j['joint']}->{j['found']}" for j in js)
        axis = ", ".join(_fmt(j["axis_deg"]) for j in js)
        pivot = ", ".join(_fmt(j["pivot_pct"]) for j in js)
        motion = ", ".join(_fmt(j["motion"], j["joint"] == "slide") for j in js)
        fl, lb, ce = r["floor"]["labels"], r["labels"], r["ceiling"]
        lines.append(f"| {r['case']} | {r['seed']} | {kinds} | {axis} | {pivot} | {motion} | "
                     f"{'yes' if r['pass_joints'] else 'no'} | {fl['first']:.3f} / {lb['first']:.3f} / {ce['first']:.3f} "
                     f"({r['first_ratio']:.3f}) | {fl['revealed']:.3f} / {lb['revealed']:.3f} / {ce['revealed']:.3f} | "
                     f"{r['cpu_seconds']} |")
    return "\n".join(lines)


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Shares weighted so that rows of one clip count once; medians over joints; the floor beside."""
    counts: dict[str, int] = {}
    for r in rows:
        counts[r["clip_id"]] = counts.get(r["clip_id"], 0) + 1
    weight = [1.0 / counts[r["clip_id"]] for r in rows]
    joints = [(w, j) for w, r in zip(weight, rows) for j in r["joints"]]
    total_j = sum(w for w, _ in joints) or 1.0
    total_c = sum(weight) or 1.0

    def median(key: str, kind: str | None = None) -> float | None:
        vals = [j[key] for _, j in joints if j[key] is not None and (kind is None or j["joint"] == kind)]
        return round(float(np.median(vals)), 2) if vals else None

    return {"rows": len(rows), "samples": round(total_c, 2),
            "joints_within_bar": round(sum(w * j["pass"] for w, j in joints) / total_j, 3),
            "joints_kind_right": round(sum(w * (j["found"] == j["joint"]) for w, j in joints) / total_j, 3),
            "cases_all_joints": round(sum(w * r["pass_joints"] for w, r in zip(weight, rows)) / total_c, 3),
            "cases_first_labels": round(sum(w * r["pass_labels"] for w, r in zip(weight, rows)) / total_c, 3),
            "cases_pass": round(sum(w * r["pass"] for w, r in zip(weight, rows)) / total_c, 3),
            "median_axis_deg": median("axis_deg"), "median_pivot_pct": median("pivot_pct", "hinge"),
            "median_hinge_motion_deg": median("motion", "hinge"), "median_slide_motion_pct": median("motion", "slide"),
            "median_first_ratio": round(float(np.median([r["first_ratio"] for r in rows])), 3) if rows else None,
            "floor_first_ratio": round(float(np.median([r["floor"]["labels"]["first"] / r["ceiling"]["first"] for r in rows])), 3) if rows else None,
            "laptop_filmed_within_bar": [r["pass_joints"] for r in rows if r["case"] == "laptop_filmed"],
            "median_cpu_seconds": float(np.median([r["cpu_seconds"] for r in rows])) if rows else 0.0}


def summary_table(rows: list[dict[str, Any]]) -> str:
    """Markdown: the issue's bars for the floor (nothing moves, one constant label), the method and the ceiling
    (exact truth; its joints score 0 by construction), rows of one clip counted once."""
    if not rows:
        return ""
    out = summary(rows)
    counts: dict[str, int] = {}
    for r in rows:
        counts[r["clip_id"]] = counts.get(r["clip_id"], 0) + 1
    weight = np.array([1.0 / counts[r["clip_id"]] for r in rows])

    def share(flags: list[bool]) -> str:
        return f"{100.0 * float((weight * np.array(flags, float)).sum() / weight.sum()):.0f} %"

    def med(key: str, part: str) -> str:
        vals = [r[key]["labels"][part] if key == "floor" else r[key][part] for r in rows]
        return f"{np.nanmedian(vals):.3f}"

    floor_first = [r["floor"]["labels"]["first"] >= LABEL_BAR * r["ceiling"]["first"] for r in rows]
    lines = ["| bar (rows of one clip count once) | floor: nothing moves, one label | recon=video | ceiling: exact truth |",
             "|---|---|---|---|",
             f"| joints within 3 deg / 3 % / 3 deg-or-% with the right kind (issue: >= 80 %) | 0 % | "
             f"{100 * out['joints_within_bar']:.0f} % | 100 % |",
             f"| joints of the right kind | 0 % | {100 * out['joints_kind_right']:.0f} % | 100 % |",
             f"| cases with every joint within the bar | 0 % | {100 * out['cases_all_joints']:.0f} % | 100 % |",
             f"| cases with first-frame labels >= 0.95 of the ceiling (issue: >= 80 %) | {share(floor_first)} | "
             f"{100 * out['cases_first_labels']:.0f} % | 100 % |",
             f"| first-frame labels, median | {med('floor', 'first')} | {med('labels', 'first')} | {med('ceiling', 'first')} |",
             f"| revealed-surface labels, median | {med('floor', 'revealed')} | {med('labels', 'revealed')} | "
             f"{med('ceiling', 'revealed')} |",
             f"| axis error, median [deg] | 90 | {out['median_axis_deg']} | 0 |",
             f"| hinge pivot error, median [% of size] | inf | {out['median_pivot_pct']} | 0 |",
             f"| hinge motion error, median [deg] | - | {out['median_hinge_motion_deg']} | 0 |",
             f"| slide motion error, median [% of travel] | - | {out['median_slide_motion_pct']} | 0 |",
             f"| the filmed default laptop within the bar, per seed | no | "
             f"{', '.join('yes' if ok else 'no' for ok in out['laptop_filmed_within_bar']) or '-'} | yes |",
             f"| samples (distinct clips) / rows | | {out['samples']} / {out['rows']} | |"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m sync4d.evaluate recon_suite", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--only", nargs="*", default=[], help="case name prefixes")
    parser.add_argument("--no-laptops", action="store_true", help="leave out the two laptop cases")
    parser.add_argument("--cache", default="outputs/cache/articulated")
    parser.add_argument("--out", default="outputs/recon_suite")
    parser.add_argument("--merge", nargs="*", default=[], metavar="RESULTS_JSON",
                        help="run nothing: merge these results.json files (e.g. of parallel runs) into --out")
    parser.add_argument("--frames", type=int, default=0, help="score the first N frames of every clip (0: all)")
    parser.add_argument("--world-up", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                        help="give the reconstruction the clips' world up (the suite's MuJoCo clips: 0 0 1), as the "
                             "video front end gives it for a phone's video")
    parser.add_argument("--camera", choices=("static", "handheld"), default="static",
                        help="the MuJoCo clips from static views (default) or filmed hand-held along the default "
                             "scene's arc (needs --no-laptops)")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="recon=video overrides (dotted keys, YAML values) beside the suite's bones and seed")
    args = parser.parse_args(argv)
    overrides = dotlist(args.set, option="--set")
    if {"bones", "seed"} & set(overrides):
        raise InputError("--set bones/seed: the suite sets them per case (bones: its parts; seed: --seeds)")
    if args.frames < 0 or args.frames == 1:
        raise InputError(f"--frames {args.frames}: 0 (every frame) or at least 2")
    if args.camera == "handheld" and not args.no_laptops and not args.merge:
        raise InputError("--camera handheld: the laptop cases have no hand-held clip in the suite; add --no-laptops")
    missing = [f for f in args.merge if not Path(f).is_file()]
    if missing:
        raise InputError(f"--merge {missing[0]}: not found")
    start = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = [r for f in args.merge for r in json.loads(Path(f).read_text())]
    rows.sort(key=lambda r: (r["case"], r["seed"]))
    cases = [] if args.merge else suite_cases(Path(args.cache), args.only, not args.no_laptops, args.seeds, args.frames,
                                              args.camera)
    for name, seed, load in cases:
        rows.append(run_case(name, seed, load, overrides, args.world_up))
        print(json.dumps(rows[-1]), flush=True)
        (out / "results.json").write_text(json.dumps(rows, indent=1))  # never lose computed rows
    (out / "results.json").write_text(json.dumps(rows, indent=1))
    (out / "table.md").write_text(summary_table(rows) + "\n\n" + table(rows) + "\n")
    print(table(rows))
    result = {**summary(rows), "wall_seconds": round(time.perf_counter() - start, 1), "table": str(out / "table.md")}
    print(json.dumps(result))
    return result
