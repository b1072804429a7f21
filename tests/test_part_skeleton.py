"""A drive a joined body can meet (``pivot=joint``): the target's parts as a tree, each child turning about its
joint with its parent and carried by it, so neighbours agree where they meet."""

from __future__ import annotations

import numpy as np

from sync4d.geometry import apply_rigid, rotation_about_axis
from sync4d.transfer.motion import articulate, part_skeleton


def body() -> tuple[np.ndarray, np.ndarray]:
    """A torso (part 1, the heaviest), an arm (part 0) on its right, a hand (part 2) on the arm's end, and a
    loose block (part 3) touching nothing."""
    g = np.stack(np.meshgrid(*[np.arange(0, 1, 0.05)] * 3, indexing="ij"), -1).reshape(-1, 3)
    torso = g * [0.3, 0.6, 0.2]
    arm = g[::4] * [0.3, 0.1, 0.1] + [0.3, 0.45, 0.05]
    hand = g[::16] * [0.08, 0.08, 0.08] + [0.6, 0.46, 0.06]
    loose = g[::16] * 0.1 + [2.0, 0.0, 0.0]
    points = np.concatenate([torso, arm, hand, loose])
    parts = np.repeat([1, 0, 2, 3], [len(torso), len(arm), len(hand), len(loose)])
    return points, parts


def test_the_skeleton_hangs_each_part_from_the_one_it_touches_most():
    points, parts = body()
    skeleton = part_skeleton(points, parts, 4)
    assert skeleton.parent.tolist() == [1, -1, 0, -1]
    assert abs(skeleton.joint[0, 0] - 0.3) < 0.03  # on the torso's right face, where the arm starts
    assert abs(skeleton.joint[2, 0] - 0.6) < 0.03
    order = skeleton.order.tolist()
    assert order.index(1) < order.index(0) < order.index(2)


def test_articulated_neighbours_agree_at_their_joints():
    points, parts = body()
    skeleton = part_skeleton(points, parts, 4)
    T = 5
    relative = np.tile(np.eye(4), (T, 4, 1, 1))
    for t in range(T):  # each part turns about its own centroid, as the part-centroid drive does
        for b, angle in ((0, 15.0 * t), (1, 5.0 * t), (2, -20.0 * t)):
            rot = rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.array([np.deg2rad(angle)]))[0]
            c = points[parts == b].mean(0)
            relative[t, b, :3, :3], relative[t, b, :3, 3] = rot, c - rot @ c + [0.01 * t, 0, 0]
    out = articulate(relative, skeleton)
    for child in (0, 2):
        j = skeleton.joint[child]
        parent = skeleton.parent[child]
        gap_before = max(np.linalg.norm(apply_rigid(relative[t, child], j[None]) - apply_rigid(relative[t, parent], j[None]))
                         for t in range(T))
        gap_after = max(np.linalg.norm(apply_rigid(out[t, child], j[None]) - apply_rigid(out[t, parent], j[None]))
                        for t in range(T))
        assert gap_before > 0.02 and gap_after < 1e-12
        np.testing.assert_allclose(out[:, child, :3, :3], relative[:, child, :3, :3])  # its own rotation kept
    np.testing.assert_allclose(out[:, [1, 3]], relative[:, [1, 3]])  # roots unchanged


def test_touching_parts_that_swing_apart_are_not_joined():
    """Two thighs touching along their length hang from the pelvis they swing about, not from each other, when
    the driving motion is known (by contact alone they would join each other: they touch the most)."""
    g = np.stack(np.meshgrid(*[np.arange(0, 1, 0.05)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pelvis = g * [0.6, 0.15, 0.02] + [-0.15, 0.478, 0.04]  # a thin plate on the thighs' tops (ties in weight)
    left = g * [0.1, 0.5, 0.1] + [0.048, 0.0, 0.0]
    right = g * [0.1, 0.5, 0.1] + [0.151, 0.0, 0.0]
    points = np.concatenate([pelvis, left, right])
    parts = np.repeat([0, 1, 2], [len(pelvis), len(left), len(right)])
    assert part_skeleton(points, parts, 3).parent.tolist() == [-1, 2, 0]  # contact alone chains the thighs
    T = 6
    motion = np.tile(np.eye(4), (T, 3, 1, 1))
    for t in range(T):
        for b, sign, hip in ((1, 1.0, [0.1, 0.5, 0.05]), (2, -1.0, [0.2, 0.5, 0.05])):
            rot = rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.array([sign * np.deg2rad(6.0 * t)]))[0]
            motion[t, b, :3, :3], motion[t, b, :3, 3] = rot, np.asarray(hip) - rot @ hip
    skeleton = part_skeleton(points, parts, 3, motion=motion)
    assert skeleton.parent.tolist() == [-1, 0, 0]
