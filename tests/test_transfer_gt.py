"""transfer_gt: pairs whose truth is the target's own kinematic model, and the command's output."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sync4d.registry import component
from sync4d.sim.kinematic import Kinematic
from sync4d.transfer import TransferConfig, run_transfer
from sync4d.sim.lbs import LinearBlendSkinning
from sync4d_tools.evaluate import transfer_gt as G


def test_rescaled_skeleton_keeps_every_segment_direction_and_scales_its_length():
    from sync4d.io.mocap import SkeletonMotion

    rng = np.random.default_rng(0)
    parents = np.array([-1, 0, 1, 0, 3])
    pos = np.cumsum(rng.normal(size=(4, 5, 3)), axis=1)
    pos[:, 3] = pos[:, 0] + rng.normal(size=(4, 3))
    pos[:, 4] = pos[:, 3] + rng.normal(size=(4, 3))
    m = SkeletonMotion(tuple("abcde"), parents, pos, None, 30.0)
    factors = np.array([1.0, 1.5, 0.5, 2.0, 1.0])
    out = G.rescale_segments(m, factors).positions
    for j in range(1, 5):
        a, b = pos[:, j] - pos[:, parents[j]], out[:, j] - out[:, parents[j]]
        np.testing.assert_allclose(b, factors[j] * a, atol=1e-12)
    np.testing.assert_allclose(out[:, 0], pos[:, 0])


def test_laptop_pair_truth_turns_the_lid_about_the_targets_own_hinge():
    pair = G.load_pair("laptop", 6, 600)
    from sync4d.scenes.laptop import hinge_pivot

    np.testing.assert_allclose(pair.truth[0], pair.target.means, atol=1e-12)
    lid = pair.part_map.tgt_part == 1
    pivot = hinge_pivot(0.18, 0.03)  # the target's depth and base thickness, not the reference's
    r0 = np.linalg.norm((pair.truth[0, lid] - pivot)[:, 1:], axis=1)
    for t in range(1, 6):
        # distances to the target's hinge axis (x through the pivot) are kept; the base does not move
        np.testing.assert_allclose(np.linalg.norm((pair.truth[t, lid] - pivot)[:, 1:], axis=1), r0, atol=1e-9)
        np.testing.assert_allclose(pair.truth[t, ~lid], pair.truth[0, ~lid], atol=1e-12)
    assert np.abs(pair.truth[5, lid] - pair.truth[0, lid]).max() > 0.02


def test_mocap_pair_target_has_other_proportions_and_the_same_bones(shared_data):
    pair = G.load_pair("dog_trot", 3, 300)
    assert pair.part_map.num_parts == pair.reference.num_bones
    ref_ext = np.ptp(pair.reference.rest_vertices, axis=0)
    tgt_ext = np.ptp(pair.target_vertices, axis=0)
    assert not np.allclose(ref_ext / ref_ext.max(), tgt_ext / tgt_ext.max(), atol=0.05)


def test_kinematic_with_every_gaussian_is_point_wise_rigid_motion():
    """sim=kinematic without control points is exactly lbs with hard labels (free flight of rigid steps)."""
    pair = G.load_pair("laptop", 4, 400)
    motion = G.pair_motion(pair, 4)
    every = TransferConfig(control_grid=None)
    none = component("velocity", {"type": "none"}).build
    a = run_transfer(Kinematic(Kinematic.Config()), none, every, pair.target, pair.part_map, motion, num_frames=4)
    b = run_transfer(LinearBlendSkinning(LinearBlendSkinning.Config(neighbours=1)), none, every, pair.target,
                     pair.part_map, motion, num_frames=4)
    np.testing.assert_allclose(a.x, b.x, atol=1e-9)


def test_command_prints_every_metric_per_pair_and_method(tmp_path):
    out_json = tmp_path / "out.json"
    res = G.main(["--pairs", "laptop", "--methods", "lbs_hard,kinematic", "--frames", "3", "--gaussians", "400",
                  "--json", str(out_json), "--charts", str(tmp_path / "charts")])
    assert json.loads(out_json.read_text())["pairs"].keys() == {"laptop"}
    row = res["pairs"]["laptop"]
    assert set(row) == {"truth", "lbs_hard", "kinematic"}
    for key in ("pose_error_pct", "torn_pairs_pct", "strain_p99_pct", "fragments", "volume_change_pct",
                "seconds_per_frame"):
        assert key in row["lbs_hard"]
    assert row["truth"]["pose_error_pct"] == 0.0
    assert row["lbs_hard"]["pose_error_pct"] > 0.0  # the target's hinge is elsewhere: the transfer is not exact
    assert (tmp_path / "charts" / "fidelity_integrity.png").is_file()


def test_unknown_pair_or_method_is_one_line():
    from sync4d.errors import ConfigError

    with pytest.raises(ConfigError, match="--methods"):
        G.main(["--methods", "nope", "--charts", ""])
    with pytest.raises(ConfigError, match="--pairs"):
        G.load_pair("nope", 3, 100)
