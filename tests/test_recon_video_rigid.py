"""``recon.video.rigid``: first labels under a known moving camera from the tracks' rigid motions."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d.recon.video.rigid import project_frames, rigid_labels

K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])


def look_at(eye: np.ndarray) -> np.ndarray:
    """(4, 4) world-to-camera of a camera at ``eye`` (3,) [m] looking at the origin, world +Y up (image down)."""
    forward = -eye / np.linalg.norm(eye)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([right, down, forward])
    w2c[:3, 3] = -w2c[:3, :3] @ eye
    return w2c


def rot_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def two_part_scene(frames: int = 10, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A still box's front (z = 0.1 m plane, lower half) and a lid above it turning about its bottom edge (a
    level hinge, 3 deg a frame), filmed from above (about 30 deg) by a camera orbiting 1.2 deg a frame; returns (uv0 (N, 2),
    uv (T, N, 2) [px] with 0.1 px noise, extrinsics (T, 4, 4), true labels (N,))."""
    xs, ys = np.meshgrid(np.linspace(-0.4, 0.4, 17), np.linspace(-0.4, 0.4, 17))
    pts = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.1)], 1)
    truth = (pts[:, 1] > 0.01).astype(int)  # the upper half is the lid
    hinge = np.array([0.0, 0.01, 0.1])
    angles = np.deg2rad(1.2 * np.arange(frames))
    extrinsics = np.stack([look_at(2.0 * np.array([np.sin(a), 0.6, np.cos(a)])) for a in angles])
    uv = np.empty((frames, len(pts), 2))
    for t in range(frames):
        moved = pts.copy()
        moved[truth == 1] = (pts[truth == 1] - hinge) @ rot_x(np.deg2rad(-3.0 * t)).T + hinge
        uv[t] = np.stack([project_frames(moved[n:n + 1], extrinsics[t:t + 1], K)[0, 0] for n in range(len(pts))])
    uv += np.random.default_rng(seed).normal(0.0, 0.1, uv.shape)
    return uv[0].copy(), uv, extrinsics, truth


FAR = np.abs(np.repeat(np.linspace(-0.4, 0.4, 17), 17) - 0.01) > 0.1  # points over 0.1 m from the hinge line


def test_a_turning_lid_is_told_from_the_still_box_under_a_moving_camera() -> None:
    uv0, uv, extrinsics, truth = two_part_scene()
    labels, depth, still = rigid_labels(uv0, uv, np.ones(uv.shape[:2], bool), K, extrinsics, 2,
                                        np.random.default_rng(0))
    assert still.shape == uv.shape and depth.shape == truth.shape
    # part 0 is the still root, not a permutation; the lid's two rows next to its hinge move little
    assert (labels == truth).mean() > 0.85
    assert (labels[FAR] == truth[FAR]).all()


def test_one_part_is_all_root() -> None:
    uv0, uv, extrinsics, _ = two_part_scene(frames=4)
    labels = rigid_labels(uv0, uv, np.ones(uv.shape[:2], bool), K, extrinsics, 1, np.random.default_rng(0))[0]
    assert (labels == 0).all()


@pytest.mark.parametrize("parts", [2, 3])
def test_every_part_keeps_tracks_when_nothing_moves(parts: int) -> None:
    uv0, uv, extrinsics, _ = two_part_scene(frames=4)
    still_uv = np.stack([uv0] * len(uv))  # a camera that moves while the tracks do not: nothing is explained
    labels = rigid_labels(uv0, still_uv, np.ones(uv.shape[:2], bool), K, extrinsics, parts,
                          np.random.default_rng(0))[0]
    assert set(np.unique(labels)) == set(range(parts))
