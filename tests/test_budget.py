"""budget=auto: sizes follow the scene (particle count, density per cell, CFL)."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d.transfer.budget import choose_budget, choose_control_grid, grid_for_cells
from sync4d.transfer.motion import driving_motion
from sync4d.scenes.laptop import laptop_reference
from sync4d.sim import physics


def test_control_grid_reaches_the_particle_target_and_is_skipped_for_small_targets():
    rng = np.random.default_rng(0)
    means = rng.random((20000, 3))
    grid, count = choose_control_grid(means, 1500)
    assert grid is not None and count >= 1500
    # One step coarser would have given too few points.
    from sync4d.sim.control import make_control_points

    assert len(make_control_points(means, grid - 1)[0]) < 1500
    assert choose_control_grid(means[:1000], 1500) == (None, 1000)


def test_substeps_satisfy_the_cfl_bound_and_grow_with_stiffness():
    ref = laptop_reference(6)
    motion = driving_motion(ref, target_points=ref.rest_vertices, target_faces=ref.rest_faces, num_frames=6)
    means = ref.rest_vertices
    kw = dict(nu=0.3, density=1000.0, frame_time=0.02, padding=0.25, wall=3, cfl_safety=0.3)
    soft = choose_budget(means, motion, E=1e4, **kw)
    stiff = choose_budget(means, motion, E=1e6, **kw)
    dx = physics.fit_grid(means, n_grid=soft.n_grid, padding=0.25, wall=3).dx
    assert 0.02 / soft.substeps <= physics.cfl_dt(dx, 1e4, 0.3, 1000.0, v_max=soft.v_max, safety=0.3) + 1e-12
    assert stiff.substeps > 5 * soft.substeps
    assert soft.v_max > 0


def test_grid_for_cells_gives_that_many_cells_over_the_longest_extent():
    rng = np.random.default_rng(2)
    points = rng.random((500, 3)) * [0.34, 0.05, 0.24]
    n = grid_for_cells(12, padding=0.25, wall=3)
    spec = physics.fit_grid(points, n_grid=n, padding=0.25, wall=3)
    assert 12.0 <= np.ptp(points, axis=0).max() / spec.dx < 13.0


def _laptop_scene():
    from sync4d.scenes.targets import LaptopTarget

    ref = laptop_reference(6)
    target = LaptopTarget(LaptopTarget.Config(num_surface=600, num_interior=200)).load()
    motion = driving_motion(ref, target_points=ref.rest_vertices, target_faces=ref.rest_faces, num_frames=6)
    return target, motion


def test_stiff_material_is_refused_before_simulating_naming_E_and_the_fix():
    import pytest

    from sync4d.errors import ConfigError
    from sync4d.sim.mpm_warp import MPMWarp
    from sync4d.transfer import TransferConfig
    from sync4d.transfer.budget import check_run_cost

    target, motion = _laptop_scene()
    with pytest.raises(ConfigError, match=r"^sim\.E=1e\+12 Pa: .* substeps per frame exceed sim\.max_substeps=2000 .*"
                       r"lower sim\.E \(about .* Pa or less fits\)") as info:
        check_run_cost(MPMWarp.Config(E=1e12), TransferConfig(), True, target, motion, frames=24)
    assert "\n" not in str(info.value)


def test_cost_estimate_follows_the_cfl_model_and_scales_with_stiffness():
    from sync4d.transfer.budget import SimSettings, estimate_cost
    from sync4d.sim.mpm_warp import MPMWarp

    target, motion = _laptop_scene()
    cfg = MPMWarp.Config()
    soft = estimate_cost(target.means, motion, SimSettings.of(cfg, None), frames=24, iterations=12)
    stiff = estimate_cost(target.means, motion, SimSettings.of(MPMWarp.Config(E=1e6), None), frames=24,
                          iterations=12)
    frame_time = 1.0 / motion.fps
    # the substep meets the CFL bound used by the simulator (with the transfer's speed headroom)
    assert soft.dt <= physics.cfl_dt(soft.dx, cfg.E, cfg.nu, cfg.density, v_max=soft.v_max, safety=cfg.cfl_safety)
    assert soft.substeps * soft.dt == pytest_approx(frame_time)
    assert stiff.cause == "E" and stiff.substeps > 5 * soft.substeps
    assert stiff.seconds_per_frame > 1.5 * soft.seconds_per_frame and soft.particles == target.num
    assert soft.peak_memory_mb > 0 and soft.total_seconds == soft.seconds_per_frame * 23


def pytest_approx(value):
    import pytest

    return pytest.approx(value, rel=1e-9)


@pytest.mark.slow
def test_train_refuses_a_stiff_material_before_simulating(tmp_path):
    from _runs import run_train

    proc = run_train(tmp_path / "run", "reference=laptop", "recon=ground_truth", "target=laptop", "sim.E=1e12",
                     "render_video=false", "logger=none")
    assert proc.returncode == 2
    assert "sim.E=1e+12 Pa" in proc.stderr and "exceed sim.max_substeps" in proc.stderr
    assert not (tmp_path / "run" / "metrics.json").exists()


def test_estimated_memory_of_a_control_point_run_does_not_grow_with_frames_times_gaussians():
    """With control points the run holds per-point frames: 4x the frames adds megabytes, not N x T."""
    from sync4d.transfer.budget import SimSettings, estimate_cost
    from sync4d.sim.mpm_warp import MPMWarp

    _, motion = _laptop_scene()
    means = np.random.default_rng(0).random((200_000, 3)) * 0.3
    settings = SimSettings.of(MPMWarp.Config(), 20)
    short = estimate_cost(means, motion, settings, frames=24, iterations=0)
    long = estimate_cost(means, motion, settings, frames=96, iterations=0)
    assert short.particles <= 20**3
    assert long.peak_memory_mb - short.peak_memory_mb < 72 * short.particles * 2 * 96 / 2**20 + 1.0
    # every Gaussian simulated: the frames are per Gaussian and the estimate grows with them
    every = SimSettings.of(MPMWarp.Config(), None)
    few = means[:20_000]
    grow = estimate_cost(few, motion, every, frames=96, iterations=0).peak_memory_mb - \
        estimate_cost(few, motion, every, frames=24, iterations=0).peak_memory_mb
    assert grow > 72 * 20_000 * 96 / 2**20
