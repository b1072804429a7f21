"""Benchmark: a real splat enlarged to 50 k, 500 k and 2 M Gaussians (SH degree 3) run end to end, 24 frames.

Target: ``sunflowers_lod3_tile_0.ply`` (1,971 trained Gaussians, SH degree 3; mkkellogg/GaussianSplats3D,
MIT) enlarged by drawing each copy's centre from its source Gaussian's own distribution N(mu, Sigma)
(scales shrunk by copies^(1/3), so the copies fill the same volume) plus 0.05 % floaters up to 10x the
tile's size away. Reference: the laptop with its exact bones (``reference=laptop recon=ground_truth``),
everything else the project's default configuration.

What runs is ``train.py``'s own code: each size composes ``train.py``'s config from its command line
(``train_overrides``) and calls ``pipeline.run_guarded``, as ``train.py`` does, in a process of its own
under ``/usr/bin/time -v`` (peak resident memory, CPU and wall of the whole run). Inside it the
pipeline's functions are wrapped with timers, nothing else changed: ``load`` (.ply, floater removal,
frame 0), ``reference``, ``figures``, ``match``, ``motion``, ``cost`` (the estimate before simulating),
``simulate`` (the transfer on the control points), ``carry+write`` (``FrameWriter.on_frame``: every
Gaussian of the frame carried, SH rotated, written to ``frames/*.ply``, state and checkpoint),
``metrics`` (``FrameWriter.finish``) and ``render+export``; each with its exclusive wall and CPU seconds
and the peak resident memory sampled (every 20 ms) while it ran. The enlarged splat is made beforehand
in another process. Frames are deleted after the run (2 M Gaussians x 24 frames is 11 GB).

Usage:
    python benchmarks/scale.py [--sizes 50000 500000 2000000] [--frames 24] [--json PATH]
    python benchmarks/scale.py --show benchmarks/results/scale.json
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sync4d.types import TargetGaussians

ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))
sys.path.insert(0, str(ROOT))

SOURCE = (
    Path(os.environ.get("SYNC4D_SHARED_DATA", ROOT.parent / "shared" / "data"))
    / "targets/gaussians/sunflowers_lod3_tile_0.ply"
)
SIZES = [50_000, 500_000, 2_000_000]
WORK = ROOT / "outputs" / "bench_scale"
FLOATER_FRACTION = 5e-4


def enlarged_splat(n: int, seed: int = 0) -> TargetGaussians:
    """The source splat enlarged to ``n`` Gaussians (see the module docstring), floaters included."""
    import numpy as np

    from sync4d.io.ply import read_gaussians_ply

    src = read_gaussians_ply(SOURCE)
    rng = np.random.default_rng(seed)
    floaters = int(round(FLOATER_FRACTION * n))
    copies = -(-(n - floaters) // src.num)
    pick = np.tile(np.arange(src.num), copies)[: n - floaters]
    chol = np.linalg.cholesky(src.covariances() + 1e-12 * np.eye(3))
    means = src.means[pick] + np.einsum("nij,nj->ni", chol[pick], rng.normal(size=(len(pick), 3)))
    lo, hi = src.means.min(0), src.means.max(0)
    size = float((hi - lo).max())
    far = (
        lo
        + (hi - lo) * rng.random((floaters, 3))
        + rng.choice([-1, 1], (floaters, 3)) * rng.uniform(1, 10, (floaters, 1)) * size
    )
    pick = np.concatenate([pick, rng.integers(0, src.num, floaters)])
    return src.replace(
        means=np.concatenate([means, far]).astype(np.float32), quats=src.quats[pick],
        log_scales=(src.log_scales[pick] - np.log(copies) / 3.0).astype(np.float32),
        opacity_logits=src.opacity_logits[pick], sh=src.sh[pick],
        normals=None if src.normals is None else src.normals[pick], name=f"sunflowers_x{copies}",
    )  # fmt: skip


def make_target(n: int) -> Path:
    """The enlarged splat as ``<WORK>/<n>/target.ply`` (made once; outside the measured process)."""
    from sync4d.io.ply import write_gaussians_ply

    path = WORK / str(n) / "target.ply"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        write_gaussians_ply(path, enlarged_splat(n))
    return path


def train_overrides(ply: Path, frames: int) -> list[str]:
    """The ``train.py`` command line of one size: the laptop's exact bones driving the enlarged splat."""
    return [
        "reference=laptop",
        "recon=ground_truth",
        "target=ply",
        f"target.path={ply}",
        f"frames={frames}",
        "cache=false",
    ]


