"""Videos of a run: render a sequence, write mp4 / GIF, compose side by side, log to TensorBoard.

* mp4 goes through imageio + imageio-ffmpeg (its bundled ffmpeg, H.264, yuv420p so every player opens
  it) with ``macro_block_size=1`` so imageio does not rescale frames to multiples of 16; H.264 in
  yuv420p still needs even sizes, so an odd width or height is padded by one replicated pixel.
* GIFs are written with Pillow (frame duration in ms, looping forever).
* TensorBoard: ``add_video`` silently logs nothing without the 2020 ``moviepy``, so
  :func:`log_gif_tensorboard` writes the animated GIF bytes into an image summary itself (TensorBoard's
  image panel plays them) and also logs a static strip of frames with ``add_image``.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from sync4d.errors import InputError
from sync4d.io.atomic import atomic_write, atomic_write_bytes
from sync4d.types import Camera

if TYPE_CHECKING:
    from torch.utils.tensorboard import SummaryWriter
    from torch.utils.tensorboard.writer import FileWriter

def to_uint8(frames: Any) -> np.ndarray:
    """Images to uint8.

    Args:
        frames: (..., H, W, 3) float in [0, 1] (numpy or torch) or uint8; (..., H, W) greyscale is
            expanded to 3 channels.

    Returns:
        (..., H, W, 3) uint8.
    """
    if isinstance(frames, torch.Tensor):
        frames = frames.detach().cpu().numpy()
    arr = np.asarray(frames)
    if arr.dtype != np.uint8:
        arr = np.clip(np.nan_to_num(arr.astype(np.float32)) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if arr.ndim >= 2 and arr.shape[-1] not in (3, 4):
        arr = np.repeat(arr[..., None], 3, axis=-1)
    return arr[..., :3]


def write_mp4(path: str | Path, frames: Any, fps: float, *, quality: float = 8.0) -> Path:
    """Write an H.264 mp4 (atomically: a temporary name, then renamed).

    Args:
        path: output file.
        frames: (T, H, W, 3) float in [0, 1] or uint8, or a sequence of (H, W, 3) frames.
        fps: frame rate [1/s].
        quality: imageio-ffmpeg quality, 0 (worst) .. 10 (best).

    Returns:
        The path written.
    """
    import imageio.v2 as iio

    path = Path(path)
    video = to_uint8(frames if isinstance(frames, (np.ndarray, torch.Tensor)) else np.stack([to_uint8(f) for f in frames]))
    if video.ndim != 4 or len(video) == 0:
        raise InputError(f"write_mp4: expected (T, H, W, 3) frames, got shape {video.shape}")
    pad_h, pad_w = video.shape[1] % 2, video.shape[2] % 2
    if pad_h or pad_w:
        video = np.pad(video, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")

    def write(tmp: Path) -> None:
        writer = iio.get_writer(
            tmp, format="FFMPEG", mode="I", fps=float(fps), codec="libx264", quality=quality,
            pixelformat="yuv420p", macro_block_size=1,
        )
        try:
            for frame in video:
                writer.append_data(frame)
        finally:
            writer.close()

    return atomic_write(path, write)


def encode_gif(frames: Any, fps: float) -> bytes:
    """Animated GIF bytes of (T, H, W, 3) frames at ``fps`` [1/s], looping forever."""
    from PIL import Image

    video = to_uint8(frames)
    if video.ndim != 4 or len(video) == 0:
        raise InputError(f"encode_gif: expected (T, H, W, 3) frames, got shape {video.shape}")
    images = [Image.fromarray(f) for f in video]
    buf = io.BytesIO()
    # GIF delays are in 1/100 s; Pillow takes milliseconds and rounds.
    duration = max(int(round(1000.0 / max(fps, 1e-6))), 20)
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0,
                   optimize=False, disposal=1)
    return buf.getvalue()


def write_gif(path: str | Path, frames: Any, fps: float) -> Path:
    """Write an animated GIF atomically. Args as in :func:`encode_gif`; returns the path."""
    return atomic_write_bytes(path, encode_gif(frames, fps))


def read_video(path: str | Path) -> np.ndarray:
    """(T, H, W, 3) uint8 frames of an mp4/GIF (for checks and for reference videos)."""
    import imageio.v2 as iio

    return np.stack([to_uint8(f) for f in iio.mimread(str(path), memtest=False)])


def _resize_height(frame: np.ndarray, height: int) -> np.ndarray:
    from PIL import Image

    h, w = frame.shape[:2]
    if h == height:
        return frame
    width = max(int(round(w * height / h)), 1)
    return np.asarray(Image.fromarray(frame).resize((width, height), Image.Resampling.BILINEAR))


def _draw_label(frame: np.ndarray, text: str) -> np.ndarray:
    from PIL import Image, ImageDraw

    img = Image.fromarray(frame)
    draw = ImageDraw.Draw(img)
    x, y = 4, 3
    box = draw.textbbox((x, y), text)
    draw.rectangle((box[0] - 2, box[1] - 2, box[2] + 2, box[3] + 2), fill=(255, 255, 255))
    draw.text((x, y), text, fill=(0, 0, 0))
    return np.asarray(img)


def side_by_side(
    videos: Sequence[Any],
    *,
    labels: Sequence[str] | None = None,
    loop: bool = True,
    gap: int = 4,
    gap_color: Sequence[int] = (255, 255, 255),
) -> np.ndarray:
    """Panels side by side, frame-aligned with the last panel, each resized to its height.

    Frame t of the output shows frame t of every panel; a shorter panel is looped (or held at its last
    frame when ``loop`` is False), as the pipeline loops the reference motion.

    Args:
        videos: panels, each (T_i, H_i, W_i, 3) frames (float in [0, 1] or uint8); the last one sets T and H.
        labels: one caption per panel drawn in its top-left corner, or None.
        loop: loop shorter panels, else hold their last frame.
        gap: pixels between panels.
        gap_color: RGB of the gaps.

    Returns:
        (T, H, sum of resized widths + gaps, 3) uint8.
    """
    panels = [to_uint8(v) for v in videos]
    if not panels or any(p.ndim != 4 or len(p) == 0 for p in panels):
        raise InputError(f"side_by_side: expected (T, H, W, 3) frames, got {[p.shape for p in panels]}")
    if labels is not None and len(labels) != len(panels):
        raise InputError(f"side_by_side: {len(labels)} labels for {len(panels)} panels")
    num, height = len(panels[-1]), panels[-1].shape[1]
    sep = np.empty((height, gap, 3), dtype=np.uint8)
    sep[:] = np.asarray(gap_color, dtype=np.uint8)
    out = []
    for t in range(num):
        row = []
        for k, panel in enumerate(panels):
            frame = _resize_height(panel[t % len(panel) if loop else min(t, len(panel) - 1)], height)
            row += [_draw_label(frame, labels[k]) if labels is not None else frame, sep]
        out.append(np.concatenate(row[:-1], axis=1))
    return np.stack(out)


def compare(
    reference: Any,
    target: Any,
    *,
    loop_reference: bool = True,
    gap: int = 4,
    gap_color: Sequence[int] = (255, 255, 255),
    labels: tuple[str, str] | None = None,
) -> np.ndarray:
    """Two panels: reference (T_r, H_r, W_r, 3) left, target (T, H, W, 3) right; see :func:`side_by_side`.

    Returns:
        (T, H, W_r' + gap + W, 3) uint8.
    """
    return side_by_side([reference, target], labels=labels, loop=loop_reference, gap=gap, gap_color=gap_color)


def frame_strip(frames: Any, *, max_frames: int = 8, columns: int | None = None) -> np.ndarray:
    """A grid of up to ``max_frames`` evenly spaced frames, as one (H', W', 3) uint8 image."""
    video = to_uint8(frames)
    idx = np.unique(np.linspace(0, len(video) - 1, min(max_frames, len(video))).round().astype(int))
    picks = video[idx]
    cols = columns or len(picks)
    rows = -(-len(picks) // cols)
    h, w = picks.shape[1:3]
    grid = np.full((rows * h, cols * w, 3), 255, dtype=np.uint8)
    for k, frame in enumerate(picks):
        r, c = divmod(k, cols)
        grid[r * h : (r + 1) * h, c * w : (c + 1) * w] = frame
    return grid


def log_gif_tensorboard(
    writer: SummaryWriter,
    tag: str,
    frames: Any,
    step: int,
    *,
    fps: float,
    gif_path: str | Path | None = None,
    max_frames: int = 8,
) -> None:
    """Log a clip to TensorBoard without moviepy: the animated GIF as an image summary, plus a strip.

    Args:
        writer: a ``torch.utils.tensorboard.SummaryWriter`` (the GIF goes through its public ``file_writer``,
            as ``add_hparams`` does: ``add_image`` would encode a PNG).
        tag: summary tag; the GIF is logged under ``tag`` and the frame strip under ``tag + "/strip"``.
        frames: (T, H, W, 3) frames.
        step: global step.
        fps: frame rate of the GIF [1/s].
        gif_path: also write the GIF file here (e.g. the run folder), if given.
        max_frames: frames in the strip.
    """
    video = to_uint8(frames)
    gif = encode_gif(video, fps)
    if gif_path is not None:
        atomic_write_bytes(gif_path, gif)
    from tensorboard.compat.proto.summary_pb2 import Summary

    image = Summary.Image(height=video.shape[1], width=video.shape[2], colorspace=3, encoded_image_string=gif)
    file_writer: FileWriter | None = writer.file_writer
    if file_writer is None:
        raise ValueError(f"log_gif_tensorboard({tag}): the SummaryWriter is closed")
    file_writer.add_summary(Summary(value=[Summary.Value(tag=tag, image=image)]), step)
    writer.add_image(f"{tag}/strip", frame_strip(video, max_frames=max_frames), step, dataformats="HWC")


def render_sequence(
    renderer: Any,
    means: Any,
    covariances: Any,
    colors: Any,
    opacities: Any,
    camera: Camera | Sequence[Camera],
    *,
    progress: bool = True,
    desc: str = "render",
) -> np.ndarray:
    """Render a Gaussian sequence to uint8 frames, with a progress bar.

    Args:
        renderer: a built ``render`` component (``render(means, covs, colors, opacities, camera)``).
        means: (T, N, 3) positions per frame [m].
        covariances: (N, 3, 3) fixed or (T, N, 3, 3) per-frame covariances [m^2].
        colors: (N, 3) RGB or (N, K, 3) SH coefficients.
        opacities: (N,) in [0, 1].
        camera: one camera for all frames, or one per frame (e.g. :func:`~sync4d.render.camera.orbit`).
        progress: show a tqdm bar.
        desc: label of the bar.

    Returns:
        (T, H, W, 3) uint8 frames.
    """
    from tqdm.auto import tqdm

    means_a = np.asarray(means)
    covs_a = np.asarray(covariances)
    num = means_a.shape[0]
    cams = [camera] * num if isinstance(camera, Camera) else list(camera)
    if len(cams) != num:
        raise InputError(f"render_sequence: {len(cams)} cameras for {num} frames")
    frames = []
    for t in tqdm(range(num), desc=desc, disable=not progress, leave=False):
        covs_t = covs_a[t] if covs_a.ndim == 4 else covs_a
        frames.append(to_uint8(renderer.render(means_a[t], covs_t, colors, opacities, cams[t])))
    return np.stack(frames)
