"""Benchmark: a real splat enlarged to 50 k, 500 k and 2 M Gaussians (SH degree 3) run end to end, 24 frames.

Target: ``sunflowers_lod3_tile_0.ply`` (1,971 trained Gaussians, SH degree 3; mkkellogg/GaussianSplats3D,
MIT) enlarged by drawing each copy's centre from its source Gaussian's own distribution N(mu, Sigma)
(scales shrunk by copies^(1/3), so the copies fill the same volume) plus 0.05 % floaters up to 10x the
tile's size away. Reference: the laptop with its exact bones (``reference=laptop recon=ground_truth``),
everything else the project's default configuration.

Stages (each timed, with the peak resident memory reached inside it, sampled every 20 ms):
``load`` (.ply with plyfile, floater removal), ``match`` (features on the bounded surface sample,
labels for every Gaussian), ``motion``, ``cost`` (the estimate, before simulating), ``control``
(control points), ``simulate`` (the transfer on the control points, 24 frames), ``carry+write``
(every Gaussian of every frame carried by its control point, SH rotated, streamed to ``frames/*.ply``)
and ``preview`` (a bounded render: at most 100 k Gaussians at 192 x 192, every frame). Each size runs
in its own subprocess so its peaks are its own.

The pipeline's own stages are used (``pipeline.stage_target``, ``stage_match``, ``target_surface``,
``transfer.run_mpm_transfer``); what differs from ``train.py`` is the output side: the simulator is handed
the control points as its target and every frame is carried and written as it arrives, instead of the
run writer holding every frame's per-Gaussian x and F (see docs/scale.md). Frames are deleted after
the run (2 M Gaussians x 24 frames is 11 GB).

Usage:
    python benchmarks/scale.py [--sizes 50000 500000 2000000] [--frames 24] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))
sys.path.insert(0, str(ROOT))

SOURCE = Path(os.environ.get("SYNC4D_SHARED_DATA", ROOT.parent / "shared" / "data")) / "targets/gaussians/sunflowers_lod3_tile_0.ply"
SIZES = [50_000, 500_000, 2_000_000]
WORK = ROOT / "outputs" / "bench_scale"
PREVIEW_GAUSSIANS = 100_000
PREVIEW_SIZE = 192
FLOATER_FRACTION = 5e-4


class PeakSampler:
    """Samples this process's resident memory every 20 ms; ``stage()`` returns and resets the peak [MB]."""

    def __init__(self) -> None:
        self.peak = 0.0
        self._stop = False
        threading.Thread(target=self._run, daemon=True).start()

    @staticmethod
    def rss_mb() -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

    def _run(self) -> None:
        while not self._stop:
            self.peak = max(self.peak, self.rss_mb())
            time.sleep(0.02)

    def stage(self) -> float:
        peak, self.peak = max(self.peak, self.rss_mb()), self.rss_mb()
        return peak


def enlarged_splat(n: int, seed: int = 0):
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
    far = lo + (hi - lo) * rng.random((floaters, 3)) + rng.choice([-1, 1], (floaters, 3)) * rng.uniform(1, 10, (floaters, 1)) * size
    pick = np.concatenate([pick, rng.integers(0, src.num, floaters)])
    return src.replace(
        means=np.concatenate([means, far]).astype(np.float32), quats=src.quats[pick],
        log_scales=(src.log_scales[pick] - np.log(copies) / 3.0).astype(np.float32),
        opacity_logits=src.opacity_logits[pick], sh=src.sh[pick],
        normals=None if src.normals is None else src.normals[pick], name=f"sunflowers_x{copies}",
    )  # fmt: skip


def compose(ply: Path, run_dir: Path, frames: int):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from sync4d.config_schemas import register_schemas

    register_schemas()
    overrides = ["reference=laptop", "recon=ground_truth", "target=ply", f"target.path={ply}", f"frames={frames}",
                 "cache=false", "logger=none"]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        return hydra_compose(config_name="config", overrides=overrides), overrides


