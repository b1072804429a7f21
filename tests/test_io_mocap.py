"""BVH parsing and forward kinematics; joint-position files and skeleton inference."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sync4d.errors import DataMissingError, InputError
from sync4d.io.mocap import (
    infer_skeleton,
    minimal_rotation,
    parse_bvh,
    read_bvh,
    read_joint_position_motion,
    read_joint_positions,
    rotations_from_positions,
)

TINY_BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT Thigh
  {
    OFFSET 0 -1 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT Shin
    {
      OFFSET 0 -2 0
      CHANNELS 3 Zrotation Yrotation Xrotation
      End Site
      {
        OFFSET 0 0 0.5
      }
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.5
0 10 0   0 0 0   0 0 0   0 0 0
1 10 0   0 90 0  0 0 90  0 0 0
2 10 0   0 0 0   30 20 10  0 0 45
"""


def write(tmp_path: Path, text: str = TINY_BVH) -> Path:
    path = tmp_path / "tiny.bvh"
    path.write_text(text)
    return path


def test_bvh_hierarchy_and_motion(tmp_path: Path) -> None:
    skel, motion, frame_time = parse_bvh(TINY_BVH)
    assert skel.names == ("Hips", "Thigh", "Shin", "Shin_End")
    assert skel.parents.tolist() == [-1, 0, 1, 2]
    assert motion.shape == (3, 12) and frame_time == 0.5
    assert skel.channels[3] == ()


def test_bvh_forward_kinematics_by_hand(tmp_path: Path) -> None:
    m = read_bvh(write(tmp_path), unit_scale=0.5)
    assert m.fps == 2.0 and m.positions.shape == (3, 4, 3)
    # frame 0: straight down chain from (0, 5, 0)
    assert np.allclose(m.positions[0], [[0, 5, 0], [0, 4.5, 0], [0, 3.5, 0], [0, 3.5, 0.25]])
    # frame 1: root turned 90 deg about y, thigh 90 deg about x: the shin points along the root's +z -> world +x
    root_r = Rotation.from_euler("Y", 90, degrees=True).as_matrix()
    thigh_r = root_r @ Rotation.from_euler("X", 90, degrees=True).as_matrix()
    knee = np.array([0.5, 4.5, 0]) + thigh_r @ np.array([0, -1.0, 0])
    assert np.allclose(m.positions[1, 2], knee)
    assert np.allclose(m.rotations[1, 1], thigh_r)


def test_bvh_bone_lengths_are_constant(tmp_path: Path) -> None:
    m = read_bvh(write(tmp_path), unit_scale=1.0)
    lengths = np.linalg.norm(m.positions[:, 1:] - m.positions[:, m.parents[1:]], axis=-1)
    assert np.abs(lengths - lengths[0]).max() < 1e-12


@pytest.mark.parametrize(
    "text, match",
    [
        ("nonsense", "not a BVH"),
        (TINY_BVH.replace("Frames: 3", "Frames: 4"), "MOTION holds 36 numbers"),
        (TINY_BVH.split("MOTION")[0], "no MOTION"),
        (TINY_BVH.replace("Frame Time: 0.5", "Frame Time: 0"), "Frame Time must be > 0"),
    ],
)
def test_bvh_errors(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(InputError, match=match):
        read_bvh(write(tmp_path, text))


def test_missing_files(tmp_path: Path) -> None:
    with pytest.raises(DataMissingError, match="absent.bvh"):
        read_bvh(tmp_path / "absent.bvh")
    with pytest.raises(DataMissingError):
        read_joint_positions(tmp_path / "absent.txt")


def test_minimal_rotation() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(10, 3)), rng.normal(size=(10, 3))
    r = minimal_rotation(a, b)
    assert np.allclose(np.einsum("nij,nj->ni", r, a / np.linalg.norm(a, axis=1, keepdims=True)),
                       b / np.linalg.norm(b, axis=1, keepdims=True))
    assert np.allclose(np.linalg.det(r), 1.0)
    # the axis a x b is fixed (minimal: no twist)
    axis = np.cross(a, b)
    assert np.allclose(np.einsum("nij,nj->ni", r, axis), axis)
    flip = minimal_rotation(np.array([1.0, 0, 0]), np.array([-1.0, 0, 0]))
    assert np.allclose(flip @ [1, 0, 0], [-1, 0, 0]) and np.isclose(np.linalg.det(flip), 1)


def chain_motion(frames: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """(T, 5, 3) a Y-shaped rigid tree walking along x with a swinging branch; and its parents."""
    parents = np.array([-1, 0, 1, 1, 3])
    out = []
    for t in range(frames):
        a = 0.5 * np.sin(t)
        root = np.array([0.2 * t, 1.0, 0.0])
        p1 = root + [0, 0.3, 0]
        p2 = p1 + [0.25, 0.25, 0]
        p3 = p1 + [-0.3 * np.cos(a), 0.3 * np.sin(a), 0]
        p4 = p3 + [-0.2 * np.cos(2 * a), 0.2 * np.sin(2 * a), 0]
        out.append([root, p1, p2, p3, p4])
    return np.asarray(out), parents


def test_infer_skeleton_recovers_a_rigid_tree() -> None:
    pos, parents = chain_motion()
    assert infer_skeleton(pos, root=0).tolist() == parents.tolist()


def test_joint_position_file_roundtrip(tmp_path: Path) -> None:
    pos, parents = chain_motion()
    path = tmp_path / "joints.txt"
    path.write_text("\n".join(",\t".join(f"{v:.6f}" for v in frame.reshape(-1)) for frame in pos))
    m = read_joint_position_motion(path, fps=30.0)
    assert m.positions.shape == (8, 5, 3) and m.parents.tolist() == parents.tolist() and m.rotations is None
    (tmp_path / "ragged.txt").write_text("1 2 3\n1 2 3 4 5 6\n")
    with pytest.raises(InputError, match="different lengths"):
        read_joint_positions(tmp_path / "ragged.txt")
    (tmp_path / "odd.txt").write_text("1 2 3 4\n")
    with pytest.raises(InputError, match="multiple of 3"):
        read_joint_positions(tmp_path / "odd.txt")


def test_rotations_from_positions_carry_segments() -> None:
    pos, parents = chain_motion()
    rot = rotations_from_positions(pos, parents)
    assert np.allclose(rot[0], np.eye(3))
    # segment 3 -> 4 is carried exactly by joint 3's rotation
    carried = np.einsum("tij,j->ti", rot[:, 3], pos[0, 4] - pos[0, 3])
    assert np.allclose(carried, pos[:, 4] - pos[:, 3], atol=1e-9)
    assert np.allclose(np.linalg.det(rot), 1.0)


def test_cmu_bvh(shared_data: Path) -> None:
    """CMU mocap 131_01 (mocap.cs.cmu.edu; created with funding from NSF EIA-0196217), via bvh11."""
    m = read_bvh(shared_data / "motion" / "cmu_bvh" / "131_01.bvh")
    real = [n for n in m.names if not n.endswith("_End")]
    assert len(real) == 31 and m.num_frames == 994 and abs(m.fps - 120.0) < 0.01
    child = np.flatnonzero(m.parents >= 0)
    lengths = np.linalg.norm(m.positions[:, child] - m.positions[:, m.parents[child]], axis=-1)
    assert np.abs(lengths - lengths[0]).max() < 1e-6
    # a standing adult in metres: feet near y = 0, head ~1.5-1.9 m up
    height = m.positions[0, :, 1].max() - m.positions[0, :, 1].min()
    assert 1.3 < height < 2.0
