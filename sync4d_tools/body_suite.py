"""The ``recon_joints`` suite: render every clip/view with truth, fit it with one configuration, tabulate.

    python -m sync4d_tools.body_suite --out outputs/body_suite [--only cmu,deepmimic,dog]

Humans are scored twice: with the renders' camera (``--camera``) and with the camera unknown (the fit's
assumed field of view); quadrupeds with the camera known (their fit needs a static camera): the dog trot (the template's own
capsules) and the Lab4D shiba-haru-1002 export (a real dog's shape and motion, :mod:`sync4d_tools.shiba_clip`;
the ``export`` view is its own handheld camera, written as a static camera and a moving dog). Prints a
Markdown table and writes ``suite.json``; every clip is reported, failures included.

``--split`` (quadruped clips already in ``--out``) splits each clip's error instead of fitting from scratch:
``A1`` the template's joints fitted to the truth joints directly (forward kinematics, per-frame pose, lengths
and scale free, no priors: the floor of the joint definitions), ``A2`` the same under the fit's priors (limb
lengths, joint limits: the floor of the template's proportions), ``B`` the silhouette clip fit started at A2
(thickness first, then the clip schedule: where the objective's minimum lies). The defaults' own row (the
search from scratch) minus B is the search's share, B minus A2 the objective's and body shape's.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
from pathlib import Path

import numpy as np

from sync4d_tools.body_clips import write_clip
from sync4d_tools.evaluate.recon_joints import main as recon_joints
from sync4d_tools.shiba_clip import write_clip as write_shiba

CLIPS = (
    ("cmu", "front", 30, 12),
    ("cmu", "side", 30, 12),
    ("cmu", "oblique", 30, 12),
    ("deepmimic", "front", 39, 1),
    ("deepmimic", "oblique", 39, 1),
    ("deepmimic", "side", 39, 1),
    ("dog", "side", 17, 2),
    ("dog", "oblique", 17, 2),
    ("dog", "front", 17, 2),
    ("shiba", "side", 21, 1),
    ("shiba", "oblique", 21, 1),
    ("shiba", "front", 21, 1),
    ("shiba", "export", 21, 1),
)
QUADRUPEDS = ("dog", "shiba")


def run_clip(out: Path, clip: str, view: str, frames: int, stride: int) -> list[dict]:
    """Render (if absent) and score one clip; one row per camera setting."""
    folder = out / f"{clip}_{view}"
    human = clip not in QUADRUPEDS
    size = (320, 480) if human else (480, 320)
    if not (folder / "gt.npz").is_file() and clip == "shiba":
        write_shiba(folder, view)
    elif not (folder / "gt.npz").is_file():
        write_clip(folder, clip, view, frames=frames, stride=stride, width=size[0], height=size[1], fov_deg=50.0)
    rows = []
    for camera in [True, False] if human else [True]:
        args = [
            "--video",
            str(folder / "rgb.mp4"),
            "--masks",
            str(folder / "masks"),
            "--gt",
            str(folder / "gt.npz"),
            "--subject",
            "human" if human else "quadruped",
        ]
        if camera:
            args += ["--camera", str(folder / "camera.npz")]
        with contextlib.redirect_stdout(io.StringIO()):
            result = recon_joints(args)
        rows.append({"clip": clip, "view": view, "camera": "known" if camera else "assumed fov", **result})
    return rows


def _truth_start(prob, truth_cam: np.ndarray, names: list[str], up_cam: np.ndarray) -> dict:
    """Fit parameters whose root follows the truth (pelvis position, heading from pelvis to neck, up)."""
    import math

    import torch
    from scipy.spatial.transform import Rotation

    from sync4d.recon.pose import quadruped_fit as qf

    g = {nm: truth_cam[:, i] for i, nm in enumerate(names)}
    rots = []
    for fwd in g["neck"] - g["pelvis"]:
        up = up_cam - fwd * (up_cam @ fwd) / (fwd @ fwd)
        fwd, up = fwd / np.linalg.norm(fwd), up / np.linalg.norm(up)
        rots.append(Rotation.from_matrix(np.stack([-fwd, up, np.cross(-fwd, up)], 1)).as_rotvec())
    length = float(np.linalg.norm(g["head"] - g["tail_base"], axis=-1).mean())
    n, nj = len(truth_cam), len(qf.DOG_PARENTS)

    def leaf(x):
        return torch.tensor(np.asarray(x), dtype=qf.DTYPE).requires_grad_(True)

    return {
        "root_rot": leaf(np.array(rots)),
        "root_pos": leaf(g["pelvis"]),
        "local": leaf(np.zeros((n, nj, 3))),
        "log_len": leaf(np.zeros(nj)),
        "log_scale": leaf(math.log(length)),
        "log_thick": leaf(0.0),
    }


def _fit_to_truth(prob, params: dict, truth_cam: np.ndarray, ids: list[int], cfg, priors: bool, steps: int = 1500):
    """Adam on the template's joints ``ids`` against the truth (camera frame), with or without the fit's priors."""
    import torch

    from sync4d.recon.pose import quadruped_fit as qf

    target = torch.tensor(truth_cam, dtype=qf.DTYPE)
    opt = torch.optim.Adam([v for k, v in params.items() if k != "log_thick"], lr=0.02)
    for _ in range(steps):
        opt.zero_grad()
        joints = qf._joints(prob, params)
        loss = 100 * ((joints[:, ids] - target) / params["log_scale"].exp()).pow(2).sum(-1).mean()
        if priors:
            lengths, limit = qf.shape_priors(prob, params, cfg)
            loss = loss + cfg.length_weight * lengths + cfg.limit_weight * limit
        loss.backward()
        opt.step()


def split_clip(folder: Path) -> dict:
    """The A1 / A2 / B split of one quadruped clip (see the module docstring); mpjpe in % of the height."""
    from sync4d.recon.pose import quadruped_fit as qf
    from sync4d.sources.references import VideoSource
    from sync4d_tools.evaluate.recon_joints import joint_errors, quadruped_map

    src = VideoSource(
        VideoSource.Config(video=str(folder / "rgb.mp4"), masks=str(folder / "masks"), camera=str(folder / "camera.npz"))
    ).load()
    gt = np.load(folder / "gt.npz")
    names, truth = [str(n) for n in gt["names"]], np.asarray(gt["joints"], dtype=np.float64)
    w2c = src.camera.world_to_cam
    truth_cam = truth @ w2c[:3, :3].T + w2c[:3, 3]
    ids = [qf.DOG_NAMES.index(quadruped_map()[n]) for n in names]
    height = float((truth[..., 1].max(1) - truth[..., 1].min(1)).max())
    cfg = qf.QuadrupedFitConfig()
    prob = qf._Problem(src.video.masks, src.camera, cfg, src.video.frames)
    prob.rate = src.fps / qf.SMOOTH_FPS
    frames, up_cam = np.arange(len(truth)), w2c[:3, :3] @ np.array([0.0, 1.0, 0.0])
    row = {"clip": folder.name}
    for key, priors in (("A1", False), ("A2", True)):
        params = _truth_start(prob, truth_cam, names, up_cam)
        _fit_to_truth(prob, params, truth_cam, ids, cfg, priors)
        _, joints, _ = qf._run(prob, frames, params, cfg, 0)
        row[key] = round(100 * float(joint_errors(joints[:, ids], truth).mean()) / height, 2)
    qf._run(prob, frames, params, cfg, 60, free=("log_thick",))
    row["A2_loss"] = round(qf._run(prob, frames, params, cfg, 0)[0], 4)
    loss, joints, iou = qf._run(prob, frames, params, cfg, cfg.iterations + cfg.swap_iterations)
    row["B"] = round(100 * float(joint_errors(joints[:, ids], truth).mean()) / height, 2)
    row["B_loss"], row["B_iou"] = round(loss, 4), round(float(iou.mean()), 3)
    return row


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="outputs/body_suite")
    parser.add_argument("--only", default="", help="comma-separated clip names (cmu, deepmimic, dog, shiba)")
    parser.add_argument("--split", action="store_true", help="split the quadruped clips' error (module docstring)")
    args = parser.parse_args(argv)
    out = Path(args.out)
    keep = set(args.only.split(",")) if args.only else None
    if args.split:
        rows = [
            split_clip(out / f"{c}_{v}") for c, v, _, _ in CLIPS if c in QUADRUPEDS and (keep is None or c in keep)
        ]
        print(json.dumps(rows, indent=1))
        (out / "split.json").write_text(json.dumps(rows, indent=1))
        return {"rows": rows}
    rows = []
    for clip, view, frames, stride in CLIPS:
        if keep is None or clip in keep:
            rows += run_clip(out, clip, view, frames, stride)
    print("| clip | view | camera | mpjpe % height | pck10 | mask IoU | frames | CPU s |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['clip']} | {r['view']} | {r['camera']} | {r['mpjpe_pct_height']:.2f} | {r['pck10']:.3f} | "
            f"{r['mask_iou']:.3f} | {r['frames']} | {r['cpu_seconds']:.0f} |"
        )
    out.mkdir(parents=True, exist_ok=True)
    (out / "suite.json").write_text(json.dumps(rows, indent=1))
    return {"rows": rows}


if __name__ == "__main__":
    main()