def child(n: int, frames: int) -> dict:
    """One size, end to end (see the module docstring); returns per-stage seconds and peak MB."""
    import numpy as np

    from sync4d import pipeline
    from sync4d.budget import check_run_cost
    from sync4d.io.ply import write_gaussians_ply
    from sync4d.motion import driving_motion
    from sync4d.plugins import load_all
    from sync4d.registry import build
    from sync4d.sim.control import carry_frame
    from sync4d.transfer import make_particles
    from sync4d.types import PartMap

    load_all()
    work = WORK / str(n)
    shutil.rmtree(work, ignore_errors=True)
    (work / "frames").mkdir(parents=True)
    ply = write_gaussians_ply(work / "target.ply", enlarged_splat(n))
    cfg, overrides = compose(ply, work, frames)
    sampler = PeakSampler()
    sampler.stage()
    rows: list[dict] = []

    cpu = [time.process_time()]

    def record(name: str, started: float, **extra) -> None:
        now = time.process_time()
        rows.append({"stage": name, "seconds": time.perf_counter() - started, "cpu_seconds": now - cpu[0],
                     "peak_mb": sampler.stage(), **extra})
        cpu[0] = now

    ctx = pipeline.RunContext(cfg=cfg, run_dir=work, cache_root=work / "cache", logger=None)
    t0 = time.perf_counter()
    reference, recon_key = pipeline.stage_reference(ctx)
    record("reference", t0)
    t0 = time.perf_counter()
    source = build("target", pipeline.group_cfg(cfg, "target"), device=cfg.device, seed=cfg.seed)
    target, report = source.load_checked()  # what pipeline.stage_target does, keeping the floater report
    target.validate()
    record("load", t0, gaussians=target.num, sh_degree=target.sh_degree, file_mb=ply.stat().st_size / 2**20,
           floaters=report.as_dict() if report is not None else None)
    t0 = time.perf_counter()
    part_map = pipeline.stage_match(ctx, reference, recon_key, target, source)
    record("match", t0)
    t0 = time.perf_counter()
    points, faces = pipeline.target_surface(target, source)
    from sync4d.metrics import part_centroids

    anchor = part_centroids(target.means.astype(np.float64), part_map.tgt_part, part_map.num_parts)
    motion = driving_motion(reference, target_points=points, target_faces=faces, num_frames=frames,
                            loop=bool(cfg.loop_reference), part_centroids=anchor,
                            rotation=pipeline.reference_to_target_rotation(cfg, reference, points))
    record("motion", t0, surface_points=len(points))
    sim_cfg = pipeline.group_cfg(cfg, "sim")
    velocity_cfg = pipeline.group_cfg(cfg, "velocity")
    t0 = time.perf_counter()
    cost = check_run_cost(sim_cfg, velocity_cfg, target, motion, frames=frames)
    record("cost", t0, estimate_s_per_frame=cost.seconds_per_frame, estimate_substeps=cost.substeps,
           estimate_peak_mb=cost.peak_memory_mb)
    t0 = time.perf_counter()
    simulator = build("sim", sim_cfg, device=cfg.device)
    particles = make_particles(target, part_map, simulator.cfg.control_grid)
    from sync4d.types import TargetGaussians

    p = len(particles.points)
    points_target = TargetGaussians(
        means=particles.points.astype(np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (p, 1)),
        log_scales=np.full((p, 3), -5.0, np.float32), opacity_logits=np.zeros(p, np.float32),
        sh=np.zeros((p, 1, 3), np.float32), name="control points",
    )  # fmt: skip
    points_map = PartMap(ref_part=part_map.ref_part, tgt_part=particles.part, confidence=np.ones(p),
                         num_parts=part_map.num_parts)
    point_sim = build("sim", {**sim_cfg, "control_grid": None}, device=cfg.device)
    record("control", t0, particles=p)

    carry = {"seconds": 0.0, "cpu": 0.0, "bytes": 0}
    frame_stats: list[dict] = []

    def on_frame(t, x, F, stats, checkpoint=None) -> None:
        started, started_cpu = time.perf_counter(), time.process_time()
        frame_stats.append({k: float(v) for k, v in stats.items()})
        frame = carry_frame(target, particles.gaussian_to_point, particles.points, x, F, motion.global_transforms[t])
        path = write_gaussians_ply(work / "frames" / f"{t:06d}.ply", frame)
        carry["bytes"] += path.stat().st_size
        carry["seconds"] += time.perf_counter() - started
        carry["cpu"] += time.process_time() - started_cpu

    t0 = time.perf_counter()
    trajectory = point_sim.run(points_target, points_map, motion, velocity_cfg=velocity_cfg, num_frames=frames,
                               on_frame=on_frame)
    total, total_cpu = time.perf_counter() - t0, time.process_time() - cpu[0]
    cpu[0] = time.process_time()
    peak = sampler.stage()
    sim_frames = frame_stats[1:]
    rows.append({"stage": "simulate", "seconds": total - carry["seconds"], "cpu_seconds": total_cpu - carry["cpu"],
                 "peak_mb": peak, "seconds_per_frame": (total - carry["seconds"]) / max(frames - 1, 1),
                 "substeps_per_frame": [r.get("time/substeps") for r in sim_frames],
                 "iterations_per_frame": [r.get("loss/iterations") for r in sim_frames]})
    rows.append({"stage": "carry+write", "seconds": carry["seconds"], "cpu_seconds": carry["cpu"], "peak_mb": peak,
                 "disk_mb": carry["bytes"] / 2**20, "seconds_per_frame": carry["seconds"] / frames})
    t0 = time.perf_counter()
    preview = render_preview(cfg, target, particles, trajectory, motion)
    record("preview", t0, **preview)
    shutil.rmtree(work / "frames", ignore_errors=True)
    wall = sum(r["seconds"] for r in rows)
    return {"gaussians": n, "frames": frames, "rows": rows, "wall_seconds": wall, "overrides": overrides,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "frame_mb": carry["bytes"] / max(frames, 1) / 2**20}


