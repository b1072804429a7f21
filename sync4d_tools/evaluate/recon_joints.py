"""``recon_joints``: joint error of ``recon=body_video`` on a clip with exact joint truth.

    python -m sync4d.evaluate recon_joints --video V [--masks DIR] [--camera NPZ] --subject human --gt GT.npz
        [--max-frames N] [--set KEY=VALUE ...]     # recon=body_video overrides, e.g. quadruped.starts=2

``GT.npz`` holds ``joints`` (T, J, 3) [m] and ``names`` (J,) from this vocabulary (names not present are
skipped): human ``head, l_shoulder, r_shoulder, l_elbow, r_elbow, l_wrist, r_wrist, l_hip, r_hip, l_knee,
r_knee, l_ankle, r_ankle``; quadruped ``head, neck, pelvis, tail_base`` and ``<leg>_upper``, ``<leg>_middle``,
``<leg>_paw`` for each leg ``fl, fr, hl, hr``. Clips with truth: ``python -m sync4d_tools.body_clips``.

Prints one JSON object on the last line:
    * ``mpjpe_pct_height``: mean per-joint position error after ONE similarity (rotation, translation,
      scale) aligning the fitted joints of the whole clip to the truth, in % of the subject's height
      (the largest extent of the truth joints along the world's y axis over the clip);
    * ``pck10``: fraction of (frame, joint) pairs within 10% of that height after the same alignment;
    * ``mask_iou``: mean IoU of the fit's masks against ``--masks`` (humans: the learned segmentation;
      quadrupeds: the fitted body's silhouette); null without ``--masks``;
    * ``frames``, ``joints``, ``seconds`` (wall), ``cpu_seconds`` (this process), ``height_m``.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from sync4d.errors import InputError
from sync4d.match.align import umeyama
from sync4d.recon.body_video import BodyVideoFit, BodyVideoReconstructor
from sync4d.registry import make_config
from sync4d.sources.references import VideoSource
from sync4d_tools import video_of
from sync4d_tools.evaluate import dotlist

#: the issue's human vocabulary (gt.npz ``names``); the fitted skeleton uses the same names
HUMAN_VOCABULARY = (
    "head",
    "l_shoulder",
    "r_shoulder",
    "l_elbow",
    "r_elbow",
    "l_wrist",
    "r_wrist",
    "l_hip",
    "r_hip",
    "l_knee",
    "r_knee",
    "l_ankle",
    "r_ankle",
)
# recon_joints vocabulary -> joint name in the fitted skeleton
HUMAN_MAP = {n: n for n in HUMAN_VOCABULARY}


def quadruped_map(template: str) -> dict[str, str]:
    """Vocabulary -> joint names of the quadruped fit's body template ``template`` (each registered template
    declares its own vocabulary, :attr:`sync4d.recon.pose.templates.BodyTemplate.vocabulary`)."""
    from sync4d.recon.pose.templates import body_template

    return dict(body_template(template).vocabulary)


def joint_errors(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(T, J) distances [m] after one similarity aligning all of ``pred`` (T, J, 3) to ``truth``."""
    sim = umeyama(pred.reshape(-1, 3), truth.reshape(-1, 3), with_scale=True)
    aligned = sim.apply(pred.reshape(-1, 3)).reshape(pred.shape)
    return np.linalg.norm(aligned - truth, axis=-1)


def mask_iou(pred: np.ndarray, truth: np.ndarray) -> float:
    """Mean over frames of |pred & truth| / |pred | truth| for (T, H, W) bool masks."""
    inter = (pred & truth).sum((1, 2))
    union = np.maximum((pred | truth).sum((1, 2)), 1)
    return float((inter / union).mean())


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(
        prog="python -m sync4d.evaluate recon_joints",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--video", required=True)
    parser.add_argument("--masks", default="", help="folder of truth masks (also the quadruped fit's input)")
    parser.add_argument("--camera", default="", help="camera .npz (K, cam_pos, cam_forward, cam_up); default: unknown")
    parser.add_argument("--subject", choices=["human", "quadruped"], default="human")
    parser.add_argument("--gt", required=True, help="GT.npz with joints (T, J, 3) [m] and names (J,)")
    parser.add_argument("--max-frames", type=int, default=0)
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="recon=body_video overrides (dotted keys, YAML values), e.g. quadruped.starts=2")
    args = parser.parse_args(argv)
    overrides = dotlist(args.set, option="--set")
    if "subject" in overrides:
        raise InputError("--set subject=...: the subject is chosen by --subject human|quadruped")
    if not Path(args.gt).is_file():
        raise InputError(f"--gt {args.gt}: not found; a clip with truth: python -m sync4d_tools.body_clips")

    start, cpu = time.perf_counter(), time.process_time()
    gt = np.load(args.gt)
    truth_all, names = np.asarray(gt["joints"], dtype=np.float64), [str(n) for n in gt["names"]]
    source = VideoSource(
        VideoSource.Config(video=args.video, masks=args.masks, camera=args.camera, max_frames=args.max_frames)
    ).load()
    clip = video_of(source)
    masks_in = clip.masks if args.masks else None
    if args.subject == "human":
        # the learned model makes its own masks; the truth masks are only for the score
        source = replace(source, video=replace(clip, masks=np.zeros_like(clip.masks), extrinsics=None))
    _, config = make_config("recon", {"type": "body_video", "figures": False, **overrides, "subject": args.subject})
    recon = BodyVideoReconstructor(config)
    fit = recon.fit(source)
    mapping = HUMAN_MAP if args.subject == "human" else quadruped_map(recon.config.quadruped.template)
    pairs = [(i, fit.names.index(mapping[n])) for i, n in enumerate(names) if n in mapping]
    if not pairs:
        raise InputError(f"{args.gt}: none of its joint names {names} is in the {args.subject} vocabulary")
    frames = min(len(truth_all), len(fit.joints))
    truth = truth_all[:frames, [i for i, _ in pairs]]
    pred = fit.joints[:frames, [j for _, j in pairs]]
    height = float((truth[..., 1].max(1) - truth[..., 1].min(1)).max())
    err = joint_errors(pred, truth)
    iou = None
    if masks_in is not None:
        pm = fit.masks if args.subject == "human" else fit_silhouettes(fit)
        iou = round(mask_iou(pm[:frames], masks_in[:frames]), 4)
    out = {
        "mpjpe_pct_height": round(100.0 * float(err.mean()) / height, 3),
        "pck10": round(float((err < 0.1 * height).mean()), 4),
        "mask_iou": iou,
        "frames": int(frames),
        "joints": len(pairs),
        "height_m": round(height, 4),
        "seconds": round(time.perf_counter() - start, 2),
        "cpu_seconds": round(time.process_time() - cpu, 2),
    }
    print(json.dumps(out))
    return out


def fit_silhouettes(fit: BodyVideoFit) -> np.ndarray:
    """(T, H, W) bool silhouettes of the fitted quadruped body (its mesh seen by each frame's camera)."""
    if fit.silhouettes is None:
        raise ValueError("fit_silhouettes: a human fit has no body silhouettes (its masks are fit.masks)")
    return fit.silhouettes


if __name__ == "__main__":
    main()
