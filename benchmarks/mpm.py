"""Benchmark of the Warp MLS-MPM simulator (issues 4, 22): speed forward and forward+backward, peak memory,
against the plain taped Warp reference (``benchmarks/mpm_reference.py``) run in the same invocation.

Scene: a cube of side 0.3 m filled with uniformly random particles, density 1000 kg/m^3, uniform initial
velocity (1, 0.5, 0) m/s, E = 1e4 Pa, nu = 0.3, dt = 1e-4 s, 100 substeps; 10k and 50k particles on
32^3 and 64^3 grids (n_grid nodes along the padded cube). Every case runs in its own subprocess so its
peak RSS (``ru_maxrss``) is its own. The simulator runs with its default threads (``sim.cpu_threads``
null: the usable cores) and, at 50k / 64^3, also on one thread; the reference runs on one thread (Warp's
CPU backend). Ratios are of wall time (the goal: forward + backward >= 3.6x the reference at 50k / 64^3)
and of CPU time. The machine may be shared (and with autogroup scheduling a second thread then gains
nothing): each record also estimates the wall time on idle cores from per-thread CPU times (serial CPU
plus the slowest thread of every parallel section, :class:`_CriticalPath`; for the one-thread reference
its CPU time), and the ratio of those estimates is printed beside the measured one.
Also prints the per-substep split P2G / grid / G2P (kernels timed one by one with a device
synchronisation; the stress is fused into P2G, so it is timed separately with a stress-only kernel).
The held drive (``sim.drive=complementary``, issue 39) is measured on the same cube cut into 8 octant parts, each
driven to turn 5 deg about its centroid and shift 1 cm over the rollout: its cost is the ratio of that run to the
same run without a pose (the drive off), forward and forward+backward, and its kernels' share of a substep.

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
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:
    from sync4d.sim.mpm_warp.model import Workspace
    from sync4d.types import FramePose

ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))
sys.path.insert(0, str(ROOT))

CASES = [(10_000, 32), (10_000, 64), (50_000, 32), (50_000, 64)]
QUICK = [(50_000, 64)]
MAIN = (50_000, 64)  # the case the goals are stated for
SUBSTEPS = 100
DT = 1e-4
# issue 4's absolute goals [particle-substeps/s] and issue 22's ratio to the in-run reference
GOAL = {"fwd": 3.3e6, "fwdbwd": 1.0e6}
GOAL_RATIO_FWDBWD = 3.6
GOAL_PEAK_MB = 1024.0


def _thread_cpu() -> dict[int, float]:
    """CPU seconds (user + system) of every thread of this process, by native thread id (Linux)."""
    out = {}
    tick = os.sysconf("SC_CLK_TCK")
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            out[int(tid)] = (int(fields[11]) + int(fields[12])) / tick
        except (OSError, IndexError, ValueError):
            continue
    return out


class _CriticalPath:
    """Wraps the simulator's thread hand-over (``Workspace.run``) to estimate the wall time on idle cores.

    Each parallel section costs the CPU time of its slowest task (``time.thread_time`` in each thread);
    everything else the main thread does is serial. Estimate = main thread's CPU - its CPU inside the
    sections + sum of the slowest task per section. Assumes the threads would not slow each other down
    (shared memory bandwidth), so it is a lower bound on the idle wall time.
    """

    def __init__(self) -> None:
        from sync4d.sim.mpm_warp.model import Workspace

        self.sections = 0.0  # sum over sections of the slowest task [CPU s]
        self.main_inside = 0.0  # main thread's CPU inside sections [s]
        self._orig = Workspace.run
        path = self

        def run(ws: Workspace, task: Callable[[int], None]) -> None:
            if ws.threads == 1:
                c = time.thread_time()
                task(0)
                d = time.thread_time() - c
                path.sections += d
                path.main_inside += d
                return
            spent = [0.0] * ws.threads

            def timed(t: int) -> None:
                c = time.thread_time()
                task(t)
                spent[t] = time.thread_time() - c

            c0 = time.thread_time()
            path._orig(ws, timed)
            path.main_inside += time.thread_time() - c0
            path.sections += max(spent)

        setattr(Workspace, "run", run)  # the probe wraps every section (as benchmarks/scale.py wraps its stages)


def _scene(n_particles: int, n_grid: int, checkpoint_every: int | None = None, threads: int | None = None,
           held: bool = False) -> tuple[Any, Any, dict[str, Any], Any, FramePose | None]:
    """(simulator, model, initial state, initial velocities (P, 3) torch, pose) of the benchmark cube; with
    ``held``, cut into 8 octant parts and the pose that drives them (else None)."""
    import numpy as np
    import torch

    from sync4d.geometry import rotation_about_axis
    from sync4d.sim.mpm_warp import MPMWarp
    from sync4d.types import FramePose

    cfg = MPMWarp.Config(
        E=1e4, nu=0.3, density=1000.0, n_grid=n_grid, checkpoint_every=checkpoint_every, cpu_threads=threads
    )
    sim = MPMWarp(cfg, device="cpu")
    pts = np.random.default_rng(0).uniform(0.0, 0.3, (n_particles, 3))
    part = ((pts > 0.15).astype(int) * [1, 2, 4]).sum(1)
    model = sim.prepare(pts, volume=0.3**3, part=part if held else None)
    st = sim.initial_state(model)
    v0 = torch.tensor([1.0, 0.5, 0.0]).repeat(n_particles, 1)
    pose = None
    if held:
        end = np.tile(np.eye(4), (8, 1, 1))
        for b in range(8):
            rot = rotation_about_axis(np.array([0.0, 0.3, 1.0]) / np.hypot(0.3, 1.0), np.array([np.deg2rad(5.0)]))[0]
            c = pts[part == b].mean(0)
            end[b, :3, :3], end[b, :3, 3] = rot, c - rot @ c + [0.01, 0.0, 0.0]
        pose = FramePose(np.tile(np.eye(4), (8, 1, 1)), end)
    return sim, model, st, v0, pose


def run_case(n_particles: int, n_grid: int, mode: str, threads: int | None = None, held: bool = False) -> dict:
    """Time one case in this process; returns one JSON record (``threads`` None: the simulator's default;
    ``held``: the octant parts held to their drive)."""
    import torch

    torch.set_num_threads(1)
    sim, model, st, v0, pose = _scene(n_particles, n_grid, threads=threads, held=held)
    # warm-up: kernel load and workspace allocation (not timed)
    v = v0.clone().requires_grad_(mode == "fwdbwd")
    x, *_ = sim.rollout(model, st["x"], v, st["F"], st["C"], substeps=2, dt=DT, pose=pose)
    if mode == "fwdbwd":
        x.sum().backward()
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    v = v0.clone().requires_grad_(mode == "fwdbwd")
    path = _CriticalPath()
    tc0 = _thread_cpu()
    m0 = time.thread_time()
    t0 = time.perf_counter()
    c0 = time.process_time()
    x, vo, F, C = sim.rollout(model, st["x"], v, st["F"], st["C"], substeps=SUBSTEPS, dt=DT, pose=pose)
    t1 = time.perf_counter()
    if mode == "fwdbwd":
        # a centroid-displacement loss of one half of the cube plus a term on F (all outputs used)
        part = st["x"][:, 0] < 0.15
        loss = x[part].mean(0).square().sum() + (F - torch.eye(3)).square().mean()
        loss.backward()
        assert v.grad is not None and torch.isfinite(v.grad).all()
    t2 = time.perf_counter()
    c2 = time.process_time()
    m2 = time.thread_time()
    tc2 = _thread_cpu()
    idle_estimate = (m2 - m0) - path.main_inside + path.sections
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    per_thread = sorted((tc2[t] - tc0.get(t, 0.0) for t in tc2), reverse=True)
    return {
        "solver": "mpm_warp_held" if held else "mpm_warp",
        "threads": sim.threads_for(n_particles),
        "n_particles": n_particles,
        "n_grid": n_grid,
        "grid_dims": list(model.grid.dims),
        "substeps": SUBSTEPS,
        "mode": mode,
        "seconds": t2 - t0,
        "forward_seconds": t1 - t0,
        "cpu_seconds": c2 - c0,
        # the busiest threads' CPU seconds (clock ticks)
        "thread_cpu_seconds": [round(c, 2) for c in per_thread[:4]],
        # wall time on idle cores, estimated from per-thread CPU times (see _CriticalPath)
        "idle_wall_estimate_s": idle_estimate,
        "particle_substeps_per_s": n_particles * SUBSTEPS / (t2 - t0),
        # the machine is shared: CPU time of this process (all threads; torch limited to one) too
        "particle_substeps_per_cpu_s": n_particles * SUBSTEPS / (c2 - c0),
        "checkpoint_every": sim.checkpoint_interval(n_particles, SUBSTEPS),
        "peak_rss_mb": peak,
        "rss_before_rollout_mb": base_rss,
    }


def run_split(n_particles: int, n_grid: int, held: bool = False) -> dict:
    """Per-substep kernel times [s] (synchronised after each launch): p2g (incl. stress), grid, g2p (with
    ``held``: G2P and the drive's moments), drive (the correction), stress."""
    import numpy as np
    import warp as wp

    from sync4d.sim.mpm_warp import kernels as K

    sim, model, st, v0, pose = _scene(n_particles, n_grid, held=held)
    sim.rollout(model, st["x"], v0, st["F"], st["C"], substeps=2, dt=DT, pose=pose)
    timers: dict[str, float] = {}
    sim.rollout(model, st["x"], v0, st["F"], st["C"], substeps=SUBSTEPS, dt=DT, timers=timers, pose=pose)
    # the stress alone on the same deformation gradients (fused into P2G in the real substep)
    rng = np.random.default_rng(1)
    F = np.eye(3)[None] + 0.05 * rng.normal(size=(n_particles, 3, 3))
    Fw: wp.array = wp.array(F.astype(np.float32), dtype=wp.mat33, device="cpu")
    tau = wp.empty(n_particles, dtype=wp.mat33, device="cpu")
    wp.launch(K.kirchhoff_stress, dim=n_particles, inputs=[Fw, model.mu, model.lam], outputs=[tau], device="cpu")
    wp.synchronize_device("cpu")
    t0 = time.perf_counter()
    for _ in range(SUBSTEPS):
        wp.launch(K.kirchhoff_stress, dim=n_particles, inputs=[Fw, model.mu, model.lam], outputs=[tau], device="cpu")
    wp.synchronize_device("cpu")
    timers["stress"] = time.perf_counter() - t0
    return {k: v / SUBSTEPS for k, v in timers.items()}


def run_parts_split(n_particles: int, n_grid: int, variant: str) -> dict:
    """Per-substep kernel times [s] of the benchmark cube cut into four x-y quadrants held by their drive (identity
    poses): ``drive`` without a part tree (one velocity field), ``fields`` with the tree 1->0, 2->0, 3->1 (the
    unjoined diagonal neighbours and 2-3 conflict: three fields, bonded at the joints 0-2 and 1-3)."""
    import numpy as np

    from sync4d.types import FramePose

    sim, model, st, v0, _ = _scene(n_particles, n_grid)
    x = st["x"].double().numpy()
    part = (x[:, 0] > 0.15).astype(int) + 2 * (x[:, 1] > 0.15).astype(int)
    parent = np.array([-1, 0, 0, 1]) if variant == "fields" else None
    model = sim.prepare(x, volume=0.3**3, part=part, parent=parent)
    pose = FramePose(np.stack([np.eye(4)] * 4), np.stack([np.eye(4)] * 4))
    sim.rollout(model, st["x"], v0, st["F"], st["C"], substeps=2, dt=DT, pose=pose)
    timers: dict[str, float] = {}
    sim.rollout(model, st["x"], v0, st["F"], st["C"], substeps=SUBSTEPS, dt=DT, pose=pose, timers=timers)
    out = {k: v / SUBSTEPS for k, v in timers.items()}
    out["fields"] = float(getattr(model, "num_fields", 1))
    return out


def _subprocess(args: list[str], script: Path | None = None) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [sys.executable, str(script or __file__), *args]
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"benchmark case {args} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="only 50k particles on 64^3, with the reference")
    parser.add_argument("--json", type=Path, help="write the records to this JSON file")
    parser.add_argument("--case", nargs="+", metavar="P G MODE THREADS [held]", help=argparse.SUPPRESS)
    parser.add_argument("--split", nargs="+", metavar="P G [held]", help=argparse.SUPPRESS)
    parser.add_argument("--parts-split", nargs=3, metavar=("P", "G", "VARIANT"), help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.case:
        threads = None if args.case[3] == "auto" else int(args.case[3])
        held = args.case[4:] == ["held"]
        print(json.dumps(run_case(int(args.case[0]), int(args.case[1]), args.case[2], threads, held)))
        return
    if args.split:
        print(json.dumps(run_split(int(args.split[0]), int(args.split[1]), args.split[2:] == ["held"])))
        return
    if args.parts_split:
        n, g, variant = args.parts_split
        print(json.dumps(run_parts_split(int(n), int(g), variant)))
        return

    reference = ROOT / "benchmarks" / "mpm_reference.py"
    records = []

    def run(n: int, g: int, mode: str, solver: str, threads: str = "auto") -> None:
        if solver == "reference":
            rec = _subprocess(["--case", str(n), str(g), mode], script=reference)
        else:
            held = ["held"] if solver == "mpm_warp_held" else []
            rec = _subprocess(["--case", str(n), str(g), mode, threads, *held])
        records.append(rec)
        print(
            f"  ran {solver} ({rec['threads']} thr) {n} particles, {g}^3, {mode}: {rec['seconds']:.2f} s wall, "
            f"{rec['cpu_seconds']:.2f} s CPU",
            file=sys.stderr,
        )

    for n, g in QUICK if args.quick else CASES:
        for mode in ("fwd", "fwdbwd"):
            run(n, g, mode, "mpm_warp")
            if (n, g) == MAIN:
                run(n, g, mode, "reference")
                run(n, g, mode, "mpm_warp", "1")
                run(n, g, mode, "mpm_warp_held")

    print(
        f"\nMLS-MPM (Warp {_warp_version()}, cpu, {len(os.sched_getaffinity(0))} cores usable, load average "
        f"{os.getloadavg()[0]:.1f}), {SUBSTEPS} substeps of dt={DT:g} s, E=1e4 Pa, nu=0.3\n"
    )
    print(
        f"{'solver':>10} {'thr':>3} {'particles':>9} {'grid':>8} {'mode':>7} {'M p-substeps/s':>15} "
        f"{'(per CPU s)':>12} {'wall s':>7} {'CPU s':>7} {'idle est. s':>11} {'peak RSS MB':>12}"
    )
    for r in records:
        grid = "x".join(str(d) for d in r["grid_dims"])
        print(
            f"{r['solver']:>10} {r['threads']:>3} {r['n_particles']:>9} {grid:>8} {r['mode']:>7} "
            f"{r['particle_substeps_per_s'] / 1e6:>15.3f} {r['particle_substeps_per_cpu_s'] / 1e6:>12.3f} "
            f"{r['seconds']:>7.2f} {r['cpu_seconds']:>7.2f} {_idle(r):>11.2f} {r['peak_rss_mb']:>12.0f}"
        )

    summary = {}
    print(f"\nAt {MAIN[0]} particles / {MAIN[1]}^3, against the plain reference measured above:")
    for mode in ("fwd", "fwdbwd"):
        pick = {
            (r["solver"], r["threads"] == 1): r
            for r in records
            if (r["n_particles"], r["n_grid"]) == MAIN and r["mode"] == mode and r["solver"] != "mpm_warp_held"
        }
        held = next(r for r in records if (r["n_particles"], r["n_grid"]) == MAIN and r["mode"] == mode
                    and r["solver"] == "mpm_warp_held")
        ref, ours, one = pick[("reference", True)], pick.get(("mpm_warp", False)), pick[("mpm_warp", True)]
        ours = ours or one  # a one-core machine: the default is one thread
        wall = ref["seconds"] / ours["seconds"]
        cpu = ref["cpu_seconds"] / ours["cpu_seconds"]
        one_wall = ref["seconds"] / one["seconds"]
        idle = _idle(ref) / _idle(ours)
        summary[mode] = {
            "held_drive_cost_ratio": held["seconds"] / ours["seconds"],
            "held_drive_cpu_ratio": held["cpu_seconds"] / ours["cpu_seconds"],
            "wall_ratio": wall,
            "cpu_ratio": cpu,
            "one_thread_wall_ratio": one_wall,
            "idle_estimate_ratio": idle,
            "peak_rss_mb": ours["peak_rss_mb"],
        }
        goal = ""
        if mode == "fwdbwd":
            ok = wall >= GOAL_RATIO_FWDBWD and ours["peak_rss_mb"] <= GOAL_PEAK_MB
            goal = (
                f"  goal >= {GOAL_RATIO_FWDBWD}x at <= {GOAL_PEAK_MB:.0f} MB: "
                f"{'met' if ok else 'NOT met'} ({ours['peak_rss_mb']:.0f} MB)"
            )
        print(
            f"  {mode:>6}: reference {ref['particle_substeps_per_s'] / 1e6:.3f} M/s, ours "
            f"{ours['particle_substeps_per_s'] / 1e6:.3f} M/s ({ours['threads']} threads): {wall:.2f}x wall "
            f"(one thread {one_wall:.2f}x), {cpu:.2f}x CPU time, {idle:.2f}x estimated on idle cores{goal}"
        )
        print(
            f"          vs issue 4's absolute goal {GOAL[mode] / 1e6:.1f} M/s: "
            f"{ours['particle_substeps_per_s'] / GOAL[mode]:.2f}"
        )
        print(
            f"          held drive (8 parts): {held['seconds'] / ours['seconds']:.3f}x the wall time without it, "
            f"{held['cpu_seconds'] / ours['cpu_seconds']:.3f}x the CPU time (goal <= 1.25x)"
        )

    split = _subprocess(["--split", "50000", "64"])
    total = split["p2g"] + split["grid"] + split["g2p"]
    print("\nPer-substep split, 50k particles / 64^3, default threads (kernels synchronised one by one):")
    print(
        f"  P2G incl. stress {1e3 * split['p2g']:.2f} ms ({100 * split['p2g'] / total:.0f}%), stress alone "
        f"(one thread) ~{1e3 * split['stress']:.2f} ms"
    )
    print(f"  grid update      {1e3 * split['grid']:.2f} ms ({100 * split['grid'] / total:.0f}%)")
    print(f"  G2P              {1e3 * split['g2p']:.2f} ms ({100 * split['g2p'] / total:.0f}%)")
    held_split = _subprocess(["--split", "50000", "64", "held"])
    held_total = sum(held_split[k] for k in ("p2g", "grid", "g2p", "drive"))
    print(
        f"  with the held drive (8 parts): G2P + moments {1e3 * held_split['g2p']:.2f} ms, correction "
        f"{1e3 * held_split['drive']:.2f} ms; substep {1e3 * held_total:.2f} ms, {held_total / total:.3f}x"
    )
    parts = {v: _subprocess(["--parts-split", "50000", "64", v]) for v in ("drive", "fields")}
    _print_parts(split, parts)

    if not args.quick:
        agree = _subprocess(["--agree", "10000", "32"], script=reference)
        print(
            f"\nReference vs sim=mpm_warp, 10k / 32^3, 100 substeps: max |dx| {agree['max_dx_over_cell']:.2g} "
            f"cells, dL/dv0 relative L2 error {agree['grad_rel_l2']:.2g} (cosine {agree['grad_cosine']:.6f})"
        )
        summary["agreement"] = agree

    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        split_ms = {k: 1e3 * v for k, v in split.items()}
        held_ms = {k: 1e3 * v for k, v in held_split.items()}
        out = {"records": records, "split_ms": split_ms, "held_split_ms": held_ms, "summary": summary,
               "load_average": os.getloadavg()[0]}
        args.json.write_text(json.dumps(out, indent=2))
        print(f"\nwrote {args.json}")


def _print_parts(plain: dict, parts: dict[str, dict]) -> None:
    """The substep of four driven quadrants, one field and with velocity fields, against the plain substep."""
    base = plain["p2g"] + plain["grid"] + plain["g2p"]
    print("\nThe cube as four driven quadrants (same scene; ms per substep, P2G / grid / G2P / drive):")
    for name, rec in parts.items():
        total = rec["p2g"] + rec["grid"] + rec["g2p"] + rec.get("drive", 0.0)
        print(f"  {name:>6} ({rec['fields']:.0f} fields): {1e3 * rec['p2g']:.2f} / {1e3 * rec['grid']:.2f} / "
              f"{1e3 * rec['g2p']:.2f} / {1e3 * rec.get('drive', 0.0):.2f} = {1e3 * total:.2f} ms, "
              f"{100 * (total / base - 1):+.0f}% on the plain substep")
    d, f = (sum(parts[v].get(k, 0.0) for k in ("p2g", "grid", "g2p", "drive")) for v in ("drive", "fields"))
    print(f"  the fields add {100 * (f / d - 1):+.0f}% to the driven substep")


def _idle(rec: dict) -> float:
    """Estimated wall time [s] on idle cores: the critical path, or the CPU time of a one-thread record."""
    return float(rec.get("idle_wall_estimate_s", rec["cpu_seconds"]))


def _warp_version() -> str:
    import warp

    return warp.__version__


if __name__ == "__main__":
    main()
