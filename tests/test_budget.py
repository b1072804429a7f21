"""budget=auto: sizes follow the scene (particle count, density per cell, CFL)."""

from __future__ import annotations

import numpy as np

from sync4d.budget import choose_budget, choose_control_grid, grid_for_cells
from sync4d.motion import driving_motion
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
