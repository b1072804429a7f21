"""DeepMimic clips: URDF skeleton, JSON frames, forward kinematics (analytic cases), and the shared walk."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sync4d.errors import ConfigError, InputError
from sync4d.geometry import quat_to_matrix
from sync4d.io.deepmimic import (
    parse_deepmimic_frames,
    read_deepmimic,
    read_urdf_skeleton,
    rpy_matrix,
)

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "motion" / "deepmimic"

# base -> root (fixed) -> upper (spherical, 1 up) -> lower (revolute about z, 2 along -y in upper's
# frame); lower is a leaf with a sphere of radius 0.5 centred 1 further down -> end site at 1.5.
URDF = """<robot name="arm">
  <link name="base"/>
  <link name="root"/>
  <link name="upper"/>
  <link name="lower"><collision><origin rpy="0 0 0" xyz="0 -1 0"/><geometry><sphere radius="0.5"/></geometry></collision></link>
  <joint name="root" type="fixed"><parent link="base"/><child link="root"/><origin rpy="0 0 0" xyz="0 0 0"/></joint>
  <joint name="upper" type="spherical"><parent link="root"/><child link="upper"/><origin rpy="0 0 0" xyz="0 1 0"/></joint>
  <joint name="lower" type="revolute"><parent link="upper"/><child link="lower"/><origin rpy="0 0 0" xyz="0 -2 0"/><axis xyz="0 0 1"/></joint>
</robot>
"""


def write_clip(folder: Path, frames: list[list[float]]) -> tuple[Path, Path]:
    urdf = folder / "arm.urdf"
    urdf.write_text(URDF)
    clip = folder / "clip.txt"
    clip.write_text(json.dumps({"Loop": "none", "Frames": frames}))
    return clip, urdf


def test_rotation_helpers_match_scipy() -> None:
    rpy = np.array([0.3, -0.7, 1.1])
    np.testing.assert_allclose(rpy_matrix(rpy), Rotation.from_euler("xyz", rpy).as_matrix(), atol=1e-12)
    q = np.array([0.8, 0.1, -0.4, 0.3])
    expected = Rotation.from_quat(np.r_[q[1:], q[0]]).as_matrix()  # scipy wants (x, y, z, w)
    np.testing.assert_allclose(quat_to_matrix(q), expected, atol=1e-12)


def test_urdf_tree_order_scale_and_end_site(tmp_path: Path) -> None:
    _, urdf = write_clip(tmp_path, [[0.1] + [0.0] * 8 + [0.0]])
    sk = read_urdf_skeleton(urdf, scale=0.5)
    assert sk.names == ("root", "upper", "lower", "lower_end")
    assert sk.parents.tolist() == [-1, 0, 1, 2]
    assert sk.types == ("root", "spherical", "revolute", "end")
    np.testing.assert_allclose(sk.offsets[2], [0.0, -1.0, 0.0])       # 0.5 x (0, -2, 0)
    np.testing.assert_allclose(sk.offsets[3], [0.0, -0.75, 0.0])      # 0.5 x (centre 1 + radius 0.5)
    assert sk.motion_width == 8 + 4 + 1


def test_forward_kinematics_against_hand_computed_poses(tmp_path: Path) -> None:
    half = np.sqrt(0.5)
    frames = [
        # at rest: root at the origin, no rotations
        [0.05, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0.0],
        # root moved by (3, 0, 0); upper turned 90 deg about x; elbow bent 90 deg about z
        [0.05, 3, 0, 0, 1, 0, 0, 0, half, half, 0, 0, np.pi / 2],
    ]
    clip, urdf = write_clip(tmp_path, frames)
    motion = read_deepmimic(clip, urdf, urdf_scale=1.0)
    assert motion.fps == pytest.approx(20.0) and motion.up_axis == 1
    pos = motion.positions
    np.testing.assert_allclose(pos[0], [[0, 0, 0], [0, 1, 0], [0, -1, 0], [0, -2.5, 0]], atol=1e-12)
    # frame 1: upper at root + (0, 1, 0); its frame turns y into z, so the elbow offset (0, -2, 0)
    # lands at (0, 0, -2); the bend about the (turned) z axis, i.e. world -y, swings the end site's
    # (0, -1.5, 0) from world -z to world -x.
    np.testing.assert_allclose(pos[1, 1], [3, 1, 0], atol=1e-12)
    np.testing.assert_allclose(pos[1, 2], [3, 1, -2], atol=1e-12)
    np.testing.assert_allclose(pos[1, 3], [3 + 1.5, 1, -2], atol=1e-12)
    lengths = np.linalg.norm(pos[:, 1:] - pos[:, motion.parents[1:]], axis=2)
    np.testing.assert_allclose(lengths[0], lengths[1], atol=1e-12)


@pytest.mark.parametrize(
    "text, message",
    [
        ("not json", "not a DeepMimic clip"),
        ('{"Loop": "wrap"}', "no 'Frames'"),
        ('{"Frames": [[0.1, 1, 2], [0.1, 1]]}', "differ in length"),
        ('{"Frames": [[0.1, NaN], [0.1, 1]]}', "NaN"),
        ('{"Frames": [[0.0, 1], [0.1, 1]]}', "durations"),
    ],
)
def test_malformed_clips_name_the_problem(text: str, message: str) -> None:
    with pytest.raises(InputError, match=message):
        parse_deepmimic_frames(text, source="clip.txt")


def test_clip_that_does_not_fit_its_urdf(tmp_path: Path) -> None:
    clip, urdf = write_clip(tmp_path, [[0.1] + [0.0] * 10, [0.1] + [0.0] * 10])
    with pytest.raises(InputError, match="needs 13"):
        read_deepmimic(clip, urdf)


def test_mocap_reconstructor_reads_a_clip_by_content_and_finds_its_urdf(tmp_path: Path) -> None:
    from sync4d.recon.mocap import MocapReconstructor
    from sync4d.types import ReferenceInput

    frames = [[0.05, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, a] for a in np.linspace(0, 1.2, 6)]
    clip, _ = write_clip(tmp_path, frames)
    recon = MocapReconstructor(MocapReconstructor.Config(target_fps=0.0))
    ref = recon.reconstruct(ReferenceInput(name="arm", fps=20.0, path=str(clip)))
    assert ref.num_frames == 6 and recon.last_fit_report["bone_length_max_dev"] < 1e-9
    (tmp_path / "other.urdf").write_text(URDF)
    with pytest.raises(ConfigError, match="recon.urdf"):
        recon.reconstruct(ReferenceInput(name="arm", fps=20.0, path=str(clip)))


@pytest.mark.skipif(not (SHARED / "humanoid3d_walk.txt").is_file(), reason="needs ../shared/data/motion/deepmimic")
def test_shared_humanoid_walk_is_rigid_and_walks() -> None:
    motion = read_deepmimic(SHARED / "humanoid3d_walk.txt", SHARED / "humanoid.urdf")
    assert motion.positions.shape == (39, 20, 3) and motion.fps == pytest.approx(30.0, rel=1e-3)
    pos = motion.positions
    lengths = np.linalg.norm(pos[:, 1:] - pos[:, motion.parents[1:]], axis=2)
    assert np.abs(lengths - lengths[0]).max() < 1e-9
    # a 1.6 m humanoid standing on the ground (Y up) that walks about a metre forward
    assert pos[0, :, 1].max() == pytest.approx(1.58, abs=0.05) and pos[0, :, 1].min() < 0.05
    assert 0.8 < np.linalg.norm(pos[-1, 0, [0, 2]] - pos[0, 0, [0, 2]]) < 1.6
