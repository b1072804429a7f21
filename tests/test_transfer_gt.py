"""transfer_gt: pairs with two truths (the target's own skinning model, an elastic solid), the floor and the
ceiling beside every method, and criteria that fail a frozen and a torn target."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sync4d.registry import component
from sync4d.sim.kinematic import Kinematic
from sync4d.sim.lbs import LinearBlendSkinning
from sync4d.transfer import TransferConfig, run_transfer
from sync4d_tools.evaluate import transfer_gt as G
from sync4d_tools.truth import pairs as P

pytest.importorskip("igl")


@pytest.fixture(scope="module")
def laptop():
    return P.load_pair("laptop", 5, 600)


def test_rescaled_skeleton_keeps_every_segment_direction_and_scales_its_length():
    from sync4d.io.mocap import SkeletonMotion

    rng = np.random.default_rng(0)
    parents = np.array([-1, 0, 1, 0, 3])
    pos = np.cumsum(rng.normal(size=(4, 5, 3)), axis=1)
    pos[:, 3] = pos[:, 0] + rng.normal(size=(4, 3))
    pos[:, 4] = pos[:, 3] + rng.normal(size=(4, 3))
    m = SkeletonMotion(tuple("abcde"), parents, pos, None, 30.0)
    factors = np.array([1.0, 1.5, 0.5, 2.0, 1.0])
    out = P.rescale_segments(m, factors).positions
    for j in range(1, 5):
        a, b = pos[:, j] - pos[:, parents[j]], out[:, j] - out[:, parents[j]]
        np.testing.assert_allclose(b, factors[j] * a, atol=1e-12)
    np.testing.assert_allclose(out[:, 0], pos[:, 0])


def test_laptop_truths_turn_the_lid_about_the_targets_own_hinge(laptop):
    from sync4d.scenes.laptop import hinge_pivot

    skin, solid = laptop.truths["skinning"], laptop.truths["elastic"]
    np.testing.assert_allclose(skin[0], laptop.target.means, atol=1e-12)
    np.testing.assert_allclose(solid[0], laptop.target.means, atol=1e-6)
    lid = laptop.part_map.tgt_part == 1
    pivot = hinge_pivot(0.18, 0.03)  # the target's depth and base thickness, not the reference's
    r0 = np.linalg.norm((skin[0, lid] - pivot)[:, 1:], axis=1)
    for t in range(1, 5):
        # distances to the target's hinge axis (x through the pivot) are kept; the base does not move
        np.testing.assert_allclose(np.linalg.norm((skin[t, lid] - pivot)[:, 1:], axis=1), r0, atol=1e-9)
        np.testing.assert_allclose(skin[t, ~lid], skin[0, ~lid], atol=1e-12)
    assert np.abs(skin[4, lid] - skin[0, lid]).max() > 0.02
    # the elastic truth: the cores follow their bones exactly, the solid near the hinge bends between them
    core = laptop.core >= 0
    np.testing.assert_allclose(solid[4, core], skin[4, core], atol=1e-9)
    diagonal = np.linalg.norm(np.ptp(laptop.target.means, axis=0))
    gap = np.linalg.norm(solid[4] - skin[4], axis=1)
    assert 1e-4 * diagonal < gap.max() < 0.05 * diagonal


def test_deepmimic_pair_runs_from_the_projects_own_data_with_other_proportions():
    pair = P.load_pair("deepmimic_run", 3, 400)
    assert pair.part_map.num_parts == pair.reference.num_bones
    ref_ext = np.ptp(pair.reference.rest_vertices, axis=0)
    tgt_ext = np.ptp(pair.target_vertices, axis=0)
    assert not np.allclose(ref_ext / ref_ext.max(), tgt_ext / tgt_ext.max(), atol=0.05)
    assert np.isfinite(pair.truths["elastic"]).all() and (pair.core >= 0).mean() > 0.03


def test_fastest_window_finds_the_vigorous_stretch():
    from sync4d.io.mocap import SkeletonMotion

    pos = np.zeros((30, 2, 3))
    pos[12:20, 1, 0] = np.arange(8) * 0.1  # only frames 12..19 move
    pos[20:, 1, 0] = 0.7
    m = SkeletonMotion(("a", "b"), np.array([-1, 0]), pos, None, 30.0)
    assert P.fastest_window(m, 8) == 12


def test_kinematic_with_every_gaussian_is_point_wise_rigid_motion(laptop):
    """sim=kinematic without control points is exactly lbs with hard labels (free flight of rigid steps)."""
    motion = G.pair_motion(laptop, 4)
    every = TransferConfig(control_grid=None)
    none = component("velocity", {"type": "none"}).build
    a = run_transfer(Kinematic(Kinematic.Config()), none, every, laptop.target, laptop.part_map, motion, num_frames=4)
    b = run_transfer(LinearBlendSkinning(LinearBlendSkinning.Config(neighbours=1)), none, every, laptop.target,
                     laptop.part_map, motion, num_frames=4)
    np.testing.assert_allclose(a.x, b.x, atol=1e-9)


def torn_rows(pair):
    """Rows of the non-physics methods, the bounds and a torn target (lbs-hard with its lid pulled 15 cm off its base)."""
    methods = G.resolve_methods(["lbs_hard", "lbs_smooth", "kinematic"])
    rows = G.score_pair(pair, methods, ["frozen", "rigid_oracle"], 5)
    motion = G.pair_motion(pair, 5)
    traj, seconds = G.run_method(pair.target, pair.part_map, methods["lbs_hard"], motion, 5)
    x = traj.x.copy()
    lid = pair.part_map.tgt_part == 1
    away = x[0, lid].mean(axis=0) - x[0, ~lid].mean(axis=0)
    x[1:, lid] += 0.15 * away / np.linalg.norm(away)
    torn = G.Trajectory(x=x, F=None, frame_dt=traj.frame_dt)
    for truth in P.TRUTHS:
        rows[truth]["torn"] = G.score(pair, torn, motion, seconds, truth)
    return rows


def test_criteria_fail_a_frozen_and_a_torn_target_and_pass_the_oracle(laptop):
    rows = torn_rows(laptop)
    for truth in P.TRUTHS:
        frozen = G.criteria(rows[truth], truth, "frozen")
        assert not frozen["passed"]
        pose = "pose_within_0.25_of_best_non_physics" if truth == "skinning" else "pose_lowest_of_all_methods"
        assert not frozen[pose]  # only the pose bar catches a target that never moves
        torn = G.criteria(rows[truth], truth, "torn")
        assert not torn["passed"] and not torn["fragments_zero"] and not torn["torn_below_lbs_hard_at_20"]
        oracle = G.criteria(rows[truth], truth, "rigid_oracle")
        # the bars can be met; on the elastic truth hard LBS on the laptop's two rigid parts, driven about their
        # joint, tears exactly the truth's own few hinge pairs, as the oracle does: a tie, which "fewer" refuses
        assert oracle["passed"] if truth == "skinning" else all(v for k, v in oracle.items() if k not in (
            "passed", "torn_below_lbs_hard_at_10", "best_other_pose_error_pct"))
        assert rows[truth]["rigid_oracle"]["tear_curve"]["torn_pairs_pct"]["10"] <= \
            rows[truth]["lbs_hard"]["tear_curve"]["torn_pairs_pct"]["10"]
        # the floor and the ceiling bracket the methods on pose; the follow error fails the frozen target
        for method in ("lbs_hard", "lbs_smooth", "kinematic"):
            assert rows[truth]["rigid_oracle"]["pose_error_pct"] <= rows[truth][method]["pose_error_pct"]
            assert rows[truth][method]["pose_error_pct"] < rows[truth]["frozen"]["pose_error_pct"]
        assert rows[truth]["frozen"]["follow_rotation_max_deg"] > 5.0
        assert rows[truth]["lbs_hard"]["follow_rotation_max_deg"] < 1e-6
        assert rows[truth]["torn"]["follow_translation_max_pct"] > 5.0


def test_quick_command_writes_every_truth_method_and_bound(tmp_path):
    out_json = tmp_path / "out.json"
    res = G.main(["--quick", "--json", str(out_json), "--table", str(tmp_path / "t.md"),
                  "--charts", str(tmp_path / "charts")])
    assert json.loads(out_json.read_text())["pairs"].keys() == {"laptop"}
    for truth in ("skinning", "elastic"):
        rows = res["pairs"]["laptop"][truth]
        assert set(rows) == {"truth", "lbs_hard", "lbs_smooth", "kinematic", "mpm_none", "frozen", "rigid_oracle"}
        for key in (*G.KEYS, "tear_curve"):
            assert key in rows["mpm_none"]
        assert set(rows["mpm_none"]["tear_curve"]["torn_pairs_pct"]) == {"5", "10", "20", "30"}
        assert rows["truth"]["pose_error_pct"] == 0.0
        assert rows["lbs_hard"]["pose_error_pct"] > 0.0  # the target's hinge is elsewhere: not exact
        assert "passed" in res["criteria"]["laptop"][truth]
    assert "Truth: elastic" in (tmp_path / "t.md").read_text()
    assert (tmp_path / "charts" / "physics_tear_curves.png").is_file()
    assert (tmp_path / "charts" / "physics_fidelity_integrity_elastic.png").is_file()


def test_methods_are_configurations_and_identical_ones_run_once():
    methods = G.resolve_methods(["default", "mpm_triplane", "mpm_none"])
    assert methods["default"].sim["type"] == "mpm_warp"
    assert G.method_key(methods["mpm_none"]) != G.method_key(methods["mpm_triplane"])
    # a new method is one entry: a name and its sim / velocity / transfer groups
    G.METHODS["stiff"] = G.Method({"type": "mpm_warp", "E": 1e5})
    try:
        assert G.method_key(G.resolve_methods(["stiff"])["stiff"]) != G.method_key(methods["mpm_none"])
    finally:
        del G.METHODS["stiff"]


def test_unknown_pair_or_method_is_one_line():
    from sync4d.errors import ConfigError

    with pytest.raises(ConfigError, match="--methods"):
        G.main(["--methods", "nope"])
    with pytest.raises(ConfigError, match="--pairs"):
        P.load_pair("nope", 3, 100)


def test_follow_error_passes_the_oracle_and_kinematic_and_fails_the_frozen_target(laptop):
    """Issue 39's follow metric on the laptop pair (both truths): the rigid oracle fitted to the truth scores
    <= 1 deg, sim=kinematic (each part on its drive) ~0, a frozen target its drive's own angle."""
    rows = torn_rows(laptop)
    motion = G.pair_motion(laptop, 5)
    drive = motion.part_transforms[1:] @ np.linalg.inv(motion.part_transforms[0])[None]
    lid_angle = np.degrees(np.arccos(np.clip((np.trace(drive[:, 1, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)))
    for truth in P.TRUTHS:
        assert rows[truth]["rigid_oracle"]["follow_rotation_deg"] <= 1.0
        assert rows[truth]["kinematic"]["follow_rotation_max_deg"] < 1e-3
        frozen = rows[truth]["frozen"]
        assert frozen["follow_rotation_max_deg"] == pytest.approx(lid_angle.max(), rel=1e-3)
