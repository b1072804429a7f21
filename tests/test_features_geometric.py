"""features=geometric: heat/wave kernel signatures and the coordinate block."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from sync4d.errors import ConfigError
from sync4d.features._common import (
    fourier_encoding,
    heat_kernel_signature,
    laplacian,
    laplacian_spectrum,
    standardize_columns,
    unit_rms,
)
from sync4d.features.geometric import GeometricFeatures
from sync4d.registry import build


def geometric(**overrides) -> GeometricFeatures:
    return build("features", {"type": "geometric", "n_eigen": 36, **overrides}, device="cpu")


def test_hks_of_sphere_is_constant() -> None:
    sphere = trimesh.creation.icosphere(3)
    hks, wks = geometric().spectral(sphere.vertices, sphere.faces)
    assert np.all(hks.std(axis=0) / hks.mean(axis=0) < 0.01)
    assert np.all(wks.std(axis=0) / wks.mean(axis=0) < 0.05)


def test_laplacian_spectrum_of_sphere() -> None:
    """The unit sphere's Laplacian eigenvalues are l(l+1): 0, 2 (x3), 6 (x5)."""
    sphere = trimesh.creation.icosphere(4)
    L, M = laplacian(np.asarray(sphere.vertices), np.asarray(sphere.faces))
    evals, evecs = laplacian_spectrum(L, M, 9)
    assert evals[0] == pytest.approx(0.0, abs=1e-6)
    assert np.allclose(evals[1:4], 2.0, rtol=0.02)
    assert np.allclose(evals[4:9], 6.0, rtol=0.02)
    assert np.allclose(evecs.T @ (M @ evecs), np.eye(9), atol=1e-6)


def test_hks_decreases_with_time_and_is_positive() -> None:
    mesh = trimesh.creation.capsule(height=1.0, radius=0.2, count=[12, 12])
    L, M = laplacian(unit_rms(np.asarray(mesh.vertices)), np.asarray(mesh.faces))
    evals, evecs = laplacian_spectrum(L, M, 30)
    raw = heat_kernel_signature(evals, evecs, 8, scaled=False)
    assert np.all(raw > 0)
    assert np.all(np.diff(raw, axis=1) <= 1e-12)


@pytest.mark.parametrize("with_faces", [True, False])
def test_spectral_blocks_invariant_to_rigid_motion_and_scale(with_faces: bool) -> None:
    mesh = trimesh.creation.capsule(height=1.0, radius=0.25, count=[10, 12])
    mesh.vertices[:, 0] *= 1.6  # break the symmetry a little
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if not with_faces:  # random samples: a regular grid makes the local Delaunay steps degenerate
        v, f = np.asarray(trimesh.sample.sample_surface(mesh, 400, seed=0)[0]), None
    moved = 3.7 * v @ Rotation.random(random_state=4).as_matrix().T + [1.0, -2.0, 0.5]
    ex = geometric(xyz_weight=0.0)
    a, b = ex.extract(v, f), ex.extract(moved, f)
    assert a.shape == (len(v), 16 + 16 + ex.config.xyz_dims)
    assert np.allclose(a[:, :32], b[:, :32], atol=1e-3)


def test_coordinate_block_is_the_fourier_code_of_the_given_points() -> None:
    pts = np.random.default_rng(0).normal(size=(200, 3))
    ex = geometric(hks_weight=0.0, wks_weight=0.0, xyz_weight=2.0, xyz_dims=128)
    feats = ex.extract(pts, None)
    code = fourier_encoding(pts, dims=128, bandwidth=0.15, seed=0)
    assert feats.shape == (200, 128)  # spectral blocks of weight 0 are skipped
    assert np.allclose(feats, 2.0 * code, atol=1e-5)
    # Cosine of Fourier codes approximates the Gaussian kernel of the distance.
    x = np.zeros((1, 3))
    y = np.array([[0.15, 0.0, 0.0]])
    big = fourier_encoding(np.vstack([x, y]), dims=20000, bandwidth=0.15, seed=1)
    assert big[0] @ big[1] == pytest.approx(np.exp(-0.5), abs=0.03)
    assert ex.coordinates(pts).shape == (200, 128)


def test_normalize_xyz_makes_coordinates_scale_invariant() -> None:
    pts = np.random.default_rng(1).normal(size=(100, 3))
    ex = geometric(hks_weight=0.0, wks_weight=0.0, normalize_xyz=True, xyz_dims=64)
    assert np.allclose(ex.coordinates(pts), ex.coordinates(5.0 * pts + 2.0))


def test_standardize_columns_zeroes_constant_columns() -> None:
    block = np.c_[np.full(10, 3.0), np.arange(10.0)]
    out = standardize_columns(block)
    assert np.allclose(out[:, 0], 0.0)
    assert np.mean((out**2).sum(axis=1)) == pytest.approx(0.5)


def test_disconnected_mesh_uses_point_cloud_laplacian() -> None:
    """Two separate shells: 'auto' connects them through space (one zero eigenvalue, not two)."""
    a = trimesh.creation.icosphere(2)
    b = trimesh.creation.icosphere(2)
    b.apply_translation([1.5, 0, 0])
    both = trimesh.util.concatenate([a, b])
    ex = geometric()
    hks_auto, _ = ex.spectral(both.vertices, both.faces)
    hks_mesh, _ = geometric(laplacian="mesh").spectral(both.vertices, both.faces)
    assert not np.allclose(hks_auto, hks_mesh)


@pytest.mark.parametrize(
    "bad", [{"n_eigen": 2}, {"hks_weight": -1.0}, {"xyz_encoding": "sine"}, {"laplacian": "x"}, {"nope": 1}]
)
def test_bad_config_fails_with_key(bad: dict) -> None:
    with pytest.raises(ConfigError):
        build("features", {"type": "geometric", **bad}, device="cpu")
