"""The articulated suite: its objects, a tiny MuJoCo clip in the laptop renders' layout, and its scores."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sync4d_tools.articulated.objects import suite_objects
from sync4d_tools.evaluate.recon_suite import part_mapping, passes


def test_suite_has_what_the_issue_asks() -> None:
    """>= 8 objects, >= 2 slides, one with three parts, textured and plain, starting closed and open."""
    objects = suite_objects()
    assert len(objects) >= 8
    kinds = [k for o in objects for k in o.joints]
    assert len(kinds) >= 9
    assert any(len(o.joints) == 2 for o in objects)
    assert {o.textured for o in objects} == {True, False}
    for o in objects:
        values = o.trajectory(24)
        assert values.shape == (24, len(o.joints))
        assert np.allclose(values[0], o.start) and np.allclose(values[-1], o.start)
        assert np.allclose(values[np.argmax(np.abs(values - values[0]).sum(1))], o.turn, atol=0.02)


def test_part_mapping_scores_and_can_fail() -> None:
    """Bones named either way map to their parts; relabelling half of one part lowers the score."""
    gt = np.zeros((2, 4, 4), np.uint8)
    gt[:, :, :2], gt[:, :, 2:] = 1, 2
    rendered = [np.where(gt[t][gt[t] > 0] == 1, 1, 0) for t in range(2)]  # bone 1 = base, bone 0 = lid
    mapping, _, agree = part_mapping(rendered, gt, 2, 2)
    assert mapping.tolist() == [2, 1] and agree == 1.0
    broken = [r.copy() for r in rendered]
    broken[0][:4] = 1 - broken[0][:4]
    assert part_mapping(broken, gt, 2, 2)[2] < 0.9
    assert passes([{"error": 2.9}], 0.96) and not passes([{"error": 3.1}], 0.99) and not passes([], 0.94)


@pytest.mark.slow
def test_a_tiny_mujoco_clip_has_the_laptop_layout(tmp_path: Path) -> None:
    import os

    os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is first imported: headless rendering
    pytest.importorskip("mujoco")
    pytest.importorskip("metaworld")
    from sync4d_tools.articulated.render import VIEWS, render_clip

    obj = next(o for o in suite_objects() if o.name == "desk_lid_drawer")
    try:
        render_clip(obj, VIEWS[0], tmp_path / "clip", frames=4, width=64, height=48, cache=tmp_path)
    except Exception as err:  # no OpenGL context on this machine: nothing to check
        pytest.skip(f"MuJoCo cannot render here: {err}")
    gt = dict(np.load(tmp_path / "clip" / "gt.npz"))
    assert gt["part_labels"].shape == (4, 48, 64) and set(np.unique(gt["part_labels"])) <= {0, 1, 2, 3}
    assert gt["joint_type"].tolist() == ["hinge", "slide"] and gt["joint_value"].shape == (4, 2)
    assert {"K", "cam_pos", "cam_forward", "cam_up", "part_depth_m"} <= set(gt)
    assert len(list((tmp_path / "clip" / "masks").glob("*.png"))) == 4
