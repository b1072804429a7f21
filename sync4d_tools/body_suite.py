"""The ``recon_joints`` suite: render every clip/view with truth, fit it with one configuration, tabulate.

    python -m sync4d_tools.body_suite --out outputs/body_suite [--only cmu,deepmimic,dog]

Humans are scored twice: with the renders' camera (``--camera``) and with the camera unknown (the fit's
assumed field of view); quadrupeds with the camera known (their fit needs a static camera): the dog trot (the template's own
capsules) and the Lab4D shiba-haru-1002 export (a real dog's shape and motion, :mod:`sync4d_tools.shiba_clip`;
the ``export`` view is its own handheld camera, written as a static camera and a moving dog). Prints a
Markdown table and writes ``suite.json``; every clip is reported, failures included.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
from pathlib import Path

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


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="outputs/body_suite")
    parser.add_argument("--only", default="", help="comma-separated clip names (cmu, deepmimic, dog, shiba)")
    args = parser.parse_args(argv)
    out = Path(args.out)
    keep = set(args.only.split(",")) if args.only else None
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
