"""The articulated suite: its objects, a tiny MuJoCo clip, and scores that move when the thing they measure breaks."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from sync4d.types import Camera
from sync4d_tools.articulated.objects import suite_objects
from sync4d_tools.articulated.score import constant_labels, joint_row, label_scores, missing_row
from sync4d_tools.articulated.truth import CaseTruth
from sync4d_tools.evaluate.recon_suite import part_mapping, passes, summary

H, W = 60, 80
K = np.array([[80.0, 0, W / 2], [0, 80.0, H / 2], [0, 0, 1]])


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


def plate_truth(kind: str, values: np.ndarray | None = None, poses: np.ndarray | None = None) -> tuple[CaseTruth, Camera]:
    """A camera at the origin; a static base plate 2.5 m away on the left, a moving plate (front face at 2 m,
    back face 0.06 m behind) on the right that turns about a vertical hinge at its left edge (60 deg by
    default) or slides 0.3 m to the right. Labels and depths z-buffered from dense points on the faces, seen
    in frame t through ``poses[t]`` (T, 4, 4) world-to-camera when given (a moving camera; frame 0's the
    returned camera)."""
    camera = Camera(K=K, world_to_cam=np.eye(4) if poses is None else poses[0], width=W, height=H)
    if values is None:
        values = np.radians([0.0, 20.0, 40.0, 60.0]) if kind == "hinge" else np.array([0.0, 0.1, 0.2, 0.3])
    truth = CaseTruth(part_labels=np.zeros((len(values), H, W), np.uint8), depth=np.zeros((len(values), H, W), np.float32),
                      kinds=(kind,), axes=np.array([[0.0, 1.0, 0.0]] if kind == "hinge" else [[1.0, 0.0, 0.0]]),
                      pivots=np.array([[0.0, 0.0, 2.0]]), values=np.asarray(values, np.float64)[:, None])
    g = np.stack(np.meshgrid(np.linspace(0, 1, 160), np.linspace(0, 1, 160)), -1).reshape(-1, 2)
    base = np.stack([-0.9 + 0.8 * g[:, 0], -0.5 + g[:, 1], np.full(len(g), 2.5)], 1)
    front = np.stack([0.7 * g[:, 0], -0.4 + 0.8 * g[:, 1], np.full(len(g), 2.0)], 1)
    moving = np.concatenate([front, front + [0.0, 0.0, 0.06]])
    for t, motion in enumerate(truth.motions()):
        posed = moving @ motion[1, :3, :3].T + motion[1, :3, 3]
        pts, part = np.concatenate([base, posed]), np.repeat([1, 2], [len(base), len(posed)])
        if poses is not None:
            pts = pts @ poses[t, :3, :3].T + poses[t, :3, 3]
        u, v = (pts[:, 0] / pts[:, 2] * K[0, 0] + K[0, 2]).astype(int), (pts[:, 1] / pts[:, 2] * K[1, 1] + K[1, 2]).astype(int)
        order = np.argsort(-pts[:, 2])  # far first; near points overwrite
        ok = order[(u[order] >= 0) & (u[order] < W) & (v[order] >= 0) & (v[order] < H)]
        truth.part_labels[t, v[ok], u[ok]] = part[ok]
        truth.depth[t, v[ok], u[ok]] = pts[ok, 2]
    return truth, camera


def rigid(rotvec: np.ndarray, pivot: np.ndarray, shift: np.ndarray | None = None) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    out[:3, 3] = pivot - out[:3, :3] @ pivot + (0.0 if shift is None else shift)
    return out


def test_joint_scores_are_zero_at_the_truth_and_move_when_the_joint_breaks() -> None:
    """The exact hinge scores 0; an axis tilted 10 deg, a pivot moved 10 % of the size, angles 20 % short, a
    wrong kind each fail on their own score; the same for a slide's direction and travel."""
    truth, camera = plate_truth("hinge")
    pts = truth.points(camera, 2)
    size = truth.size(camera)
    exact = truth.motions()[:, 1]
    row = joint_row(exact, "hinge", 0, truth, camera, pts)
    assert row["axis_deg"] < 1e-6 and row["pivot_pct"] < 1e-6 and row["motion"] < 1e-6 and row["pass"]
    values, pivot = truth.values[:, 0], truth.pivots[0]
    tilted = np.array([np.sin(np.radians(10)), np.cos(np.radians(10)), 0.0])
    moved = pivot + np.array([0.1 * size, 0.0, 0.0])
    cases = {
        "axis_deg": (np.stack([rigid(v * tilted, pivot) for v in values]), 10.0),
        "pivot_pct": (np.stack([rigid(v * truth.axes[0], moved) for v in values]), 10.0),
        "motion": (np.stack([rigid(0.8 * v * truth.axes[0], pivot) for v in values]), np.degrees(0.2 * values).mean()),
    }
    for key, (rel, expected) in cases.items():
        broken = joint_row(rel, "hinge", 0, truth, camera, pts)
        assert broken[key] == pytest.approx(expected, rel=0.02), (key, broken)
        assert not broken["pass"]
    backwards = joint_row(np.stack([rigid(-v * truth.axes[0], pivot) for v in values]), "hinge", 0, truth, camera, pts)
    assert backwards["motion"] == pytest.approx(2 * np.degrees(np.abs(values)).mean()) and not backwards["pass"]
    assert not joint_row(exact, "slide", 0, truth, camera, pts)["pass"]  # right motion, wrong kind
    slide, camera = plate_truth("slide")
    exact = slide.motions()[:, 1]
    pts = slide.points(camera, 2)
    assert joint_row(exact, "slide", 0, slide, camera, pts)["pass"]
    oblique = np.array([np.cos(np.radians(8)), 0.0, np.sin(np.radians(8))])
    off = joint_row(np.stack([rigid(np.zeros(3), np.zeros(3), v * oblique) for v in slide.values[:, 0]]), "slide", 0,
                    slide, camera, pts)
    assert off["axis_deg"] == pytest.approx(8.0, abs=0.1) and not off["pass"]
    short = joint_row(np.stack([rigid(np.zeros(3), np.zeros(3), 0.9 * v * slide.axes[0]) for v in slide.values[:, 0]]),
                      "slide", 0, slide, camera, pts)
    assert short["motion"] == pytest.approx(10.0 * np.abs(slide.values[:, 0]).mean() / np.ptp(slide.values), rel=0.01) and not short["pass"]
    assert not missing_row(0, slide)["pass"] and missing_row(0, slide)["motion"] > 3


