"""recon=video on a tiny synthetic video (two textured plates on a hinge), plus its image helpers."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d.errors import ConfigError, InputError
from sync4d.recon.video import (
    background_masks,
    flow_consistency,
    optical_flow,
    rotation_angle_deg,
    sample_image,
    track_points,
)
from sync4d.registry import build
from sync4d.types import Camera, ReferenceInput, VideoClip

H, W = 96, 128
K = np.array([[120.0, 0, W / 2], [0, 120.0, H / 2], [0, 0, 1]])


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0, 0, 1.0]])


def hinge_video(frames: int = 6, max_deg: float = 40.0) -> tuple[VideoClip, np.ndarray, np.ndarray]:
    """Two textured plates seen by a camera at the origin (OpenCV axes), slightly tilted: a base on the
    left and an arm hinged at its right edge, turning about the (nearly) viewing direction by up to
    ``max_deg``. Rendered by z-buffered point splatting. Returns (clip, part labels (T, H, W) 0/1/2,
    arm angles [deg])."""
    rng = np.random.default_rng(0)
    n = 30000
    uv = rng.uniform(0, 1, (n, 2))
    tilt = np.array([0.0, 0.94, 0.34])  # the plates' second axis, tilted away from the camera
    hinge = np.array([0.0, 0.0, 1.2])
    base = hinge + (uv[:, :1] - 1.0) * 0.35 * np.array([1.0, 0, 0]) + (uv[:, 1:] - 0.5) * 0.2 * tilt
    lid_rest = hinge + uv[:, :1] * 0.3 * np.array([1.0, 0, 0]) + (uv[:, 1:] - 0.5) * 0.15 * tilt
    checker = ((np.floor(uv[:, 0] * 6) + np.floor(uv[:, 1] * 4)) % 2)[:, None]
    col_base = np.array([60, 90, 200]) + checker * np.array([120, 80, 0]) + uv[:, 1:] * 40
    col_lid = np.array([200, 70, 40]) + checker * np.array([0, 120, 120]) + uv[:, :1] * 40
    angles = np.linspace(0.0, max_deg, frames)
    imgs, labels = [], []
    for a in angles:
        lid = (lid_rest - hinge) @ rot_z(np.deg2rad(-a)).T + hinge
        pts = np.concatenate([base, lid])
        cols = np.concatenate([col_base, col_lid])
        part = np.concatenate([np.ones(n, int), np.full(n, 2)])
        pix = pts @ K.T
        u = (pix[:, 0] / pix[:, 2]).astype(int)
        v = (pix[:, 1] / pix[:, 2]).astype(int)
        inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        order = np.argsort(-pts[:, 2])  # far first; near points overwrite
        img = np.zeros((H, W, 3), np.uint8)
        lab = np.zeros((H, W), int)
        for i in order[inside[order]]:
            img[v[i], u[i]] = np.clip(cols[i], 0, 255)
            lab[v[i], u[i]] = part[i]
        imgs.append(img)
        labels.append(lab)
    clip = VideoClip(frames=np.stack(imgs), masks=np.stack(labels) > 0, fps=10.0, intrinsics=K, source="synthetic")
    return clip.validate(), np.stack(labels), angles


def test_flow_helpers_on_a_translating_pattern() -> None:
    yy, xx = np.mgrid[0:H, 0:W]
    base = (128 + 60 * np.sin(xx / 3.0) * np.cos(yy / 4.0)).astype(np.uint8)
    frames = np.stack([np.repeat(np.roll(base, s, axis=1)[..., None], 3, -1) for s in (0, 2, 4)])
    fwd, bwd = optical_flow(frames, "dis")
    centre = (slice(10, 38), slice(12, 52))
    assert np.abs(np.median(fwd[0][centre][..., 0]) - 2.0) < 0.3
    assert flow_consistency(fwd, bwd)[0][centre].mean() > 0.8
    tracks = track_points(np.array([[30.0, 24.0]]), fwd)
    assert np.allclose(tracks[-1], [34.0, 24.0], atol=0.6)
    assert np.allclose(sample_image(np.arange(12.0).reshape(3, 4), np.array([[1.5, 1.0]])), 5.5)


def test_background_model_finds_the_moving_object() -> None:
    frames = np.full((7, H, W, 3), 40, np.uint8)
    for t in range(7):
        frames[t, 10:20, 5 + 6 * t : 15 + 6 * t] = 220
    masks = background_masks(frames)
    assert masks[3, 12:18, 25:31].all() and not masks[3, :, :20].any()


def test_config_errors() -> None:
    with pytest.raises(ConfigError, match="auto"):
        build("recon", {"type": "video", "bones": "auto"})
    with pytest.raises(ConfigError, match="same length"):
        build("recon", {"type": "video", "levels": [4, 2], "iterations": [10]})
    with pytest.raises(InputError, match="needs a video"):
        build("recon", {"type": "video"}).reconstruct(ReferenceInput(name="none", fps=1.0))


@pytest.mark.slow
def test_two_plate_hinge_is_recovered() -> None:
    clip, labels, angles = hinge_video()
    camera = Camera(K=K, world_to_cam=np.eye(4), width=W, height=H)
    recon = build("recon", {"type": "video", "bones": 2, "gaussians": 300, "init_depth": 1.2, "levels": [2],
                            "iterations": [20], "track_steps": 20, "first_frame_steps": 20, "pixels_per_frame": 400,
                            "flow_pixels_per_frame": 200, "frames_per_step": 3}, device="cpu")
    ref = recon.reconstruct(ReferenceInput(name="hinge", fps=10.0, video=clip, camera=camera))
    assert ref.num_bones == 2 and ref.num_frames == len(angles) and ref.rest_faces is None
    # parts: each Gaussian's bone agrees with the plate under its first-frame pixel
    import torch

    from sync4d.recon._softsplat import project_points

    uv, _ = project_points(torch.as_tensor(ref.rest_vertices), torch.as_tensor(K), torch.eye(4, dtype=torch.float64))
    u = np.clip(uv[:, 0].numpy().astype(int), 0, W - 1)
    v = np.clip(uv[:, 1].numpy().astype(int), 0, H - 1)
    plate = labels[0][v, u]
    bone = ref.part_labels()
    on = plate > 0
    agree = max(((bone == plate - 1) & on).sum(), ((bone == 2 - plate) & on).sum()) / on.sum()
    assert agree > 0.9, agree
    # the relative rotation between the bones follows the lid angle
    j = ref.bone_transforms
    rel = rotation_angle_deg(np.einsum("tji,tjk->tik", j[:, 0, :3, :3], j[:, 1, :3, :3]))
    assert abs(rel[-1] - angles[-1]) < 8.0, rel
    assert np.all(np.diff(rel) > 0), rel  # opening monotonically, as the arm does
    assert recon.last_fit_report["gaussians"] == 300
