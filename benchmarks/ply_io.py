"""Benchmark: 3DGS .ply read and write through plyfile (sync4d.io.ply) against raw NumPy I/O.

The raw NumPy reader (``np.fromfile`` of the structured vertex table after the header) is what the
former hand-written reader did, and the fastest a binary reader can be; the question is whether plyfile's
parsing costs enough to need it back. Three read figures: the table through plyfile (memory map + one
copy), the raw table, and the whole ``read_gaussians_ply`` (table, NaN/range checks, 3DGS arrays). Case: 1 M Gaussians, SH degree 3 (62 float properties, 236 MB),
median of 3 runs each.

Usage:
    python benchmarks/ply_io.py [--gaussians 1000000] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    import numpy as np

    from sync4d.types import TargetGaussians

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def splat(n: int) -> TargetGaussians:
    import numpy as np

    from sync4d.types import TargetGaussians

    rng = np.random.default_rng(0)
    q = rng.normal(size=(n, 4))
    return TargetGaussians(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        quats=(q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
        log_scales=rng.normal(-4, 1, size=(n, 3)).astype(np.float32),
        opacity_logits=rng.normal(size=n).astype(np.float32), sh=rng.normal(size=(n, 16, 3)).astype(np.float32),
    )  # fmt: skip


def raw_read(path: Path) -> np.ndarray:
    """Header by hand, then one np.fromfile of the vertex table (all float32 little-endian)."""
    import numpy as np

    with path.open("rb") as f:
        names, count = [], 0
        while (line := f.readline().decode("ascii").strip()) != "end_header":
            words = line.split()
            if words[:2] == ["element", "vertex"]:
                count = int(words[2])
            elif words and words[0] == "property":
                names.append(words[2])
        return np.fromfile(f, dtype=[(n, "<f4") for n in names], count=count)


def timed(fn: Callable[[], object], repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        fn()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    import numpy as np

    from sync4d.io.ply import gaussians_table, read_gaussians_ply, write_gaussians_ply

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "ply_io.json")
    args = parser.parse_args(argv)
    g = splat(args.gaussians)
    with tempfile.TemporaryDirectory(dir=ROOT / "outputs") as tmp:
        path = Path(tmp) / "g.ply"
        write_s = timed(lambda: write_gaussians_ply(path, g))
        raw_path = Path(tmp) / "raw.ply"
        table = gaussians_table(g)
        assert table.dtype.names is not None  # a structured table: one field per property
        header = ("ply\nformat binary_little_endian 1.0\n" f"element vertex {g.num}\n"
                  + "".join(f"property float {n}\n" for n in table.dtype.names) + "end_header\n").encode()

        def raw_write() -> None:
            with raw_path.open("wb") as f:
                f.write(header)
                gaussians_table(g).tofile(f)

        raw_write_s = timed(raw_write)
        read_s = timed(lambda: read_gaussians_ply(path))
        raw_read_s = timed(lambda: raw_read(path))
        import plyfile

        parse_s = timed(lambda: np.array(plyfile.PlyData.read(str(path))["vertex"].data))
        assert np.array_equal(raw_read(path)["x"], read_gaussians_ply(path).means[:, 0])
        size_mb = path.stat().st_size / 2**20
    result = {"gaussians": args.gaussians, "file_mb": size_mb, "plyfile_write_s": write_s, "raw_write_s": raw_write_s,
              "plyfile_read_s": read_s, "plyfile_table_s": parse_s, "raw_read_s": raw_read_s}
    print(f"{args.gaussians:,} Gaussians, SH 3, {size_mb:.0f} MB  (median of 3)")
    print(f"{'':<8}{'plyfile (sync4d.io.ply)':>26}{'raw numpy':>12}")
    print(f"{'write':<8}{write_s:>24.2f} s{raw_write_s:>10.2f} s")
    print(f"{'read':<8}{parse_s:>24.2f} s{raw_read_s:>10.2f} s  (the vertex table alone)")
    print(f"{'read+':<8}{read_s:>24.2f} s{'':>12}  (read_gaussians_ply: table, checks, 3DGS arrays)")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
