"""render=splat_torch against analytic images, exact compositing values and finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sync4d.errors import ConfigError, InputError
from sync4d.registry import build
from sync4d.render.camera import look_at
from sync4d.geometry import SH_C0, rgb_to_sh_dc
from sync4d.render.sh import SH_C1
from sync4d.render.splat_torch import SplatTorch, footprint_boxes, project_gaussians
from sync4d.types import Camera


def axis_camera(width: int, height: int, f: float) -> Camera:
    """Camera at the origin looking down +z (world = camera axes), principal point at the centre."""
    K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    return Camera(K=K, world_to_cam=np.eye(4), width=width, height=height)


def iso_cov(sigma: float, n: int = 1) -> np.ndarray:
    return np.repeat((sigma**2 * np.eye(3))[None], n, axis=0)


def renderer(**kw) -> SplatTorch:
    return SplatTorch(SplatTorch.Config(**kw), device="cpu")


def test_single_gaussian_matches_analytic_2d_gaussian() -> None:
    """Off-axis isotropic Gaussian: every pixel within 2.5 sigma equals o exp(-d^T S^-1 d / 2) with the
    EWA covariance S = sigma^2 J J^T + 0.3 I, and the image moments give the projected mean and S."""
    W, H, f, z, sigma, o = 96, 80, 120.0, 4.0, 0.12, 0.8
    cam = axis_camera(W, H, f)
    mean = np.array([[0.31, -0.22, z]])
    rnd = renderer(background=[0.0, 0.0, 0.0], alpha_min=1e-12, sigma_cutoff=7.0, dtype="float64")
    out = rnd.render_full(mean, iso_cov(sigma), np.ones((1, 3)), np.array([o]), cam)
    alpha = out["alpha"].astype(np.float64)

    x, y = mean[0, 0], mean[0, 1]
    u, v = f * x / z + W / 2, f * y / z + H / 2
    J = np.array([[f / z, 0, -f * x / z**2], [0, f / z, -f * y / z**2]])
    S = sigma**2 * J @ J.T + 0.3 * np.eye(2)
    cols, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = np.stack([cols - u, rows - v], -1)
    maha = np.einsum("hwi,ij,hwj->hw", d, np.linalg.inv(S), d)
    expected = o * np.exp(-0.5 * maha)
    disc = maha < 2.5**2
    np.testing.assert_allclose(alpha[disc], expected[disc], rtol=1e-5, atol=1e-7)
    # Peak at the pixel containing the projected mean.
    assert np.unravel_index(np.argmax(alpha), alpha.shape) == (int(v), int(u))
    # Moments of the (untruncated, 7-sigma) image: mean and covariance of the 2D Gaussian.
    mass = alpha.sum()
    assert mass == pytest.approx(o * 2 * math.pi * math.sqrt(np.linalg.det(S)), rel=1e-3)
    mu = np.array([(alpha * cols).sum(), (alpha * rows).sum()]) / mass
    np.testing.assert_allclose(mu, [u, v], atol=2e-3)
    dc, dr = cols - mu[0], rows - mu[1]
    cov = np.array([[(alpha * dc * dc).sum(), (alpha * dc * dr).sum()],
                    [(alpha * dc * dr).sum(), (alpha * dr * dr).sum()]]) / mass
    # Point samples on a unit grid reproduce the moments of a Gaussian this wide to ~1e-6.
    np.testing.assert_allclose(cov, S, rtol=2e-3, atol=2e-3)
    # Depth image: the Gaussian's camera depth wherever it is drawn.
    np.testing.assert_allclose(out["depth"][alpha > 1e-3], z, rtol=1e-6)


def test_on_axis_spread_is_f_sigma_over_z_and_peak_is_opacity() -> None:
    W = H = 65  # odd: the principal point (32.5, 32.5) is the centre of pixel (32, 32)
    f, z, sigma, o = 100.0, 2.0, 0.05, 0.6
    cam = axis_camera(W, H, f)
    bg = np.array([0.2, 0.3, 0.4])
    color = np.array([[0.9, 0.5, 0.1]])
    rnd = renderer(background=bg.tolist())
    out = rnd.render_full(np.array([[0.0, 0.0, z]]), iso_cov(sigma), color, np.array([o]), cam)
    assert out["alpha"][32, 32] == pytest.approx(o, rel=1e-6)
    np.testing.assert_allclose(out["rgb"][32, 32], o * color[0] + (1 - o) * bg, rtol=1e-6)
    # Along the row through the centre: alpha(dx) = o exp(-dx^2 / (2 s^2)), s^2 = (f sigma / z)^2 + 0.3.
    s2 = (f * sigma / z) ** 2 + 0.3
    for dx in (1, 2, 4, 6):
        assert out["alpha"][32, 32 + dx] == pytest.approx(o * math.exp(-dx * dx / (2 * s2)), rel=1e-5)
    # Far corners are background.
    np.testing.assert_allclose(out["rgb"][0, 0], bg, atol=1e-7)
    assert out["alpha"][0, 0] == 0.0 and out["depth"][0, 0] == 0.0


@pytest.mark.parametrize("front_first", [True, False])
def test_two_overlapping_gaussians_composite_front_to_back(front_first: bool) -> None:
    W = H = 33
    cam = axis_camera(W, H, 50.0)
    red, green, bg = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    o_front, o_back = 0.7, 0.6
    means = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]])  # same pixel, red in front
    covs = np.stack([0.2**2 * np.eye(3), 0.3**2 * np.eye(3)])
    colors, opac = np.stack([red, green]), np.array([o_front, o_back])
    if not front_first:  # input order must not matter: compositing sorts by depth
        means, covs, colors, opac = means[::-1], covs[::-1], colors[::-1], opac[::-1]
    out = renderer(background=bg.tolist()).render_full(means, covs, colors, opac, cam)
    expected = o_front * red + (1 - o_front) * o_back * green + (1 - o_front) * (1 - o_back) * bg
    np.testing.assert_allclose(out["rgb"][16, 16], expected, rtol=1e-6)
    assert out["alpha"][16, 16] == pytest.approx(1 - (1 - o_front) * (1 - o_back), rel=1e-6)
    w_front, w_back = o_front, (1 - o_front) * o_back
    assert out["depth"][16, 16] == pytest.approx((2.0 * w_front + 3.0 * w_back) / (w_front + w_back), rel=1e-6)
    assert out["rgb"][16, 16, 0] > out["rgb"][16, 16, 1]  # the front colour dominates


def test_alpha_is_capped_at_099_as_in_3dgs() -> None:
    cam = axis_camera(17, 17, 30.0)
    out = renderer(background=[0.0, 0.0, 0.0]).render_full(
        np.array([[0.0, 0.0, 1.0]]), iso_cov(0.2), np.ones((1, 3)), np.array([1.0]), cam
    )
    assert out["alpha"].max() == pytest.approx(0.99, rel=1e-6)


def test_behind_camera_and_offscreen_gaussians_are_culled() -> None:
    cam = axis_camera(32, 32, 40.0)
    means = np.array([[0.0, 0.0, -2.0], [50.0, 0.0, 2.0], [0.0, 0.0, 0.005]])
    out = renderer(background=[0.1, 0.1, 0.1]).render_full(
        means, iso_cov(0.1, 3), np.ones((3, 3)), np.full(3, 0.9), cam
    )
    assert np.all(out["alpha"] == 0.0)
    np.testing.assert_allclose(out["rgb"], 0.1, atol=1e-7)


def test_banding_and_tile_size_do_not_change_the_image() -> None:
    """The image is the same for any tile size and band budget (tiles only bin the work)."""
    rng = np.random.default_rng(3)
    n = 300
    cam = look_at((2.0, -2.5, 1.5), (0, 0, 0), (0, 0, 1), 45.0, 70, 50)
    means = rng.uniform(-0.5, 0.5, (n, 3))
    covs = iso_cov(1.0, n) * rng.uniform(0.01, 0.05, (n, 1, 1)) ** 2
    colors, opac = rng.uniform(0, 1, (n, 3)), rng.uniform(0.2, 1.0, n)
    ref = renderer(tile_size=4, dtype="float64").render_full(means, covs, colors, opac, cam)
    for kw in ({"tile_size": 1}, {"tile_size": 16}, {"tile_size": 4, "max_pairs": 2000}):
        other = renderer(**kw, dtype="float64").render_full(means, covs, colors, opac, cam)
        np.testing.assert_allclose(other["rgb"], ref["rgb"], atol=1e-6)
        np.testing.assert_allclose(other["alpha"], ref["alpha"], atol=1e-6)
    # The float32 default agrees with float64 to well below one 8-bit level.
    single = renderer().render_full(means, covs, colors, opac, cam)
    np.testing.assert_allclose(single["rgb"], ref["rgb"], atol=1e-4)


def _tiny_scene(dtype=torch.float64):
    rng = np.random.default_rng(7)
    n = 4
    means = torch.tensor(rng.uniform(-0.3, 0.3, (n, 3)) + [0, 0, 3.0], dtype=dtype)
    A = rng.normal(size=(n, 3, 3)) * 0.08
    covs = torch.tensor(A @ A.transpose(0, 2, 1) + 0.01 * np.eye(3), dtype=dtype)
    colors = torch.tensor(rng.uniform(0, 1, (n, 3)), dtype=dtype)
    opac = torch.tensor(rng.uniform(0.3, 0.9, n), dtype=dtype)
    return means, covs, colors, opac


def test_gradients_match_finite_differences() -> None:
    """Autograd gradients w.r.t. means, covariances, colours and opacities against central differences
    (float64; a huge cutoff keeps every Gaussian on every pixel so the image is smooth in the inputs)."""
    cam = look_at((0.0, 0.0, 0.0), (0.0, 0.0, 3.0), (0.0, -1.0, 0.0), 50.0, 12, 10)
    rnd = renderer(alpha_min=1e-300, sigma_cutoff=50.0, background=[0.3, 0.2, 0.1])
    means, covs, colors, opac = _tiny_scene()
    weights = torch.tensor(np.random.default_rng(1).normal(size=(10, 12, 3)))

    def loss(m, c, col, o):
        out = rnd.render_full(m, 0.5 * (c + c.transpose(1, 2)), col, o, cam)
        return (out["rgb"] * weights).sum() + (out["alpha"] ** 2).sum()

    assert torch.autograd.gradcheck(loss, (means.requires_grad_(), covs.requires_grad_(), colors.requires_grad_(),
                                           opac.requires_grad_()), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_float32_gradient_of_mean_matches_finite_difference_at_default_settings() -> None:
    """At the default (float32, 1/255 cut-off) settings the gradient of a smooth loss w.r.t. a mean
    is still right to ~1% (the cut-offs move only pixels with alpha ~ 1/255)."""
    cam = look_at((0.0, 0.0, 0.0), (0.0, 0.0, 3.0), (0.0, -1.0, 0.0), 50.0, 40, 32)
    rnd = renderer()
    means, covs, colors, opac = (t.float() for t in _tiny_scene())
    target = torch.linspace(0, 1, 40 * 32 * 3).reshape(32, 40, 3)

    def loss(m):
        return ((rnd.render(m, covs, colors, opac, cam) - target) ** 2).sum()

    m = means.clone().requires_grad_()
    loss(m).backward()
    h = 1e-3
    for i, k in [(0, 0), (1, 1), (2, 2)]:
        mp, mm = means.double().clone(), means.double().clone()
        mp[i, k] += h
        mm[i, k] -= h
        fd = (loss(mp.float()).double() - loss(mm.float()).double()) / (2 * h)
        assert float(m.grad[i, k]) == pytest.approx(float(fd), rel=2e-2, abs=2e-2)


def test_sh_degree0_equals_rgb_and_degree1_is_view_dependent() -> None:
    rng = np.random.default_rng(0)
    n = 50
    cam = look_at((1.5, -2.0, 1.0), (0, 0, 0), (0, 0, 1), 40.0, 48, 40)
    means = rng.uniform(-0.4, 0.4, (n, 3))
    covs = iso_cov(0.05, n)
    rgb = rng.uniform(0.05, 0.95, (n, 3))
    opac = rng.uniform(0.3, 1.0, n)
    rnd = renderer()
    img_rgb = rnd.render(means, covs, rgb, opac, cam)
    sh0 = rgb_to_sh_dc(torch.tensor(rgb)).numpy()
    np.testing.assert_allclose(rnd.render(means, covs, sh0, opac, cam), img_rgb, atol=1e-5)
    # Degree 1 with only the y-band coefficient: colour = 0.5 + C0 dc - C1 d_y c1 for view direction d.
    sh1 = np.zeros((1, 4, 3))
    sh1[0, 0] = (np.array([0.5, 0.5, 0.5]) - 0.5) / SH_C0
    sh1[0, 1] = [0.4, 0.0, -0.4]
    mean = np.array([[0.1, 0.2, -0.1]])
    center = -cam.world_to_cam[:3, :3].T @ cam.world_to_cam[:3, 3]
    d = (mean[0] - center) / np.linalg.norm(mean[0] - center)
    expected = np.clip(0.5 - SH_C1 * d[1] * sh1[0, 1], 0, None)
    wide = renderer(background=[0, 0, 0])
    proj = wide.project(torch.tensor(mean), torch.tensor(iso_cov(0.3)), torch.tensor([0.5]), cam)
    colors = wide._colors(torch.tensor(sh1), torch.tensor(mean), proj.index, cam).numpy()
    np.testing.assert_allclose(colors[0], expected, rtol=1e-6)
    # sh_degree=0 ignores the higher bands.
    colors0 = renderer(sh_degree=0)._colors(torch.tensor(sh1), torch.tensor(mean), proj.index, cam).numpy()
    np.testing.assert_allclose(colors0[0], 0.5, rtol=1e-6)


def test_numpy_in_numpy_out_torch_in_torch_out() -> None:
    cam = axis_camera(17, 13, 20.0)  # the mean projects to the centre of pixel (6, 8)
    args = (np.array([[0.0, 0.0, 2.0]]), iso_cov(0.1), np.ones((1, 3)), np.array([0.5]))
    rnd = renderer()
    img = rnd.render(*args, cam)
    assert isinstance(img, np.ndarray) and img.shape == (13, 17, 3) and img.dtype == np.float32
    t = rnd.render(*(torch.tensor(a, dtype=torch.float32) for a in args), cam)
    assert isinstance(t, torch.Tensor) and t.shape == (13, 17, 3)
    np.testing.assert_allclose(t.numpy(), img, atol=1e-7)
    # Arbitrary feature channels composite over zeros (e.g. part labels as one-hot).
    feats = rnd.render(args[0], args[1], np.array([[1.0, 2.0, 3.0, 4.0, 5.0]]), args[3], cam)
    assert feats.shape == (13, 17, 5) and feats[6, 8, 4] == pytest.approx(5 * 0.5, rel=1e-5)


def test_bad_inputs_and_config_fail_clearly() -> None:
    cam = axis_camera(8, 8, 10.0)
    rnd = renderer()
    with pytest.raises(InputError, match="covariances"):
        rnd.render(np.zeros((2, 3)), np.zeros((3, 3, 3)), np.ones((2, 3)), np.ones(2), cam)
    with pytest.raises(InputError, match="SH"):
        rnd.render(np.zeros((2, 3)), iso_cov(0.1, 2), np.ones((2, 5, 3)), np.ones(2), cam)
    with pytest.raises(ConfigError, match="render.background"):
        build("render", {"type": "splat_torch", "background": [1, 1]}, device="cpu")
    with pytest.raises(ConfigError, match="render.tile_size"):
        build("render", {"type": "splat_torch", "tile_size": 0}, device="cpu")


def test_projection_and_footprint_helpers() -> None:
    cam = axis_camera(64, 48, 100.0)
    means = torch.tensor([[0.2, -0.1, 2.0]], dtype=torch.float64)
    m2d, cov2d, depth, valid = project_gaussians(means, torch.tensor(iso_cov(0.02)), cam, eps2d=0.0)
    np.testing.assert_allclose(m2d[0].numpy(), [100 * 0.1 + 32, 100 * -0.05 + 24])
    assert bool(valid[0]) and float(depth[0]) == 2.0
    boxes, vis, k2 = footprint_boxes(m2d, cov2d, torch.tensor([1.0], dtype=torch.float64), 64, 48)
    sx = 3.0 * math.sqrt(float(cov2d[0, 0, 0]))
    x0, x1 = math.ceil(42 - sx - 0.5), math.floor(42 - 0.5 + sx)
    assert bool(vis[0]) and boxes[0, 0] == x0 and boxes[0, 1] == x1 and float(k2[0]) == pytest.approx(9.0)


def test_deformed_covariances_render_like_deformed_geometry() -> None:
    """Stretching a Gaussian by F = diag(2, 1, 1) doubles its on-screen spread along x (on axis)."""
    from sync4d.render.splat_torch import deform_covariances

    F = np.diag([2.0, 1.0, 1.0])[None]
    cov = iso_cov(0.05)
    stretched = deform_covariances(cov, F)
    np.testing.assert_allclose(stretched[0], np.diag([0.01, 0.0025, 0.0025]))
    seq = deform_covariances(torch.tensor(cov), torch.tensor(np.stack([F, F])))
    assert tuple(seq.shape) == (2, 1, 3, 3)
    cam = axis_camera(65, 65, 100.0)
    out = renderer(eps2d=0.0).render_full(np.array([[0.0, 0.0, 2.0]]), stretched, np.ones((1, 3)),
                                         np.array([0.9]), cam)
    # alpha(dx, 0) = o exp(-dx^2 / (2 sx^2)) with sx = f * 0.1 / z = 5 px; along y sy = 2.5 px.
    assert out["alpha"][32, 37] == pytest.approx(0.9 * math.exp(-0.5), rel=1e-5)
    assert out["alpha"][34, 32] == pytest.approx(0.9 * math.exp(-0.5 * (2 / 2.5) ** 2), rel=1e-5)
