"""MLS-MPM simulator (sim=mpm_warp): physics against analytic results, gradients against finite
differences, and the stability / divergence guards. CPU, tiny scenes."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
import torch

from sync4d.errors import ConfigError, SimulationDiverged, SimulationUnstable
from sync4d.sim import physics
from sync4d.sim.mpm_warp import MPMWarp


def make_sim(**overrides) -> MPMWarp:
    cfg = MPMWarp.Config(**overrides)
    return MPMWarp(cfg, device="cpu")


def blob(n: int, size: float = 0.1, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, size, (n, 3))


def rollout(sim, model, state, v, *, substeps, dt, frames=1, **kw):
    x, F, C = state["x"], state["F"], state["C"]
    for f in range(frames):
        x, v, F, C = sim.rollout(model, x, v, F, C, substeps=substeps, dt=dt, frame_index=f, **kw)
    return x, v, F, C


# --------------------------------------------------------------------------------------------------
# pure helpers
# --------------------------------------------------------------------------------------------------


def test_lame_parameters_and_wave_speed():
    mu, lam = physics.lame_parameters(1e4, 0.3)
    assert mu == pytest.approx(1e4 / 2.6)
    assert lam == pytest.approx(1e4 * 0.3 / (1.3 * 0.4))
    assert physics.p_wave_speed(1e4, 0.3, 1000.0) == pytest.approx(math.sqrt((lam + 2 * mu) / 1000.0))
    # nu = 0: lam = 0 and the p-wave speed is the bar speed sqrt(E / rho)
    assert physics.p_wave_speed(1e4, 0.0, 1000.0) == pytest.approx(math.sqrt(10.0))


def test_cfl_bound_and_substeps():
    c = physics.p_wave_speed(1e4, 0.3, 1000.0)
    assert physics.cfl_dt(0.01, 1e4, 0.3, 1000.0, safety=0.3) == pytest.approx(0.3 * 0.01 / c)
    assert physics.cfl_dt(0.01, 1e4, 0.3, 1000.0, v_max=2.0, safety=0.3) == pytest.approx(0.3 * 0.01 / (c + 2.0))
    n, dt = physics.substeps_for(0.04, 1.5e-3, min_substeps=4)
    assert n == 27 and dt == pytest.approx(0.04 / 27) and dt <= 1.5e-3
    assert physics.substeps_for(0.04, 1.0, min_substeps=4) == (4, 0.01)


def test_fit_grid_crops_short_axes_and_keeps_points_inside():
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.2, 0.1]])
    g = physics.fit_grid(pts, n_grid=40, padding=0.1, wall=3)
    assert g.dims[0] == 40 and g.dims[1] < 40 and g.dims[2] < g.dims[1]
    assert g.contains(pts)
    # padded box exactly spans the wall-free interior along the longest axis
    assert g.interior_hi[0] - g.interior_lo[0] == pytest.approx(1.2, rel=1e-9)


# --------------------------------------------------------------------------------------------------
# configuration guards
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("key", "value", "needle"),
    [("nu", 0.5, "sim.nu"), ("E", 0.0, "sim.E"), ("E", -1e3, "sim.E"), ("density", 0.0, "sim.density")],
)
def test_bad_material_refused_at_build(key, value, needle):
    from sync4d.registry import make_config

    with pytest.raises(ConfigError, match=needle) as err:
        make_config("sim", {"type": "mpm_warp", key: value})
    if key == "nu":
        assert "lambda infinite" in str(err.value)


def test_yaml_builds(repo_root):
    from omegaconf import OmegaConf

    from sync4d.registry import build

    cfg = OmegaConf.load(repo_root / "conf/sim/mpm_warp.yaml")
    cfg.pop("defaults", None)  # Hydra's schema line; the values come from MPMWarp.Config
    sim = build("sim", cfg, device="cpu")
    assert isinstance(sim, MPMWarp) and sim.config.E == MPMWarp.Config().E and sim.config.n_grid == MPMWarp.Config().n_grid
    # the simulated time of a frame is the reference's frame interval unless set
    assert sim.config.frame_time is None and sim.frame_time_for(12.0) == pytest.approx(1 / 12)
    with pytest.raises(ConfigError, match="sim.frame_time"):
        sim.frame_time_for(None)


def test_prepare_mass_and_volume_from_density_and_share():
    sim = make_sim(density=500.0)
    pts = blob(100)
    model = sim.prepare(pts, volume=2e-3)
    assert model.volume.sum() == pytest.approx(2e-3)
    np.testing.assert_allclose(model.mass, 500.0 * model.volume)
    w = np.arange(1, 101, dtype=float)
    model = sim.prepare(pts, volume=2e-3, weights=w)
    np.testing.assert_allclose(model.volume, 2e-3 * w / w.sum())
    # estimate from occupancy: a filled 0.1 m cube of points is ~1e-3 m^3
    dense = blob(8000)
    assert sim.prepare(dense).volume.sum() == pytest.approx(1e-3, rel=0.35)


# --------------------------------------------------------------------------------------------------
# physics against analytic results
# --------------------------------------------------------------------------------------------------


def test_free_flight_conserves_mass_and_momentum():
    sim = make_sim(E=1e4, n_grid=24, grid_padding=1.2)
    pts = blob(400)
    model = sim.prepare(pts, volume=1e-3)
    st = sim.initial_state(model)
    rng = np.random.default_rng(1)
    v0 = torch.tensor(np.array([0.3, -0.2, 0.1]) + 0.2 * rng.normal(size=(400, 3)), dtype=torch.float32)
    m = torch.tensor(model.mass)
    p0 = (m[:, None] * v0.double()).sum(0)
    x, v, F, C = rollout(sim, model, st, v0, substeps=200, dt=1e-3)
    assert model.grid.contains(x.double().numpy()), "test scene must stay off the walls"
    p1 = (m[:, None] * v.double()).sum(0)
    assert torch.linalg.norm(p1 - p0) <= 1e-5 * torch.linalg.norm(p0)
    # the elastic body did deform (otherwise the test would be trivial)
    assert float((F - torch.eye(3)).abs().max()) > 1e-2
    # P2G puts exactly the particles' mass and momentum on the grid, before and after
    for xs, vs, Fs, Cs, p in ((st["x"], v0, st["F"], st["C"], p0), (x, v, F, C, p1)):
        gm, gp = sim.grid_totals(model, xs, vs, Fs, Cs, dt=1e-3)
        assert gm == pytest.approx(model.mass.sum(), rel=1e-5)
        assert np.linalg.norm(gp - p.numpy()) <= 1e-5 * np.linalg.norm(p.numpy())


def test_rigid_translation_keeps_pairwise_distances():
    sim = make_sim(E=1e4, n_grid=24, grid_padding=1.0)
    pts = blob(200)
    model = sim.prepare(pts, volume=1e-3)
    st = sim.initial_state(model)
    vel = torch.tensor([0.25, -0.15, 0.1])
    x, v, F, C = rollout(sim, model, st, vel.repeat(200, 1), substeps=200, dt=1e-3)
    d0 = torch.cdist(st["x"].double(), st["x"].double())
    d1 = torch.cdist(x.double(), x.double())
    size = 0.1
    assert float((d1 - d0).abs().max()) <= 1e-5 * size
    np.testing.assert_allclose(
        x.double().mean(0).numpy(), (st["x"].double().mean(0) + 0.2 * vel.double()).numpy(), atol=1e-5 * size
    )
    assert float((F - torch.eye(3)).abs().max()) < 1e-5 and float(C.abs().max()) < 1e-3


def test_free_fall_follows_half_g_t_squared():
    g = -9.81
    sim = make_sim(n_grid=16, grid_padding=0.5, gravity=[0.0, 0.0, g])
    model = sim.prepare(blob(300), volume=1e-3)
    st = sim.initial_state(model)
    dt, per_frame, frames = 1e-4, 200, 10  # t = 0.2 s; the grid follows the body between frames
    x, v, F, C = rollout(sim, model, st, torch.zeros(300, 3), substeps=per_frame, dt=dt, frames=frames)
    t = dt * per_frame * frames
    drop = float(x.double()[:, 2].mean() - st["x"].double()[:, 2].mean())
    assert drop == pytest.approx(0.5 * g * t * t, rel=1e-3)
    assert float(x.double()[:, :2].mean(0).sub(st["x"].double()[:, :2].mean(0)).abs().max()) < 1e-6


def test_stretched_bar_oscillates_with_longitudinal_wave_period():
    E, rho, L = 1e4, 1000.0, 0.4
    sim = make_sim(E=E, nu=0.3, density=rho, n_grid=48, grid_padding=0.15)
    h = L / 64  # particle spacing: 2 per cell per axis
    gx = np.arange(h / 2, L, h)
    gy = np.arange(h / 2, 0.04, h)
    rest = np.stack(np.meshgrid(gx, gy, gy, indexing="ij"), -1).reshape(-1, 3)
    stretch = 1.05
    pts = rest.copy()
    pts[:, 0] = L / 2 + stretch * (rest[:, 0] - L / 2)
    model = sim.prepare(pts, volume=L * 0.04 * 0.04)
    st = sim.initial_state(model)
    F = st["F"].clone()
    F[:, 0, 0] = stretch
    left = torch.as_tensor(rest[:, 0] < 0.1 * L)
    right = torch.as_tensor(rest[:, 0] > 0.9 * L)
    period = 2 * L / math.sqrt(E / rho)
    n_sub, dt = sim.substeps_for(model, fps=50.0)
    dt = min(dt, period / 200)
    steps_per_sample = 4
    x, v, C = st["x"], torch.zeros_like(st["x"]), st["C"]
    times, lengths = [0.0], [float(x[right, 0].mean() - x[left, 0].mean())]
    while times[-1] < 1.3 * period:
        x, v, F, C = sim.rollout(model, x, v, F, C, substeps=steps_per_sample, dt=dt)
        times.append(times[-1] + steps_per_sample * dt)
        lengths.append(float(x[right, 0].mean() - x[left, 0].mean()))
    ell = np.array(lengths) - 0.5 * (max(lengths) + min(lengths))
    t = np.array(times)
    # it recoils: shorter than at rest at some point, then long again
    assert min(lengths) < lengths[0] - 0.5 * (stretch - 1) * 0.8 * L
    # crossings of the mid-length: at T/4 (going down) and 3T/4 (going up) for the d'Alembert solution
    crossings = [
        t[i] - ell[i] * (t[i + 1] - t[i]) / (ell[i + 1] - ell[i])
        for i in range(len(ell) - 1)
        if ell[i] * ell[i + 1] < 0
    ]
    assert len(crossings) >= 2
    measured = 2.0 * (crossings[1] - crossings[0])
    assert measured == pytest.approx(period, rel=0.10)


def test_fixed_region_holds_particles():
    pts = blob(400)
    box = [-1.0, -1.0, -1.0, 0.03, 1.0, 1.0]  # the slab x < 0.03 m
    sim = make_sim(E=5e3, n_grid=20, grid_padding=0.5, fixed_box=box)
    model = sim.prepare(pts, volume=1e-3)
    st = sim.initial_state(model)
    v0 = torch.tensor([0.0, 0.0, 0.5]).repeat(400, 1)
    x, v, F, C = rollout(sim, model, st, v0, substeps=50, dt=1e-3)
    held = torch.as_tensor(pts[:, 0] < 0.01)
    free = torch.as_tensor(pts[:, 0] > 0.09)
    dz = (x - st["x"])[:, 2]
    assert float(dz[held].abs().max()) < 0.2 * float(dz[free].mean())
    assert float(dz[free].mean()) > 0.005


# --------------------------------------------------------------------------------------------------
# gradients against central finite differences
# --------------------------------------------------------------------------------------------------


def _grad_scene(checkpoint_every: int = 10, cpu_threads: int | None = None):
    sim = make_sim(E=2e3, nu=0.3, n_grid=16, checkpoint_every=checkpoint_every, cpu_threads=cpu_threads)
    rng = np.random.default_rng(0)
    pts = rng.uniform(0.0, 0.1, (300, 3))
    model = sim.prepare(pts, volume=1e-3)
    st = sim.initial_state(model)
    v0 = torch.tensor(rng.normal(0.0, 0.3, (300, 3)), dtype=torch.float32)
    part = torch.as_tensor(pts[:, 0] < 0.05)  # a "part": half of the body
    target = torch.tensor([0.06, 0.05, 0.04])
    return sim, model, st, v0, part, target


@pytest.mark.parametrize("substeps,threads", [(5, None), (100, None), (100, 2)])
def test_velocity_gradient_matches_finite_differences(substeps, threads):
    """(threads None: this small scene runs on one thread; 2: the particle chunks on two threads.)"""
    sim, model, st, v0, part, target = _grad_scene(cpu_threads=threads)
    dt = 1e-3
    assert model.wave_speed * dt / model.grid.dx < 0.3

    def loss(v):
        x, _, _, _ = sim.rollout(model, st["x"], v, st["F"], st["C"], substeps=substeps, dt=dt)
        return ((x[part].mean(0) - target) ** 2).sum()

    v = v0.clone().requires_grad_(True)
    loss(v).backward()
    grad = v.grad.double()
    rng = np.random.default_rng(substeps)
    eps = 3e-3
    checks = []
    for _ in range(2):  # random directions over all particles
        d = torch.tensor(rng.normal(size=(300, 3)), dtype=torch.float32)
        checks.append((d, float((grad * d.double()).sum())))
    for flat in torch.argsort(grad.abs().flatten(), descending=True)[:2]:  # the largest single entries
        d = torch.zeros(300, 3)
        d.view(-1)[flat] = 1.0
        checks.append((d, float(grad.view(-1)[flat])))
    with torch.no_grad():
        for d, adjoint in checks:
            fd = (float(loss(v0 + eps * d)) - float(loss(v0 - eps * d))) / (2 * eps)
            assert adjoint == pytest.approx(fd, rel=5e-2), (adjoint, fd)
            assert abs(fd) > 1e-7


@pytest.mark.parametrize("threads", [None, 2])
def test_position_F_C_gradients_match_finite_differences(threads):
    sim, model, st, v0, part, target = _grad_scene(cpu_threads=threads)
    rng = np.random.default_rng(3)
    F0 = st["F"] + torch.tensor(0.02 * rng.normal(size=(300, 3, 3)), dtype=torch.float32)
    C0 = torch.tensor(0.5 * rng.normal(size=(300, 3, 3)), dtype=torch.float32)
    x0 = st["x"]

    def loss(x, F, C):
        xo, vo, Fo, Co = sim.rollout(model, x, v0, F, C, substeps=5, dt=1e-3)
        # a loss on every output, so the chain through F and C across frames is checked too
        fo = ((Fo - torch.eye(3)) ** 2).mean()
        return ((xo[part].mean(0) - target) ** 2).sum() + 0.1 * fo + 1e-3 * (Co**2).mean() + 0.1 * (vo**2).mean()

    xs, Fs, Cs = (t.clone().requires_grad_(True) for t in (x0, F0, C0))
    loss(xs, Fs, Cs).backward()
    for which, base, grad, eps in (("x", x0, xs.grad, 1e-4), ("F", F0, Fs.grad, 3e-4), ("C", C0, Cs.grad, 3e-2)):
        d = torch.tensor(rng.normal(size=base.shape), dtype=torch.float32)
        args = {"x": x0, "F": F0, "C": C0}
        with torch.no_grad():
            plus = dict(args, **{which: base + eps * d})
            minus = dict(args, **{which: base - eps * d})
            fd = (float(loss(**plus)) - float(loss(**minus))) / (2 * eps)
        adjoint = float((grad.double() * d.double()).sum())
        assert adjoint == pytest.approx(fd, rel=5e-2), (which, adjoint, fd)


def test_checkpointing_gives_the_same_gradient():
    grads = []
    for k in (1, 7, 100):
        sim, model, st, v0, part, target = _grad_scene(checkpoint_every=k)
        v = v0.clone().requires_grad_(True)
        x, _, _, _ = sim.rollout(model, st["x"], v, st["F"], st["C"], substeps=40, dt=1e-3)
        ((x[part].mean(0) - target) ** 2).sum().backward()
        grads.append(v.grad.clone())
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-5, atol=1e-9)
    torch.testing.assert_close(grads[0], grads[2], rtol=1e-5, atol=1e-9)


def test_two_chained_rollouts_backpropagate_to_the_first_frame():
    sim, model, st, v0, part, target = _grad_scene()

    def loss(v):
        x, vv, F, C = sim.rollout(model, st["x"], v, st["F"], st["C"], substeps=10, dt=1e-3, frame_index=0)
        x, vv, F, C = sim.rollout(model, x, vv, F, C, substeps=10, dt=1e-3, frame_index=1)
        return ((x[part].mean(0) - target) ** 2).sum()

    v = v0.clone().requires_grad_(True)
    loss(v).backward()
    d = torch.tensor(np.random.default_rng(5).normal(size=(300, 3)), dtype=torch.float32)
    with torch.no_grad():
        fd = (float(loss(v0 + 3e-3 * d)) - float(loss(v0 - 3e-3 * d))) / 6e-3
    assert float((v.grad.double() * d.double()).sum()) == pytest.approx(fd, rel=5e-2)


# --------------------------------------------------------------------------------------------------
# both cores: particle chunks on several threads
# --------------------------------------------------------------------------------------------------


def _threaded_run(threads: int, *, substeps: int = 30):
    """Forward + backward of a 1000-particle blob on ``threads`` threads: (x, F, dL/dv0, dL/dF0, sim)."""
    sim = make_sim(E=2e3, nu=0.3, n_grid=16, cpu_threads=threads, checkpoint_every=7)
    rng = np.random.default_rng(4)
    pts = rng.uniform(0.0, 0.1, (1001, 3))  # odd: the chunks differ in size
    model = sim.prepare(pts, volume=1e-3)
    st = sim.initial_state(model)
    v = torch.tensor(rng.normal(0.0, 0.3, (1001, 3)), dtype=torch.float32).requires_grad_(True)
    F = (st["F"] + torch.tensor(0.02 * rng.normal(size=(1001, 3, 3)), dtype=torch.float32)).requires_grad_(True)
    x, vo, Fo, Co = sim.rollout(model, st["x"], v, F, st["C"], substeps=substeps, dt=1e-3)
    part = torch.as_tensor(pts[:, 0] < 0.05)
    loss = (x[part].mean(0) ** 2).sum() + ((Fo - torch.eye(3)) ** 2).mean() + 0.1 * (vo**2).mean() + (Co**2).mean()
    loss.backward()
    return x.detach(), Fo.detach(), v.grad, F.grad, sim


def test_threads_match_one_thread_and_are_deterministic():
    x1, F1, gv1, gF1, sim1 = _threaded_run(1)
    assert sim1.workspace.threads == 1
    for threads in (2, 3):
        x, F, gv, gF, sim = _threaded_run(threads)
        ws = sim.workspace
        assert ws.threads == threads and ws.grids.shape[0] == threads
        assert sorted(hi - lo for lo, hi in ws.bounds) == ([500, 501] if threads == 2 else [333, 334, 334])
        # the node sums are added in another order: equal up to float rounding, not bit for bit
        torch.testing.assert_close(x, x1, rtol=0, atol=1e-6)
        torch.testing.assert_close(F, F1, rtol=0, atol=1e-5)
        torch.testing.assert_close(gv, gv1, rtol=1e-3, atol=1e-6 * float(gv1.abs().max()))
        torch.testing.assert_close(gF, gF1, rtol=1e-3, atol=1e-6 * float(gF1.abs().max()))
    # and the threaded result does not depend on which thread finishes first
    x2, F2, gv2, gF2, _ = _threaded_run(2)
    x2b, F2b, gv2b, gF2b, _ = _threaded_run(2)
    assert torch.equal(x2, x2b) and torch.equal(F2, F2b) and torch.equal(gv2, gv2b) and torch.equal(gF2, gF2b)


def test_particles_leaving_the_grid_in_the_second_thread_raise_diverged():
    sim = make_sim(n_grid=16, cpu_threads=2)
    pts = blob(400)
    model = sim.prepare(pts, volume=1e-3)
    st = sim.initial_state(model)
    v0 = torch.zeros(400, 3)
    v0[torch.as_tensor(pts[:, 0] > 0.09), 0] = 200.0  # the highest-x cells: the last chunk after sorting
    with pytest.raises(SimulationDiverged, match=r"frame 2, substep \d of 10: particles left the grid"):
        sim.rollout(model, st["x"], v0, st["F"], st["C"], substeps=10, dt=1e-3, frame_index=2, check_cfl=False)
    assert sim.workspace.threads == 2
    assert int(sim.workspace.status_of[0].numpy()[0]) == 2147483647 and int(sim.workspace.status_of[1].numpy()[0]) < 10


def test_thread_count_rules():
    sim = make_sim()
    cores = len(os.sched_getaffinity(0))
    assert sim.threads_for(100) == 1  # tiny scenes stay on one thread
    assert sim.threads_for(50_000) == min(cores, 50_000 // 8192)
    assert sim.threads_for(9_400) == 1  # the default pipeline's control points: one thread
    assert make_sim(cpu_threads=3).threads_for(100) == 3 and make_sim(cpu_threads=3).threads_for(2) == 2
    sim.wp_device = "cuda:0"  # never split on CUDA
    assert sim.threads_for(50_000) == 1
    with pytest.raises(ConfigError, match=r"sim.cpu_threads=0"):
        make_sim(cpu_threads=0)


# --------------------------------------------------------------------------------------------------
# stability and divergence guards
# --------------------------------------------------------------------------------------------------


def _stiff_scene(auto: bool):
    sim = make_sim(E=1e5, nu=0.3, n_grid=16, auto_substep=auto, frame_time=0.02, substeps=4)
    model = sim.prepare(blob(300), volume=1e-3)
    return sim, model


def test_dt_ten_times_over_cfl_raises_without_auto_substep():
    sim, model = _stiff_scene(auto=False)
    dt_max = sim.max_stable_dt(model)
    st = sim.initial_state(model)
    with pytest.raises(SimulationUnstable, match=r"CFL bound .* use dt <="):
        sim.rollout(model, st["x"], st["v"], st["F"], st["C"], substeps=5, dt=10 * dt_max)
    sim.config.frame_time = 4 * 10 * dt_max  # 4 substeps of 10x the bound
    with pytest.raises(SimulationUnstable, match="sim.auto_substep=true"):
        sim.substeps_for(model)


def test_dt_ten_times_over_cfl_runs_stably_with_auto_substep():
    sim, model = _stiff_scene(auto=True)
    dt_max = sim.max_stable_dt(model)
    st = sim.initial_state(model)
    rng = np.random.default_rng(2)
    v0 = torch.tensor(0.3 * rng.normal(size=(300, 3)), dtype=torch.float32)
    m = torch.tensor(model.mass)
    ke0 = float(0.5 * (m * (v0.double() ** 2).sum(1)).sum())
    x, v, F, C = rollout(sim, model, st, v0, substeps=5, dt=10 * dt_max, frames=3)
    assert torch.isfinite(x).all() and torch.isfinite(F).all()
    ke = float(0.5 * (m * (v.double() ** 2).sum(1)).sum())
    assert ke <= 1.01 * ke0  # started undeformed: kinetic energy cannot exceed the initial energy
    sim.config.frame_time = 4 * 10 * dt_max
    n, dt = sim.substeps_for(model)
    assert n >= 40 and dt <= dt_max


def test_blow_up_is_reported_not_crashed():
    sim, model = _stiff_scene(auto=False)
    dt_max = sim.max_stable_dt(model)
    st = sim.initial_state(model)
    v0 = torch.tensor(0.3 * np.random.default_rng(2).normal(size=(300, 3)), dtype=torch.float32)
    with pytest.raises(SimulationDiverged, match=r"frame 0, substep \d+ .*largest finite speed"):
        sim.rollout(model, st["x"], v0, st["F"], st["C"], substeps=200, dt=10 * dt_max, check_cfl=False)


def test_particles_leaving_the_grid_raise_diverged():
    sim = make_sim(n_grid=16)
    model = sim.prepare(blob(200), volume=1e-3)
    st = sim.initial_state(model)
    v0 = torch.tensor([200.0, 0.0, 0.0]).repeat(200, 1)  # ~10 cells per substep: through the walls
    with pytest.raises(SimulationDiverged, match=r"frame 3, substep \d of 10: particles left the grid") as err:
        sim.rollout(model, st["x"], v0, st["F"], st["C"], substeps=10, dt=1e-3, frame_index=3, check_cfl=False)
    assert "lower dt" in str(err.value)
    # the simulator is still usable afterwards
    x, *_ = sim.rollout(model, st["x"], torch.zeros(200, 3), st["F"], st["C"], substeps=2, dt=1e-3)
    assert torch.isfinite(x).all()


def test_nonfinite_input_is_refused():
    sim = make_sim(n_grid=16)
    model = sim.prepare(blob(50), volume=1e-3)
    st = sim.initial_state(model)
    v = torch.zeros(50, 3)
    v[3, 1] = float("nan")
    with pytest.raises(SimulationDiverged, match="NaN"):
        sim.rollout(model, st["x"], v, st["F"], st["C"], substeps=2, dt=1e-3)


# --------------------------------------------------------------------------------------------------
# the stress kernel and its hand-written adjoint
# --------------------------------------------------------------------------------------------------


def _random_F(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = np.eye(3)[None] + 0.1 * rng.normal(size=(n, 3, 3))  # the Newton path
    large = np.eye(3)[None] + 0.6 * rng.normal(size=(n, 3, 3))  # many take the SVD fallback
    inverted = small[: n // 4] * np.array([1.0, 1.0, -1.0])[None, None, :]  # det F < 0
    return np.concatenate([small, large, inverted])


def test_kirchhoff_stress_matches_svd_formula():
    import warp as wp

    from sync4d.sim.mpm_warp import kernels as K

    F = _random_F(400, 0)
    mu, lam = physics.lame_parameters(1e4, 0.3)
    U, S, Vt = np.linalg.svd(F)
    # proper rotation: flip the smallest singular direction when det(U V^T) < 0 (signed SVD)
    flip = np.linalg.det(U @ Vt) < 0
    U[flip, :, 2] *= -1
    R = U @ Vt
    J = np.linalg.det(F)
    expected = 2 * mu * (F - R) @ F.transpose(0, 2, 1) + (lam * (J - 1) * J)[:, None, None] * np.eye(3)
    Fw = wp.array(F.astype(np.float32), dtype=wp.mat33, device="cpu")
    tau = wp.empty(len(F), dtype=wp.mat33, device="cpu")
    wp.launch(K.kirchhoff_stress, dim=len(F), inputs=[Fw, mu, lam], outputs=[tau], device="cpu")
    got = tau.numpy()
    scale = np.abs(expected).max(axis=(1, 2)) + mu
    # nearly degenerate singular values make R ill-defined; compare where the SVD is well separated
    sep = np.minimum(np.abs(S[:, 0] - S[:, 1]), np.abs(S[:, 1] + np.where(flip, -1, 1) * S[:, 2]))
    good = sep > 1e-2
    assert good.mean() > 0.9
    err = np.abs(got - expected).max(axis=(1, 2)) / scale
    # the first 400 are moderate deformations (Newton polar): float32 accuracy
    assert err[:400].max() < 1e-5
    # large and inverted ones fall back to wp.svd3, whose fixed Jacobi sweeps are good to ~1e-3 there
    assert err[good].max() < 2e-3 and np.median(err[good]) < 1e-5


def test_hand_written_stress_adjoint_matches_warp_autodiff():
    import warp as wp

    from sync4d.sim.mpm_warp import kernels as K

    F = _random_F(400, 1)
    F = F[np.linalg.det(F) > 0.05]  # away from the inversion kink of the SVD branch
    mu, lam = physics.lame_parameters(1e4, 0.3)
    G = np.random.default_rng(2).normal(size=F.shape)
    Fw = wp.array(F.astype(np.float32), dtype=wp.mat33, device="cpu")
    Gw = wp.array(G.astype(np.float32), dtype=wp.mat33, device="cpu")
    hand = wp.empty(len(F), dtype=wp.mat33, device="cpu")
    wp.launch(K.kirchhoff_stress_adjoint, dim=len(F), inputs=[Fw, mu, lam, Gw], outputs=[hand], device="cpu")
    auto = wp.zeros(len(F), dtype=wp.mat33, device="cpu")
    tau = wp.empty(len(F), dtype=wp.mat33, device="cpu")
    wp.launch(
        K.kirchhoff_stress, dim=len(F), inputs=[Fw, mu, lam], outputs=[tau],
        adj_inputs=[auto, None, None], adj_outputs=[Gw], adjoint=True, device="cpu",
    )  # fmt: skip
    h, a = hand.numpy(), auto.numpy()
    rel = np.abs(h - a).max(axis=(1, 2)) / (np.abs(a).max(axis=(1, 2)) + 1e-3 * mu)
    # Warp differentiates the unrolled Newton iterations / the SVD; the hand adjoint is the exact polar
    # derivative: they agree closely where Newton converged (most), loosely where the SVD took over.
    assert np.median(rel) < 1e-4
    assert np.quantile(rel, 0.9) < 1e-2


def _bspline_1d(f: float) -> np.ndarray:
    """Quadratic B-spline weights of the three nodes base, base+1, base+2 for offset f in cells from base."""
    return np.array([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2])


def _one_particle_grid(F: np.ndarray, *, scale: float = 1.0):
    """Grid (nx, ny, nz, 4) after one P2G of a single resting particle with deformation gradient F."""
    import dataclasses

    import warp as wp

    from sync4d.sim.mpm_warp import kernels as K
    from sync4d.sim.mpm_warp.solver import Launch

    sim = make_sim(n_grid=16)
    model = sim.prepare(np.array([[0.0, 0.0, 0.0], [0.1, 0.1, 0.1]]))
    xp = np.array([[0.0437, 0.0512, 0.0581]])  # off-centre in its cell: asymmetric weights
    model = dataclasses.replace(
        model, rest_points=xp, mass=np.array([0.7]), volume=np.array([2e-4]), mu=model.mu * scale, lam=model.lam * scale
    )
    dt = 1e-3
    launch = Launch(
        model=model,
        ws=sim.workspace_for(1, model.grid.dims),
        mass=wp.array(np.array([0.7], np.float32), dtype=float, device="cpu"),
        volume=wp.array(np.array([2e-4], np.float32), dtype=float, device="cpu"),
        dt=dt,
        mass_eps=1e-12,
    )
    t = torch.as_tensor
    launch.ws.ping.load(
        t(xp, dtype=torch.float32),
        torch.zeros(1, 3),
        t(F[None], dtype=torch.float32),
        torch.zeros(1, 3, 3),
    )
    launch.ws.grid.zero_()
    i, o = launch.p2g_args(launch.ws.ping, 0)
    wp.launch(K.p2g, dim=1, inputs=i, outputs=o, device="cpu")
    return launch.ws.grid.numpy().astype(np.float64), model, xp[0], dt


def _axis_rotation(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K_ = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K_ + (1 - np.cos(angle)) * K_ @ K_


def test_p2g_momentum_of_a_large_deformation_matches_the_analytic_stress():
    """One particle at rest with F = R diag(1.5, 0.8, 1.1): node momenta are -w_i dt V (4/dx^2) tau (x_i - x_p)
    with tau = 2 mu (F - R) F^T + lam (J - 1) J I, written out here from the definition (drop F^T and this fails)."""
    R = _axis_rotation([0.3, -0.5, 0.8], 0.7)
    F = R @ np.diag([1.5, 0.8, 1.1])
    grid, model, xp, dt = _one_particle_grid(F)
    J = np.linalg.det(F)
    tau = 2 * model.mu * (F - R) @ F.T + model.lam * (J - 1) * J * np.eye(3)
    g = model.grid
    gp = (xp - g.origin) / g.dx
    base = np.floor(gp - 0.5).astype(int)
    fx = gp - base
    w = [_bspline_1d(f) for f in fx]
    expected = np.zeros_like(grid)
    k = dt * 2e-4 * 4.0 / g.dx**2
    for a in range(3):
        for b in range(3):
            for c in range(3):
                wi = w[0][a] * w[1][b] * w[2][c]
                node = base + (a, b, c)
                rel = g.origin + node * g.dx - xp
                expected[tuple(node)][:3] = -wi * k * tau @ rel
                expected[tuple(node)][3] = wi * 0.7
    scale = np.abs(expected[..., :3]).max()
    assert scale > 0
    np.testing.assert_allclose(grid[..., :3], expected[..., :3], atol=2e-5 * scale)
    np.testing.assert_allclose(grid[..., 3], expected[..., 3], atol=1e-6)
    # the stress really is what moves the momentum: x4 gives four times the node momenta
    grid4, *_ = _one_particle_grid(F, scale=4.0)
    np.testing.assert_allclose(grid4[..., :3], 4 * expected[..., :3], atol=8e-5 * scale)
