"""budget=auto: sizes follow the scene (particle count, density per cell, CFL)."""

from __future__ import annotations

import numpy as np

from sync4d.budget import choose_budget, choose_control_grid, choose_grid, occupied_cells
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


def test_grid_is_the_finest_with_enough_particles_per_cell():
    rng = np.random.default_rng(1)
    points = rng.random((4000, 3)) * [0.3, 0.1, 0.2]
    n, dx, ppc = choose_grid(points, padding=0.25, wall=3, particles_per_cell=8.0)
    assert ppc >= 8.0
    finer = [g for g in (16, 20, 24, 32, 40, 48, 64) if g > n]
    if finer:
        spec = physics.fit_grid(points, n_grid=finer[0], padding=0.25, wall=3)
        assert len(points) / occupied_cells(points, spec.dx) < 8.0


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