class Stages:
    """Exclusive wall and CPU seconds and peak resident MB of named stages (nested calls are their own).

    ``wrap(owner, attribute, name)`` replaces a function or method of the pipeline's modules by a timed
    one; the memory sampler charges each sample to the innermost running stage (``other`` outside).
    """

    def __init__(self) -> None:
        self.stack: list[list] = []  # [name, wall start, cpu start, children's wall, children's cpu]
        self.rows: dict[str, dict] = {}
        self.peak: dict[str, float] = {}
        self._stop = False
        threading.Thread(target=self._sample, daemon=True).start()

    @staticmethod
    def rss_mb() -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

    def _sample(self) -> None:
        while not self._stop:
            name = self.stack[-1][0] if self.stack else "other"
            self.peak[name] = max(self.peak.get(name, 0.0), self.rss_mb())
            time.sleep(0.02)

    def wrap(self, owner: object, attribute: str, name: str) -> None:
        inner = getattr(owner, attribute)

        def timed(*args: Any, **kwargs: Any) -> Any:
            self.stack.append([name, time.perf_counter(), time.process_time(), 0.0, 0.0])
            try:
                return inner(*args, **kwargs)
            finally:
                _, wall0, cpu0, child_wall, child_cpu = self.stack.pop()
                wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
                row = self.rows.setdefault(name, {"stage": name, "seconds": 0.0, "cpu_seconds": 0.0, "calls": 0})
                row["seconds"] += wall - child_wall
                row["cpu_seconds"] += cpu - child_cpu
                row["calls"] += 1
                if self.stack:
                    self.stack[-1][3] += wall
                    self.stack[-1][4] += cpu

        setattr(owner, attribute, timed)

    def wrap_thread(self, owner: object, attribute: str, name: str) -> None:
        """Time a function run in another thread (its wall and that thread's CPU seconds); its CPU is
        also inside the process CPU of whichever stage ran meanwhile (``time.process_time`` counts every
        thread), so this row is what of those stages was this work."""
        inner = getattr(owner, attribute)

        def timed(*args: Any, **kwargs: Any) -> Any:
            wall0, cpu0 = time.perf_counter(), time.thread_time()
            try:
                return inner(*args, **kwargs)
            finally:
                row = self.rows.setdefault(
                    name, {"stage": name, "seconds": 0.0, "cpu_seconds": 0.0, "calls": 0, "thread": True}
                )
                row["seconds"] += time.perf_counter() - wall0
                row["cpu_seconds"] += time.thread_time() - cpu0
                row["calls"] += 1

        setattr(owner, attribute, timed)


def child(n: int, frames: int) -> dict:
    """One size through ``train.py``'s own code (``pipeline.run_guarded``), its stages timed in place."""
    from hydra import compose, initialize_config_dir
    from omegaconf import open_dict

    from sync4d.config_schemas import register_schemas
    from sync4d.run import exports, figures, pipeline, writer

    ply = WORK / str(n) / "target.ply"
    run_dir = WORK / str(n) / "run"
    shutil.rmtree(run_dir, ignore_errors=True)
    register_schemas()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=train_overrides(ply, frames))
    with open_dict(cfg):
        cfg.run_dir = str(run_dir)
    run_dir.mkdir(parents=True)
    logging.basicConfig(
        filename=run_dir / "train.log",
        level=logging.INFO,  # as train.py's Hydra logging
        format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s",
    )
    stages = Stages()
    for owner, attribute, name in (
        (pipeline, "stage_target", "load"),
        (pipeline, "stage_reference", "reference"),
        (pipeline, "write_gaussians_ply", "load"),
        (figures, "save_reference_parts", "figures"),
        (figures, "save_match_figure", "figures"),
        (pipeline, "stage_match", "match"),
        (pipeline, "driving_motion", "motion"),
        (pipeline, "check_run_cost", "cost"),
        (pipeline, "run_transfer", "simulate"),
        (writer.FrameWriter, "on_frame", "carry+write"),
        (writer.FrameWriter, "finish", "metrics"),
        (exports, "render_run_outputs", "render+export"),
    ):
        stages.wrap(owner, attribute, name)
    stages.wrap_thread(writer.FrameWriter, "write_frame", "(.ply thread)")
    started, started_cpu = time.perf_counter(), time.process_time()
    metrics = pipeline.run_guarded(cfg)
    wall, cpu = time.perf_counter() - started, time.process_time() - started_cpu
    stages._stop = True
    rows = list(stages.rows.values())
    main = [r for r in rows if not r.get("thread")]
    rows.append(
        {
            "stage": "other",
            "seconds": wall - sum(r["seconds"] for r in main),
            "cpu_seconds": cpu - sum(r["cpu_seconds"] for r in main),
            "calls": 1,
        }
    )
    rows.append({"stage": "start-up", "seconds": None, "cpu_seconds": started_cpu, "calls": 1})
    for row in rows:
        row["peak_mb"] = stages.peak.get(row["stage"], 0.0)
    frames_mb = sum(p.stat().st_size for p in (run_dir / "frames").glob("*.ply")) / 2**20
    shutil.rmtree(run_dir / "frames", ignore_errors=True)  # 2 M Gaussians x 24 frames is 11 GB
    floaters = (metrics or {}).get("floaters") or {}
    return {
        "gaussians": n,
        "frames": frames,
        "rows": rows,
        "wall_seconds": wall,
        "status": (metrics or {}).get("status"),
        "overrides": train_overrides(ply, frames),
        "frames_mb": frames_mb,
        "floaters": floaters,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "metrics": {k: v for k, v in (metrics or {}).items() if isinstance(v, (int, float))},
    }


