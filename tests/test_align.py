"""Alignment: normalisation, principal frames, the candidate search and similarity ICP."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from sync4d.match.align import (
    Similarity,
    align_shapes,
    candidate_rotations,
    normalization,
    principal_frame,
    proper_axis_rotations,
    umeyama,
)
from sync4d.errors import ConfigError


def l_shape(n: int = 1500, seed: int = 0) -> np.ndarray:
    """An asymmetric point set (an L of two unequal boxes plus a knob) with distinct principal axes."""
    long_box = trimesh.creation.box(extents=[1.0, 0.2, 0.3])
    short_box = trimesh.creation.box(extents=[0.2, 0.6, 0.3])
    short_box.apply_translation([0.4, 0.4, 0.0])
    knob = trimesh.creation.icosphere(2, radius=0.12)
    knob.apply_translation([-0.5, 0.0, 0.2])
    mesh = trimesh.util.concatenate([long_box, short_box, knob])
    return np.asarray(trimesh.sample.sample_surface(mesh, n, seed=seed)[0])


def test_normalization_unit_rms_and_bbox() -> None:
    pts = np.random.default_rng(0).normal(size=(500, 3)) * [3.0, 1.0, 0.5] + [5.0, -2.0, 1.0]
    out = normalization(pts).apply(pts)
    assert np.allclose(out.mean(axis=0), 0.0, atol=1e-12)
    assert np.sqrt((out**2).sum(axis=1).mean()) == pytest.approx(1.0)
    box = normalization(pts, mode="bbox").apply(pts)
    assert np.linalg.norm(box.max(axis=0) - box.min(axis=0)) == pytest.approx(1.0)


def test_similarity_compose_and_inverse() -> None:
    rng = np.random.default_rng(1)
    a = Similarity(Rotation.random(random_state=1).as_matrix(), 2.0, rng.normal(size=3))
    b = Similarity(Rotation.random(random_state=2).as_matrix(), 0.5, rng.normal(size=3))
    x = rng.normal(size=(10, 3))
    assert np.allclose(a.then(b).apply(x), b.apply(a.apply(x)))
    assert np.allclose(a.inverse().apply(a.apply(x)), x)
    assert np.allclose((a.matrix() @ np.c_[x, np.ones(10)].T).T[:, :3], a.apply(x))


def test_cube_group_has_24_distinct_proper_rotations() -> None:
    mats = proper_axis_rotations()
    assert mats.shape == (24, 3, 3)
    assert np.allclose(mats[0], np.eye(3))
    assert np.allclose(np.linalg.det(mats), 1.0)
    assert len({m.round().astype(int).tobytes() for m in mats}) == 24
    assert candidate_rotations().shape == (168, 3, 3)


def test_principal_frame_follows_rotation() -> None:
    """Skewness-signed principal axes rotate with the shape (so the identity candidate is right)."""
    pts = l_shape()
    rot = Rotation.random(random_state=5).as_matrix()
    f0 = principal_frame(pts)
    f1 = principal_frame(pts @ rot.T)
    assert np.linalg.det(f0) == pytest.approx(1.0)
    assert np.allclose(f1, f0 @ rot.T, atol=1e-6)


def test_umeyama_recovers_exact_similarity() -> None:
    rng = np.random.default_rng(2)
    src = rng.normal(size=(50, 3))
    true = Similarity(Rotation.random(random_state=3).as_matrix(), 1.7, rng.normal(size=3))
    est = umeyama(src, true.apply(src))
    assert np.allclose(est.rotation, true.rotation, atol=1e-9)
    assert est.scale == pytest.approx(1.7)
    assert np.allclose(est.translation, true.translation)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_align_recovers_random_rotation_and_scale(seed: int) -> None:
    """A resampled, jittered copy under a large random rotation, scale and shift is brought back."""
    rng = np.random.default_rng(seed)
    reference = l_shape(2000, seed=seed)
    copy = l_shape(1500, seed=seed + 10)  # other samples of the same surface: no shared points
    true = Similarity(Rotation.random(random_state=seed + 20).as_matrix(), float(rng.uniform(0.3, 3.0)), rng.normal(size=3) * 5)
    moved = true.apply(copy) + rng.normal(scale=0.003 * true.scale, size=copy.shape)
    result = align_shapes(moved, reference, method="pca_icp")
    est = result.transform
    assert est.scale * true.scale == pytest.approx(1.0, rel=0.02)
    angle = Similarity(est.rotation @ true.rotation, 1.0, np.zeros(3)).rotation_angle_deg
    assert angle < 2.0
    assert np.abs(est.apply(true.apply(copy)) - copy).max() < 0.03
    assert result.residual < 0.05


def test_align_none_is_identity_and_bad_method_fails() -> None:
    pts = l_shape(300)
    assert np.allclose(align_shapes(pts, pts, method="none").transform.matrix(), np.eye(4))
    with pytest.raises(ConfigError, match="match.align"):
        align_shapes(pts, pts, method="bogus")
