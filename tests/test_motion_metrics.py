"""Coverage ratio, driving motion, metrics and velocity fields: pure functions against known answers."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from sync4d.run import metrics as M
from sync4d.transfer.motion import coverage, driving_motion, frame_indices
from sync4d.scenes.laptop import laptop_reference, lid_angles_of
from sync4d.types import Reference
from sync4d.velocity.fields import NoField, PerPartField, TriplaneField, total_variation


def scaled_reference(ref: Reference, k: float) -> Reference:
    """The same reference uniformly scaled by k about the origin (bones, motion and all)."""
    S = np.diag([k, k, k, 1.0])
    conj = S @ ref.bone_transforms @ np.linalg.inv(S)
    return Reference(
        rest_vertices=ref.rest_vertices * k, rest_faces=ref.rest_faces, bone_centers=ref.bone_centers * k,
        bone_covariances=ref.bone_covariances * k * k, skinning=ref.skinning, bone_transforms=conj,
        global_transforms=ref.global_transforms, fps=ref.fps,
    )


def test_coverage_is_rotation_invariant_and_scales_exactly():
    mesh = trimesh.creation.box(extents=[0.3, 0.1, 0.2]).subdivide()
    rot = trimesh.transformations.random_rotation_matrix(seed=0)[:3, :3]
    s = coverage(mesh.vertices, mesh.faces)
    assert coverage(mesh.vertices @ rot.T + 5.0, mesh.faces) == pytest.approx(s, rel=1e-9)
    assert coverage(2.5 * mesh.vertices, mesh.faces) == pytest.approx(2.5 * s, rel=1e-12)
    # Tessellation-independent: a finer mesh of the same box has the same coverage (sampling noise only).
    finer = mesh.subdivide().subdivide()
    assert coverage(finer.vertices, finer.faces) == pytest.approx(s, rel=0.02)


def test_scaled_copy_of_reference_gets_exactly_scaled_motion():
    ref = laptop_reference(8)
    k = 1.7
    motion = driving_motion(ref, target_points=k * ref.rest_vertices, target_faces=ref.rest_faces, num_frames=8)
    assert motion.coverage_ratio == pytest.approx(k, rel=1e-12)
    expected = k * np.diff(ref.bone_centers_at(), axis=0)
    np.testing.assert_allclose(motion.part_displacements, expected, atol=1e-12)
    # Same answer when the reference itself is the scaled copy (ratio 1, same displacements).
    big = scaled_reference(ref, k)
    again = driving_motion(big, target_points=big.rest_vertices, target_faces=big.rest_faces, num_frames=8)
    np.testing.assert_allclose(again.part_displacements, expected, atol=1e-12)


def test_looping_uses_the_motion_step_across_the_seam():
    ref = laptop_reference(24, period_frames=24)
    motion = driving_motion(ref, target_points=ref.rest_vertices, target_faces=ref.rest_faces, num_frames=50)
    assert motion.num_frames == 50
    np.testing.assert_array_equal(frame_indices(24, 50, loop=True)[[0, 23, 24, 49]], [0, 23, 0, 1])
    # The seam step (23 -> 24 = 0) equals b_0 - b_23, not a jump.
    centers = ref.bone_centers_at()
    np.testing.assert_allclose(motion.part_displacements[23], centers[0] - centers[23], atol=1e-12)


def test_laptop_reference_follows_its_schedule():
    ref = laptop_reference(24, rest_angle_deg=110, min_angle_deg=40, period_frames=24)
    rel = lid_angles_of(ref)
    assert rel[0] == pytest.approx(0.0, abs=1e-9)
    assert rel.min() == pytest.approx(-70.0, abs=1e-6)
    # The lid's vertices stay at a fixed distance from the hinge line (rigid rotation about it).
    lid = ref.part_labels() == 1
    pivot = np.array([0.0, 0.02, -0.12])
    d0 = np.linalg.norm((ref.rest_vertices[lid] - pivot)[:, 1:], axis=1)
    d5 = np.linalg.norm((ref.posed_vertices(5)[lid] - pivot)[:, 1:], axis=1)
    np.testing.assert_allclose(d0, d5, atol=1e-12)


def test_displacement_error_and_drift():
    x0 = np.array([[0.0, 0, 0], [1, 0, 0], [5, 0, 0], [6, 0, 0]])
    parts = np.array([0, 0, 1, 1])
    x1 = x0 + np.array([[0.1, 0, 0], [0.1, 0, 0], [0, 0.2, 0], [0, 0.2, 0]])
    target = np.array([[0.1, 0, 0], [0, 0.1, 0]])
    # part 0 exact, part 1 off by 0.1 -> mean 0.05 over a diagonal of 6 -> 0.8333 %
    assert M.displacement_error(x0, x1, parts, target, 6.0) == pytest.approx(0.05 / 6 * 100)
    assert M.drift(x1, x0, parts, target, 6.0) == pytest.approx(0.05 / 6 * 100)


def test_procrustes_residual_is_zero_for_rigid_motion_and_positive_for_shear():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3))
    rot = trimesh.transformations.random_rotation_matrix(seed=1)[:3, :3]
    assert M.procrustes_residual(pts, pts @ rot.T + 3) < 1e-12
    shear = pts.copy()
    shear[:, 0] += 0.5 * pts[:, 1]
    assert M.procrustes_residual(pts, shear) > 0.1


def test_jitter_ratio_is_one_for_the_reference_itself_and_grows_with_noise():
    t = np.linspace(0, 1, 20)[:, None, None]
    seq = np.concatenate([np.sin(3 * t), t**2, 0 * t], axis=2) * np.ones((1, 10, 1))
    assert M.jitter_ratio(seq, seq, 1.0) == pytest.approx(1.0)
    noisy = seq + np.random.default_rng(0).normal(scale=0.01, size=seq.shape)
    assert M.jitter_ratio(noisy, seq, 1.0) > 2.0


def test_velocity_fields_start_at_zero_and_train():
    bounds = (np.zeros(3), np.ones(3))
    x = torch.rand(64, 3)
    part = torch.randint(0, 2, (64,))
    tri = TriplaneField(TriplaneField.Config(resolution=8, features=4, hidden=16), num_parts=2, bounds=bounds)
    assert torch.count_nonzero(tri(x, part)) == 0
    target = torch.randn(64, 3) * 0.1
    opt = torch.optim.Adam(tri.parameters(), lr=1e-2)
    first = None
    for _ in range(100):
        opt.zero_grad()
        loss = (tri(x, part) - target).abs().mean()
        loss.backward()
        opt.step()
        first = first if first is not None else float(loss)
    assert float(loss) < 0.7 * first
    per = PerPartField(PerPartField.Config(), num_parts=2, bounds=bounds)
    assert per(x, part).shape == (64, 3) and per.trainable
    none = NoField(NoField.Config(alpha=3.0), num_parts=2, bounds=bounds)
    assert not none.trainable and none.velocity_scale == 3.0


def test_total_variation_matches_its_definition():
    planes = torch.zeros(3, 1, 3, 3)
    planes[0, 0, 1, 1] = 2.0  # one spike: 4 neighbours differ by 2 -> 4 * 4 = 16
    assert float(total_variation(planes)) == pytest.approx(16.0)


def test_recentred_parts_keep_rotation_and_move_centroid_by_bone_displacement():
    from sync4d.transfer.motion import recentre_on_parts
    from sync4d.scenes.laptop import rigid, rotation_x

    T = np.stack([np.eye(4), rigid(rotation_x(0.7), np.array([0.0, 0.02, -0.12]))])[None]  # (1, 2, 4, 4)
    bone_centers = np.array([[0.0, 0.01, 0.0], [0.0, 0.13, -0.17]])
    centroids = np.array([[0.05, 0.0, 0.01], [0.02, 0.1, -0.15]])
    A = recentre_on_parts(T, bone_centers, centroids)
    np.testing.assert_allclose(A[..., :3, :3], T[..., :3, :3])
    for b in range(2):
        bone_shift = T[0, b, :3, :3] @ bone_centers[b] + T[0, b, :3, 3] - bone_centers[b]
        moved = A[0, b, :3, :3] @ centroids[b] + A[0, b, :3, 3]
        np.testing.assert_allclose(moved - centroids[b], bone_shift, atol=1e-12)
    # Where the centroid is the bone centre, nothing changes.
    np.testing.assert_allclose(recentre_on_parts(T, bone_centers, bone_centers), T, atol=1e-12)