def time_v(stderr: str) -> dict:
    """Peak RSS [MB], user + system CPU [s] and wall [s] from ``/usr/bin/time -v``'s report."""
    values = {}
    for line in stderr.splitlines():
        key, _, value = line.strip().rpartition(": ")
        values[key] = value
    h, m, sec = (["0"] + values["Elapsed (wall clock) time (h:mm:ss or m:ss)"].split(":"))[-3:]
    return {
        "max_rss_mb": int(values["Maximum resident set size (kbytes)"]) / 1024.0,
        "cpu_seconds": float(values["User time (seconds)"]) + float(values["System time (seconds)"]),
        "wall_seconds": 3600 * float(h) + 60 * float(m) + float(sec),
    }


def table(results: list[dict]) -> str:
    """Per stage and size: wall seconds, CPU seconds, peak resident MB; then the whole process."""
    stages = list(dict.fromkeys(r["stage"] for result in results for r in result["rows"]))
    head = f"{'stage':<14}" + "".join(f"{r['gaussians']:>26,}" for r in results)
    lines = [head, f"{'':<14}" + "".join(f"{'wall s':>9}{'CPU s':>8}{'peak MB':>9}" for _ in results)]
    for s in stages:
        cells = ""
        for r in results:
            row = next((x for x in r["rows"] if x["stage"] == s), None)
            if row is None:
                cells += f"{'':>26}"
            else:
                wall = "" if row["seconds"] is None else f"{row['seconds']:.1f}"
                cells += f"{wall:>9}{row['cpu_seconds']:>8.1f}{row.get('peak_mb', 0.0):>9.0f}"
        lines.append(f"{s:<14}{cells}")
    total = "".join(
        f"{r['process']['wall_seconds']:>9.1f}{r['process']['cpu_seconds']:>8.1f}" f"{r['process']['max_rss_mb']:>9.0f}"
        for r in results
    )
    lines.append(f"{'process':<14}{total}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=SIZES)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "scale.json")
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--make", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--show", type=Path, default=None, help="print the table of a results JSON and exit")
    args = parser.parse_args(argv)
    if args.show is not None:
        print(table(json.loads(args.show.read_text())["results"]))
        return 0
    if args.make is not None:
        make_target(args.make)
        return 0
    if args.child is not None:
        print(json.dumps(child(args.child, args.frames)))
        return 0
    if not SOURCE.is_file():
        print(f"scale: the source splat {SOURCE} is not on this machine (set SYNC4D_SHARED_DATA)", file=sys.stderr)
        return 2
    results = []
    for n in args.sizes:
        subprocess.run([sys.executable, __file__, "--make", str(n)], check=True)
        command = ["/usr/bin/time", "-v", sys.executable, __file__, "--child", str(n), "--frames", str(args.frames)]
        proc = subprocess.run(command, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            print(proc.stderr[-4000:], file=sys.stderr)
            return 1
        result = json.loads(proc.stdout.strip().splitlines()[-1])
        result["process"] = time_v(proc.stderr)
        results.append(result)
        p = result["process"]
        print(
            f"{n:,} Gaussians: train.py {p['wall_seconds']:.0f} s wall, {p['cpu_seconds']:.0f} CPU s, "
            f"peak {p['max_rss_mb']:.0f} MB (/usr/bin/time -v)",
            flush=True,
        )
        args.json.parent.mkdir(parents=True, exist_ok=True)  # after every size: a long sweep keeps what it has
        args.json.write_text(json.dumps({"results": results, "source": str(SOURCE.name)}, indent=1) + "\n")
    print(table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
