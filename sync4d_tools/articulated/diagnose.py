"""Where does ``recon=video`` go wrong on a suite clip: the tracks, the objective or the search?

    python -m sync4d_tools.articulated.diagnose outputs/cache/articulated/clips/mw_drawer-left [--fit]

From a clip's ``gt.npz`` (frame-0 depth ``depth_m``, ``joint_axis``, ``joint_pos``, ``joint_value``) the exact
image motion of every tracked frame-0 point is computed and compared with the chained-flow tracks
(``track error``: median / 90th percentile [px] of trusted tracks; ``motion ratio``: tracked over true
displacement of the moving parts' points, least squares). The fit's objective (data terms of
:mod:`sync4d.recon.video.joints`) is evaluated at the truth; with ``--fit`` the method is run and its loss at
its own solution printed beside it (loss(truth) < loss(found): the search fails; else the objective is biased).
Ground truth comes from the MuJoCo model, never from the method.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from sync4d.sources.references import VideoSource
from sync4d.recon.video import joints as jt
from sync4d.recon.video.images import backproject
from sync4d.recon.video.reconstructor import VideoReconstructor
from sync4d.recon.video.stages import Tracks, init_parts, reference_depth, track_grid, video_masks
from sync4d.types import Camera, VideoClip
from sync4d_tools import camera_of, video_of
from sync4d_tools.articulated.ceiling import exact_splats, rendered_labels
from sync4d_tools.articulated.truth import CaseTruth, clip_truth


def model_from(
    scene: jt.Scene,
    labels: np.ndarray,
    root: int,
    kinds: list[str],
    axes: np.ndarray,
    pivots: np.ndarray,
    values: np.ndarray,
    depth: np.ndarray,
) -> jt.Articulation:
    """An Articulation holding the given joints (slide values in m) and per-point depths [m] exactly."""
    vals = values.copy()
    for b, kind in enumerate(kinds):
        if kind == "slide":
            vals[:, b] /= scene.width
    model = jt.Articulation(scene, labels, root, kinds, axes, pivots, vals, np.log(depth))
    with torch.no_grad():
        coords = model.coords.numpy()
        for b in range(len(kinds)):
            own = labels == b
            if own.sum() >= 3:
                model.plane[b] = torch.as_tensor(np.linalg.lstsq(coords[own], 1.0 / depth[own], rcond=None)[0])
        model.resid[:] = torch.as_tensor(np.log(depth)) - model.log_depth() + model.resid
    return model


def losses(model: jt.Articulation, frames: int, cfg: jt.FitConfig) -> dict[str, float]:
    with torch.no_grad():
        track, inside, cover = jt.data_terms(model, frames)
    data = float(track + cfg.inside_weight * inside + cfg.cover_weight * cover)
    return {
        "track": round(float(track), 4),
        "inside": round(float(inside), 4),
        "cover": round(float(cover), 4),
        "data": round(data, 4),
    }


def diagnose(folder: Path, run_fit: bool, seed: int = 0, *, labels_ceiling: bool = False) -> dict:
    gt = dict(np.load(folder / "gt.npz"))
    source = VideoSource(
        VideoSource.Config(video=str(folder / "rgb.mp4"), masks=str(folder / "masks"), camera=str(folder / "gt.npz"))
    ).load()
    n_parts = len(gt["joint_type"]) + 1
    cfg = VideoReconstructor.Config(bones=n_parts, seed=seed)
    clip, camera = video_of(source).validate(), camera_of(source)
    masks = video_masks(clip, cfg.masks)
    tracks = track_grid(clip.frames, masks, cfg.tracks)
    pix = np.floor(tracks.uv0).astype(int)
    labels = gt["part_labels"][0][pix[:, 1], pix[:, 0]].astype(int) - 1
    depth = gt["depth_m"][pix[:, 1], pix[:, 0]].astype(np.float64)
    x0 = backproject(tracks.uv0, depth, camera)
    truth = clip_truth(gt)
    motion = truth.motions()[:, labels]  # (T, N, 4, 4)
    xt = np.einsum("tnij,nj->tni", motion[..., :3, :3], x0) + motion[..., :3, 3]
    pc = xt @ camera.world_to_cam[:3, :3].T + camera.world_to_cam[:3, 3]
    uv_gt = (pc @ camera.K.T)[..., :2] / (pc @ camera.K.T)[..., 2:3]
    err = np.linalg.norm(tracks.uv - uv_gt, axis=-1)
    ok = tracks.trusted & (labels >= 1)[None]
    d_tr, d_gt = (tracks.uv - tracks.uv0)[ok], (uv_gt - tracks.uv0)[ok]
    report = {
        "clip": folder.name,
        "points": len(labels),
        "trusted_moving_frac": round(float(ok[1:].mean() / max((labels >= 1).mean(), 1e-9)), 3),
        "track_err_px_median": round(float(np.median(err[ok])), 3),
        "track_err_px_p90": round(float(np.quantile(err[ok], 0.9)), 3),
        "motion_ratio": round(float((d_tr * d_gt).sum() / max((d_gt**2).sum(), 1e-9)), 3),
        "gt_max_disp_px": round(float(np.linalg.norm(uv_gt - tracks.uv0, axis=-1).max()), 1),
    }
    init = init_parts(tracks, n_parts, cfg.init, static_px=cfg.fit.static_root_px)
    agree = max(float((np.array(p)[init.labels] == labels).mean()) for p in _perms(n_parts))
    report["init_label_agreement"] = round(agree, 3)
    z_ref = reference_depth(camera)
    scene = jt.make_scene(
        tracks, masks, camera, init, z_ref, np.tile(np.eye(4), (len(masks), 1, 1)), np.random.default_rng(seed)
    )
    kinds = ["root"] + [str(k) for k in gt["joint_type"]]
    axes = np.concatenate([np.zeros((1, 3)), gt["joint_axis"]])
    pivots = np.concatenate([np.zeros((1, 3)), gt["joint_pos"]])
    values = np.concatenate([np.zeros((len(masks), 1)), gt["joint_value"] - gt["joint_value"][:1]], 1)
    truth_model = model_from(scene, labels, 0, kinds, axes, pivots, values, depth)
    report["loss_truth"] = losses(truth_model, len(masks), cfg.fit)
    if labels_ceiling:
        report["oracle_labels_revealed"] = exact_label_score(truth, tracks, masks, clip, camera, scene.width)
    pairs = jt.neighbour_pairs(tracks.uv0, labels, tracks.stride)
    torch.set_num_threads(1)
    jt.optimise(truth_model, cfg.fit, cfg.fit.steps // 2, pairs, windows=1)
    report["loss_truth_refined"] = losses(truth_model, len(masks), cfg.fit)
    report["truth_refined_angle_err"] = _value_err(truth_model, gt, scene)
    report["truth_refined_joints"] = refined_scores(truth_model, truth, camera)
    if run_fit:
        fit = jt.fit_joints(scene, tracks, init, cfg.fit)
        found = model_from(scene, fit.labels, fit.root, fit.kinds, fit.axes, fit.pivots, fit.values, fit.depth)
        report["found_kinds"] = fit.kinds
        report["loss_found"] = losses(found, len(masks), cfg.fit)
    return report


def exact_label_score(truth: CaseTruth, tracks: Tracks, masks: np.ndarray, clip: VideoClip, camera: Camera,
                      width: float) -> float:
    """The suite's label score of the exact truth in the method's representation (frame-0 points and the
    surfaces later frames reveal): the labels' ceiling (:mod:`sync4d_tools.articulated.ceiling`)."""
    from sync4d_tools.evaluate.recon_suite import part_mapping

    exact = exact_splats(tracks, masks, truth, clip, camera, width)
    rendered = rendered_labels(exact, truth.part_labels)
    return round(part_mapping(rendered, truth.part_labels, exact.reference.num_bones, len(truth.kinds) + 1)[2], 4)


