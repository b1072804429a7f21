"""The plain reference of benchmarks/mpm.py (benchmarks/mpm_reference.py) integrates the same problem as
sim=mpm_warp: same final positions and velocity gradients on a small scene, so the benchmark's ratio compares
like with like. Written independently (SVD stress, Warp's generated adjoints through a wp.Tape), it is also a
second check of the simulator's hand-written adjoints."""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parent.parent


def _reference():
    spec = importlib.util.spec_from_file_location("mpm_reference", ROOT / "benchmarks" / "mpm_reference.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["mpm_reference"] = mod
    spec.loader.exec_module(mod)
    return mod


def _scene_and_sim(threads):
    from sync4d.sim.mpm_warp import MPMWarp

    sim = MPMWarp(MPMWarp.Config(E=1e4, nu=0.3, n_grid=20, cpu_threads=threads), device="cpu")
    rng = np.random.default_rng(0)
    pts = rng.uniform(0.0, 0.1, (1500, 3))
    model = sim.prepare(pts, volume=1e-3)
    st = sim.initial_state(model)
    # a velocity field that deforms the body, so the stress matters
    v0 = torch.tensor(rng.normal(0.0, 0.2, (1500, 3)), dtype=torch.float32)
    return sim, model, st, v0


def _reference_grad(ref, scene, st, v0, substeps, dt):
    x0, F0, C0 = st["x"].numpy(), st["F"].numpy(), st["C"].numpy()
    tape, first, last = ref.rollout(scene, x0, v0.numpy(), F0, C0, substeps=substeps, dt=dt, grad=True)
    xr, Fr = last[0].numpy(), last[3].numpy()
    _, gx, gF = ref.loss_and_grads(xr, Fr, x0 * 3.0)  # the x < 0.15 m half of the scaled-up body
    ref.backward(tape, last, gx, gF)
    return xr, first[1].grad.numpy().astype(np.float64)


@pytest.mark.parametrize("threads", [1, 2])
def test_reference_and_simulator_agree_and_a_wrong_stress_is_seen(threads):
    ref = _reference()
    sim, model, st, v0 = _scene_and_sim(threads)
    substeps, dt = 60, 3e-4
    scene = ref.make_scene(model)
    xr, gr = _reference_grad(ref, scene, st, v0, substeps, dt)

    v = v0.clone().requires_grad_(True)
    xs, _, Fs, _ = sim.rollout(model, st["x"], v, st["F"], st["C"], substeps=substeps, dt=dt)
    part = st["x"][:, 0] * 3.0 < 0.15
    (xs[part].mean(0).square().sum() + (Fs - torch.eye(3)).square().mean()).backward()
    gs = v.grad.numpy().astype(np.float64)

    dx = np.abs(xs.detach().numpy() - xr).max() / model.grid.dx
    rel = np.linalg.norm(gs - gr) / np.linalg.norm(gr)
    assert dx < 1e-4, dx  # measured 1.8e-6 cells
    assert rel < 1e-4, rel  # measured 2e-6

    # the comparison can fail: the reference with the stress doubled is far from the simulator
    xw, gw = _reference_grad(ref, dataclasses.replace(scene, mu=2 * scene.mu, lam=2 * scene.lam), st, v0, substeps, dt)
    assert np.abs(xs.detach().numpy() - xw).max() / model.grid.dx > 100 * dx
    assert np.linalg.norm(gs - gw) / np.linalg.norm(gw) > 0.05  # measured 0.32