def test_first_frame_surface_is_split_from_the_revealed() -> None:
    """The slide uncovers background only: every object pixel shows surface frame 0 saw. A part that turns
    so that its far side faces the camera shows revealed surface; labels score each set on its own, and a
    constant label is the floor."""
    slide, camera = plate_truth("slide")
    seen = slide.seen_first(camera)
    assert seen[slide.part_labels > 0].mean() > 0.97
    flipped, camera = plate_truth("hinge", np.radians([0.0, 0.0, 180.0, 0.0]))
    seen = flipped.seen_first(camera)
    assert seen[1][flipped.part_labels[1] > 0].mean() > 0.97
    assert seen[2][flipped.part_labels[2] == 2].mean() < 0.03  # its back faces the camera
    labels = flipped.part_labels
    correct = [labels[t][labels[t] > 0] > 0 for t in range(len(labels))]
    correct[2][labels[2][labels[2] > 0] == 2] = False  # the revealed back wrongly labelled
    scores = label_scores(correct, seen, labels)
    assert scores["first"] == 1.0 and scores["revealed"] == 0.0 and scores["all"] < 1.0
    share = np.bincount(labels[labels > 0])
    assert constant_labels(labels, seen)["all"] == pytest.approx(share.max() / share.sum(), abs=1e-4)


