"""``python -m sync4d_tools.compare_frames RUN OUT.jpg [--frames 0 8 16]``: a picture of a run's ``compare.mp4``.

Stacks the chosen frames of a finished run's side-by-side video (input video | reconstructed reference | target)
into one image, for docs and the README (the viewer shows the same run interactively).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def stacked_frames(video: Path, frames: list[int]) -> np.ndarray:
    """(sum H, W, 3) uint8: the given frames of ``video`` one under the other (indices past the end are clipped)."""
    import imageio.v3 as iio

    clip = np.stack(list(iio.imiter(video)))
    picked = [clip[min(max(i, 0), len(clip) - 1)] for i in frames]
    return np.concatenate(picked, axis=0)


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a finished run's folder (holds compare.mp4)")
    parser.add_argument("out", type=Path, help="the picture to write (.jpg or .png)")
    parser.add_argument("--frames", type=int, nargs="+", default=[0, 8, 16])
    args = parser.parse_args(argv)
    from PIL import Image

    video = args.run / "compare.mp4"
    if not video.is_file():
        print(f"error: compare_frames: {video} not found; pass a finished run's folder", file=sys.stderr)
        raise SystemExit(2)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(stacked_frames(video, args.frames)).save(args.out, quality=88)
    print(args.out)
    return args.out


if __name__ == "__main__":
    main()
