"""Reading reference videos and their foreground masks into a :class:`~sync4d.types.VideoClip`.

A video is an .mp4 (or any format imageio-ffmpeg reads) or a folder of images (png/jpg, sorted by
name); masks are a folder of PNGs (non-zero = object) or a video (grey > 127 = object).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sync4d.errors import DataMissingError, InputError
from sync4d.types import VideoClip

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".gif", ".m4v")


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def read_frames(path: str | Path) -> tuple[np.ndarray, float | None]:
    """Read all frames of a video file or an image folder.

    Args:
        path: video file or folder of images.

    Returns:
        (frames (T, H, W, C) uint8 with C = 3 for colour input or 1 for grey, fps [1/s] or None if the
        source does not say).

    Raises:
        DataMissingError: the path does not exist.
        InputError: no frames, frames of different sizes, or an unreadable file.
    """
    import imageio.v2 as imageio

    path = Path(path)
    if not path.exists():
        raise DataMissingError(f"video not found: {path}")
    fps: float | None = None
    frames: list[np.ndarray] = []
    if path.is_dir():
        files = _image_files(path)
        if not files:
            raise InputError(f"{path}: no images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
        frames = [np.asarray(imageio.imread(f)) for f in files]
    else:
        try:
            reader = imageio.get_reader(str(path))
            meta = reader.get_meta_data()
            fps = float(meta["fps"]) if meta.get("fps") else None
            # imageio's stubs type a v2 reader as an array; it is an iterator of frames.
            frames = [np.asarray(f) for f in reader]  # type: ignore[attr-defined]
            reader.close()
        except (OSError, ValueError, RuntimeError) as err:
            raise InputError(f"{path}: cannot read the video ({type(err).__name__}: {err})") from None
    if not frames:
        raise InputError(f"{path}: the video has no frames")
    shapes = {f.shape[:2] for f in frames}
    if len(shapes) != 1:
        raise InputError(f"{path}: frames have different sizes {sorted(shapes)}")
    arr = np.stack([f if f.ndim == 3 else f[..., None] for f in frames])
    if arr.dtype != np.uint8:
        # 16-bit PNGs and float images are scaled to 8 bits.
        top = 65535.0 if arr.dtype == np.uint16 else max(float(arr.max()), 1.0)
        arr = np.clip(arr.astype(np.float64) / top * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return arr, fps


def read_masks(path: str | Path) -> np.ndarray:
    """Read foreground masks: (T, H, W) bool, True where the first channel exceeds 127.

    Raises:
        DataMissingError: the path does not exist.
        InputError: no masks, or sizes differ.
    """
    frames, _ = read_frames(path)
    return frames[..., 0] > 127


def read_video_clip(
    video_path: str | Path,
    masks_path: str | Path | None,
    fps: float | None = None,
    *,
    intrinsics: np.ndarray | None = None,
    max_frames: int | None = None,
    stride: int = 1,
) -> VideoClip:
    """Read a video and its masks into a validated :class:`VideoClip`.

    Args:
        video_path: video file or folder of images.
        masks_path: folder of mask PNGs or a mask video; None gives all-False masks (the caller then
            estimates them, e.g. by a background model).
        fps: frames per second [1/s]; overrides the file's value; required for image folders.
        intrinsics: (3, 3) pinhole K in pixels, if known.
        max_frames: keep at most this many frames (after ``stride``).
        stride: keep every ``stride``-th frame (fps divided accordingly).

    Raises:
        DataMissingError: a path does not exist.
        InputError: no frames; mask count or size differs from the frames; every mask is empty.
    """
    frames, file_fps = read_frames(video_path)
    if frames.shape[-1] == 1:
        frames = np.repeat(frames, 3, axis=-1)
    elif frames.shape[-1] == 4:
        frames = frames[..., :3]
    rate = fps if fps is not None else file_fps
    if rate is None:
        raise InputError(f"{video_path}: the frame rate is unknown (image folder); pass fps")
    masks: np.ndarray
    if masks_path is None:
        masks = np.zeros(frames.shape[:3], dtype=bool)
    else:
        masks = read_masks(masks_path)
        if masks.shape[1:] != frames.shape[1:3]:
            raise InputError(
                f"{masks_path}: masks are {masks.shape[2]}x{masks.shape[1]} but the video {video_path} is "
                f"{frames.shape[2]}x{frames.shape[1]}; masks must match the frames' size"
            )
        if len(masks) != len(frames):
            raise InputError(f"{masks_path}: {len(masks)} masks for {len(frames)} frames of {video_path}")
        if not masks.any():
            raise InputError(f"{masks_path}: every mask is empty (no pixel > 127); check the mask folder")
    stride = max(1, int(stride))
    frames, masks = frames[::stride], masks[::stride]
    if max_frames is not None:
        frames, masks = frames[:max_frames], masks[:max_frames]
    return VideoClip(
        frames=np.ascontiguousarray(frames),
        masks=np.ascontiguousarray(masks),
        fps=float(rate) / stride,
        intrinsics=None if intrinsics is None else np.asarray(intrinsics, dtype=np.float64),
        source=str(video_path),
    ).validate()


def write_video(path: str | Path, frames: np.ndarray, fps: float) -> None:
    """Write (T, H, W, 3) uint8 frames as a video (any size: ``macro_block_size=1``)."""
    import imageio.v2 as imageio

    with imageio.get_writer(str(path), fps=fps, macro_block_size=1) as writer:
        for f in frames:
            # imageio's stubs give the v2 writer's base class, which lacks append_data.
            writer.append_data(np.asarray(f, dtype=np.uint8))  # type: ignore[attr-defined]