def refined_scores(model: jt.Articulation, truth: CaseTruth, camera: Camera) -> list[dict[str, float | None]]:
    """Per gt joint, the suite's joint scores (axis [deg], pivot [% size], motion) of a model whose part b is
    gt joint b - 1 (the truth refined: where the objective pulls the exact joints)."""
    from sync4d_tools.articulated.score import joint_row

    fit = jt.joint_fit_of(model, 0.0, [])
    motions = fit.transforms()
    means = model.scene.centre.numpy() + fit.depth[:, None] * model.scene.rays.numpy()
    out = []
    for j in range(len(truth.kinds)):
        row = joint_row(motions[:, j + 1], fit.kinds[j + 1], j, truth, camera, means[fit.labels == j + 1])
        out.append({k: (None if row[k] is None else round(float(row[k]), 2)) for k in ("axis_deg", "pivot_pct", "motion")})
    return out


def _value_err(model: jt.Articulation, gt: dict[str, np.ndarray], scene: jt.Scene) -> list[float]:
    """Per gt joint: mean |fitted - gt| joint value after the refinement [deg, or % of travel]."""
    vals = np.concatenate([np.zeros((1, len(model.kinds))), model.values.detach().numpy()], 0)
    out = []
    for j, kind in enumerate(gt["joint_type"]):
        delta = gt["joint_value"][:, j] - gt["joint_value"][0, j]
        if kind == "hinge":
            out.append(round(float(np.degrees(np.abs(vals[:, j + 1] - delta).mean())), 2))
        else:
            out.append(round(float(np.abs(vals[:, j + 1] * scene.width - delta).mean() / np.ptp(delta) * 100), 2))
    return out


def _perms(n: int) -> list[tuple[int, ...]]:
    from itertools import permutations

    return list(permutations(range(n)))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("clips", nargs="+")
    parser.add_argument("--fit", action="store_true", help="also run the fit and score its solution")
    parser.add_argument("--labels", action="store_true", help="also the labels' ceiling (the exact truth rendered)")
    args = parser.parse_args(argv)
    for c in args.clips:
        print(json.dumps(diagnose(Path(c), args.fit, labels_ceiling=args.labels)), flush=True)


if __name__ == "__main__":
    main()
