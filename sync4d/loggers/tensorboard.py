"""Run loggers: TensorBoard event files, or nothing."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sync4d.registry import register

log = logging.getLogger(__name__)


@register("logger", "tensorboard")
class TensorBoardLogger:
    """Scalars, images and hparams to ``<run>/tb`` (open with ``tensorboard --logdir outputs``)."""

    @dataclass
    class Config:
        subdir: str = "tb"       # event folder inside the run folder
        flush_secs: int = 10

    def __init__(self, config: Config, *, run_dir: Path) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.dir = Path(run_dir) / config.subdir
        self.writer = SummaryWriter(log_dir=str(self.dir), flush_secs=config.flush_secs)

    def scalar(self, tag: str, value: float, step: int) -> None:
        self.writer.add_scalar(tag, float(value), step)

    def image(self, tag: str, image: np.ndarray, step: int = 0) -> None:
        """Log an (H, W, 3) uint8 or float [0, 1] image."""
        img = np.asarray(image)
        if img.dtype != np.uint8:
            img = (np.clip(img, 0, 1) * 255).astype(np.uint8)
        self.writer.add_image(tag, img, step, dataformats="HWC")

    def video(self, tag: str, frames: np.ndarray, fps: float, step: int = 0, *, gif_path: Path | None = None) -> None:
        """Log (T, H, W, 3) frames as an animated GIF (TensorBoard's image panel plays it) and a strip of frames."""
        from sync4d.render.video import log_gif_tensorboard

        log_gif_tensorboard(self.writer, tag, frames, step, fps=fps, gif_path=gif_path)

    def hparams(self, params: dict[str, Any], metrics: dict[str, float]) -> None:
        clean = {k: (v if isinstance(v, (int, float, str, bool)) else str(v)) for k, v in params.items()}
        finite = {f"hparam/{k}": float(v) for k, v in metrics.items() if isinstance(v, (int, float)) and np.isfinite(v)}
        # run_name="." keeps the hparams in the run's own event folder so TensorBoard pairs them.
        self.writer.add_hparams(clean, finite, run_name=".")

    def close(self) -> None:
        self.writer.flush()
        self.writer.close()


@register("logger", "none")
class NullLogger:
    """Logs nothing (e.g. for benchmarks); the run's files are still written."""

    @dataclass
    class Config:
        pass

    def __init__(self, config: Config, *, run_dir: Path) -> None:
        pass

    def scalar(self, tag: str, value: float, step: int) -> None:
        pass

    def image(self, tag: str, image: np.ndarray, step: int = 0) -> None:
        pass

    def hparams(self, params: dict[str, Any], metrics: dict[str, float]) -> None:
        pass

    def close(self) -> None:
        pass
