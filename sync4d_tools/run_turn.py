"""``python -m sync4d_tools.run_turn RUN [--up 0 1 0]``: how far a run's target turns and tips over the clip.

Reads a finished run's ``sequence.npz`` (the per-frame global transform G^t the target was given) and prints,
per frame, the rotation of G^t from the first frame's and the tilt of the body's up (``--up``, in the
sequence's world) from where it pointed in the first frame [deg]. An animal walking on a level floor keeps its
up within a few degrees; a body that tumbles does not. The world's up is not needed: the tilt is relative.
A target that never turns reads 0 as well, so read the tilt beside the run's pictures, not alone.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def turn_and_tilt(transforms: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T,) rotation of each (4, 4) transform from the first one's, and (T,) tilt of ``up`` carried by it [deg]."""
    rot = transforms[:, :3, :3] @ transforms[0, :3, :3].T
    cos = np.clip((np.trace(rot, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    axis = up / np.linalg.norm(up)
    moved = np.einsum("tij,j->ti", rot, axis)
    tilt = np.clip(moved @ axis / np.linalg.norm(moved, axis=1), -1.0, 1.0)
    return np.degrees(np.arccos(cos)), np.degrees(np.arccos(tilt))


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a finished run's folder (holds sequence.npz)")
    parser.add_argument("--up", type=float, nargs=3, default=[0.0, 1.0, 0.0], help="the body's up in the run's world")
    args = parser.parse_args(argv)
    path = args.run / "sequence.npz"
    if not path.is_file():
        print(f"error: run_turn: {path} not found; pass a finished run's folder", file=sys.stderr)
        raise SystemExit(2)
    transforms = np.load(path)["global_transforms"].astype(np.float64)
    turn, tilt = turn_and_tilt(transforms, np.asarray(args.up, dtype=np.float64))
    result = {"frames": len(turn), "turn_deg": [round(float(x), 1) for x in turn],
              "tilt_deg": [round(float(x), 1) for x in tilt], "tilt_max_deg": round(float(tilt.max()), 1)}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