def orbit_poses(frames: int, degrees: float) -> np.ndarray:
    """(T, 4, 4) world-to-camera of a camera turning by up to ``degrees`` about a vertical line through the
    plates (x = 0, z = 2.25 m), as a hand-held arc does: frame 0 the identity."""
    from scipy.spatial.transform import Rotation

    out = np.tile(np.eye(4), (frames, 1, 1))
    centre = np.array([0.0, 0.0, 2.25])
    for t, angle in enumerate(np.radians(np.linspace(0.0, degrees, frames))):
        rot = Rotation.from_rotvec([0.0, angle, 0.0]).as_matrix()  # camera-to-world turn about the centre
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = rot, centre - rot @ centre
        out[t] = np.linalg.inv(c2w)
    return out


def test_a_moving_camera_is_scored_frame_by_frame() -> None:
    """Filmed by a camera that turns 12 deg: with each frame's camera the slide uncovers nothing (every object
    pixel shows surface frame 0 saw) and the exact joints score 0; read through frame 0's camera alone, the
    same pixels land elsewhere and most are called revealed."""
    from sync4d_tools.articulated.ceiling import frame_cameras

    poses = orbit_poses(4, 12.0)
    slide, camera = plate_truth("slide", poses=poses)
    cameras = frame_cameras(camera, poses)
    assert isinstance(cameras, list) and len(cameras) == 4 and np.array_equal(cameras[2].world_to_cam, poses[2])
    assert frame_cameras(camera, None) is camera
    seen = slide.seen_first(cameras)
    assert seen[slide.part_labels > 0].mean() > 0.97
    assert slide.seen_first(camera)[3][slide.part_labels[3] > 0].mean() < 0.5  # one camera for every frame: wrong
    assert np.allclose(slide.points(cameras, 1, frame=3).mean(0), slide.points(cameras, 1).mean(0), atol=0.02)
    exact = slide.motions()[:, 1]
    assert joint_row(exact, "slide", 0, slide, camera, slide.points(camera, 2))["pass"]
    hinge, camera = plate_truth("hinge", poses=poses)
    row = joint_row(hinge.motions()[:, 1], "hinge", 0, hinge, camera, hinge.points(camera, 2))
    assert row["axis_deg"] < 1e-6 and row["pivot_pct"] < 1e-6 and row["pass"]


def test_the_handheld_arc_starts_at_the_view_and_sweeps_like_the_default_scene() -> None:
    """The suite's hand-held poses: frame 0 is the static view exactly; ~30 deg of azimuth about z over the
    clip, elevation within a few degrees, distance within 5 %, unit orthogonal forward and up; seeded."""
    from sync4d_tools.articulated.render import free_camera_eye, handheld_poses

    lookat = np.array([0.1, -0.2, 0.3])
    eye = free_camera_eye(lookat, 1.5, 55.0, -28.0)
    fwd0 = (lookat - eye) / 1.5
    assert np.degrees(np.arcsin(fwd0[2])) == pytest.approx(-28.0) and np.linalg.norm(lookat - eye) == pytest.approx(1.5)
    poses = handheld_poses(lookat, eye, 0.4, 24, np.random.default_rng([1, 7]))
    assert poses.shape == (24, 3, 3)
    assert np.allclose(poses[0, 0], eye) and np.allclose(poses[0, 1], fwd0)
    fwd, up = poses[:, 1], poses[:, 2]
    assert np.allclose(np.linalg.norm(fwd, axis=1), 1) and np.allclose(np.linalg.norm(up, axis=1), 1)
    assert np.abs(np.einsum("ti,ti->t", fwd, up)).max() < 1e-9
    azimuth = np.degrees(np.unwrap(np.arctan2(-fwd[:, 1], -fwd[:, 0])))
    assert 25.0 < abs(azimuth[-1] - azimuth[0]) < 35.0
    assert np.ptp(np.degrees(np.arcsin(fwd[:, 2]))) < 10.0
    distance = np.linalg.norm(poses[:, 0] - lookat, axis=1) / 1.5
    assert distance.min() > 0.94 and distance.max() < 1.06
    assert np.array_equal(poses, handheld_poses(lookat, eye, 0.4, 24, np.random.default_rng([1, 7])))
    assert not np.array_equal(poses, handheld_poses(lookat, eye, 0.4, 24, np.random.default_rng([2, 7])))


