"""People filmed by a moving camera: the body fit takes the per-frame camera, the ground at the feet gives the
camera's translation unit, and the suite's hand-held renders."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sync4d.recon.body_video import ground_camera, moving_camera
from sync4d.recon.pose.human_fit import HumanFitConfig, fit_human
from sync4d.sources.references import camera_from_look
from tests.test_recon_pose import standing_body, synthetic_track

K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])


def shaking_cameras(count: int, rng: np.random.Generator) -> np.ndarray:
    """(T, 4, 4) world-to-camera: a 15 deg arc around a point 3 m ahead, 2 deg of shake a frame (OpenCV world,
    the first camera at the origin looking down +z, y down)."""
    out = []
    for t in range(count):
        a = np.radians(15.0) * t / max(count - 1, 1)
        pos = np.array([0.2 - 3.0 * np.sin(a), 0.1, 3.0 - 3.0 * np.cos(a)])
        aim = np.array([0.2, 0.1, 3.0]) + rng.normal(0.0, np.radians(2.0) * 3.0, 3)
        # camera_from_look takes a y-up 'up'; the OpenCV world's up is -y
        out.append(camera_from_look(K, pos, aim - pos, np.array([0.0, -1.0, 0.0]), 320, 240).world_to_cam)
    return np.stack(out)


def test_human_fit_reads_a_shaking_camera_as_the_camera() -> None:
    """A person standing still (one arm swinging) filmed by a shaking, orbiting camera: with the per-frame
    camera the fitted body stands still in the world; taken as static, the camera's motion is the body's."""
    rng = np.random.default_rng(0)
    world = standing_body(10)  # in the world (the first camera's frame at rest)
    w2c = shaking_cameras(len(world), rng)
    cam = np.einsum("tij,tkj->tki", w2c[:, :3, :3], world) + w2c[:, None, :3, 3]
    track = synthetic_track(cam, K, rng, noise_px=1.0)
    moving = fit_human(track, K, HumanFitConfig(), extrinsics=w2c)
    still = fit_human(track, K, HumanFitConfig())
    assert moving.extrinsics is not None
    # both in the first frame's camera; the truth there is world seen by camera 0
    truth0 = world @ w2c[0, :3, :3].T + w2c[0, :3, 3]
    err_moving = np.linalg.norm(moving.joints - truth0, axis=-1).mean()
    err_still = np.linalg.norm(still.joints - truth0, axis=-1).mean()
    assert err_moving < 0.06, err_moving  # [m], no alignment
    assert err_still > 3 * err_moving, (err_still, err_moving)
    pelvis = moving.joints[:, 0]
    assert np.ptp(pelvis, axis=0).max() < 0.1  # the body stays put; the camera moved ~0.8 m


def floor_frames(w2c: np.ndarray, floor_y: float, size: tuple[int, int] = (240, 320)) -> np.ndarray:
    """(T, H, W, 3) uint8 views of a floor (the plane y = ``floor_y``, OpenCV world, y down) textured with 8 cm
    cells of random grey, and a plain grey sky."""
    h, w = size
    vv, uu = np.mgrid[0:h, 0:w] + 0.5
    rays = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], 1) @ np.linalg.inv(K).T
    shades = np.random.default_rng(1).integers(20, 235, (400, 400))
    frames = []
    for e in w2c:
        d = rays @ e[:3, :3]  # R^T applied to each ray
        o = -e[:3, :3].T @ e[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (floor_y - o[1]) / d[:, 1]
        hit = o + d * lam[:, None]
        cell = np.floor(hit[:, [0, 2]] / 0.08).astype(np.int64) % 400
        grey = np.where((lam > 0) & np.isfinite(lam), shades[cell[:, 0], cell[:, 1]], 128)
        frames.append(np.repeat(grey.reshape(h, w, 1), 3, axis=2).astype(np.uint8))
    return np.stack(frames)


def test_ground_beside_the_feet_measures_the_cameras_path() -> None:
    """A camera sliding along a textured floor and turning: given its turns only, the ground at the feet's
    (known) depth gives its path back in metres."""
    count = 10
    w2c = np.stack([camera_from_look(K, np.array([0.06 * t, 0.02 * np.sin(t), 0.0]),
                                     np.array([0.1 * t / count, 0.35, 1.0]), np.array([0.0, -1.0, 0.0]), 320,
                                     240).world_to_cam for t in range(count)])
    frames = floor_frames(w2c, floor_y=1.5)
    feet_world = np.array([[0.5, 1.5, 3.5], [0.7, 1.5, 3.6]])  # two feet on the floor [m]
    feet = np.einsum("tij,kj->tki", w2c[:, :3, :3], feet_world) + w2c[:, None, :3, 3]
    masks = np.zeros(frames.shape[:3], bool)
    up = np.array([0.0, -1.0, 0.0])
    found = ground_camera(frames, masks, K, w2c[:, :3, :3], feet, up)
    assert found is not None
    assert np.allclose(found[:, :3, :3], w2c[:, :3, :3])
    centres = np.einsum("tji,tj->ti", found[:, :3, :3], -found[:, :3, 3])
    truth = np.einsum("tji,tj->ti", w2c[:, :3, :3], -w2c[:, :3, 3])
    assert np.abs(centres - (truth - truth[0])).max() < 0.03, centres  # [m]; 0.54 m travelled
    # a plain floor has nothing to track: no path
    assert ground_camera(np.full_like(frames, 128), masks, K, w2c[:, :3, :3], feet, up) is None


def test_moving_camera() -> None:
    assert not moving_camera(None)
    assert not moving_camera(np.tile(np.eye(4), (5, 1, 1)))
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[3, 0, 3] = 0.1
    assert moving_camera(poses)


def test_handheld_cameras_pan_shake_and_keep_the_walker_in_view() -> None:
    from sync4d_tools.body_clips import handheld_cameras

    t = np.linspace(0.0, 1.0, 12)[:, None]
    pelvis = np.concatenate([1.5 * t, np.full_like(t, 0.9), np.zeros_like(t)], axis=1)  # 1.5 m walk along +x
    tracks = {"pelvis": pelvis, "neck": pelvis + [0.0, 0.5, 0.0], "l_ankle": pelvis + [0.1, -0.85, 0.0],
              "r_ankle": pelvis + [-0.1, -0.85, 0.0], "l_toe": pelvis + [0.1, -0.9, 0.15],
              "r_toe": pelvis + [-0.1, -0.9, 0.15]}
    cams = handheld_cameras(tracks, "oblique", 320, 480, 50.0, seed=3)
    again = handheld_cameras(tracks, "oblique", 320, 480, 50.0, seed=3)
    assert all(np.array_equal(a.world_to_cam, b.world_to_cam) for a, b in zip(cams, again))
    rel = cams[-1].world_to_cam[:3, :3] @ cams[0].world_to_cam[:3, :3].T
    assert np.degrees(np.arccos((np.trace(rel) - 1) / 2)) > 5.0  # a pan, not a still camera
    for cam, p in zip(cams, pelvis):
        x = cam.world_to_cam[:3, :3] @ p + cam.world_to_cam[:3, 3]
        u, v = (cam.K @ x)[:2] / x[2]
        assert x[2] > 0 and 0 < u < 320 and 0 < v < 480


@pytest.mark.slow
def test_body_video_takes_a_handheld_camera(tmp_path: Path, shared_data: Path) -> None:
    """A hand-held render with its per-frame camera: the fit keeps the camera's turns, re-measures its path
    in metres from the ground (close to the truth), stays within the static clips' error, and the reference
    builds. (The gain over a camera taken as static is measured by ``sync4d_tools.body_suite``.)"""
    from dataclasses import replace

    from sync4d.io.video import read_video_clip
    from sync4d.recon.body_video import BodyVideoReconstructor
    from sync4d.types import Camera, ReferenceInput, VideoClip
    from sync4d_tools.body_clips import write_clip
    from sync4d_tools.body_suite import joint_score

    folder = tmp_path / "hh"
    write_clip(folder, "cmu", "front", frames=16, stride=8, width=240, height=360, fov_deg=50.0, handheld=0)
    video = read_video_clip(folder / "rgb.mp4", None)
    cam, gt = np.load(folder / "camera.npz"), np.load(folder / "gt.npz")
    w2c = cam["world_to_cam"]
    clip = VideoClip(video.frames, np.zeros(video.frames.shape[:3], bool), video.fps, cam["K"], w2c).validate()
    source = ReferenceInput(name="hh", fps=video.fps, video=clip,
                            camera=Camera(K=cam["K"], world_to_cam=w2c[0], width=240, height=360).validate())
    recon = BodyVideoReconstructor(BodyVideoReconstructor.Config(figures=False))
    moving = recon.fit(source)
    still = recon.fit(replace(source, video=replace(clip, extrinsics=None)))
    assert moving.extrinsics is not None and still.extrinsics is None
    assert np.allclose(moving.extrinsics[:, :3, :3], w2c[:, :3, :3])
    centres = np.einsum("tji,tj->ti", w2c[:, :3, :3], -w2c[:, :3, 3])
    found = np.einsum("tji,tj->ti", moving.extrinsics[:, :3, :3], -moving.extrinsics[:, :3, 3])
    assert np.abs(found - (centres - centres[0])).max() < 0.15  # [m]
    names = [str(n) for n in gt["names"]]

    def err(fit) -> float:
        return joint_score(fit.joints[:, [fit.names.index(n) for n in names]], gt["joints"])["mpjpe_pct_height"]

    assert err(moving) < 12.0 and err(still) < 20.0, (err(moving), err(still))
    assert recon.reconstruct(source).validate().num_frames == 16
