"""Shape-integrity metrics move when the shape breaks: a torn limb, a stretched seam, a shrunk part."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d.run import metrics as M


@pytest.fixture(scope="module")
def body():
    """A torso block (part 0) with an arm block (part 1) attached on its side; ~1500 points, 5 mm spacing."""
    rng = np.random.default_rng(0)
    torso = rng.uniform([0.0, 0.0, 0.0], [0.1, 0.3, 0.05], (1000, 3))
    arm = rng.uniform([0.1, 0.2, 0.0], [0.25, 0.25, 0.05], (500, 3))
    rest = np.concatenate([torso, arm])
    parts = np.repeat([0, 1], [1000, 500])
    return rest, parts, M.integrity_model(rest, parts, 2, gap=0.02)


def test_rest_shape_and_rigid_motion_are_whole(body):
    rest, parts, model = body
    angle = 0.4
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    for x in (rest, rest @ rot.T + [0.3, -0.1, 0.2]):
        f = M.integrity_frame(model, x)
        assert f.torn_pairs_pct == 0 and f.strain_p99_pct < 1e-9 and f.fragments == 0
        np.testing.assert_allclose(f.volume_change_pct, 0.0, atol=1e-9)
    assert model.seam.any() and not model.seam.all()


def test_torn_limb_counts_one_fragment_and_torn_seam_pairs(body):
    rest, parts, model = body
    x = rest.copy()
    x[parts == 1] += [0.1, 0.0, 0.0]  # the arm floats 10 cm away (5 grid cells of 2 cm)
    f = M.integrity_frame(model, x)
    assert f.fragments == 1
    assert f.torn_seam_pairs_pct > 90.0
    assert 0 < f.torn_pairs_pct < 20.0  # only the seam pairs tore
    # the same arm only 1 cm off is torn but still touching: not a fragment
    x[parts == 1] -= [0.09, 0.0, 0.0]
    assert M.integrity_frame(model, x).fragments == 0


def test_scattered_gaussians_are_fragments(body):
    rest, parts, model = body
    x = rest.copy()
    x[[5, 700]] += [0.0, 0.0, 0.5]
    assert M.integrity_frame(model, x).fragments == 2


def test_stretched_seam_moves_strain_and_seam_tearing(body):
    rest, parts, model = body
    x = rest.copy()
    # stretch a 2 cm band around the seam (x in [0.09, 0.11]) by 40% along x, shifting the arm with it
    band = (rest[:, 0] > 0.09) & (rest[:, 0] < 0.11)
    x[band, 0] = 0.09 + 1.4 * (rest[band, 0] - 0.09)
    x[rest[:, 0] >= 0.11, 0] += 0.4 * 0.02
    f = M.integrity_frame(model, x)
    assert f.torn_seam_pairs_pct > 30.0
    assert f.strain_p99_pct > 20.0
    assert f.fragments == 0


def test_shrunk_part_shows_in_its_volume(body):
    rest, parts, model = body
    x = rest.copy()
    c = rest[parts == 1].mean(axis=0)
    x[parts == 1] = c + 0.9 * (rest[parts == 1] - c)
    f = M.integrity_frame(model, x)
    assert f.volume_change_pct[1] == pytest.approx((0.9**3 - 1) * 100, abs=0.5)
    assert abs(f.volume_change_pct[0]) < 1e-9
    # the body figure weighs the arm's loss by its share of the rest volume
    share = model.rest_volume[1] / model.rest_volume.sum()
    assert f.body_volume_change_pct == pytest.approx(share * (1 - 0.9**3) * 100, rel=0.02)


def test_summary_leaves_frame_zero_out_and_reports_the_worst_frame(body):
    rest, parts, model = body
    bad = rest.copy()
    bad[parts == 1] += [0.1, 0.0, 0.0]
    frames = [M.integrity_frame(model, x) for x in (bad, rest, bad)]  # frame 0 torn on purpose: must not count
    s = M.integrity_summary(frames)
    one = M.integrity_frame(model, bad)
    assert s["torn_pairs_pct"] == pytest.approx(one.torn_pairs_pct / 2)
    assert s["strain_p99_max_pct"] == pytest.approx(one.strain_p99_pct)
    assert s["fragments"] == 1


def test_jitter_ratio_against_a_truth_moves_with_noise():
    t = np.linspace(0, 1, 12)[:, None]
    path = np.concatenate([t, 0.1 * t**2, np.zeros_like(t)], axis=1)  # (T, 3): a smooth curve
    truth = path[:, None, :] + np.random.default_rng(0).uniform(size=(1, 50, 3))
    assert M.jitter_ratio(truth, truth, 1.0) == pytest.approx(1.0)
    noisy = truth + np.random.default_rng(1).normal(scale=0.01, size=truth.shape)
    assert M.jitter_ratio(noisy, truth, 1.0) > 3.0


def test_pairs_the_truth_separates_are_not_counted_as_torn(body):
    """Two limbs side by side at rest that the correct motion moves apart are no tear; a method that does the
    same as the truth scores 0, one that tears what the truth keeps does not."""
    rest, parts, _ = body
    moved = rest.copy()
    moved[parts == 1] += [0.1, 0.0, 0.0]  # in this "truth" the arm really does move away
    truth = np.stack([rest, moved])
    model = M.integrity_model(rest, parts, 2, gap=0.02, truth=truth)
    assert not model.seam.any()  # every seam pair is one the truth separates
    f = M.integrity_frame(model, moved, true_volume=M.part_volumes(moved, parts, 2))
    assert f.torn_pairs_pct == 0 and f.strain_p99_pct < 1e-9
    np.testing.assert_allclose(f.volume_change_pct, 0.0, atol=1e-9)
    torn = moved.copy()
    torn[:500, 2] *= 1.5  # the method stretches the torso, which the truth keeps
    assert M.integrity_frame(model, torn).torn_pairs_pct > 5.0


def test_tear_curve_moves_with_the_threshold(body):
    """A seam band stretched by 15% tears at 5% and 10%, not at 20% or 30%; a detached arm is a fragment at
    every threshold; pairs the truth itself stretches are left out at each threshold."""
    rest, parts, _ = body
    band = (rest[:, 0] > 0.09) & (rest[:, 0] < 0.11)
    x = rest.copy()
    x[band, 0] = 0.09 + 1.15 * (rest[band, 0] - 0.09)
    x[rest[:, 0] >= 0.11, 0] += 0.15 * 0.02
    curve = M.tear_curve(rest, np.stack([rest, x, x]), 0.02)
    torn = curve["torn_pairs_pct"]
    assert set(torn) == {"5", "10", "20", "30"}
    assert torn["5"] >= torn["10"] > 0.5 and torn["20"] == 0 and torn["30"] == 0
    assert all(v == 0 for v in curve["fragments"].values())
    off = rest.copy()
    off[parts == 1] += [0.1, 0.0, 0.0]
    assert all(v == 1 for v in M.tear_curve(rest, np.stack([rest, off]), 0.02)["fragments"].values())
    # the same stretch done by the truth: nothing left to count
    truth = np.stack([rest, x, x])
    assert all(v == 0 for v in M.tear_curve(rest, truth, 0.02, truth=truth)["torn_pairs_pct"].values())


def test_fragment_gap_without_a_grid_is_two_cells_of_the_default_mpm_grid():
    """``sim=lbs`` and ``sim=kinematic`` runs are judged with the cell the default ``sim=mpm_warp`` would use on the
    same shape (not a stale constant of a former default)."""
    from sync4d.run.writer import fragment_gap
    from sync4d.sim.mpm_warp import MPMWarp

    rest = np.random.default_rng(0).uniform(0.0, 1.0, (500, 3)) * [0.8, 0.4, 0.2]
    model = MPMWarp(MPMWarp.Config(), device="cpu").prepare(rest, volume=0.01)
    assert fragment_gap(rest, None) == 2.0 * model.grid.dx
    assert fragment_gap(rest, 0.01) == 0.02
