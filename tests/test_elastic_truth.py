"""The elastic truth's solver on known answers: a rigid motion of every handle moves the whole solid rigidly, a bar
pulled by its end faces stretches uniformly; and bone cores sit on the bone, away from the joints."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

pytest.importorskip("igl")

from sync4d_tools.truth import elastic as E  # noqa: E402


def grid_tets(n: tuple[int, int, int], h: float) -> E.TetMesh:
    """A box of n cells (edge h [m]), each cube cut into six tets along its diagonal (a conforming mesh)."""
    idx = np.arange(np.prod(np.add(n, 1))).reshape(np.add(n, 1))
    vertices = np.stack(np.meshgrid(*[np.arange(k + 1) for k in n], indexing="ij"), -1).reshape(-1, 3) * h
    tets = []
    for order in itertools.permutations(range(3)):
        for cell in itertools.product(*[range(k) for k in n]):
            p = np.array(cell)
            path = [idx[tuple(p)]]
            for axis in order:
                p = p.copy()
                p[axis] += 1
                path.append(idx[tuple(p)])
            tets.append(path)
    tets = np.array(tets, dtype=np.int64)
    flip = E.tet_quality(vertices.astype(float), tets) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return E.TetMesh(vertices.astype(float), tets, np.ones(len(vertices), dtype=bool))


def rigid(angle: float, axis: int, shift) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    rot = np.eye(3)
    i, j = [k for k in range(3) if k != axis]
    rot[i, i], rot[i, j], rot[j, i], rot[j, j] = c, -s, s, c
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, shift
    return out


def test_bar_pulled_by_its_ends_stretches_uniformly():
    mesh = grid_tets((20, 4, 4), 0.05)  # 1 m x 0.2 m x 0.2 m
    x = mesh.vertices[:, 0]
    core = np.where(x < 1e-9, 0, np.where(x > 1 - 1e-9, 1, -1))
    motion = np.tile(np.eye(4), (3, 2, 1, 1))
    motion[1, 1, 0, 3], motion[2, 1, 0, 3] = 0.1, 0.3  # the far end pulled 10 cm, then 30 cm
    frames = E.arap_frames(mesh, core, motion)
    for t, s in ((0, 1.0), (1, 1.1), (2, 1.3)):
        expected = mesh.vertices * [s, 1.0, 1.0]
        assert np.abs(frames[t] - expected).max() < 1e-5


def test_every_handle_moved_rigidly_moves_the_solid_rigidly():
    import trimesh

    rng = np.random.default_rng(0)
    box = trimesh.creation.box(extents=[0.4, 0.2, 0.1])
    points = np.concatenate([rng.uniform(-0.2, 0.2, (600, 1)) * [1, 0, 0] + rng.uniform(-1, 1, (600, 3)) * [0, 0.1, 0.05],
                             box.sample(400, seed=1)])
    mesh = E.tetrahedralise(points, box.vertices, box.faces)
    assert mesh.used.mean() > 0.9 and len(mesh.tets) > len(points)
    core = np.where(np.abs(points[:, 0]) > 0.12, (points[:, 0] > 0).astype(int), -1)  # both ends, two bones
    move = rigid(0.8, 2, [0.3, -0.1, 0.2]) @ rigid(0.4, 0, [0, 0, 0])
    frames = E.arap_frames(mesh, core, np.stack([np.tile(np.eye(4), (2, 1, 1)), np.stack([move, move])]))
    expected = points @ move[:3, :3].T + move[:3, 3]
    # every vertex, the unused ones too, to the solver tolerance of 60 iterations from rest (~2e-5 of the size)
    assert np.abs(frames[1] - expected).max() < 1e-5
    assert np.abs(frames[0] - points).max() < 1e-8


def test_a_bent_joint_bends_the_solid_between_the_cores():
    mesh = grid_tets((20, 2, 2), 0.05)
    x = mesh.vertices[:, 0]
    core = np.where(x <= 0.3, 0, np.where(x >= 0.7, 1, -1))
    bend = rigid(np.radians(45.0), 2, [0, 0, 0])
    pivot = np.array([0.5, 0.05, 0.05])
    bend[:3, 3] = pivot - bend[:3, :3] @ pivot
    frames = E.arap_frames(mesh, core, np.stack([np.tile(np.eye(4), (2, 1, 1)), np.stack([np.eye(4), bend])]))
    held = core == 1
    np.testing.assert_allclose(frames[1][held], mesh.vertices[held] @ bend[:3, :3].T + bend[:3, 3], atol=1e-12)
    middle = np.abs(x - 0.5) < 0.01
    # the joint's middle turns about half-way, as an elastic joint does (neither rigid part's motion)
    d = frames[1][middle].mean(axis=0) - mesh.vertices[middle].mean(axis=0)
    assert 0.002 < np.linalg.norm(d) < 0.05


def test_bone_cores_lie_on_the_segment_and_avoid_the_joint():
    rng = np.random.default_rng(2)
    points = np.concatenate([rng.uniform([0, -0.05, -0.05], [1, 0.05, 0.05], (2000, 3))])
    weights = np.zeros((2000, 2))
    w1 = np.clip((points[:, 0] - 0.4) / 0.2, 0, 1)  # bones meet at x = 0.5, blended over 0.4..0.6
    weights[:, 0], weights[:, 1] = 1 - w1, w1
    centers = np.array([[0.25, 0, 0], [0.75, 0, 0]])
    cov = np.stack([np.diag([0.02, 0.001, 0.001])] * 2)
    core = E.bone_cores(points, weights, centers, cov)
    assert set(np.unique(core)) == {-1, 0, 1}
    radial = np.linalg.norm(points[:, 1:], axis=1)
    assert radial[core >= 0].max() < 0.05 and radial[core == -1].mean() > radial[core >= 0].mean()
    assert not ((core >= 0) & (np.abs(points[:, 0] - 0.5) < 0.08)).any()  # the blended joint is elastic
