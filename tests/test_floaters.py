"""Floater removal: far Gaussians, isolated ones and small floating clouds go; the object stays."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d.errors import InputError
from sync4d.sources.floaters import FloaterConfig, find_floaters, remove_floaters


def shell(n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points on a 20 cm sphere's surface, a little thickened [m]."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return 0.1 * d / np.linalg.norm(d, axis=1, keepdims=True) * (1.0 + 0.02 * rng.normal(size=(n, 1)))


def test_far_isolated_and_clustered_floaters_are_removed_and_the_object_kept():
    rng = np.random.default_rng(1)
    obj = shell(5000)
    far = np.array([[1e4, 0.0, 0.0]])                               # 10 km away (the case)
    cloud = np.array([0.0, 0.25, 0.0]) + 0.005 * rng.normal(size=(20, 3))  # a small cloud beside the object
    loners = rng.uniform(-0.3, 0.3, size=(10, 3))
    loners = loners[np.linalg.norm(loners, axis=1) > 0.16]          # stray single Gaussians in the box
    pts = np.concatenate([obj, far, cloud, loners])
    keep, report = find_floaters(pts, FloaterConfig())
    assert keep[:5000].mean() > 0.99
    assert not keep[5000:].any()
    assert report.removed == (~keep).sum() and report.removed_far >= 1
    assert report.removed_box is not None and report.removed_box[1, 0] == pytest.approx(1e4)
    # the simulation domain is the robust extent: the object's own box, not 10 km
    assert np.all(report.kept_box[1] - report.kept_box[0] < 0.25)


def test_a_clean_object_loses_almost_nothing():
    keep, report = find_floaters(shell(3000, seed=3), FloaterConfig())
    assert keep.mean() >= 0.99 and report.removed_far == 0


def test_real_splat_keeps_its_object(shared_data):
    from sync4d.io.ply import read_gaussians_ply

    g = read_gaussians_ply(shared_data / "targets/gaussians/sunflowers_lod3_tile_0.ply")
    far = np.concatenate([g.means, [[1e4, 0.0, 0.0]]])
    keep, report = find_floaters(far, FloaterConfig())
    assert not keep[-1] and keep[:-1].mean() > 0.97


def test_almost_nothing_left_is_a_one_line_error():
    """Scattered points none of whose neighbourhoods reach min_neighbours: nothing is an object."""
    noise = np.random.default_rng(4).uniform(-1.0, 1.0, size=(400, 3))
    with pytest.raises(InputError, match=r"noisy\.ply: floater removal kept only 0 of 400 Gaussians") as info:
        remove_floaters(noise, FloaterConfig(min_neighbours=64), source="noisy.ply")
    assert "\n" not in str(info.value)
    keep, report = remove_floaters(noise, FloaterConfig(enabled=False), source="noisy.ply")
    assert keep.all() and report is None


def test_ply_target_removes_floaters_and_reports(tmp_path):
    from sync4d.io.ply import write_gaussians_ply
    from sync4d.sources.targets import PlyTarget
    from sync4d.types import TargetGaussians

    pts = np.concatenate([shell(2000), [[1e4, 0.0, 0.0]]]).astype(np.float32)
    n = len(pts)
    g = TargetGaussians(means=pts, quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                        log_scales=np.full((n, 3), -5.0, np.float32), opacity_logits=np.zeros(n, np.float32),
                        sh=np.zeros((n, 1, 3), np.float32))
    path = write_gaussians_ply(tmp_path / "floaty.ply", g)
    source = PlyTarget(PlyTarget.Config(path=str(path)))
    loaded, report = source.load_checked()
    assert loaded.num < n and np.abs(loaded.means).max() < 1.0
    assert report is not None and report.as_dict()["removed_far"] == 1


@pytest.mark.slow
def test_run_on_a_splat_with_a_far_floater_reports_it_and_keeps_the_physics_sane(shared_data, tmp_path):
    """The issue's case end to end: one Gaussian 10 km away no longer sets the grid or the coverage ratio."""
    import json

    from _runs import run_train

    from sync4d.io.ply import read_gaussians_ply, write_gaussians_ply

    g = read_gaussians_ply(shared_data / "targets/gaussians/sunflowers_lod3_tile_0.ply")
    floaty = g.subset(np.r_[np.arange(g.num), 0])
    floaty.means[-1] = [1e4, 0.0, 0.0]
    path = write_gaussians_ply(tmp_path / "floaty.ply", floaty)
    run = tmp_path / "run"
    proc = run_train(run, "reference=laptop", "recon=ground_truth", "target=ply", f"target.path={path}",
                     "render_video=false", "logger=none")
    assert proc.returncode == 0, proc.stderr[-2000:]
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["floaters"]["removed_far"] == 1 and metrics["floaters"]["removed_box_m"][1][0] == pytest.approx(1e4)
    assert metrics["coverage_ratio"] < 100  # 5,320 with the floater in
    assert json.loads((run / "cost_estimate.json").read_text())["substeps"] >= 1
