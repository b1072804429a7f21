"""``render=gsplat``: the same renderer interface through the CUDA rasteriser of the ``gsplat`` package.

gsplat only renders on CUDA and needs a CUDA toolchain to build, so it is not in ``requirements.txt``;
install it on a CUDA machine with ``pip install gsplat``. Selecting ``render=gsplat`` where CUDA or gsplat
is missing stops at start-up with a :class:`~sync4d.errors.ConfigError` suggesting ``render=splat_torch``.

Colours are evaluated here with the same SH code as ``render=splat_torch`` and the background is
composited here too, so both renderers share every convention (pixel centres at half-integers, 0.3 px^2
dilation, 0.99 alpha cap, 1/255 alpha threshold); they differ only in footprint details (gsplat's
16x16 tiles and eigenvalue radius, its early stop at transmittance 1e-4), i.e. by a few 8-bit levels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from sync4d.errors import ConfigError
from sync4d.registry import register
from sync4d.render.splat_torch import SplatTorch, check_inputs
from sync4d.types import Camera


def gsplat_unavailable_reason() -> str | None:
    """Why ``render=gsplat`` cannot run here (None when it can)."""
    if not torch.cuda.is_available():
        return "render=gsplat needs CUDA, which this machine does not have; use render=splat_torch"
    try:
        import gsplat  # noqa: F401
    except ImportError as err:
        return f"render=gsplat needs the gsplat package (pip install gsplat; {err}); or use render=splat_torch"
    return None


@register("render", "gsplat")
class GsplatRenderer(SplatTorch):
    """gsplat's CUDA rasteriser behind the :class:`SplatTorch` interface (``render``, ``render_full``)."""

    @dataclass
    class Config(SplatTorch.Config):
        tile_size: int = 16  # gsplat's CUDA tile side [px]

    def __init__(self, config: Config | None = None, *, device: str = "cuda") -> None:
        reason = gsplat_unavailable_reason()
        if reason is not None:
            raise ConfigError(reason)
        self.config = config if config is not None else self.Config()
        self.config.validate()
        # gsplat runs on CUDA whatever the run's device; results go back to the inputs' device.
        self.device = torch.device(device if str(device).startswith("cuda") else "cuda:0")

    def _render(
        self, means: Any, covariances: Any, colors: Any, opacities: Any, camera: Camera, background: Any | None
    ) -> dict[str, torch.Tensor]:
        from gsplat import rasterization

        config = self.config
        out_device = means.device if isinstance(means, torch.Tensor) else torch.device("cpu")
        dtype = torch.float32  # gsplat's kernels are float32 only
        dev = self.device
        means_t = self._tensor(means, dtype, dev)
        covs_t = self._tensor(covariances, dtype, dev)
        cols_t = self._tensor(colors, dtype, dev)
        opac_t = self._tensor(opacities, dtype, dev).reshape(-1)
        check_inputs(means_t, covs_t, cols_t, opac_t)
        if cols_t.ndim == 3:
            all_idx = torch.arange(means_t.shape[0], device=dev)
            cols_t = self._colors(cols_t, means_t, all_idx, camera)
        channels = cols_t.shape[1]
        bg = background if background is not None else (config.background if channels == 3 else [0.0] * channels)
        bg_t = self._tensor(bg, dtype, dev).reshape(-1)
        viewmat = torch.as_tensor(np.asarray(camera.world_to_cam), dtype=dtype, device=dev)[None]
        K = torch.as_tensor(np.asarray(camera.K), dtype=dtype, device=dev)[None]
        img, alpha, _meta = rasterization(
            means_t, None, None, opac_t, cols_t, viewmat, K, int(camera.width), int(camera.height),
            near_plane=config.near, far_plane=config.far, eps2d=config.eps2d, tile_size=config.tile_size,
            render_mode="RGB+ED", covars=covs_t, packed=False,
        )
        img, alpha = img[0], alpha[0, ..., 0]
        rgb = img[..., :channels] + (1.0 - alpha)[..., None] * bg_t
        depth = torch.where(alpha > 1e-10, img[..., channels], torch.zeros_like(alpha))
        return {k: v.to(out_device) for k, v in {"rgb": rgb, "alpha": alpha, "depth": depth}.items()}