def test_rows_of_one_clip_count_once() -> None:
    """Three rows of one fixed clip weigh as one sample against a passing row of another clip."""
    good = {"joint": "hinge", "found": "hinge", "axis_deg": 1.0, "pivot_pct": 1.0, "motion": 1.0, "pass": True}
    bad = {**good, "axis_deg": 30.0, "pass": False}
    floor = {"labels": {"first": 0.5}}

    def row(clip: str, joint: dict) -> dict:
        return {"case": clip, "clip_id": clip, "joints": [joint], "pass_joints": joint["pass"], "pass_labels": True,
                "pass": joint["pass"], "first_ratio": 1.0, "ceiling": {"first": 0.9}, "floor": floor, "cpu_seconds": 1.0}

    out = summary([row("fixed", bad), row("fixed", bad), row("fixed", bad), row("other", good)])
    assert out["samples"] == 2 and out["joints_within_bar"] == 0.5 and out["cases_pass"] == 0.5
    assert passes([good]) and not passes([good, bad]) and not passes([])


@pytest.mark.slow
def test_a_tiny_mujoco_clip_has_its_truth(tmp_path: Path) -> None:
    """A desk clip at 64x48: labels, per-frame depth, joints as lines; its truth scores itself exactly and
    shows the drawer's revealed sides. Needs requirements-suite.txt (skipped without mujoco; any other
    failure fails)."""
    os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is first imported: headless rendering
    pytest.importorskip("mujoco")
    pytest.importorskip("metaworld")
    from sync4d.sources.references import VideoSource
    from sync4d_tools.articulated.render import VIEWS, render_clip, variant
    from sync4d_tools.articulated.truth import clip_truth

    obj = next(o for o in suite_objects() if o.name == "desk_lid_drawer")
    obj1, view1, look1 = variant(obj, VIEWS[0], 1)
    assert (view1.azimuth, obj1.start, look1.floor) != (VIEWS[0].azimuth, obj.start, variant(obj, VIEWS[0], 0)[2].floor)
    render_clip(obj, VIEWS[0], tmp_path / "clip", frames=5, width=64, height=48, cache=tmp_path)
    gt = dict(np.load(tmp_path / "clip" / "gt.npz"))
    assert gt["part_labels"].shape == (5, 48, 64) and set(np.unique(gt["part_labels"])) == {0, 1, 2, 3}
    assert gt["joint_type"].tolist() == ["hinge", "slide"] and gt["joint_value"].shape == (5, 2)
    assert gt["depth_t"].shape == (5, 48, 64) and (gt["depth_t"][gt["part_labels"] > 0] > 0).all()
    assert len(list((tmp_path / "clip" / "masks").glob("*.png"))) == 5
    source = VideoSource(VideoSource.Config(video=str(tmp_path / "clip" / "rgb.mp4"), masks=str(tmp_path / "clip" / "masks"),
                                            camera=str(tmp_path / "clip" / "gt.npz"))).load()
    truth = clip_truth(gt)
    seen = truth.seen_first(source.camera)
    assert seen[0][truth.part_labels[0] > 0].mean() > 0.95  # frame 0 sees itself
    assert seen[2][truth.part_labels[2] > 0].mean() < seen[0][truth.part_labels[0] > 0].mean()
    for j in range(2):
        row = joint_row(truth.motions()[:, j + 1], truth.kinds[j], j, truth, source.camera, truth.points(source.camera, j + 2))
        assert row["pass"] and row["axis_deg"] < 0.5 and row["motion"] < 0.5, row


