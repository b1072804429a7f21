"""Control points: the mean of the Gaussians per lattice cell, and Gaussians carried with F Sigma F^T."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sync4d.errors import ConfigError
from sync4d.geometry import gaussian_covariances
from sync4d.sim.control import carry_gaussians, make_control_points
from sync4d.transfer.particles import make_particles
from sync4d.types import PartMap


def test_control_points_are_cell_means():
    rng = np.random.default_rng(0)
    # a 1 m cube split in a 4^3 lattice; fill three chosen cells with random Gaussians
    cells = np.array([[0, 0, 0], [1, 2, 3], [3, 3, 3]])
    counts = [5, 9, 2]
    means = np.concatenate([c * 0.25 + rng.uniform(0.01, 0.24, (k, 3)) for c, k in zip(cells, counts)])
    means = np.concatenate([means, [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]])  # pin the lattice to [0, 1]^3
    points, g2p, n = make_control_points(means, 4)
    assert len(points) == 3 and n.sum() == len(means)
    for idx in range(len(points)):
        np.testing.assert_allclose(points[idx], means[g2p == idx].mean(0), rtol=0, atol=1e-12)
    # the Gaussians of one cell share a point, those of different cells do not
    starts = np.cumsum([0] + counts)
    for a, b in zip(starts[:-1], starts[1:]):
        assert len(set(g2p[a:b])) == 1
    assert len({g2p[0], g2p[starts[1]], g2p[starts[2]]}) == 3
    # fewer points than Gaussians, never more cells than the lattice has
    big = rng.uniform(0, 1, (5000, 3))
    pts, g, k = make_control_points(big, 5)
    assert len(pts) <= 125 and k.sum() == 5000 and g.max() == len(pts) - 1


def test_control_grid_must_be_positive():
    with pytest.raises(ConfigError, match="control_grid"):
        make_control_points(np.zeros((3, 3)), 0)


def test_carry_gaussians_affine_and_covariance():
    rng = np.random.default_rng(1)
    means0 = rng.normal(size=(6, 3))
    scales = rng.uniform(0.01, 0.1, (6, 3))
    quats = rng.normal(size=(6, 4))
    cov0 = gaussian_covariances(scales, quats)
    g2p = np.array([0, 0, 1, 1, 1, 0])
    points0 = np.stack([means0[g2p == i].mean(0) for i in range(2)])
    shift = np.array([[0.1, 0.2, 0.3], [-0.5, 0.0, 0.4]])
    F = np.stack([np.diag([1.2, 0.9, 1.0]), np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])])
    means_t, cov_t = carry_gaussians(means0, cov0, g2p, points0, points0 + shift, F)
    for gi in range(6):
        c = g2p[gi]
        np.testing.assert_allclose(means_t[gi], points0[c] + shift[c] + F[c] @ (means0[gi] - points0[c]), atol=1e-12)
        np.testing.assert_allclose(cov_t[gi], F[c] @ cov0[gi] @ F[c].T, atol=1e-12)
    # a rotation keeps each Gaussian's shape (eigenvalues of Sigma)
    for gi in np.flatnonzero(g2p == 1):
        np.testing.assert_allclose(np.linalg.eigvalsh(cov_t[gi]), np.linalg.eigvalsh(cov0[gi]), rtol=1e-10)
    # identity motion leaves everything in place; torch gives the same numbers and gradients flow
    same_m, same_c = carry_gaussians(means0, cov0, g2p, points0, points0, np.stack([np.eye(3)] * 2))
    np.testing.assert_allclose(same_m, means0, atol=1e-12)
    np.testing.assert_allclose(same_c, cov0, atol=1e-12)
    Ft = torch.tensor(F, requires_grad=True)
    tm, tc = carry_gaussians(
        torch.tensor(means0), torch.tensor(cov0), torch.tensor(g2p), torch.tensor(points0), torch.tensor(points0 + shift), Ft
    )
    np.testing.assert_allclose(tm.detach().numpy(), means_t, atol=1e-12)
    np.testing.assert_allclose(tc.detach().numpy(), cov_t, atol=1e-12)
    (tm.sum() + tc.sum()).backward()
    assert Ft.grad is not None and torch.isfinite(Ft.grad).all()


def test_gaussian_covariance_from_scales_and_quats():
    cov = gaussian_covariances(np.array([[1.0, 2.0, 3.0]]), np.array([[1.0, 0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(cov[0], np.diag([1.0, 4.0, 9.0]))


def test_control_particles_share_the_volume_by_geometry():
    """Through control points every occupied lattice cell holds one cell volume, split among its per-part points
    by their Gaussians; without them every Gaussian is a particle."""
    rng = np.random.default_rng(2)
    means = rng.uniform(0, 0.2, (20000, 3)).astype(np.float32)
    target = mesh_free_target(means)
    part = (means[:, 0] > 0.1).astype(np.int64)
    part_map = PartMap(np.zeros(1, dtype=np.int64), part, np.ones(len(means)), 2)
    particles = make_particles(target, part_map, 10)
    assert len(particles.points) <= 1100 and particles.gaussian_to_point.shape == (20000,)
    side = float(np.ptp(means.astype(np.float64), axis=0).max()) / 10
    cells = len(make_control_points(means.astype(np.float64), 10)[0])  # occupied lattice cells
    assert particles.volume.sum() == pytest.approx(cells * side**3, rel=1e-6)
    assert np.all(particles.part[particles.gaussian_to_point] == part)  # a point never mixes parts
    every = make_particles(target, part_map, None)
    assert len(every.points) == 20000 and every.volume is None


def mesh_free_target(means: np.ndarray):
    from sync4d.types import TargetGaussians

    n = len(means)
    return TargetGaussians(means=means, quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                           log_scales=np.full((n, 3), -5.0, np.float32), opacity_logits=np.zeros(n, np.float32),
                           sh=np.zeros((n, 1, 3), np.float32))


def test_carry_frame_moves_every_gaussian_rigidly_with_its_control_point():
    from scipy.spatial.transform import Rotation

    from sync4d.render.sh import rotate_sh
    from sync4d.sim.control import carry_frame
    from sync4d.types import TargetGaussians

    rng = np.random.default_rng(5)
    n = 3000
    q = rng.normal(size=(n, 4))
    g = TargetGaussians(means=rng.random((n, 3)).astype(np.float32),
                        quats=(q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                        log_scales=rng.uniform(-5, -3, (n, 3)).astype(np.float32),
                        opacity_logits=np.zeros(n, np.float32), sh=rng.normal(size=(n, 16, 3)).astype(np.float32))
    points, g2p, _ = make_control_points(g.means, 6)
    R = Rotation.from_rotvec([0.3, -0.8, 0.4]).as_matrix()
    t = np.array([0.1, 0.2, -0.3])
    frame = carry_frame(g, g2p, points, points @ R.T + t, np.repeat(R[None], len(points), axis=0))
    np.testing.assert_allclose(frame.means, g.means @ R.T + t, atol=1e-5)
    np.testing.assert_allclose(frame.covariances(), R @ g.covariances() @ R.T, atol=1e-9)
    np.testing.assert_allclose(frame.sh, rotate_sh(g.sh, R), atol=1e-5)
