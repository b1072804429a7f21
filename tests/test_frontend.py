"""The video front end (sync4d.frontend): masks and camera found in synthetic clips, and the refusals of
input it cannot use (one line, before the reconstruction)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sync4d.errors import InputError
from sync4d.frontend import FrontEndConfig, Prompt, complete_video, run_front_end
from sync4d.frontend.bundle import bundle_adjust
from sync4d.frontend.camera import moving_camera, parabola_vertex, solve_camera, static_camera
from sync4d.frontend.checks import bridge_dropouts, check_subject
from sync4d.frontend.geometry import intrinsics_from_fov, pose_matrix, project
from sync4d.geometry import rotation_angle_deg, rotation_vector_to_matrix
from sync4d.frontend.outputs import write_video_inputs
from sync4d.frontend.stage import CAMERA_TO_YUP
from sync4d.frontend.tracks import Tracks
from sync4d.types import VideoClip

W, H = 128, 96


def texture(width: int, height: int, seed: int) -> np.ndarray:
    """(height, width, 3) uint8 a blotchy colour texture with corners to track."""
    import cv2

    rng = np.random.default_rng(seed)
    small = rng.uniform(0, 255, (height // 3 + 1, width // 3 + 1, 3)).astype(np.uint8)
    return cv2.resize(small, (width, height), interpolation=cv2.INTER_NEAREST)


def square_clip(n_frames: int = 8, *, pan_px: float = 0.0, speed: float = 3.0, start: float = 40.0,
                with_subject: bool = True) -> tuple[VideoClip, np.ndarray]:
    """A textured square moving right over a textured background that pans ``pan_px`` per frame; the clip
    (no masks) and the true masks."""
    big = texture(W + int(abs(pan_px) * n_frames) + 8, H, seed=1)
    big[..., 0] //= 2  # a blue-green room ...
    # ... and a red subject: their colours differ, as a real subject's and background's mostly do
    patch = np.clip(0.6 * texture(28, 28, seed=2) + [100, 0, 0], 0, 255).astype(np.uint8)
    patch[..., 1:] //= 2
    frames, masks = [], []
    for t in range(n_frames):
        x0 = int(round(pan_px * t))
        frame = big[:, x0: x0 + W].copy()
        mask = np.zeros((H, W), bool)
        if with_subject:
            u = int(round(start + speed * t))
            lo, hi = max(u, 0), min(u + 28, W)
            if hi > lo:
                frame[34:62, lo:hi] = patch[:, lo - u: hi - u]
                mask[34:62, lo:hi] = True
        frames.append(frame)
        masks.append(mask)
    clip = VideoClip(np.stack(frames), np.zeros((n_frames, H, W), bool), 10.0, source="synthetic").validate()
    return clip, np.stack(masks)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def test_a_moving_square_is_found_and_a_still_camera_is_static():
    clip, truth = square_clip()
    found = run_front_end(clip, FrontEndConfig())
    assert found.subject == "motion"
    assert found.camera.static and np.allclose(found.clip.extrinsics, CAMERA_TO_YUP)  # world: camera 0, Y up
    assert np.median([iou(a, b) for a, b in zip(found.clip.masks, truth)]) > 0.8
    assert found.clip.intrinsics is not None and found.camera.focal_source == "fov_guess"


def test_a_panning_camera_is_found_turning_and_the_square_still_found():
    clip, truth = square_clip(pan_px=2.0)
    found = run_front_end(clip, FrontEndConfig())
    assert not found.camera.static
    ext = found.clip.extrinsics
    turn = rotation_angle_deg(ext[-1, :3, :3] @ ext[0, :3, :3].T)
    expected = np.degrees(np.arctan(2.0 * (len(truth) - 1) / found.clip.intrinsics[0, 0]))
    assert abs(turn - expected) < 1.0  # a pure image shift is nearly a pan by atan(shift / f)
    assert np.median([iou(a, b) for a, b in zip(found.clip.masks, truth)]) > 0.7


def test_a_prompt_box_picks_the_subject():
    clip, truth = square_clip()
    found = run_front_end(clip, FrontEndConfig(), prompt=Prompt((36.0, 30.0, 74.0, 66.0), 0))
    assert found.subject == "prompt"
    assert np.median([iou(a, b) for a, b in zip(found.clip.masks, truth)]) > 0.7


def test_bundle_adjustment_recovers_poses_from_noisy_starts():
    rng = np.random.default_rng(0)
    K = intrinsics_from_fov(W, H, 60.0)
    points = rng.uniform([-1, -1, 4], [1, 1, 6], (80, 3))
    poses = np.stack([pose_matrix(rotation_vector_to_matrix(np.array([0.0, 0.03 * t, 0.0])), np.array([-0.1 * t, 0, 0]))
                      for t in range(5)])
    uv = np.stack([project(points, K, p)[0] for p in poses])
    tracks = Tracks(uv=uv, valid=np.ones(uv.shape[:2], bool))
    noisy = poses.copy()
    noisy[1:, :3, :3] = rotation_vector_to_matrix(rng.normal(0, 0.01, (4, 3))) @ noisy[1:, :3, :3]
    result = bundle_adjust(tracks, K, noisy, points + rng.normal(0, 0.05, points.shape), iterations=100,
                           refine_focal=False, scale_frame=4)
    err = rotation_angle_deg(result.poses[:, :3, :3] @ np.swapaxes(poses[:, :3, :3], 1, 2))
    assert err.max() < 0.05 and result.median_error_px < 0.05
    assert static_camera(tracks, 0.35) is False


def test_a_frame_the_detector_missed_is_bridged_and_a_subject_that_left_is_not():
    masks = np.zeros((10, 60, 80), bool)
    for t in range(10):
        masks[t, 20:40, 10 + 2 * t: 30 + 2 * t] = True
    missed = masks.copy()
    missed[4] = False  # one frame, and two in a row: held frames on both sides
    missed[7:9] = False
    bridged = bridge_dropouts(missed, 0.004)
    assert np.array_equal(bridged[4], masks[3]) and np.array_equal(bridged[7], masks[6])
    assert np.array_equal(bridged[8], masks[9]) and np.array_equal(bridged[[0, 1, 2, 3, 5, 6, 9]], masks[[0, 1, 2, 3, 5, 6, 9]])
    check_subject(bridged, min_area=0.004, source="clip.mp4")
    three = masks.copy()
    three[4:7] = False  # three in a row: more than a miss
    assert not bridge_dropouts(three, 0.004)[4:7].any()
    left = masks.copy()
    left[8:] = False  # gone to the end: no held frame after
    assert not bridge_dropouts(left, 0.004)[8:].any()
    with pytest.raises(InputError, match="leaves the frame"):
        check_subject(bridge_dropouts(left, 0.004), min_area=0.004, source="clip.mp4")


def test_a_focal_far_from_the_guess_is_found_by_the_search_over_starts():
    """A 50 deg lens taken for the 66 deg guess: adjusted from the guess alone the camera is lost (a turning-only
    answer, 9 deg off); from the focal starts the focal comes within 5 % and every pose within 1 deg."""
    rng = np.random.default_rng(0)
    K_true = intrinsics_from_fov(W, H, 50.0)
    floor = np.c_[rng.uniform(-1.5, 1.5, 150), np.full(150, 0.8), rng.uniform(1.5, 4.0, 150)]
    wall = np.c_[rng.uniform(-1.5, 1.5, 150), rng.uniform(-1.0, 0.8, 150), np.full(150, 4.0)]
    points, centre = np.r_[floor, wall], np.array([0.0, 0.0, 2.5])
    turns = [rotation_vector_to_matrix(np.array([0.0, np.radians(20.0) * t / 11, 0.0])) for t in range(12)]
    poses = np.stack([pose_matrix(R, centre - R @ centre) for R in turns])  # a 20 deg arc about a point 2.5 m ahead
    uv = np.stack([project(points, K_true, p)[0] for p in poses]) + rng.normal(0, 0.2, (12, len(points), 2))
    tracks = Tracks(uv=uv, valid=(uv[..., 0] > 0) & (uv[..., 0] < W) & (uv[..., 1] > 0) & (uv[..., 1] < H))
    guess, config = intrinsics_from_fov(W, H, 66.0), FrontEndConfig().camera
    fit = solve_camera(tracks, guess, config, focal_given=False)
    err = rotation_angle_deg(fit.extrinsics[:, :3, :3] @ np.swapaxes(poses[:, :3, :3], 1, 2))
    assert fit.mode == "full" and abs(fit.K[0, 0] / K_true[0, 0] - 1) < 0.05 and err.max() < 1.0
    one = moving_camera(tracks, guess, config, focal_given=False)
    one_err = rotation_angle_deg(one.extrinsics[:, :3, :3] @ np.swapaxes(poses[:, :3, :3], 1, 2))
    assert one_err.max() > 3.0  # the setup needs the search
    assert parabola_vertex(np.array([0.0, 1.0, 2.0]), np.array([2.0, 1.0, 2.0])) == pytest.approx(1.0)
    assert parabola_vertex(np.array([0.0, 1.0, 2.0]), np.array([1.0, 2.0, 1.0])) is None


def test_too_short_clip_is_refused():
    clip, _ = square_clip(2)
    with pytest.raises(InputError, match="at least 3"):
        run_front_end(clip, FrontEndConfig())


def test_a_still_image_is_refused():
    clip, _ = square_clip(6, speed=0.0)
    with pytest.raises(InputError, match="still image"):
        run_front_end(clip, FrontEndConfig())


def test_a_clip_with_no_subject_is_refused():
    clip, _ = square_clip(8, pan_px=2.0, with_subject=False)
    with pytest.raises(InputError, match="no subject"):
        run_front_end(clip, FrontEndConfig())


def test_a_subject_leaving_the_frame_is_refused():
    clip, _ = square_clip(14, speed=6.0, start=60.0)  # out of view from frame 12 on
    with pytest.raises(InputError, match="leaves the frame"):
        run_front_end(clip, FrontEndConfig())


def test_a_subject_shrinking_inside_the_frame_is_in_view_and_one_shrinking_at_the_border_left():
    """A lid turned edge-on leaves a thin mask in mid-frame: still in view. The same thin mask at the border, or
    nothing at all, is a subject that left."""
    masks = np.zeros((8, 60, 80), bool)
    masks[:, 20:40, 30:50] = True
    masks[3:6, 20:40] = False
    masks[3:6, 28:31, 30:50] = True  # 3 of 20 rows: 15 % of its area, away from the border
    check_subject(masks, min_area=0.004, source="clip.mp4")
    at_border = masks.copy()
    at_border[3:6] = False
    at_border[3:6, 28:31, 0:20] = True
    with pytest.raises(InputError, match="clip.mp4: the subject leaves the frame \\(frames 3, 4, 5\\)"):
        check_subject(at_border, min_area=0.004, source="clip.mp4")
    empty = masks.copy()
    empty[3:6] = False
    with pytest.raises(InputError, match="leaves the frame"):
        check_subject(empty, min_area=0.004, source="clip.mp4")


@pytest.mark.parametrize("prompt", [(500.0, 20.0), (10.0, 10.0, 40.0, 300.0), (-1.0, 5.0), (30.0, 30.0, 20.0, 40.0)])
def test_a_prompt_outside_the_image_is_refused(prompt: tuple[float, ...]):
    clip, _ = square_clip()
    with pytest.raises(InputError, match="reference.prompt"):
        run_front_end(clip, FrontEndConfig(), prompt=Prompt(prompt, 0))


def test_given_masks_keep_and_the_camera_is_filled_then_written(tmp_path: Path):
    clip, truth = square_clip()
    given = VideoClip(clip.frames, truth, clip.fps, source="synthetic").validate()
    out, camera = complete_video(given, None, FrontEndConfig(), masks_given=True)
    assert np.array_equal(out.masks, truth)
    assert out.extrinsics.shape == (len(truth), 4, 4) and np.allclose(camera.world_to_cam, CAMERA_TO_YUP)
    write_video_inputs(tmp_path, out, camera)
    record = json.loads((tmp_path / "camera.json").read_text())
    assert record["static"] and len(record["world_to_camera"]) == len(truth)
    assert (tmp_path / "masks.mp4").stat().st_size > 0


def test_video_source_runs_the_front_end_when_nothing_is_given(tmp_path: Path):
    from sync4d.io.video import write_video
    from sync4d.sources.references import VideoSource

    clip, truth = square_clip()
    write_video(tmp_path / "clip.mp4", clip.frames, clip.fps)
    source = VideoSource(VideoSource.Config(video=str(tmp_path / "clip.mp4"))).load()
    assert source.camera is not None and source.video.extrinsics is not None
    assert np.median([iou(a, b) for a, b in zip(source.video.masks, truth)]) > 0.6  # after video compression
    cfg = VideoSource.Config(video=str(tmp_path / "clip.mp4"), prompt=[1000.0, 5.0])
    with pytest.raises(InputError, match="outside"):
        VideoSource(cfg).load()


def bad_clip(kind: str, folder: Path) -> tuple[str, ...]:
    """Write one bad reference video into ``folder``; returns the ``train.py`` overrides that feed it."""
    import imageio.v2 as imageio

    from sync4d.io.video import write_video

    clips = {"short": square_clip(2)[0], "still_video": square_clip(6, speed=0.0)[0],
             "no_subject": square_clip(8, pan_px=2.0, with_subject=False)[0],
             "leaves": square_clip(14, speed=6.0, start=60.0)[0], "prompt": square_clip()[0]}
    if kind == "image":
        imageio.imwrite(folder / "photo.png", square_clip()[0].frames[0])
        return ("reference.video=" + str(folder / "photo.png"), "reference.fps=10")
    write_video(folder / f"{kind}.mp4", clips[kind].frames, 10.0)
    # a run reads only the frames it uses (debug=smoke: 3), so the leaving clip asks for all 14
    extra = {"prompt": ("reference.prompt=[500,20]",), "leaves": ("reference.max_frames=14",)}.get(kind, ())
    return ("reference.video=" + str(folder / f"{kind}.mp4"), *extra)


@pytest.mark.parametrize("kind, expect", [
    ("short", ("short.mp4", "at least 3")), ("image", ("photo.png", "at least 3")),
    ("still_video", ("still_video.mp4", "still image")), ("no_subject", ("no_subject.mp4", "no subject")),
    ("leaves", ("leaves.mp4", "leaves the frame")), ("prompt", ("reference.prompt", "outside")),
])
def test_bad_videos_stop_train_py_with_one_line(kind: str, expect: tuple[str, ...], tmp_path: Path):
    """Through the pipeline: exit 2, one ``sync4d:`` line naming the input, before the reconstruction."""
    from _runs import train_in_process

    overrides = bad_clip(kind, tmp_path)
    code, stderr = train_in_process(tmp_path / "run", "reference=video", "recon=video", *overrides)
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("sync4d: "), stderr[-2000:]
    for word in expect:
        assert word.lower() in lines[0].lower(), lines[0]
    assert not (tmp_path / "run" / "recon" / "masks.mp4").exists()  # refused before anything was written


def test_the_viewer_shows_the_masks_beside_the_video(tmp_path: Path):
    from _viewrun import make_run

    from sync4d.view.data import load_run

    run = make_run(tmp_path / "a", frames=3, n=200)
    clip, truth = square_clip(3)
    write_video_inputs(run / "recon", VideoClip(clip.frames, truth, 10.0).validate(), None)
    data = load_run(run)
    assert data.masks is not None and data.masks(0).shape == clip.frames.shape[1:]


def test_the_ground_is_found_among_background_points_and_walls_are_not_taken() -> None:
    """ground_up: a floor tilted 20 deg from the camera's up, a wall and noise; the floor's normal is returned
    (oriented like the up guess); with only a wall, or too few points, None."""
    from scipy.spatial.transform import Rotation

    from sync4d.frontend.geometry import ground_up

    rng = np.random.default_rng(0)
    tilt = Rotation.from_rotvec(np.radians(20.0) * np.array([1.0, 0.0, 0.0]))
    floor = tilt.apply(np.stack([rng.uniform(-2, 2, 200), rng.normal(0, 0.005, 200), rng.uniform(1, 4, 200)], 1))
    wall = np.stack([rng.uniform(-2, 2, 120), rng.uniform(0, 2, 120), np.full(120, 4.0)], 1)
    found = ground_up(np.concatenate([floor, wall]), np.array([0.0, 1.0, 0.0]))
    true = tilt.apply([0.0, 1.0, 0.0])
    assert found is not None and np.degrees(np.arccos(min(1.0, float(found @ true)))) < 2.0
    assert ground_up(wall, np.array([0.0, 1.0, 0.0])) is None
    assert ground_up(floor[:20], np.array([0.0, 1.0, 0.0])) is None


def test_the_clip_colour_model_tells_the_subject_from_the_background():
    from sync4d.frontend.segment import clip_colour_model

    frames = np.zeros((2, 8, 8, 3), np.uint8)
    frames[:, :, :4] = [200, 40, 40]  # subject: red
    frames[:, :, 4:] = [40, 40, 200]  # background: blue
    subject = np.zeros((2, 8, 8), bool)
    subject[:, :, :4] = True
    model = clip_colour_model(frames, subject, ~subject)
    like = model.likeness(frames[0])
    assert model.support == 1.0 and (like[:, :4] > 0.9).all() and (like[:, 4:] < 0.1).all()


def test_a_part_coming_into_view_joins_when_surely_the_subjects_colour_and_unexplained():
    from sync4d.frontend.segment import REVEAL, revealed

    carried = np.zeros((60, 60), bool)
    carried[20:40, 20:40] = True  # size 20: the reach is REVEAL x 20 + 1 px
    reach = int(REVEAL * 20) + 1
    likeness = np.zeros((60, 60))
    explained = np.zeros((60, 60), bool)
    likeness[20:40, 40:40 + reach] = 1.0  # right: the subject's colours, unexplained -> joins
    likeness[40:40 + reach, 20:40] = 0.6  # below: more the subject's than not, but not surely -> stays out
    likeness[20 - reach:20, 20:40] = 1.0  # above: the subject's colours, but the background explains it
    explained[20 - reach:20, 20:40] = True
    likeness[20:40, 40 + reach + 3:] = 1.0  # beyond the reach: stays out
    out = revealed(carried, likeness, explained)
    assert out[20:40, 40:40 + reach].all()
    assert not out[40:, :].any() and not out[:20, :].any() and not out[:, 40 + reach:].any()


def test_a_static_camera_mask_drops_what_shows_the_background_plate():
    from sync4d.frontend.segment import drop_plate

    clip, truth = square_clip(n_frames=10, speed=8.0, start=10.0)
    padded = np.stack([m | np.roll(m, -6, 1) for m in truth])  # the mask drags floor behind it
    kept = drop_plate(clip.frames, padded)
    assert np.median([iou(a, b) for a, b in zip(kept, truth)]) > 0.9 > np.median([iou(a, b) for a, b in zip(padded, truth)])
    still = drop_plate(np.repeat(clip.frames[:1], 10, 0), truth)  # a subject that never moves is kept whole
    assert np.array_equal(still, truth)


def test_small_holes_are_filled_and_open_gaps_kept():
    from sync4d.frontend.segment import fill_holes

    mask = np.zeros((40, 40), bool)
    mask[5:35, 5:35] = True
    mask[10:12, 10:12] = False  # a speckle inside: filled
    mask[20:35, 18:22] = False  # a gap open to the outside (between legs): kept
    filled = fill_holes(mask, 0.01)
    assert filled[10:12, 10:12].all() and not filled[25, 20]


def test_the_background_a_still_camera_sees_is_explained_and_the_square_is_not():
    from sync4d.frontend.motion import motion_evidence

    clip, truth = square_clip()
    grey = clip.frames.mean(axis=3).astype(np.uint8)
    evidence = motion_evidence(grey, static=True, sigma=4.0, min_px=0.6)
    assert evidence.explained is not None
    far = ~truth  # the background of each frame
    assert evidence.explained[3][far[3]].mean() > 0.8 and evidence.explained[3][truth[3]].mean() < 0.2


@pytest.mark.parametrize("pan_px", [0.0, 2.0])
def test_the_floor_beside_a_moving_square_is_explained_by_its_picture_and_the_square_is_not(pan_px: float):
    from sync4d.frontend.motion import picture_explained
    from sync4d.frontend.segment import morph

    clip, truth = square_clip(10, pan_px=pan_px)
    grey = clip.frames.mean(axis=3).astype(np.uint8)
    explained = picture_explained(clip.frames, grey, static=pan_px == 0.0)
    for t in (4, 5):  # frames with two frames before and after: what the square covers there is floor now
        beside = morph(truth[t], "dilate", 6) & ~morph(truth[t], "dilate", 2)  # the blur and 1 px reach 2 px
        assert explained[t][beside].mean() > 0.8
        assert explained[t][truth[t]].mean() < 0.05


def test_the_suites_box_objects_move_one_part_and_hold_their_body():
    from sync4d_tools.frontend_suite import BOX_OBJECTS, box_subject

    for name in BOX_OBJECTS:
        subject = box_subject(name, seed=0)
        step = np.linalg.norm(subject.means - subject.means[:1], axis=-1).max(axis=0)  # (N,) [m]
        assert subject.means.shape[0] == 16 and subject.colours.shape == subject.means.shape
        assert (step < 1e-9).mean() > 0.5 and step.max() > 0.1  # the body holds still, the lid/door moves
