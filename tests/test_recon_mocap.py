"""recon=mocap and the capsule body."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from sync4d.errors import ConfigError, InputError
from sync4d.recon.body import capsule_body, capsule_mesh, segment_skinning, skeleton_segments
from sync4d.recon.mocap import merge_segments
from sync4d.registry import build
from sync4d.types import ReferenceInput

from tests.test_io_mocap import TINY_BVH, chain_motion


def test_capsule_mesh_is_watertight_with_the_right_volume() -> None:
    v, f = capsule_mesh(np.zeros(3), np.array([0.3, 0.4, 0.0]), 0.1, rings=12, sectors=32)
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    exact = np.pi * 0.01 * 0.5 + 4 / 3 * np.pi * 0.001
    assert abs(mesh.volume - exact) / exact < 0.03


def test_capsule_body_labels_and_proportions() -> None:
    joints = np.array([[0, 0, 0], [0, 0, 0], [0, 1.0, 0], [0.5, 1.5, 0], [-0.5, 1.5, 0]])
    parents = np.array([-1, 0, 1, 2, 2])
    assert skeleton_segments(joints, parents).tolist() == [2, 3, 4]  # zero-length 0 -> 1 skipped
    v, f, seg = capsule_body(joints, parents, 0.1)
    assert set(seg.tolist()) == {2, 3, 4} and f.max() < len(v)
    for j in (2, 3, 4):  # every vertex lies on its own capsule's surface
        a, b = joints[parents[j]], joints[j]
        pts = v[seg == j]
        s = np.clip((pts - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
        dist = np.linalg.norm(pts - (a + s[:, None] * (b - a)), axis=1)
        assert np.allclose(dist, 0.1 * np.linalg.norm(b - a))
    thin = trimesh.Trimesh(*capsule_body(joints, parents, 0.05)[:2], process=False)
    thick = trimesh.Trimesh(*capsule_body(joints, parents, 0.2)[:2], process=False)
    assert thick.volume > 4 * thin.volume
    with pytest.raises(ValueError):
        capsule_body(np.zeros((2, 3)), np.array([-1, 0]))


def test_segment_skinning_prefers_the_nearest_segment() -> None:
    joints = np.array([[0, 0, 0], [0, 1.0, 0], [0, 2.0, 0]])
    parents = np.array([-1, 0, 1])
    w = segment_skinning(np.array([[0.1, 0.2, 0], [0.1, 1.8, 0], [0.0, 1.0, 0.1]]), joints, parents,
                         np.array([1, 2]), np.array([0.1, 0.1]))
    assert np.allclose(w.sum(1), 1) and w[0, 0] > 0.99 and w[1, 1] > 0.99 and abs(w[2, 0] - 0.5) < 1e-9


def test_merge_segments_reduces_bones() -> None:
    pos, parents = chain_motion()
    segs = skeleton_segments(pos[0], parents)
    labels = merge_segments(pos[0], parents, segs, 2)
    assert sorted(set(labels.tolist())) == [0, 1]


def test_bvh_reference(tmp_path: Path) -> None:
    path = tmp_path / "tiny.bvh"
    path.write_text(TINY_BVH)
    src = build("reference", {"type": "bvh", "path": str(path)}).load()
    assert src.fps == 2.0
    recon = build("recon", {"type": "mocap", "bvh_unit_scale": 0.5, "target_fps": 0.0}, device="cpu")
    ref = recon.reconstruct(src)
    assert ref.num_bones == 3 and ref.num_frames == 3  # Thigh, Shin, Shin_End segments
    rep = recon.last_fit_report
    assert rep["bone_length_max_dev"] < 1e-12 and rep["joint_error_m"] < 1e-12
    assert np.isclose(rep["root_travel_m"], 1.0)  # root x goes 0 -> 2 file units = 1 m
    # root motion is in G_t: the root's rest position maps to its frame-2 position
    root_rest = np.array([0.0, 5.0, 0.0])
    assert np.allclose(ref.global_transforms[2] @ np.append(root_rest, 1), [1.0, 5.0, 0.0, 1.0])
    # posed body stays around the posed skeleton: the shin capsule centre follows the knee-ankle midpoint
    motion = recon.last_motion
    shin = ref.bone_names.index("Shin")
    mid = 0.5 * (motion.positions[:, 1] + motion.positions[:, 2])
    centres = np.einsum("tij,tj->ti", ref.global_transforms, np.concatenate(
        [ref.bone_centers_at()[:, shin], np.ones((3, 1))], 1))[:, :3]
    assert np.allclose(centres, mid, atol=1e-9)


def test_target_fps_and_heading(tmp_path: Path) -> None:
    path = tmp_path / "tiny.bvh"
    path.write_text(TINY_BVH)
    recon = build("recon", {"type": "mocap", "target_fps": 1.0, "global_motion": "heading"})
    ref = recon.reconstruct(ReferenceInput(name="tiny", fps=2.0, path=str(path)))
    assert ref.num_frames == 2 and ref.fps == 1.0
    # heading keeps G_t a rotation about the vertical (y) axis
    assert np.allclose(ref.global_transforms[:, 1, :3], [0, 1, 0])


def test_joint_positions_reference(tmp_path: Path) -> None:
    pos, parents = chain_motion()
    path = tmp_path / "joints.txt"
    path.write_text("\n".join(" ".join(f"{v:.9f}" for v in frame.reshape(-1)) for frame in pos))
    recon = build("recon", {"type": "mocap", "target_fps": 0.0, "min_radius": 0.01})
    ref = recon.reconstruct(ReferenceInput(name="tree", fps=30.0, path=str(path)))
    assert ref.num_bones == 4
    # single-child joints carry their segments exactly
    assert recon.last_fit_report["bone_length_max_dev"] < 1e-6
    assert np.isclose(recon.last_fit_report["root_travel_m"], 0.2 * 7)


def test_config_and_input_errors() -> None:
    with pytest.raises(ConfigError, match="recon.bones"):
        build("recon", {"type": "mocap", "bones": 0})
    with pytest.raises(ConfigError, match="global_motion"):
        build("recon", {"type": "mocap", "global_motion": "sideways"})
    with pytest.raises(InputError, match="no path"):
        build("recon", {"type": "mocap"}).reconstruct(ReferenceInput(name="x", fps=1.0))


def test_cmu_walk(shared_data: Path) -> None:
    """CMU mocap 131_01 (mocap.cs.cmu.edu; NSF EIA-0196217), via yuki-koyama/bvh11."""
    src = build("reference", {"type": "bvh", "path": str(shared_data / "motion/cmu_bvh/131_01.bvh")}).load()
    recon = build("recon", {"type": "mocap", "target_fps": 30.0, "bones": 11})
    ref = recon.reconstruct(src)
    rep = recon.last_fit_report
    assert ref.num_bones == 11 and abs(ref.fps - 30.0) < 0.01 and ref.num_frames == 249
    assert rep["bone_length_max_dev"] < 1e-6
    assert 2.0 < rep["root_travel_m"] < 3.5


def test_dog_trot(shared_data: Path) -> None:
    """AI4Animation dog trot via erwincoumans/motion_imitation (CC BY-NC 4.0)."""
    src = build("reference", {"type": "joint_positions",
                              "path": str(shared_data / "motion/dog_mocap/dog_trot_joint_pos.txt")}).load()
    mann = [-1, 0, 1, 2, 3, 4, 2, 6, 7, 8, 9, 2, 11, 12, 13, 14, 0, 16, 17, 18, 0, 20, 21, 22, 0, 24, 25]
    recon = build("recon", {"type": "mocap", "parents": mann, "target_fps": 0.0})
    ref = recon.reconstruct(src)
    assert ref.num_frames == 33 and ref.num_bones == 25  # 26 segments minus the zero-length 0 -> 1
    assert recon.last_fit_report["bone_length_max_dev"] < 1e-4
    assert recon.last_fit_report["joint_error_m"] < 1e-4  # each segment end lands on its joint
    assert recon.last_fit_report["root_travel_m"] > 0.5
