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