@pytest.mark.slow
def test_a_tiny_handheld_mujoco_clip_has_per_frame_cameras(tmp_path: Path) -> None:
    """A hand-held desk clip at 64x48, 4 frames: one pose per frame, frame 0 the static clip's exactly; every
    frame's base pixels, cast through that frame's camera, land on the base's frame-0 surface (the depth,
    labels and cameras agree); the truth's first-frame split sees the base in every frame. Needs
    requirements-suite.txt (skipped without mujoco)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    pytest.importorskip("mujoco")
    pytest.importorskip("metaworld")
    from sync4d.sources.references import VideoSource
    from sync4d_tools.articulated.ceiling import frame_cameras
    from sync4d_tools.articulated.render import VIEWS, clip_name, render_clip
    from sync4d_tools.articulated.truth import clip_truth

    obj = next(o for o in suite_objects() if o.name == "desk_lid_drawer")
    assert clip_name("desk_lid_drawer", "left", 1, "handheld") == "desk_lid_drawer-left-s1-hh"
    for camera in ("static", "handheld"):
        render_clip(obj, VIEWS[0], tmp_path / camera, frames=4, width=64, height=48, cache=tmp_path, camera=camera)
    still, moving = (dict(np.load(tmp_path / c / "gt.npz")) for c in ("static", "handheld"))
    assert moving["cam_pos"].shape == moving["cam_forward"].shape == moving["cam_up"].shape == (4, 3)
    assert np.abs(moving["cam_pos"][0] - still["cam_pos"]).max() < 1e-6
    assert np.array_equal(moving["part_labels"][0], still["part_labels"][0])
    assert np.linalg.norm(moving["cam_pos"][3] - moving["cam_pos"][0]) > 0.05  # it moved
    source = VideoSource(VideoSource.Config(video=str(tmp_path / "handheld" / "rgb.mp4"),
                                            masks=str(tmp_path / "handheld" / "masks"),
                                            camera=str(tmp_path / "handheld" / "gt.npz"))).load()
    assert source.video is not None and source.video.extrinsics is not None
    cameras = frame_cameras(source.camera, source.video.extrinsics)
    truth = clip_truth(moving)
    for t in (1, 3):
        right, wrong = (reprojection(truth, cams, t) for cams in (cameras, cameras[0]))
        assert right[0] > 0.4 and right[1] < 0.01, (t, right)  # frame 0 hides part of the base behind the lid
        assert wrong[1] > 3 * right[1] or wrong[0] < 0.5 * right[0], (t, right, wrong)
    seen = truth.seen_first(cameras)
    base = truth.part_labels == 1
    assert seen[0][truth.part_labels[0] > 0].mean() > 0.95 and seen[3][base[3]].mean() > 0.8


def reprojection(truth: CaseTruth, cameras: list[Camera] | Camera, t: int) -> tuple[float, float]:
    """(share of frame t's base pixels that land on frame 0's base, their median relative depth error) when
    cast through ``cameras`` (per frame, or one for all) and seen through frame 0's."""
    from sync4d_tools.articulated.truth import camera_at

    first = camera_at(cameras, 0)
    pc = truth.points(cameras, 1, frame=t) @ first.world_to_cam[:3, :3].T + first.world_to_cam[:3, 3]
    uv = np.floor((pc @ first.K.T)[:, :2] / pc[:, 2:3]).astype(int)
    h, w = truth.part_labels.shape[1:]
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    on = truth.part_labels[0][uv[ok, 1], uv[ok, 0]] == 1
    err = np.abs(truth.depth[0][uv[ok, 1], uv[ok, 0]][on] - pc[ok, 2][on]) / pc[ok, 2][on]
    return float(on.mean()), float(np.median(err)) if on.any() else float("inf")