def render_preview(cfg, target, particles, trajectory, motion) -> dict:
    """Every frame of at most ``PREVIEW_GAUSSIANS`` (the most opaque, by stride) at a small size; writes a GIF."""
    import numpy as np

    from sync4d.registry import build
    from sync4d.render.camera import frame_object
    from sync4d.sim.control import carry_frame

    stride = max(1, -(-target.num // PREVIEW_GAUSSIANS))
    keep = np.arange(0, target.num, stride)
    subset = target.subset(keep)
    g2p = particles.gaussian_to_point[keep]
    renderer = build("render", {"type": "splat_torch", "width": PREVIEW_SIZE, "height": PREVIEW_SIZE}, device="cpu")
    camera = None
    images = []
    for t in range(trajectory.num_frames):
        frame = carry_frame(subset, g2p, particles.points, trajectory.x[t], trajectory.F[t], motion.global_transforms[t])
        if camera is None:
            camera = frame_object(frame.means.astype(np.float64), width=PREVIEW_SIZE, height=PREVIEW_SIZE)
        rgb = renderer.render(frame.means, frame.covariances(), frame.sh, frame.opacities, camera)
        images.append((np.clip(rgb, 0, 1) * 255).astype(np.uint8))
    import imageio.v3 as iio

    iio.imwrite(WORK / f"preview_{target.num}.gif", np.stack(images), duration=80, loop=0)
    return {"preview_gaussians": len(keep), "preview_frames": len(images),
            "preview_changed": float(np.abs(images[-1].astype(float) - images[0]).mean())}


def table(results: list[dict]) -> str:
    """Per stage and size: wall seconds, CPU seconds of this process, peak resident MB."""
    stages = [r["stage"] for r in results[0]["rows"]]
    head = f"{'stage':<12}" + "".join(f"{r['gaussians']:>26,}" for r in results)
    lines = [head, f"{'':<12}" + "".join(f"{'wall s':>9}{'CPU s':>8}{'peak MB':>9}" for _ in results)]
    for s in stages:
        cells = ""
        for r in results:
            row = next(x for x in r["rows"] if x["stage"] == s)
            cells += f"{row['seconds']:>9.1f}{row.get('cpu_seconds', float('nan')):>8.1f}{row['peak_mb']:>9.0f}"
        lines.append(f"{s:<12}{cells}")
    total = ""
    for r in results:
        cpu = sum(x.get("cpu_seconds", 0.0) for x in r["rows"])
        total += f"{r['wall_seconds']:>9.1f}{cpu:>8.1f}{r['peak_rss_mb']:>9.0f}"
    lines.append(f"{'total':<12}{total}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=SIZES)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "scale.json")
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--show", type=Path, default=None, help="print the table of a results JSON and exit")
    args = parser.parse_args(argv)
    if args.show is not None:
        print(table(json.loads(args.show.read_text())["results"]))
        return 0
    if args.child is not None:
        print(json.dumps(child(args.child, args.frames)))
        return 0
    if not SOURCE.is_file():
        print(f"scale: the source splat {SOURCE} is not on this machine (set SYNC4D_SHARED_DATA)", file=sys.stderr)
        return 2
    results = []
    for n in args.sizes:
        started = time.perf_counter()
        proc = subprocess.run([sys.executable, __file__, "--child", str(n), "--frames", str(args.frames)],
                              capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            print(proc.stderr[-4000:], file=sys.stderr)
            return 1
        result = json.loads(proc.stdout.strip().splitlines()[-1])
        result["process_seconds"] = time.perf_counter() - started
        results.append(result)
        print(f"{n:,} Gaussians: {result['wall_seconds']:.0f} s in stages, {result['process_seconds']:.0f} s "
              f"with start-up, peak {result['peak_rss_mb']:.0f} MB", flush=True)
        args.json.parent.mkdir(parents=True, exist_ok=True)  # after every size: a long sweep keeps what it has
        args.json.write_text(json.dumps({"results": results, "source": str(SOURCE.name)}, indent=1) + "\n")
    print(table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
