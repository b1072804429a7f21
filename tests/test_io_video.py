"""Reading videos and masks into a VideoClip."""

from __future__ import annotations

from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest

from sync4d.errors import DataMissingError, InputError
from sync4d.io.video import read_frames, read_video_clip, write_video


def make_frames(t: int = 5, h: int = 24, w: int = 32) -> tuple[np.ndarray, np.ndarray]:
    frames = np.zeros((t, h, w, 3), dtype=np.uint8)
    masks = np.zeros((t, h, w), dtype=bool)
    for i in range(t):
        masks[i, 6:18, 4 + i : 14 + i] = True
        frames[i][masks[i]] = (200, 60, 30)
    return frames, masks


def write_masks(folder: Path, masks: np.ndarray) -> None:
    folder.mkdir()
    for i, m in enumerate(masks):
        imageio.imwrite(folder / f"{i:05d}.png", (m * 255).astype(np.uint8))


def test_mp4_and_png_masks(tmp_path: Path) -> None:
    frames, masks = make_frames()
    write_video(tmp_path / "clip.mp4", frames, fps=12)
    write_masks(tmp_path / "masks", masks)
    clip = read_video_clip(tmp_path / "clip.mp4", tmp_path / "masks")
    assert clip.frames.shape == (5, 24, 32, 3) and clip.frames.dtype == np.uint8
    assert np.array_equal(clip.masks, masks) and clip.fps == pytest.approx(12.0)
    # lossy video: colours close to what was written inside the mask
    assert np.abs(clip.frames[2][masks[2]].astype(int).mean(0) - [200, 60, 30]).max() < 25
    strided = read_video_clip(tmp_path / "clip.mp4", tmp_path / "masks", stride=2, max_frames=2)
    assert strided.num_frames == 2 and strided.fps == pytest.approx(6.0)


def test_image_folder_needs_fps(tmp_path: Path) -> None:
    frames, masks = make_frames(t=3)
    (tmp_path / "rgb").mkdir()
    for i, f in enumerate(frames):
        imageio.imwrite(tmp_path / "rgb" / f"{i:03d}.png", f)
    write_masks(tmp_path / "masks", masks)
    with pytest.raises(InputError, match="frame rate is unknown"):
        read_video_clip(tmp_path / "rgb", tmp_path / "masks")
    clip = read_video_clip(tmp_path / "rgb", tmp_path / "masks", fps=10.0)
    assert np.array_equal(clip.frames, frames)


def test_errors(tmp_path: Path) -> None:
    frames, masks = make_frames()
    write_video(tmp_path / "clip.mp4", frames, fps=12)
    with pytest.raises(DataMissingError, match="absent.mp4"):
        read_video_clip(tmp_path / "absent.mp4", None)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no images"):
        read_frames(tmp_path / "empty")
    write_masks(tmp_path / "small", masks[:, :10, :10])
    with pytest.raises(InputError, match="masks must match the frames' size"):
        read_video_clip(tmp_path / "clip.mp4", tmp_path / "small")
    write_masks(tmp_path / "blank", np.zeros_like(masks))
    with pytest.raises(InputError, match="every mask is empty"):
        read_video_clip(tmp_path / "clip.mp4", tmp_path / "blank")
    write_masks(tmp_path / "few", masks[:3])
    with pytest.raises(InputError, match="3 masks for 5 frames"):
        read_video_clip(tmp_path / "clip.mp4", tmp_path / "few")
    (tmp_path / "broken.mp4").write_bytes(b"not a video")
    with pytest.raises(InputError, match="cannot read"):
        read_video_clip(tmp_path / "broken.mp4", None)


def test_laptop_renders(shared_data: Path) -> None:
    """Meta-World laptop (MIT) rendered with MuJoCo."""
    root = shared_data / "rendered" / "metaworld_laptop_hinge"
    clip = read_video_clip(root / "rgb.mp4", root / "masks")
    assert clip.frames.shape == (36, 240, 320, 3) and clip.fps == pytest.approx(12.0)
    gt = np.load(root / "gt.npz")
    assert np.array_equal(clip.masks, gt["part_labels"] > 0)
