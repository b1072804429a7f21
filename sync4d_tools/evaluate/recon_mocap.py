"""``recon_mocap``: import a BVH (or joint-position) clip with ``recon=mocap`` and check it.

    python -m sync4d.evaluate recon_mocap --data ../shared/data/motion/cmu_bvh/131_01.bvh

Prints one JSON object on the last line: ``bone_length_max_dev`` (max over segments and frames of the
change of a segment's length, [m]; 0 up to rounding for a rigid skeleton), ``root_travel_m`` (straight
horizontal distance of the root from the first to the last frame), ``root_path_m`` (horizontal path
length), ``joint_error_m`` (how far the bone transforms carry each segment's end from the mocap joint),
``bones``, ``frames``, ``fps``, ``seconds``.

Data: CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu; "The database was created with
funding from NSF EIA-0196217"), via yuki-koyama/bvh11.
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

from sync4d.recon.mocap import MocapReconstructor
from sync4d.sources.references import resolve_path
from sync4d.types import ReferenceInput


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m sync4d.evaluate recon_mocap", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="../shared/data/motion/cmu_bvh/131_01.bvh", help=".bvh, joint-position .txt or DeepMimic clip (JSON .txt)")
    parser.add_argument("--fps", type=float, default=60.0, help="frame rate of joint-position files [1/s]")
    parser.add_argument("--target-fps", type=float, default=0.0, help="subsample to this rate (0 = keep all)")
    parser.add_argument("--bones", default="skeleton")
    args = parser.parse_args(argv)

    start = time.perf_counter()
    path = resolve_path(args.data, what="motion file")
    recon = MocapReconstructor(MocapReconstructor.Config(bones=args.bones, target_fps=args.target_fps))
    ref = recon.reconstruct(ReferenceInput(name=path.stem, fps=args.fps, path=str(path)))
    rep = recon.last_fit_report
    out = {
        "bone_length_max_dev": rep["bone_length_max_dev"],
        "root_travel_m": round(rep["root_travel_m"], 4),
        "root_path_m": round(rep["root_path_m"], 4),
        "joint_error_m": rep["joint_error_m"],
        "bones": ref.num_bones,
        "frames": ref.num_frames,
        "fps": round(ref.fps, 4),
        "body_vertices": int(ref.rest_vertices.shape[0]),
        "seconds": round(time.perf_counter() - start, 2),
    }
    print(json.dumps(out))
    return out
