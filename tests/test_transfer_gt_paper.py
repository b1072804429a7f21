"""transfer_paper: the paper's targets driven by clips without a truth; the follow error and the criteria fail a
frozen and a torn target."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d.errors import ConfigError
from sync4d_tools.evaluate import transfer_gt as G
from sync4d_tools.evaluate import transfer_paper as TP


def test_scene_list_pairs_each_experiment_with_its_clip_and_the_clips_with_the_paper_targets():
    todo = TP.scene_list(["human_to_cross", "laptop_to_shell"], ["original", "run"])
    assert todo == [("human_to_cross", "original"), ("laptop_to_shell", "original"), ("human_to_cross", "run")]
    with pytest.raises(ConfigError, match="--scenes"):
        TP.scene_list(["nope"], ["original"])
    with pytest.raises(ConfigError, match="--clips"):
        TP.scene_list(["human_to_cross"], ["moonwalk"])


@pytest.mark.slow
def test_cross_driven_by_a_run_fails_frozen_and_torn_targets():
    """The DeepMimic run onto the procedural cross (no ../shared needed): lbs-hard follows its drive exactly,
    the frozen target and a target whose matched parts fly apart fail the criteria."""
    scene = TP.build_scene("human_to_cross", "run", 4)
    rows = TP.score_scene(scene, G.resolve_methods(["lbs_hard", "kinematic"]), True, 4)
    assert rows["lbs_hard"]["follow_rotation_max_deg"] < 1e-6
    assert rows["frozen"]["follow_rotation_deg"] > 2.0
    hard, _ = G.run_method(scene.target, scene.part_map, G.resolve_methods(["lbs_hard"])["lbs_hard"], scene.motion, 4)
    x = hard.x.copy()
    limb = scene.part_map.tgt_part == np.argmax(np.bincount(scene.part_map.tgt_part))
    away = x[0, limb].mean(axis=0) - x[0].mean(axis=0)
    x[1:, limb] += 0.5 * away / np.linalg.norm(away)  # the largest part flies 50 cm off
    rows["detached"] = TP.score(scene, G.Trajectory(x=x, F=None, frame_dt=hard.frame_dt), [0.0] * 4)
    shredded = hard.x + np.random.default_rng(0).normal(scale=0.02, size=hard.x.shape) * (np.arange(4) > 0)[:, None, None]
    rows["shredded"] = TP.score(scene, G.Trajectory(x=shredded, F=None, frame_dt=hard.frame_dt), [0.0] * 4)
    frozen = TP.paper_criteria(rows, "frozen")
    assert not frozen["follow_mean_within_3deg"] or not frozen["follow_worst_within_15deg"]
    assert not frozen["passed"]
    detached = TP.paper_criteria(rows, "detached")
    assert not detached["passed"] and not detached["fragments_zero"]
    shredded = TP.paper_criteria(rows, "shredded")
    assert not shredded["passed"] and not shredded["torn_below_lbs_hard_at_10"]
    assert rows["lbs_hard"]["strain_p99_max_pct"] <= 5.0 or not shredded["strain_half_of_lbs_hard"]
    assert TP.paper_criteria(rows, "lbs_hard")["follow_mean_within_3deg"]  # the follow bars can be met
