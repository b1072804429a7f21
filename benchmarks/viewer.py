"""Benchmark of ``python -m sync4d.view`` and the compact file: start-up and per-frame cost by run size.

For each size, a synthetic run folder (tests/_viewrun.py: a base and a swinging lid, N Gaussians, T
frames) is written with :func:`sync4d.io.seq4d.write_seq4d`; then the viewer is started in-process
(no browser: the server side's cost) and frames are stepped through. Reported: the ``.s4d`` size and
the size the same frames take as 3DGS ``.ply`` files (SH degree 0, 56 bytes a Gaussian plus a header),
their ratio, the time from opening the folder to a served first frame, the median time to show a
frame that is not cached (decode + splat buffer + message) and one that is, and the process's peak
resident memory. This machine's 2 cores are shared: compare ratios within one run.

Usage::

    python benchmarks/viewer.py [--sizes 24x4500 96x4500 24x100000] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import resource
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

PLY_HEADER_BYTES = 360  # header of a degree-0 3DGS .ply as sync4d writes it (measured: 252,360 bytes for 4,500)
PLY_ROW_BYTES = 14 * 4  # x y z f_dc_0..2 opacity scale_0..2 rot_0..3, float32 (no normals)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def measure(frames: int, gaussians: int, folder: Path) -> dict[str, float]:
    from sync4d.view.app import Viewer, ViewerConfig
    from sync4d.view.data import load_run
    from tests._viewrun import make_run

    make_run(folder, frames=frames, n=gaussians)
    s4d = (folder / "sequence.s4d").stat().st_size
    ply = frames * (PLY_HEADER_BYTES + PLY_ROW_BYTES * gaussians)
    started = time.perf_counter()
    viewer = Viewer([load_run(folder)], ViewerConfig(port=free_port()))
    startup = time.perf_counter() - started
    try:
        cold = []
        for t in range(1, min(frames, 12)):
            t0 = time.perf_counter()
            viewer.show(t)
            cold.append(time.perf_counter() - t0)
        warm = []
        for t in range(1, min(frames, 12)):
            t0 = time.perf_counter()
            viewer.show(t)
            warm.append(time.perf_counter() - t0)
    finally:
        viewer.server.stop()
    return {"frames": frames, "gaussians": gaussians, "s4d_mb": s4d / 2**20, "ply_mb": ply / 2**20,
            "ratio": ply / s4d, "startup_s": startup, "frame_cold_ms": 1e3 * statistics.median(cold),
            "frame_cached_ms": 1e3 * statistics.median(warm),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main(argv: list[str] | None = None) -> list[dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["24x4500", "96x4500", "24x100000"], help="TxN")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, size in enumerate(args.sizes):
            t, n = (int(v) for v in size.lower().split("x"))
            rows.append(measure(t, n, Path(tmp) / f"run{k}"))
    print(f"{'T':>4} {'N':>7} {'s4d MB':>7} {'ply MB':>7} {'ratio':>6} {'start s':>8} {'cold ms':>8} "
          f"{'cached ms':>9} {'peak MB':>8}")
    for r in rows:
        print(f"{r['frames']:>4} {r['gaussians']:>7} {r['s4d_mb']:>7.2f} {r['ply_mb']:>7.1f} {r['ratio']:>6.1f} "
              f"{r['startup_s']:>8.2f} {r['frame_cold_ms']:>8.1f} {r['frame_cached_ms']:>9.1f} "
              f"{r['peak_rss_mb']:>8.0f}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=2))
    return rows


if __name__ == "__main__":
    main()
