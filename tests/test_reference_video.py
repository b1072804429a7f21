"""Filming a reference for recon=video: checker texture, masks that cover the projected surface."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d.errors import ConfigError
from sync4d.registry import build
from sync4d.scenes.reference_video import FilmSettings, checker


def test_checker_alternates_between_neighbouring_cells() -> None:
    pts = np.array([[0.005, 0.005, 0.005], [0.015, 0.005, 0.005], [0.015, 0.015, 0.005], [-0.005, 0.005, 0.005]])
    np.testing.assert_array_equal(checker(pts, 0.01), [1.0, -1.0, 1.0, -1.0])


def test_film_settings_reject_nonsense() -> None:
    with pytest.raises(ConfigError, match="video_size"):
        FilmSettings(width=8, height=8).validate()
    with pytest.raises(ConfigError, match="texture"):
        FilmSettings(texture_contrast=1.5).validate()


def test_filmed_laptop_masks_cover_its_projected_vertices_and_the_lid_moves() -> None:
    source = build("reference", {"type": "laptop", "num_frames": 4, "period_frames": 4, "subdivisions": 1,
                                 "video": True, "video_width": 64, "video_height": 48, "video_gaussians": 1500,
                                 "video_exact": "masks_camera"},  # the film's own camera, checked here
                   device="cpu")
    data = source.load()
    clip, camera, ref = data.video, data.camera, data.ground_truth
    assert clip.frames.shape == (4, 48, 64, 3) and clip.masks.shape == (4, 48, 64)
    np.testing.assert_allclose(clip.intrinsics, camera.K)
    # the default film is hand-held: a pose per frame, the first one the given camera's, and it moves
    assert clip.extrinsics is not None and clip.extrinsics.shape == (4, 4, 4)
    np.testing.assert_allclose(clip.extrinsics[0], camera.world_to_cam)
    assert np.abs(clip.extrinsics[-1] - clip.extrinsics[0]).max() > 1e-3
    for t in range(4):
        posed = ref.posed_vertices(t, apply_global=True)
        w2c = clip.extrinsics[t]  # frame t's camera
        cam = posed @ w2c[:3, :3].T + w2c[:3, 3]
        assert (cam[:, 2] > 0).all()  # in front of the camera
        uv = cam[:, :2] / cam[:, 2:] @ camera.K[:2, :2].T + camera.K[:2, 2]
        px = np.floor(uv).astype(int)
        inside = (px[:, 0] >= 0) & (px[:, 0] < 64) & (px[:, 1] >= 0) & (px[:, 1] < 48)
        assert inside.all()  # the framing keeps the whole motion in view
        assert clip.masks[t][px[:, 1], px[:, 0]].mean() > 0.9
    # the lid closes between frame 0 and frame 2: the silhouette changes
    assert (clip.masks[0] != clip.masks[2]).mean() > 0.02
    # texture: the rendered object is not flat-coloured
    assert clip.frames[0][clip.masks[0]].std() > 10.0


def test_filmed_part_labels_and_hinge_angles_of_the_laptop() -> None:
    from sync4d.scenes.laptop import laptop_reference
    from sync4d.scenes.laptop import hinge_angles_rad
    from sync4d.scenes.reference_video import film_reference

    ref = laptop_reference(4, period_frames=4, subdivisions=1, rest_angle_deg=110.0, min_angle_deg=40.0)
    angles = np.degrees(hinge_angles_rad(ref))
    assert angles[0] == pytest.approx(0.0, abs=1e-9) and angles.max() == pytest.approx(70.0, abs=1e-6)
    renderer = build("render", {"type": "splat_torch", "width": 48, "height": 36}, device="cpu")
    clip, camera, labels = film_reference(ref, renderer, FilmSettings(width=48, height=36, gaussians=1500), with_labels=True)
    assert labels.shape == (4, 36, 48) and set(np.unique(labels)) == {0, 1, 2}
    np.testing.assert_array_equal(labels > 0, clip.masks)
    # the base's pixels are the bottom of the object in the image (the lid stands up behind it)
    rows = np.arange(36)[:, None]
    assert (rows * (labels[0] == 1)).sum() / (labels[0] == 1).sum() > (rows * (labels[0] == 2)).sum() / (labels[0] == 2).sum()


def test_the_static_film_is_kept_and_the_arc_starts_from_its_view() -> None:
    """reference.video_camera=static films from one camera before a plain backdrop (no poses per frame); the
    hand-held arc's first camera is that camera, its later ones turn about the up axis (about 30 deg by the
    last frame) and its background is textured."""
    from sync4d.geometry import rotation_angle_deg

    common = {"type": "laptop", "num_frames": 6, "period_frames": 6, "subdivisions": 1, "video_width": 64,
              "video_height": 48, "video_gaussians": 1500, "video_exact": "masks_camera"}
    still = build("reference", {**common, "video_camera": "static"}, device="cpu").load()
    hand = build("reference", common, device="cpu").load()
    assert still.video.extrinsics is None
    np.testing.assert_allclose(hand.camera.world_to_cam, still.camera.world_to_cam)
    turn = rotation_angle_deg(hand.video.extrinsics[-1, :3, :3] @ hand.video.extrinsics[0, :3, :3].T)
    assert 25.0 < turn < 36.0
    background = ~hand.video.masks[0]
    assert hand.video.frames[0][background].std() > 20.0 > still.video.frames[0][~still.video.masks[0]].std()
