"""Videos: mp4 and GIF files readable with the right frame count, side-by-side composition, TensorBoard."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sync4d.render.camera import frame_object
from sync4d.render.splat_torch import SplatTorch
from sync4d.render.video import (
    compare,
    frame_strip,
    log_gif_tensorboard,
    read_video,
    render_sequence,
    to_uint8,
    write_gif,
    write_mp4,
)


def ramp_frames(t: int, h: int, w: int) -> np.ndarray:
    """Frames whose mean grey level encodes the frame index (survives lossy encoding)."""
    frames = np.zeros((t, h, w, 3), dtype=np.uint8)
    for i in range(t):
        frames[i] = int(20 + 200 * i / max(t - 1, 1))
    return frames


@pytest.mark.parametrize("size", [(32, 48), (33, 47)])
def test_mp4_is_readable_with_the_right_frames(tmp_path: Path, size: tuple[int, int]) -> None:
    frames = ramp_frames(9, *size)
    path = write_mp4(tmp_path / "render.mp4", frames, fps=12)
    assert path.is_file() and not list(tmp_path.glob(".*tmp*"))  # atomic: no temporary file left
    video = read_video(path)
    assert video.shape[0] == 9
    # Odd sizes are padded by one replicated pixel for H.264 (yuv420p needs even sizes).
    assert video.shape[1:3] == (size[0] + size[0] % 2, size[1] + size[1] % 2)
    means = video[:, : size[0], : size[1]].reshape(9, -1).mean(axis=1)
    np.testing.assert_allclose(means, frames.reshape(9, -1).mean(axis=1), atol=3.0)
    import imageio.v2 as iio

    assert iio.get_reader(str(path)).get_meta_data()["fps"] == pytest.approx(12.0)


def test_gif_round_trip_is_exact(tmp_path: Path) -> None:
    frames = ramp_frames(5, 20, 30)
    path = write_gif(tmp_path / "clip.gif", frames / 255.0, fps=10)
    video = read_video(path)
    assert video.shape == (5, 20, 30, 3)
    np.testing.assert_array_equal(video, frames)


def test_compare_aligns_frames_and_matches_heights() -> None:
    ref = ramp_frames(3, 40, 30)  # shorter and taller: looped and resized to the target's height
    tgt = np.full((7, 20, 25, 3), 255, dtype=np.uint8)
    out = compare(ref, tgt, gap=2)
    assert out.shape == (7, 20, 15 + 2 + 25, 3)
    for t in range(7):
        np.testing.assert_array_equal(out[t, :, :15], ref[t % 3, ::2, ::2])
        np.testing.assert_array_equal(out[t, :, 17:], tgt[t])
    held = compare(ref, tgt, loop_reference=False, gap=2)
    np.testing.assert_array_equal(held[6, :, :15], ref[2, ::2, ::2])
    labelled = compare(ref, tgt, labels=("reference", "target"))
    assert labelled.shape[1] == 20 and (labelled[0, :8, :15] != out[0, :8, :15]).any()


def test_tensorboard_gets_an_animated_gif_and_a_strip(tmp_path: Path) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from torch.utils.tensorboard import SummaryWriter

    frames = ramp_frames(6, 16, 24)
    writer = SummaryWriter(str(tmp_path / "tb"))
    log_gif_tensorboard(writer, "video/render", frames, 3, fps=8, gif_path=tmp_path / "render.gif")
    writer.close()
    acc = EventAccumulator(str(tmp_path / "tb"))
    acc.Reload()
    assert set(acc.Tags()["images"]) == {"video/render", "video/render/strip"}
    gif = acc.Images("video/render")[0]
    assert gif.step == 3 and gif.encoded_image_string[:6] == b"GIF89a"
    assert gif.encoded_image_string == (tmp_path / "render.gif").read_bytes()
    strip = acc.Images("video/render/strip")[0]
    assert (strip.width, strip.height) == (6 * 24, 16)
    assert frame_strip(frames, max_frames=3).shape == (16, 3 * 24, 3)


def test_render_sequence_moves_with_the_means() -> None:
    n = 40
    rng = np.random.default_rng(0)
    base = rng.uniform(-0.2, 0.2, (n, 3))
    seq = np.stack([base + [0.15 * t, 0.0, 0.0] for t in range(3)])
    cam = frame_object(seq.reshape(-1, 3), (0.0, -1.0, 0.0), up=(0.0, 0.0, 1.0), width=48, height=32)
    covs = np.repeat((0.03**2 * np.eye(3))[None], n, 0)
    rnd = SplatTorch(SplatTorch.Config(background=[1, 1, 1]))
    frames = render_sequence(rnd, seq, covs, np.zeros((n, 3)), np.full(n, 0.9), cam, progress=False)
    assert frames.shape == (3, 32, 48, 3) and frames.dtype == np.uint8
    dark = 255 - frames[..., 0].astype(float)
    cols = np.arange(48)
    cx = [(d.sum(0) * cols).sum() / d.sum() for d in dark]
    assert cx[0] < cx[1] < cx[2]  # +x is to the right seen from -y with z up
    assert to_uint8(np.array([[[0.5, 1.2, -1.0]]])).tolist() == [[[128, 255, 0]]]


def test_side_by_side_puts_video_reference_and_target_in_one_frame() -> None:
    from sync4d.render.video import side_by_side

    video, ref, tgt = ramp_frames(4, 30, 40), ramp_frames(2, 60, 60), np.full((5, 30, 20, 3), 7, np.uint8)
    out = side_by_side([video, ref, tgt], gap=3)
    assert out.shape == (5, 30, 40 + 3 + 30 + 3 + 20, 3)
    np.testing.assert_array_equal(out[4, :, :40], video[0])          # looped: frame 4 of 5 shows video frame 0
    np.testing.assert_array_equal(out[3, :, 43:73], ref[1, ::2, ::2])
    np.testing.assert_array_equal(out[2, :, 76:], tgt[2])
    with pytest.raises(Exception, match="labels"):
        side_by_side([video, tgt], labels=["one"])


def test_motion_view_looks_at_the_plane_of_motion_upright() -> None:
    from sync4d.render.camera import SIDE_ON, MotionView, motion_view_direction

    rng = np.random.default_rng(0)
    base = rng.uniform(-0.1, 0.1, (50, 3))
    # A lid swinging about the x axis: its points move in the y-z plane, so it is best seen along x.
    angles = np.linspace(0.0, 1.2, 8)
    seq = np.stack([base @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]).T
                    + [0, 0.2, 0] for a in angles])
    d = motion_view_direction(seq, SIDE_ON, up=(0, 1, 0), prefer=(1, 1, 1))
    np.testing.assert_allclose(d, [1, 0, 0], atol=1e-6)
    # The same motion turned 90 degrees about the up axis is seen from the turned side (same view in its frame).
    turn = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0.0]])
    d_turned = motion_view_direction(seq @ turn.T, SIDE_ON, up=(0, 1, 0), prefer=(-1, 1, 1))
    np.testing.assert_allclose(np.abs(d_turned), [0, 0, 1], atol=1e-6)
    # Elevation raises the camera above the horizon; the side follows ``prefer``.
    raised = motion_view_direction(seq, MotionView(elevation_deg=20.0), up=(0, 1, 0),
                                   prefer=(-1, 0, 0))
    assert raised[1] == pytest.approx(np.sin(np.radians(20.0))) and raised[0] < 0
    # Z-up scenes: the camera stays upright about z.
    dz = motion_view_direction(seq[..., [0, 2, 1]], SIDE_ON, up=(0, 0, 1), prefer=(1, 1, 0))
    np.testing.assert_allclose(dz, [1, 0, 0], atol=1e-6)


def test_turntable_of_the_last_frame(tmp_path: Path) -> None:
    from sync4d.run.exports import write_turntable
    from sync4d.types import TargetGaussians

    n = 40
    rng = np.random.default_rng(4)
    target = TargetGaussians(means=rng.uniform(-0.2, 0.2, (n, 3)).astype(np.float32),
                             quats=np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32),
                             log_scales=np.full((n, 3), np.log(0.03), np.float32),
                             opacity_logits=np.full(n, 2.0, np.float32),
                             sh=rng.normal(size=(n, 1, 3)).astype(np.float32))
    rnd = SplatTorch(SplatTorch.Config(width=32, height=24, turntable_frames=3))
    path = write_turntable(tmp_path / "turntable.mp4", rnd, target.means.astype(float), target.covariances(), target,
                           8.0)
    frames = read_video(path)
    assert frames.shape == (3, 24, 32, 3) and not np.array_equal(frames[0], frames[1])
