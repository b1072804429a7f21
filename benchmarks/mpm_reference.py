"""The plain reference `benchmarks/mpm.py` measures the simulator against: straightforward taped Warp MLS-MPM.

Written from the algorithm the way PhysGaussian and PhysDreamer structure their Warp solvers (not their
code): per substep

1. a stress kernel: fixed-corotated Kirchhoff stress tau = 2 mu (F - R) F^T + lam J (J - 1) I with the
   polar rotation R = U V^T from ``wp.svd3``;
2. P2G: quadratic B-spline weights, ``atomic_add`` of node mass and of APIC/MLS momentum
   w (m v + (m C - dt V 4/dx^2 tau) (x_i - x_p));
3. a grid kernel: v_i = (m v)_i / m_i + dt g, slip walls near the grid faces;
4. G2P: v_p = sum w v_i, C_p = 4/dx^2 sum w v_i (x_i - x_p)^T, F <- (I + dt C) F, x <- x + dt v.

Every substep writes fresh arrays (particle state, stress, grid), all with gradient buffers, so nothing is
updated in place on the tape; one ``wp.Tape`` records all substeps and its ``backward`` runs Warp's
generated adjoints through them. No fusion, no checkpointing, no particle sorting, one thread (Warp's CPU
backend). The grid mass is an ordinary taped array, so its gradient is carried (the gradients are right,
unlike PhysDreamer's detached mass; :func:`agreement` checks them against ``sim=mpm_warp``).

Same scene and grid as the simulator: :func:`make_scene` takes an :class:`sync4d.sim.mpm_warp.MPMModel`
(grid origin, dx, dims, wall; particle masses and volumes; mu, lam) so both integrate the same problem.

Usage (normally run by ``benchmarks/mpm.py``):
    python benchmarks/mpm_reference.py --case P G MODE     # one JSON record, MODE fwd or fwdbwd
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

    from sync4d.sim.mpm_warp import MPMModel, MPMWarp

ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the kernels beside this file, however it is loaded
from mpm_reference_kernels import ref_g2p, ref_grid, ref_p2g, ref_stress  # noqa: E402

wp.config.log_level = wp.LOG_WARNING  # no module-load messages between the JSON records


@dataclass
class Scene:
    """What the reference integrates, copied from a simulator model (SI units)."""

    origin: np.ndarray  # (3,) node (0, 0, 0) [m]
    dx: float  # cell size [m]
    dims: tuple[int, int, int]
    wall: int
    mass: wp.array  # (P,) [kg]
    volume: wp.array  # (P,) [m^3]
    mu: float  # [Pa]
    lam: float  # [Pa]
    gravity: np.ndarray  # (3,) [m/s^2]
    mass_eps: float  # [kg]


def make_scene(model: MPMModel) -> Scene:
    """The reference's copy of a :class:`sync4d.sim.mpm_warp.MPMModel` (slip walls; no fixed box)."""
    g = model.grid
    return Scene(
        origin=np.asarray(g.origin, dtype=np.float64), dx=float(g.dx), dims=(int(g.dims[0]), int(g.dims[1]), int(g.dims[2])),
        wall=int(g.wall), mass=wp.array(model.mass.astype(np.float32), dtype=float, device="cpu"),
        volume=wp.array(model.volume.astype(np.float32), dtype=float, device="cpu"), mu=float(model.mu),
        lam=float(model.lam), gravity=np.asarray(model.gravity, dtype=np.float64),
        mass_eps=float(1e-9 * model.mass.min()),
    )  # fmt: skip


def _particles(n: int, grad: bool) -> list[wp.array]:
    return [
        wp.zeros(n, dtype=wp.vec3, device="cpu", requires_grad=grad),
        wp.zeros(n, dtype=wp.vec3, device="cpu", requires_grad=grad),
        wp.zeros(n, dtype=wp.mat33, device="cpu", requires_grad=grad),
        wp.zeros(n, dtype=wp.mat33, device="cpu", requires_grad=grad),
    ]


