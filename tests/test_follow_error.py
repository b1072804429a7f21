"""The follow error (each target part's best rigid motion against its driving motion) fails a frozen target
and a torn one, and is zero for a target that moves exactly as driven."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d.geometry import bbox_diagonal, rigid_fit, rotation_angle_deg
from sync4d.run import metrics as M


def rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rigid(rot: np.ndarray, shift) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, shift
    return out


@pytest.fixture(scope="module")
def scene():
    """A torso (part 0) that walks along x and an arm (part 1) that swings up to 40 deg about the shoulder.

    The driving transforms carry a non-identity rest (frame 0) transform, as a driving motion's do: the
    metric must take the motion relative to frame 0.
    """
    rng = np.random.default_rng(0)
    torso = rng.uniform([0.0, 0.0, 0.0], [0.1, 0.3, 0.05], (600, 3))
    arm = rng.uniform([0.1, 0.2, 0.0], [0.25, 0.25, 0.05], (300, 3))
    rest = np.concatenate([torso, arm])
    parts = np.repeat([0, 1], [600, 300])
    shoulder = np.array([0.1, 0.225, 0.025])
    frame0 = rigid(rotation_z(0.3), [0.5, -0.2, 0.1])
    T = 6
    transforms = np.zeros((T, 2, 4, 4))
    for t in range(T):
        walk = rigid(np.eye(3), [0.02 * t, 0.0, 0.0])
        swing = rigid(rotation_z(np.radians(8.0 * t)), shoulder - rotation_z(np.radians(8.0 * t)) @ shoulder)
        transforms[t, 0] = walk @ frame0
        transforms[t, 1] = walk @ swing @ frame0
    relative = transforms @ np.linalg.inv(transforms[0])[None]
    driven = np.stack([np.where(parts[:, None] == 0, rest @ relative[t, 0, :3, :3].T + relative[t, 0, :3, 3],
                                rest @ relative[t, 1, :3, :3].T + relative[t, 1, :3, 3]) for t in range(T)])
    return rest, parts, transforms, driven, bbox_diagonal(rest)


def test_rigid_fit_recovers_a_known_motion():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(50, 3))
    rot = rotation_z(0.7) @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    fit = rigid_fit(pts, pts @ rot.T + [1.0, 2.0, 3.0])
    np.testing.assert_allclose(fit[:3, :3], rot, atol=1e-12)
    np.testing.assert_allclose(fit[:3, 3], [1.0, 2.0, 3.0], atol=1e-12)
    assert rotation_angle_deg(rotation_z(np.radians(30.0))) == pytest.approx(30.0)


def test_a_target_moved_as_driven_follows_exactly(scene):
    rest, parts, transforms, driven, diagonal = scene
    follow = M.follow_error(rest, driven, parts, transforms, diagonal)
    assert np.nanmax(follow.rotation_deg) < 1e-5 and np.nanmax(follow.translation_pct) < 1e-9
    summary = M.follow_summary(follow)
    assert summary["follow_rotation_deg"] < 1e-5 and summary["follow_translation_max_pct"] < 1e-9


def test_a_frozen_target_fails(scene):
    rest, parts, transforms, driven, diagonal = scene
    frozen = np.repeat(rest[None], len(driven), axis=0)
    follow = M.follow_error(rest, frozen, parts, transforms, diagonal)
    rot, trans = follow.rotation_deg, follow.translation_pct
    # the arm's error is the swing itself, 8 deg per frame; the torso's is the walk, 2 cm per frame
    np.testing.assert_allclose(rot[:, 1], 8.0 * np.arange(len(driven)), atol=1e-6)
    np.testing.assert_allclose(trans[:, 0], 0.02 * np.arange(len(driven)) / diagonal * 100.0, atol=1e-9)
    summary = M.follow_summary(follow)
    assert summary["follow_rotation_max_deg"] == pytest.approx(40.0)
    # the mean weighs each part by its core: the torso (which needs no turn) outweighs the arm
    arm_share = follow.weight[1] / follow.weight.sum()
    assert 0.1 < arm_share < 0.34
    assert summary["follow_rotation_deg"] == pytest.approx(arm_share * 8.0 * 3.0, rel=1e-6)


def test_a_torn_target_fails(scene):
    rest, parts, transforms, driven, diagonal = scene
    detached = driven.copy()
    detached[1:, parts == 1] += [0.0, 0.0, 0.1]  # the arm flies 10 cm off its shoulder
    trans = M.follow_error(rest, detached, parts, transforms, diagonal).translation_pct
    np.testing.assert_allclose(trans[1:, 1], 0.1 / diagonal * 100.0, rtol=1e-9)
    split = driven.copy()
    arm = np.flatnonzero(parts == 1)
    far = arm[rest[arm, 0] > 0.175]
    split[1:, far] = rest[far]  # the arm's outer half stays behind: the arm is torn in two
    follow = M.follow_error(rest, split, parts, transforms, diagonal)
    rot, trans = follow.rotation_deg, follow.translation_pct
    assert rot[-1, 1] > 10.0 and trans[-1, 1] > 3.0
    assert np.nanmax(rot[:, 0]) < 1e-5  # the torso still follows


def test_undetermined_parts_are_skipped(scene):
    rest, parts, transforms, driven, diagonal = scene
    line = np.zeros((5, 3))
    line[:, 0] = np.arange(5) * 0.01
    assert not M.fit_is_determined(line) and not M.fit_is_determined(rest[:3])
    parts_with_empty = parts.copy()
    transforms3 = np.concatenate([transforms, transforms[:, :1]], axis=1)  # a third part with no points
    follow = M.follow_error(rest, driven, parts_with_empty, transforms3, diagonal)
    assert np.isnan(follow.rotation_deg[:, 2]).all() and np.isfinite(follow.rotation_deg[:, :2]).all()
    assert follow.weight[2] == 0


def test_the_seam_band_is_left_out(scene):
    """A joint's blend (arm points next to the torso dragged half-way) does not count against the arm: the
    arm's core still moves exactly as driven."""
    rest, parts, transforms, driven, diagonal = scene
    blended = driven.copy()
    core = M.part_cores(rest, parts, 2, M.SEAM_BAND_OF_DIAGONAL * diagonal)[1]
    seam = (parts == 1) & ~np.isin(np.arange(len(rest)), core)
    assert seam.sum() > 5 and rest[seam, 0].max() < 0.1 + M.SEAM_BAND_OF_DIAGONAL * diagonal
    blended[:, seam] = 0.5 * (driven[:, seam] + rest[seam])
    follow = M.follow_error(rest, blended, parts, transforms, diagonal)
    assert np.nanmax(follow.rotation_deg) < 1e-5
    whole = M.follow_error(rest, blended, parts, transforms, diagonal, band=0.0)
    assert np.nanmax(whole.rotation_deg[:, 1]) > 0.5  # without the band the blend counts
