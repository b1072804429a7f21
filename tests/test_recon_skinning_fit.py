"""recon=skinning_fit: pure skinning helpers, a synthetic two-bone bend, bones=auto, and shiba-haru."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d.errors import ConfigError, InputError
from sync4d.geometry import apply_rigid, rigid_fit
from sync4d.recon import skinning as sk
from sync4d.recon.skinning_fit import FitOptions, SkinningFit, fit_skinning
from sync4d.registry import build
from sync4d.types import ReferenceInput


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def bending_cylinder(frames: int = 6, n: int = 900, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(T, V, 3) a 1 m cylinder along x whose right half bends about z at x = 0 by up to 60 deg,
    carried by a global drift; and (V,) the true part (0 left, 1 right)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.5, 0.5, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    rest = np.stack([x, 0.08 * np.cos(phi), 0.08 * np.sin(phi)], 1)
    w1 = 1.0 / (1.0 + np.exp(-x / 0.02))  # smooth blend over ~4 cm around the joint
    seq = []
    for t in range(frames):
        angle = np.deg2rad(60.0) * t / (frames - 1)
        bent = rest @ rot_z(angle).T
        posed = (1 - w1)[:, None] * rest + w1[:, None] * bent
        glob = rot_z(0.2 * t)
        seq.append(posed @ glob.T + np.array([0.1 * t, 0.05 * t, 0.0]))
    return np.stack(seq), (x > 0).astype(int)


def test_kabsch_recovers_a_rigid_transform() -> None:
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(50, 3))
    q = rng.normal(size=4)
    from sync4d.geometry import quat_to_matrix

    true = np.eye(4)
    true[:3, :3] = quat_to_matrix(q[None])[0]
    true[:3, 3] = [0.3, -1.0, 2.0]
    est = rigid_fit(pts, apply_rigid(true, pts))
    assert np.allclose(est, true, atol=1e-9)
    assert np.allclose(sk.rigid_inverse(est) @ est, np.eye(4), atol=1e-12)


def test_farthest_point_and_kmeans_cover_the_shape() -> None:
    pts = np.concatenate([np.random.default_rng(0).normal(size=(100, 3)) * 0.05 + c for c in ([0, 0, 0], [5, 0, 0], [0, 5, 0])])
    idx = sk.farthest_point_sample(pts, 3)
    assert len(set(idx.tolist())) == 3
    labels = sk.kmeans(pts, 3)
    # each blob gets exactly one label
    assert all(len(set(labels[i * 100 : (i + 1) * 100].tolist())) == 1 for i in range(3))
    assert len(set(labels.tolist())) == 3


def test_gaussian_skinning_and_lbs_identity() -> None:
    pts = np.random.default_rng(0).normal(size=(20, 3))
    centers = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    covs = sk.bone_covariances(np.tile(np.eye(3), (2, 1, 1)), np.array([[0.5, 0.5, 0.5], [0.2, 0.3, 0.4]]))
    w = sk.gaussian_skinning(pts, centers, covs)
    assert np.allclose(w.sum(1), 1.0) and (w >= 0).all()
    assert np.allclose(sk.linear_blend(pts, w, np.tile(np.eye(4), (2, 1, 1))), pts)
    # a point at a bone centre belongs mostly to that bone
    w0 = sk.gaussian_skinning(centers, centers, covs)
    assert w0[0, 0] > 0.5 and w0[1, 1] > 0.5


def test_two_bone_bend_is_reproduced() -> None:
    seq, part = bending_cylinder()
    fit = fit_skinning(seq, 2, FitOptions(iterations=250, fit_vertices=400))
    assert fit.mean_error_pct < 1.0, fit.frame_error_pct
    assert fit.frame_error_m[0] < 1e-3
    # parts found: argmax labels agree with the true halves (up to label permutation)
    labels = fit.weights.argmax(1)
    agree = max((labels == part).mean(), (labels != part).mean())
    assert agree > 0.95
    # the bending bone turns by 60 deg relative to the other at the last frame
    rel = np.linalg.inv(fit.bone_transforms[-1, 0]) @ fit.bone_transforms[-1, 1]
    angle = np.degrees(np.arccos(np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1, 1)))
    assert abs(angle - 60.0) < 4.0


def test_reconstructor_returns_a_valid_reference_with_report() -> None:
    seq, _ = bending_cylinder(frames=4, n=300)
    recon = build("recon", {"type": "skinning_fit", "bones": 2, "iterations": 150, "fit_vertices": 0}, device="cpu")
    ref = recon.reconstruct(ReferenceInput(name="cyl", fps=10.0, mesh_sequence=seq))
    assert ref.num_bones == 2 and ref.num_frames == 4
    posed = np.stack([ref.posed_vertices(t, apply_global=True) for t in range(4)])
    err = np.linalg.norm(posed - seq, axis=-1).mean(1)
    assert np.allclose(err, recon.last_fit_report["frame_error_m"], atol=1e-6)
    assert len(recon.last_fit_report["frame_error_pct"]) == 4
    assert recon.last_fit_report["mean_error_pct"] < 2.0


def test_bones_auto_picks_the_smallest_sufficient_count() -> None:
    seq, _ = bending_cylinder(frames=4, n=300)
    recon = SkinningFit(SkinningFit.Config(bones="auto", iterations=150, fit_vertices=0,
                                           auto_candidates=[1, 2, 3], auto_tolerance_pct=1.0))
    ref = recon.reconstruct(ReferenceInput(name="cyl", fps=10.0, mesh_sequence=seq))
    curve = dict(recon.last_fit_report["bones_curve"])
    assert ref.num_bones == 2
    assert curve[1] > 1.0 >= curve[2]
    assert 3 not in curve  # stops at the first B within tolerance


@pytest.mark.parametrize("bad", [0, -3, "many", 2.5])
def test_bad_bone_counts_are_config_errors(bad: object) -> None:
    with pytest.raises(ConfigError, match="recon.bones"):
        build("recon", {"type": "skinning_fit", "bones": bad})


def test_more_bones_than_vertices_is_a_config_error() -> None:
    seq, _ = bending_cylinder(frames=2, n=5)
    recon = build("recon", {"type": "skinning_fit", "bones": 6, "iterations": 1})
    with pytest.raises(ConfigError, match="more bones than the 5 vertices"):
        recon.reconstruct(ReferenceInput(name="tiny", fps=10.0, mesh_sequence=seq))


def test_missing_mesh_sequence_is_an_input_error() -> None:
    recon = build("recon", {"type": "skinning_fit", "bones": 2})
    with pytest.raises(InputError, match="needs a mesh sequence"):
        recon.reconstruct(ReferenceInput(name="nothing", fps=10.0))


@pytest.mark.slow
def test_shiba_haru_fit_under_two_percent(shared_data) -> None:
    """ppr-diffphys shiba-haru-1002 (MIT): 21 meshes x 10,002 vertices, B = 13."""
    from sync4d.io.lab4d import find_mesh_files, read_mesh_sequence

    files = find_mesh_files(shared_data / "lab4d_export" / "shiba-haru-1002")
    seq, _, _ = read_mesh_sequence(files[:8])
    fit = fit_skinning(seq, 13, FitOptions(iterations=120, fit_vertices=800))
    assert fit.mean_error_pct < 2.0, fit.frame_error_pct