def rollout(scene: Scene, x: np.ndarray, v: np.ndarray, F: np.ndarray, C: np.ndarray, *, substeps: int, dt: float,
            grad: bool) -> tuple[wp.Tape | None, list[wp.array], list[wp.array]]:
    """Advance (x, v, F, C) (NumPy float32, (P, 3) / (P, 3, 3)) ``substeps`` substeps of ``dt`` [s].

    Returns:
        (tape, first, last): the tape (None without ``grad``) and the first and last particle states as
        lists [x, v, C, F] of Warp arrays (with gradient buffers when ``grad``).
    """
    n = len(x)
    first: list[wp.array] = [
        wp.array(np.asarray(x, np.float32), dtype=wp.vec3, device="cpu", requires_grad=grad),
        wp.array(np.asarray(v, np.float32), dtype=wp.vec3, device="cpu", requires_grad=grad),
        wp.array(np.asarray(C, np.float32), dtype=wp.mat33, device="cpu", requires_grad=grad),
        wp.array(np.asarray(F, np.float32), dtype=wp.mat33, device="cpu", requires_grad=grad),
    ]
    tape = wp.Tape() if grad else None
    origin, inv_dx = wp.vec3(*scene.origin), float(1.0 / scene.dx)
    cur = first
    with tape if tape is not None else nullcontext():
        for _ in range(substeps):
            tau = wp.zeros(n, dtype=wp.mat33, device="cpu", requires_grad=grad)
            grid_m = wp.zeros(scene.dims, dtype=float, device="cpu", requires_grad=grad)
            grid_mv = wp.zeros(scene.dims, dtype=wp.vec3, device="cpu", requires_grad=grad)
            grid_v = wp.zeros(scene.dims, dtype=wp.vec3, device="cpu", requires_grad=grad)
            nxt = _particles(n, grad)
            xs, vs, Cs, Fs = cur
            wp.launch(ref_stress, dim=n, inputs=[Fs, scene.mu, scene.lam], outputs=[tau], device="cpu")
            wp.launch(
                ref_p2g, dim=n,
                inputs=[xs, vs, Cs, tau, scene.mass, scene.volume, origin, scene.dx, inv_dx, float(dt)],
                outputs=[grid_m, grid_mv], device="cpu",
            )  # fmt: skip
            wp.launch(
                ref_grid, dim=scene.dims,
                inputs=[grid_m, grid_mv, wp.vec3(*scene.gravity), float(dt), scene.mass_eps, scene.wall],
                outputs=[grid_v], device="cpu",
            )  # fmt: skip
            wp.launch(
                ref_g2p, dim=n, inputs=[xs, Fs, grid_v, origin, inv_dx, float(dt)], outputs=nxt, device="cpu"
            )  # fmt: skip
            cur = nxt  # the tape keeps every substep's arrays alive
    return tape, first, cur


def backward(tape: wp.Tape | None, last: list[wp.array], grad_x: np.ndarray, grad_F: np.ndarray) -> None:
    """Run the tape backward from dL/dx and dL/dF of the last state (fills the first state's ``.grad``)."""
    if tape is None:
        raise ValueError("backward: the rollout was run without grad=True, so nothing was taped")
    gx: wp.array = wp.array(np.asarray(grad_x, np.float32), dtype=wp.vec3, device="cpu")
    gF: wp.array = wp.array(np.asarray(grad_F, np.float32), dtype=wp.mat33, device="cpu")
    tape.backward(grads={last[0]: gx, last[3]: gF})


def _bench_scene(n_particles: int, n_grid: int) -> tuple[MPMWarp, MPMModel, dict[str, torch.Tensor], torch.Tensor]:
    """The benchmark scene of benchmarks/mpm.py, built through the simulator so both share grid and masses."""
    import torch

    from sync4d.sim.mpm_warp import MPMWarp

    cfg = MPMWarp.Config(E=1e4, nu=0.3, density=1000.0, n_grid=n_grid)
    sim = MPMWarp(cfg, device="cpu")
    pts = np.random.default_rng(0).uniform(0.0, 0.3, (n_particles, 3))
    model = sim.prepare(pts, volume=0.3**3)
    st = sim.initial_state(model)
    v0 = torch.tensor([1.0, 0.5, 0.0]).repeat(n_particles, 1)
    return sim, model, st, v0


