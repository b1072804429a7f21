"""Benchmark of the Warp MLS-MPM simulator (issue 4): speed forward and forward+backward, peak memory.

Scene: a cube of side 0.3 m filled with uniformly random particles, density 1000 kg/m^3, uniform initial
velocity (1, 0.5, 0) m/s, E = 1e4 Pa, nu = 0.3, dt = 1e-4 s, 100 substeps; 10k and 50k particles on
32^3 and 64^3 grids (n_grid nodes along the padded cube). Every case runs in its own subprocess so its
peak RSS (``ru_maxrss``) is its own. Also prints the per-substep split stress / P2G / grid / G2P
(kernels timed one by one with a device synchronisation; the stress is fused into P2G, so it is timed
separately with a stress-only kernel and shown as a part of P2G).

Usage:
    python benchmarks/mpm.py [--quick] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))
sys.path.insert(0, str(ROOT))

CASES = [(10_000, 32), (10_000, 64), (50_000, 32), (50_000, 64)]
QUICK = [(50_000, 64)]
SUBSTEPS = 100
DT = 1e-4
# Reference figures (50k / 64^3 / 100 substeps, this machine): issue 4.
REFERENCE = {
    "fwd": ("PhysGaussian Warp", 1.08e6),
    "fwdbwd": ("PhysDreamer Warp taped", 0.245e6),
}
GOAL = {"fwd": 3.3e6, "fwdbwd": 1.0e6}


def _scene(n_particles: int, n_grid: int, checkpoint_every: int | None = None):
    import numpy as np
    import torch

    from sync4d.sim.mpm_warp import MPMWarp

    cfg = MPMWarp.Config(E=1e4, nu=0.3, density=1000.0, n_grid=n_grid, checkpoint_every=checkpoint_every)
    sim = MPMWarp(cfg, device="cpu")
    pts = np.random.default_rng(0).uniform(0.0, 0.3, (n_particles, 3))
    model = sim.prepare(pts, volume=0.3**3)
    st = sim.initial_state(model)
    v0 = torch.tensor([1.0, 0.5, 0.0]).repeat(n_particles, 1)
    return sim, model, st, v0


def run_case(n_particles: int, n_grid: int, mode: str) -> dict:
    """Time one case in this process; returns one JSON record."""
    import torch

    torch.set_num_threads(1)
    sim, model, st, v0 = _scene(n_particles, n_grid)
    # warm-up: kernel load and workspace allocation (not timed)
    v = v0.clone().requires_grad_(mode == "fwdbwd")
    x, *_ = sim.rollout(model, st["x"], v, st["F"], st["C"], substeps=2, dt=DT)
    if mode == "fwdbwd":
        x.sum().backward()
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    v = v0.clone().requires_grad_(mode == "fwdbwd")
    t0 = time.perf_counter()
    c0 = time.process_time()
    x, vo, F, C = sim.rollout(model, st["x"], v, st["F"], st["C"], substeps=SUBSTEPS, dt=DT)
    t1 = time.perf_counter()
    if mode == "fwdbwd":
        # a centroid-displacement loss of one half of the cube plus a term on F (all outputs used)
        part = st["x"][:, 0] < 0.15
        loss = x[part].mean(0).square().sum() + (F - torch.eye(3)).square().mean()
        loss.backward()
        assert v.grad is not None and torch.isfinite(v.grad).all()
    t2 = time.perf_counter()
    c2 = time.process_time()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {
        "n_particles": n_particles,
        "n_grid": n_grid,
        "grid_dims": list(model.grid.dims),
        "substeps": SUBSTEPS,
        "mode": mode,
        "seconds": t2 - t0,
        "forward_seconds": t1 - t0,
        "particle_substeps_per_s": n_particles * SUBSTEPS / (t2 - t0),
        # the machine is shared: CPU time of this process (one Warp thread, torch limited to one) too
        "particle_substeps_per_cpu_s": n_particles * SUBSTEPS / (c2 - c0),
        "checkpoint_every": sim.checkpoint_interval(n_particles, SUBSTEPS),
        "peak_rss_mb": peak,
        "rss_before_rollout_mb": base_rss,
    }


def run_split(n_particles: int, n_grid: int) -> dict:
    """Per-substep kernel times [s] (synchronised after each launch): p2g (incl. stress), grid, g2p, stress."""
    import numpy as np
    import warp as wp

    from sync4d.sim import _kernels as K

    sim, model, st, v0 = _scene(n_particles, n_grid)
    sim.rollout(model, st["x"], v0, st["F"], st["C"], substeps=2, dt=DT)
    timers: dict[str, float] = {}
    sim.rollout(model, st["x"], v0, st["F"], st["C"], substeps=SUBSTEPS, dt=DT, timers=timers)
    # the stress alone on the same deformation gradients (fused into P2G in the real substep)
    rng = np.random.default_rng(1)
    F = np.eye(3)[None] + 0.05 * rng.normal(size=(n_particles, 3, 3))
    Fw = wp.array(F.astype(np.float32), dtype=wp.mat33, device="cpu")
    tau = wp.empty(n_particles, dtype=wp.mat33, device="cpu")
    wp.launch(K.kirchhoff_stress, dim=n_particles, inputs=[Fw, model.mu, model.lam], outputs=[tau], device="cpu")
    wp.synchronize_device("cpu")
    t0 = time.perf_counter()
    for _ in range(SUBSTEPS):
        wp.launch(K.kirchhoff_stress, dim=n_particles, inputs=[Fw, model.mu, model.lam], outputs=[tau], device="cpu")
    wp.synchronize_device("cpu")
    timers["stress"] = time.perf_counter() - t0
    return {k: v / SUBSTEPS for k, v in timers.items()}


def _subprocess(args: list[str]) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True, env=env, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"benchmark case {args} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="only 50k particles on 64^3 (under a minute)")
    parser.add_argument("--json", type=Path, help="write the records to this JSON file")
    parser.add_argument("--case", nargs=3, metavar=("P", "G", "MODE"), help=argparse.SUPPRESS)
    parser.add_argument("--split", nargs=2, metavar=("P", "G"), help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.case:
        print(json.dumps(run_case(int(args.case[0]), int(args.case[1]), args.case[2])))
        return
    if args.split:
        print(json.dumps(run_split(int(args.split[0]), int(args.split[1]))))
        return

    records = []
    for n, g in QUICK if args.quick else CASES:
        for mode in ("fwd", "fwdbwd"):
            rec = _subprocess(["--case", str(n), str(g), mode])
            records.append(rec)
            print(f"  ran {n} particles, {g}^3, {mode}: {rec['seconds']:.2f} s", file=sys.stderr)

    print(f"\nMLS-MPM (Warp {_warp_version()}, cpu), {SUBSTEPS} substeps of dt={DT:g} s, E=1e4 Pa, nu=0.3\n")
    print(f"{'particles':>9} {'grid':>8} {'mode':>7} {'M p-substeps/s':>15} {'(per CPU s)':>12} {'peak RSS MB':>12} {'vs reference':>22} {'vs goal':>8}")
    for r in records:
        ref_name, ref = REFERENCE[r["mode"]]
        rate = r["particle_substeps_per_s"]
        ratio = f"{rate / ref:.2f}x {ref_name.split()[0]}" if (r["n_particles"], r["n_grid"]) == (50_000, 64) else ""
        goal = f"{rate / GOAL[r['mode']]:.2f}" if (r["n_particles"], r["n_grid"]) == (50_000, 64) else ""
        grid = "x".join(str(d) for d in r["grid_dims"])
        cpu = r["particle_substeps_per_cpu_s"] / 1e6
        print(f"{r['n_particles']:>9} {grid:>8} {r['mode']:>7} {rate / 1e6:>15.3f} {cpu:>12.3f} {r['peak_rss_mb']:>12.0f} {ratio:>22} {goal:>8}")

    split = _subprocess(["--split", "50000", "64"])
    total = split["p2g"] + split["grid"] + split["g2p"]
    print("\nPer-substep split, 50k particles / 64^3 (kernels synchronised one by one):")
    print(f"  P2G incl. stress {1e3 * split['p2g']:.2f} ms ({100 * split['p2g'] / total:.0f}%), of which stress alone "
          f"~{1e3 * split['stress']:.2f} ms ({100 * split['stress'] / total:.0f}%)")
    print(f"  grid update      {1e3 * split['grid']:.2f} ms ({100 * split['grid'] / total:.0f}%)")
    print(f"  G2P              {1e3 * split['g2p']:.2f} ms ({100 * split['g2p'] / total:.0f}%)")

    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        split_ms = {k: 1e3 * v for k, v in split.items()}
        out = [dict(r, split_ms=split_ms) if (r["n_particles"], r["n_grid"]) == (50_000, 64) else r for r in records]
        args.json.write_text(json.dumps(out, indent=2))
        print(f"\nwrote {args.json}")


def _warp_version() -> str:
    import warp

    return warp.__version__


if __name__ == "__main__":
    main()
