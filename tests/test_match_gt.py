"""Helpers of ``python -m sync4d.evaluate match_gt`` on a tiny synthetic skeleton (no shared data)."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d.evaluate.match_gt import (
    body_reference,
    grouped_body,
    rescale_skeleton,
    sample_labelled_surface,
    segment_to_part,
)

# A 'T': root 0 -> spine 1 -> left arm 2, right arm 3.
JOINTS = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-0.6, 1.0, 0.0], [0.6, 1.0, 0.0]])
PARENTS = np.array([-1, 0, 1, 1])


def test_rescale_skeleton_scales_segments_and_carries_children() -> None:
    out = rescale_skeleton(JOINTS, PARENTS, np.array([1.0, 2.0, 0.5, 1.0]))
    assert np.allclose(out[1], [0.0, 2.0, 0.0])
    assert np.allclose(out[2], [-0.3, 2.0, 0.0])
    assert np.allclose(out[3], [0.6, 2.0, 0.0])


def test_grouped_body_keeps_outer_surface_with_parts() -> None:
    joint_part = segment_to_part(["root", "spine", "larm", "rarm"], {"body": ("spine",), "arms": ("larm", "rarm")})
    assert joint_part.tolist() == [-1, 0, 1, 1]
    body = grouped_body(JOINTS, PARENTS, joint_part, np.array([0.15, 0.08]), ("body", "arms"), max_edge=0.1)
    assert set(np.unique(body.part)) == {0, 1}
    # no kept vertex is buried inside the spine capsule while belonging to an arm
    arm = body.vertices[body.part == 1]
    d_spine = np.linalg.norm(arm[:, [0, 2]], axis=1)  # distance to the vertical spine axis
    assert (d_spine[(arm[:, 1] > 0) & (arm[:, 1] < 1)] >= 0.15 * 0.98 - 1e-6).all()
    ref = body_reference(body, name="t")
    assert ref.num_bones == 2 and np.array_equal(ref.part_labels(), body.part)
    pts, lab = sample_labelled_surface(body.vertices, body.faces, body.part, 500, np.random.default_rng(0))
    assert pts.shape == (500, 3) and set(np.unique(lab)) == {0, 1}
    assert np.mean(lab == 1) == pytest.approx(np.mean(np.abs(pts[:, 0]) > 0.15), abs=0.1)
