"""features=diff3f with the no-download backbone, and features=concat."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch
import trimesh
from scipy.spatial.transform import Rotation

from sync4d.errors import ConfigError
from sync4d.features._common import neighbour_graph
from sync4d.features._raster import look_at_rotation, render_view, surface_samples, view_directions
from sync4d.features.diff3f import ShadingFourierBackbone, fill_unseen, sample_feature_maps
from sync4d.registry import build


def diff3f(**overrides):
    return build("features", {"type": "diff3f", "n_views": 4, "resolution": 48, "feature_dims": 16, **overrides}, device="cpu")


def test_render_two_stacked_squares_hides_the_far_one() -> None:
    """A near square in front of a far square: the far vertices behind it are hidden, others seen."""
    near = trimesh.creation.box(extents=[1.0, 1.0, 0.01])
    far = trimesh.creation.box(extents=[2.0, 2.0, 0.01])
    far.apply_translation([0.0, 0.0, -1.0])
    mesh = trimesh.util.concatenate([near, far])
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    samples, normals = surface_samples(v, f, 20000, seed=0)
    rot = look_at_rotation(np.array([0.0, 0.0, 1.0]))  # camera on +z looking at -z
    view = render_view(v, samples, normals, rot, resolution=64, extent=1.5, splat_radius_px=1.0, depth_tolerance_px=2.0)
    front_face_near = (v[:, 2] > 0) & (np.abs(v[:, 2]) < 0.1)
    behind = (v[:, 2] < -0.9) & (np.abs(v[:, 0]) < 0.45) & (np.abs(v[:, 1]) < 0.45)
    far_corners = (v[:, 2] > -1.0) & (v[:, 2] < -0.9) & (np.abs(v[:, 0]) > 0.9)
    assert view.vertex_visible[front_face_near].all()
    assert not view.vertex_visible[behind].any()
    assert view.vertex_visible[far_corners].all()
    # The far square covers 2/3 of the view width; 1-px splats (after flooring) widen it by <= 2 px a side.
    assert (2.0 / 3.0) ** 2 <= view.mask.mean() <= ((2.0 / 3.0) * 64 + 4) ** 2 / 64**2
    assert (view.normal[view.mask][:, 2] <= 0).all()  # normals face the camera


def test_seen_vertex_gets_its_pixel_feature_and_unseen_are_filled() -> None:
    ex = diff3f(n_views=1)
    mesh = trimesh.creation.icosphere(2)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    renders, images = ex.render_views(v, f)
    fmaps = ex.backbone(images)
    feats, seen = ex.backproject(renders, fmaps, len(v))
    view = renders[0]
    assert 0.2 < seen.mean() < 0.8  # one view sees about half of a sphere
    iu = np.floor(view.vertex_pixel[:, 0]).astype(int)
    iv = np.floor(view.vertex_pixel[:, 1]).astype(int)
    expected = fmaps[0][:, iv, iu].T.numpy()
    assert np.allclose(feats[seen], expected[seen], atol=1e-6)
    full = ex.extract(v, f)
    assert full.shape == (len(v), 16) and np.isfinite(full).all()
    assert np.allclose(full[seen], feats[seen], atol=1e-5)
    assert (np.abs(full[~seen]).sum(axis=1) > 0).all()


def test_fill_unseen_uses_graph_neighbours_then_nearest() -> None:
    # A path 0-1-2-3 plus an isolated vertex 4 near vertex 0.
    adj = sp.csr_matrix(np.array([[0, 1, 0, 0, 0], [1, 0, 1, 0, 0], [0, 1, 0, 1, 0], [0, 0, 1, 0, 0], [0, 0, 0, 0, 0]], float))
    feats = np.array([[1.0], [0.0], [0.0], [5.0], [0.0]])
    seen = np.array([True, False, False, True, False])
    pts = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [0.1, 0, 0]], float)
    out = fill_unseen(feats, seen, adj, pts)
    assert out[1, 0] == pytest.approx(1.0) and out[2, 0] == pytest.approx(5.0)
    assert out[4, 0] == pytest.approx(1.0)  # no graph path: nearest seen vertex
    with pytest.raises(ConfigError):
        fill_unseen(feats, np.zeros(5, bool), adj, pts)


def test_sample_feature_maps_bilinear_on_coarse_map() -> None:
    fmap = torch.arange(16.0).view(1, 4, 4)
    pix = np.array([[8.0, 8.0]])  # centre of a 16-px render -> centre of the 4x4 map
    assert sample_feature_maps(fmap, pix, 16)[0, 0] == pytest.approx(fmap[0, 1:3, 1:3].mean().item())


def test_backbone_is_deterministic_and_bounded() -> None:
    images = torch.rand(2, 6, 32, 32, generator=torch.Generator().manual_seed(0))
    a = ShadingFourierBackbone(scales=(1.0, 2.0), dims=8, bandwidth=1.0, seed=3)(images)
    b = ShadingFourierBackbone(scales=(1.0, 2.0), dims=8, bandwidth=1.0, seed=3)(images)
    assert a.shape == (2, 8, 32, 32) and torch.equal(a, b)
    assert a.abs().max() <= np.sqrt(2.0 / 8) + 1e-6


def test_diff3f_point_cloud_and_views() -> None:
    dirs = view_directions(6, 30.0)
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
    assert (dirs[::2, 1] > 0).all() and (dirs[1::2, 1] < 0).all()
    pts = np.asarray(trimesh.sample.sample_surface(trimesh.creation.icosphere(2), 500, seed=0)[0])
    feats = diff3f().extract(pts, None)
    assert feats.shape == (500, 16) and np.isfinite(feats).all()


def test_diff3f_features_follow_the_shape_not_the_scale() -> None:
    """The renderer frames the shape, so a scaled and shifted copy gives the same features."""
    mesh = trimesh.creation.capsule(height=1.0, radius=0.3, count=[8, 8])
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    ex = diff3f()
    a, b = ex.extract(v, f), ex.extract(2.5 * v + 1.0, f)
    # Round-off can move a projection across a pixel border; nearly every vertex must agree exactly.
    same = np.all(np.abs(a - b) < 1e-4, axis=1)
    assert same.mean() > 0.9


@pytest.mark.parametrize("backbone", ["dinov2", "stable_diffusion"])
def test_pretrained_backbones_refuse_without_local_weights(backbone: str, tmp_path) -> None:
    with pytest.raises(ConfigError, match="weights_path.*2048"):
        build("features", {"type": "diff3f", "backbone": backbone}, device="cpu")
    with pytest.raises(ConfigError, match="not found"):
        build("features", {"type": "diff3f", "backbone": backbone, "weights_path": str(tmp_path / "none")}, device="cpu")


def test_concat_normalises_and_weights_blocks() -> None:
    ex = build(
        "features",
        {"type": "concat", "parts": [{"type": "geometric", "n_eigen": 16, "xyz_dims": 128}, {"type": "diff3f", "n_views": 2, "resolution": 32, "feature_dims": 8}],
         "weights": [1.0, 0.5]},
        device="cpu",
    )
    mesh = trimesh.creation.icosphere(2)
    feats = ex.extract(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    d_geo = 16 + 16 + 128
    assert feats.shape == (len(mesh.vertices), d_geo + 8)
    assert np.allclose(np.linalg.norm(feats[:, :d_geo], axis=1), 1.0, atol=1e-5)
    assert np.allclose(np.linalg.norm(feats[:, d_geo:], axis=1), 0.5, atol=1e-5)
    with pytest.raises(ConfigError, match="weights"):
        build("features", {"type": "concat", "parts": [{"type": "geometric"}], "weights": [1.0, 2.0]}, device="cpu")
    with pytest.raises(ConfigError):
        build("features", {"type": "concat", "parts": [{"type": "geometric", "bogus": 1}]}, device="cpu")


def test_feature_yaml_files_build(repo_root) -> None:
    from omegaconf import OmegaConf

    for name in ("geometric", "diff3f", "concat"):
        cfg = OmegaConf.to_container(OmegaConf.load(repo_root / "conf" / "features" / f"{name}.yaml"))
        cfg.pop("defaults", None)  # the Hydra schema line (schema_<name>); defaults come from the Config
        assert cfg["type"] == name
        assert build("features", cfg, device="cpu").config is not None


def test_neighbour_graph_is_symmetric() -> None:
    pts = np.random.default_rng(0).normal(size=(50, 3))
    adj = neighbour_graph(pts, None, k=4)
    assert (adj != adj.T).nnz == 0 and adj.diagonal().sum() == 0
    assert (np.asarray(adj.sum(axis=1)).ravel() >= 4).all()
    rot = Rotation.random(random_state=0).as_matrix()
    assert (neighbour_graph(pts @ rot.T, None, k=4) != adj).nnz == 0
