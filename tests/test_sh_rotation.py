"""SH rotation: a turned Gaussian shows the colour it showed before from the correspondingly turned view."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sync4d.geometry import nearest_rotation
from sync4d.sim.deform import deform_gaussians
from sync4d.render.camera import look_at
from sync4d.render.sh import eval_sh, rotate_sh, sh_basis
from sync4d.render.splat_torch import SplatTorch
from sync4d.types import TargetGaussians


def rotation(axis, angle_deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    axis = np.asarray(axis, dtype=np.float64)
    return Rotation.from_rotvec(np.deg2rad(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()


def part(n: int = 40, degree: int = 3, seed: int = 0) -> TargetGaussians:
    """A small elongated part of anisotropic Gaussians with strong view-dependent colour."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    sh = 0.6 * rng.normal(size=(n, (degree + 1) ** 2, 3))
    sh[:, 0] = rng.uniform(-0.5, 0.5, size=(n, 3))
    return TargetGaussians(
        means=(rng.normal(size=(n, 3)) * [0.08, 0.03, 0.02]).astype(np.float32),
        quats=(q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
        log_scales=rng.uniform(np.log(0.006), np.log(0.02), size=(n, 3)).astype(np.float32),
        opacity_logits=np.full(n, 1.5, np.float32), sh=sh.astype(np.float32),
    )


def render(g: TargetGaussians, eye, up) -> np.ndarray:
    cam = look_at(eye, (0.0, 0.0, 0.0), up=up, fov_deg=40.0, width=48, height=40)
    rnd = SplatTorch(SplatTorch.Config(dtype="float64", background=[0.0, 0.0, 0.0]), device="cpu")
    return rnd.render(g.means.astype(np.float64), g.covariances(), g.sh.astype(np.float64), g.opacities, cam)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_rotated_coefficients_give_the_turned_colour_function(degree):
    rng = np.random.default_rng(degree)
    sh = rng.normal(size=(200, (degree + 1) ** 2, 3))
    R = np.stack([rotation(rng.normal(size=3), a) for a in rng.uniform(0, 180, size=200)])
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    turned = eval_sh(torch.tensor(rotate_sh(sh, R)), torch.tensor(d)).numpy()
    before = eval_sh(torch.tensor(sh), torch.tensor(np.einsum("nji,nj->ni", R, d))).numpy()
    np.testing.assert_allclose(turned, before, atol=1e-10)
    # the basis used for the rotation is the renderer's own
    np.testing.assert_allclose(np.einsum("nk,nkc->nc", sh_basis(d, degree), sh), eval_sh(torch.tensor(sh), torch.tensor(d)).numpy(), atol=1e-12)


def test_rotated_part_from_rotated_camera_renders_like_the_unrotated_one():
    g = part()
    R = rotation([1.0, 2.0, 0.5], 70.0)
    eye, up = np.array([0.15, 0.1, 0.45]), np.array([0.0, 1.0, 0.0])
    before = render(g, eye, up)
    n = g.num
    # a rigid motion through the simulator's path: F = R for every Gaussian (and the same via control points)
    moved = deform_gaussians(g, g.means.astype(np.float64) @ R.T, np.repeat(R[None], n, axis=0))
    via_points = deform_gaussians(g, g.means.astype(np.float64) @ R.T, R[None], index=np.zeros(n, dtype=np.int64))
    via_global = deform_gaussians(g, g.means.astype(np.float64), None, np.block([[R, np.zeros((3, 1))], [np.zeros((1, 3)), 1.0]]))
    for turned in (moved, via_points, via_global):
        after = render(turned, R @ eye, R @ up)
        assert before.max() > 0.3  # something is drawn
        np.testing.assert_allclose(after, before, atol=2e-4)
    # the test can fail: without turning the SH the colours differ
    unrotated = render(moved.replace(sh=g.sh), R @ eye, R @ up)
    assert np.abs(unrotated - before).max() > 0.05


def test_polar_rotation_of_a_stretched_rotation():
    R = rotation([0.3, -1.0, 0.2], 40.0)
    U = np.diag([1.3, 0.8, 1.1])
    np.testing.assert_allclose(nearest_rotation((R @ U)[None])[0], R, atol=1e-12)