def loss_and_grads(x: np.ndarray, F: np.ndarray, rest_x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The benchmark's loss (centroid displacement of the cube's x < 0.15 m half, plus mean (F - I)^2)
    and its gradients dL/dx (P, 3), dL/dF (P, 3, 3), by torch autograd (the same code for both solvers)."""
    import torch

    xt = torch.as_tensor(x).requires_grad_(True)
    Ft = torch.as_tensor(F).requires_grad_(True)
    part = torch.as_tensor(rest_x[:, 0] < 0.15)
    loss = xt[part].mean(0).square().sum() + (Ft - torch.eye(3)).square().mean()
    loss.backward()
    assert xt.grad is not None and Ft.grad is not None  # both are leaves the loss depends on
    return float(loss.detach()), xt.grad.numpy(), Ft.grad.numpy()


def run_case(n_particles: int, n_grid: int, mode: str, substeps: int = 100, dt: float = 1e-4) -> dict:
    """Time one reference case in this process (same record keys as benchmarks/mpm.py's)."""
    import torch

    torch.set_num_threads(1)
    _, model, st, v0 = _bench_scene(n_particles, n_grid)
    scene = make_scene(model)
    x0, F0, C0 = st["x"].numpy(), st["F"].numpy(), st["C"].numpy()
    grad = mode == "fwdbwd"
    # warm-up: kernel load (not timed)
    tape, first, last = rollout(scene, x0, v0.numpy(), F0, C0, substeps=2, dt=dt, grad=grad)
    if grad:
        backward(tape, last, np.ones((n_particles, 3)), np.zeros((n_particles, 3, 3)))
    del tape, first, last
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    t0, c0 = time.perf_counter(), time.process_time()
    tape, first, last = rollout(scene, x0, v0.numpy(), F0, C0, substeps=substeps, dt=dt, grad=grad)
    x, F = last[0].numpy(), last[3].numpy()
    t1 = time.perf_counter()
    if grad:
        _, gx, gF = loss_and_grads(x, F, x0)
        backward(tape, last, gx, gF)
        gv = first[1].grad.numpy()
        assert np.isfinite(gv).all()
    t2, c2 = time.perf_counter(), time.process_time()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {
        "solver": "reference",
        "n_particles": n_particles,
        "n_grid": n_grid,
        "grid_dims": list(scene.dims),
        "substeps": substeps,
        "mode": mode,
        "threads": 1,
        "seconds": t2 - t0,
        "forward_seconds": t1 - t0,
        "cpu_seconds": c2 - c0,
        "particle_substeps_per_s": n_particles * substeps / (t2 - t0),
        "particle_substeps_per_cpu_s": n_particles * substeps / (c2 - c0),
        "peak_rss_mb": peak,
        "rss_before_rollout_mb": base_rss,
    }


def agreement(n_particles: int, n_grid: int, substeps: int = 100, dt: float = 1e-4) -> dict:
    """Final positions and dL/dv0 of the reference against ``sim=mpm_warp`` on the benchmark scene.

    Returns max |x_ref - x_sim| [m] relative to the cell size, and the relative L2 error and cosine of
    the velocity gradients.
    """
    sim, model, st, v0 = _bench_scene(n_particles, n_grid)
    scene = make_scene(model)
    x0, F0, C0 = st["x"].numpy(), st["F"].numpy(), st["C"].numpy()
    tape, first, last = rollout(scene, x0, v0.numpy(), F0, C0, substeps=substeps, dt=dt, grad=True)
    xr, Fr = last[0].numpy(), last[3].numpy()
    _, gx, gF = loss_and_grads(xr, Fr, x0)
    backward(tape, last, gx, gF)
    gr = first[1].grad.numpy().astype(np.float64)

    v = v0.clone().requires_grad_(True)
    xs, _, Fs, _ = sim.rollout(model, st["x"], v, st["F"], st["C"], substeps=substeps, dt=dt)
    part = st["x"][:, 0] < 0.15
    import torch

    loss = xs[part].mean(0).square().sum() + (Fs - torch.eye(3)).square().mean()
    loss.backward()
    assert v.grad is not None  # v is the leaf the loss is differentiated against
    gs = v.grad.numpy().astype(np.float64)
    return {
        "max_dx_over_cell": float(np.abs(xs.detach().numpy() - xr).max() / scene.dx),
        "grad_rel_l2": float(np.linalg.norm(gs - gr) / np.linalg.norm(gr)),
        "grad_cosine": float((gs * gr).sum() / (np.linalg.norm(gs) * np.linalg.norm(gr))),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--case", nargs=3, metavar=("P", "G", "MODE"), help="time one case, print a JSON record")
    parser.add_argument("--agree", nargs=2, metavar=("P", "G"), help="compare with sim=mpm_warp, print JSON")
    args = parser.parse_args()
    if args.case:
        if args.case[2] not in ("fwd", "fwdbwd"):
            print(f"mpm_reference: MODE must be fwd or fwdbwd, got {args.case[2]!r}", file=sys.stderr)
            sys.exit(2)
        print(json.dumps(run_case(int(args.case[0]), int(args.case[1]), args.case[2])))
    elif args.agree:
        print(json.dumps(agreement(int(args.agree[0]), int(args.agree[1]))))
    else:
        parser.print_help()
        sys.exit(2)


if __name__ == "__main__":
    main()
