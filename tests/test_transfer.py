"""Frame-pair transfer on a tiny laptop self-transfer: the loss falls during each frame's optimisation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from sync4d.transfer.motion import driving_motion
from sync4d.run.writer import compute_metrics
from sync4d.scenes.laptop import laptop_mesh, laptop_reference
from sync4d.io.mesh import mesh_to_gaussians
from sync4d.sim.lbs import LinearBlendSkinning
from sync4d.sim.mpm_warp import MPMWarp
from sync4d.registry import component
from sync4d.transfer import PAPER, TransferConfig, run_transfer
from sync4d.transfer.loss import anchor_weights, initial_velocity
from sync4d.transfer.particles import make_particles
from sync4d.types import PartMap


def transfer(sim, scene, *, velocity=None, options=None, num_frames=3, on_frame=None):
    """The transfer stage on ``scene`` (reference, target, part map, motion) through ``sim``."""
    _, target, part_map, motion = scene
    make_field = component("velocity", velocity or {"type": "none"}).build
    return run_transfer(sim, make_field, options or TransferConfig(), target, part_map, motion,
                        num_frames=num_frames, on_frame=on_frame)


@pytest.fixture(scope="module")
def tiny_scene():
    ref = laptop_reference(4, subdivisions=1, rest_angle_deg=110, min_angle_deg=60, period_frames=8)
    v, f, _ = laptop_mesh(subdivisions=1)
    target = mesh_to_gaussians(v, f, num_surface=250, num_interior=120, seed=0)
    _, nearest = cKDTree(ref.rest_vertices).query(target.means)
    part_map = PartMap(ref.part_labels(), ref.part_labels()[nearest], np.ones(target.num), 2)
    motion = driving_motion(ref, target_points=v, target_faces=f, num_frames=3)
    return ref, target, part_map, motion


def test_loss_decreases_in_every_frame(tiny_scene):
    ref, target, part_map, motion = tiny_scene
    # The paper's own setting: one velocity per part, L1 on part centroids, relative targets, launched once per
    # frame (a held drive would meet the centroids by itself and leave the field nothing to learn).
    sim = MPMWarp(MPMWarp.Config(n_grid=16, frame_time=0.01, substeps=4, drive="launch"), device="cpu")
    stats = []
    options = dataclasses.replace(PAPER, iterations=15, lr=0.5, patience=15)
    transfer(sim, tiny_scene, velocity={"type": "per_part", "velocity_scale": 0.3}, options=options,
             on_frame=lambda t, x, F, s, checkpoint=None, control=None: stats.append(s))
    assert len(stats) == 3
    for s in stats[1:]:
        assert s["loss/displacement"] < 0.5 * s["loss/initial"], s


def test_untrained_rigid_init_follows_the_hinge(tiny_scene):
    """With the bone's rigid velocity field and no training the lid still tracks the reference closely."""
    ref, target, part_map, motion = tiny_scene
    sim = MPMWarp(MPMWarp.Config(n_grid=16, frame_time=0.01, substeps=4), device="cpu")  # the default transfer (init=pose)
    traj = transfer(sim, tiny_scene)
    m = compute_metrics(traj, target, part_map, motion, ref, self_transfer=True, frame_seconds=[0.0] * 3)
    assert m["pose_error_max_pct"] < 2.0


def test_lbs_self_transfer_is_exact_with_hard_weights(tiny_scene):
    ref, target, part_map, motion = tiny_scene
    # every Gaussian skinned (no control points): point-wise deformation proper
    traj = transfer(LinearBlendSkinning(LinearBlendSkinning.Config(neighbours=1)), tiny_scene,
                    options=TransferConfig(control_grid=None))
    m = compute_metrics(traj, target, part_map, motion, ref, self_transfer=True, frame_seconds=[0.0] * 3)
    assert m["pose_error_pct"] < 1e-9 and m["rigidity_residual_pct"] < 1e-9


def test_initial_velocity_of_a_rigid_step_moves_points_onto_it():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(20, 3))
    part = np.zeros(20, dtype=int)
    step = np.eye(4)
    step[:3, 3] = [0.1, 0.0, -0.2]
    v, C = initial_velocity(x, part, step[None], np.array([[0.1, 0.0, -0.2]]), 0.5, "rigid")
    np.testing.assert_allclose(x + 0.5 * v, x + step[:3, 3])
    np.testing.assert_allclose(C, 0.0)
    v2, _ = initial_velocity(x, part, step[None], np.array([[0.1, 0.0, -0.2]]), 0.5, "centroid")
    np.testing.assert_allclose(v2, v)


def test_anchors_are_affine_combinations(tiny_scene):
    _, target, part_map, _ = tiny_scene
    particles = make_particles(target, part_map, control_grid=6)
    assert np.all(np.bincount(particles.gaussian_to_point) == particles.counts)
    # A control point never mixes parts.
    assert np.all(particles.part[particles.gaussian_to_point] == part_map.tgt_part)
    w = anchor_weights(particles.points, particles.part, 2, "anchors")
    for rows in w:
        assert rows.shape[0] == 7
        np.testing.assert_allclose(rows.sum(axis=1), 1.0)


# Tolerances of the reported metrics in the mutation tests: a change larger than these is a real change.
POSE_TOL_PCT = 0.1      # pose_error_pct, % of the bounding-box diagonal
STRAIN_TOL_PCT = 1.0    # strain_p99_max_pct, percentage points


def _run_mutated(tiny_scene, scale: float = 1.0, drive: str = "complementary", frames: int = 8) -> dict:
    """The default MPM transfer over ``frames`` frames with the stress multiplied by ``scale`` (test-only: mu and
    lam scaled on the model) and the drive ``drive``."""
    import dataclasses

    ref, target, part_map, _ = tiny_scene
    v, f, _ = laptop_mesh(subdivisions=1)
    motion = driving_motion(ref, target_points=v, target_faces=f, num_frames=frames)
    sim = MPMWarp(MPMWarp.Config(n_grid=16, drive=drive), device="cpu")  # type: ignore[arg-type]
    prepare = sim.prepare

    def scaled(*args, **kwargs):
        m = prepare(*args, **kwargs)
        # E (which sets the CFL bound) follows a stiffer material; a stress-free one keeps the same dt
        return dataclasses.replace(m, mu=m.mu * scale, lam=m.lam * scale, E=m.E * max(scale, 1.0))

    sim.prepare = scaled  # type: ignore[method-assign]
    traj = transfer(sim, (ref, target, part_map, motion), options=TransferConfig(control_grid=12), num_frames=frames)
    return compute_metrics(traj, target, part_map, motion, ref, self_transfer=True, frame_seconds=[0.0] * frames)


def test_stress_and_drive_mutations_move_reported_metrics(tiny_scene):
    """Stress x0 lets the shape strain and tear (integrity breaks; the drive alone holds only each part's rigid
    motion); without the held drive (``sim.drive=launch``) the parts lag their drive (fidelity drops)."""
    base = _run_mutated(tiny_scene)
    off = _run_mutated(tiny_scene, scale=0.0)
    launched = _run_mutated(tiny_scene, drive="launch")
    assert off["strain_p99_max_pct"] > base["strain_p99_max_pct"] + 10 * STRAIN_TOL_PCT, (off, base)
    assert off["torn_pairs_pct"] > 3 * base["torn_pairs_pct"], (off, base)
    assert launched["follow_rotation_deg"] > max(3 * base["follow_rotation_deg"], base["follow_rotation_deg"] + 0.5)
