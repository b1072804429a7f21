"""``features=diff3f``: multi-view 2D features back-projected to vertices (Diff3F, Dutt et al. 2024).

Pipeline: render the shape from K views with our z-buffer splatting renderer (:mod:`._raster`), run a
2D backbone on every view, give each vertex the mean feature of the pixels it is visible at over all
views, and fill vertices that no view sees from their mesh (or k-nearest-neighbour) neighbours.

Backbones (``backbone``):
    * ``shading_fourier``: a deterministic, download-free stand-in. Multi-scale Gaussian derivatives of
      the rendered normal, depth, silhouette and shading images, passed through fixed random Fourier
      features. It describes local surface shape as seen from each view; it carries no semantics (it
      cannot tell a head from a tail), so it exercises the machinery, it does not reproduce Diff3F.
    * ``dinov2`` (ViT-B/14 patch tokens, 768 dims) and ``stable_diffusion`` (UNet decoder features,
      1280 dims), loaded only from ``weights_path`` on this machine. Diff3F's public code concatenates
      the two (2048 dims per vertex, not the 1024 its paper states); use ``features=concat`` with one
      part per backbone to do the same. Nothing is ever downloaded at run time.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import scipy.sparse as sp
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

from sync4d.errors import ConfigError
from sync4d.features._common import check_shape, neighbour_graph
from sync4d.features._raster import (
    look_at_rotation,
    point_spacing,
    render_view,
    surface_samples,
    view_directions,
)
from sync4d.registry import register

log = logging.getLogger(__name__)

BACKBONES: tuple[str, ...] = ("shading_fourier", "dinov2", "stable_diffusion")
WEIGHTS_HELP = (
    "Diff3F's backbones are pretrained networks that this project never downloads at run time. "
    "Download them once on a machine with network access and point features.weights_path at the local "
    "copy: for dinov2 a Hugging Face `transformers` folder of facebook/dinov2-base (config.json + "
    "model.safetensors; `pip install transformers`), for stable_diffusion a `diffusers` folder of a "
    "Stable Diffusion 1.5/2.1 pipeline (unet/, vae/, text_encoder/, tokenizer/; `pip install diffusers "
    "transformers`). Diff3F's public code concatenates SD (1280) + DINOv2 (768) = 2048 dims per vertex: "
    "use features=concat with one diff3f part per backbone. Without weights use backbone=shading_fourier "
    "(a no-download stand-in) or features=geometric."
)


class Backbone(Protocol):
    """A 2D feature network: (K, 6, H, W) view images -> (K, D, h, w) feature maps.

    Input channels: normal x, y, z (camera frame), depth in [0, 1] (1 on the background), silhouette,
    shading in [0, 1].
    """

    def __call__(self, images: torch.Tensor) -> torch.Tensor: ...


def gaussian_kernel1d(sigma: float) -> torch.Tensor:
    """(2r+1,) normalised 1D Gaussian with r = ceil(3 sigma)."""
    r = max(1, int(np.ceil(3 * sigma)))
    x = torch.arange(-r, r + 1, dtype=torch.float32)
    k = torch.exp(-(x**2) / (2 * sigma**2))
    return k / k.sum()


class ShadingFourierBackbone:
    """Multi-scale Gaussian-derivative filter bank + random Fourier features (no weights).

    For each scale sigma the images are smoothed (G), and differentiated (sigma dG/dx, sigma dG/dy:
    scale-normalised so every scale has comparable magnitude); the stacked responses z (6 x 3 x S
    channels) are mapped per pixel to ``sqrt(2/D) cos(W z / h + b)`` with a fixed seeded W, b.
    """

    def __init__(self, *, scales: tuple[float, ...], dims: int, bandwidth: float, seed: int) -> None:
        self.scales = scales
        in_ch = 6 * 3 * len(scales)
        gen = torch.Generator().manual_seed(seed)
        self.w = torch.randn(dims, in_ch, generator=gen) / bandwidth
        self.b = torch.rand(dims, generator=gen) * 2 * np.pi
        self.dims = dims

    def filter_bank(self, images: torch.Tensor) -> torch.Tensor:
        """(K, C, H, W) -> (K, 3 C S, H, W) smoothed and scale-normalised derivative responses."""
        k, c, h, w = images.shape
        out = []
        for sigma in self.scales:
            g = gaussian_kernel1d(sigma)
            r = len(g) // 2
            x = images.reshape(k * c, 1, h, w)
            x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), g.view(1, 1, 1, -1))
            x = F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), g.view(1, 1, -1, 1))
            dx = 0.5 * (F.pad(x, (0, 2, 0, 0), mode="replicate") - F.pad(x, (2, 0, 0, 0), mode="replicate"))[..., 1:-1]
            dy = 0.5 * (F.pad(x, (0, 0, 0, 2), mode="replicate") - F.pad(x, (0, 0, 2, 0), mode="replicate"))[..., 1:-1, :]
            out += [x.reshape(k, c, h, w), sigma * dx.reshape(k, c, h, w), sigma * dy.reshape(k, c, h, w)]
        return torch.cat(out, dim=1)

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        z = self.filter_bank(images.float())  # (K, Z, H, W)
        proj = torch.einsum("dz,kzhw->kdhw", self.w, z) + self.b.view(1, -1, 1, 1)
        return np.sqrt(2.0 / self.dims) * torch.cos(proj)


def _check_weights(path: str, backbone: str) -> Path:
    if not path:
        raise ConfigError(f"features.weights_path is empty but backbone={backbone} needs local weights. {WEIGHTS_HELP}")
    folder = Path(os.path.expanduser(path))
    if not folder.exists():
        raise ConfigError(f"features.weights_path={path}: not found on this machine (backbone={backbone}). {WEIGHTS_HELP}")
    return folder


class Dinov2Backbone:
    """DINOv2 patch tokens from a local ``transformers`` folder, upsampled to the patch grid."""

    def __init__(self, weights_path: str, *, device: str) -> None:
        folder = _check_weights(weights_path, "dinov2")
        try:
            from transformers import AutoModel
        except ImportError:
            raise ConfigError(f"backbone=dinov2 needs the `transformers` package, which is not installed. {WEIGHTS_HELP}") from None
        os.environ["HF_HUB_OFFLINE"] = "1"  # belt and braces: never reach the network
        self.model = AutoModel.from_pretrained(str(folder), local_files_only=True).to(device).eval()
        self.device = device
        self.patch = int(self.model.config.patch_size)  # 14 for DINOv2

    @torch.no_grad()
    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        k, _, h, w = images.shape
        side = max(self.patch, (max(h, w) * 4 // self.patch) * self.patch)  # ~4x upsampling like Diff3F's 224+
        rgb = images[:, 5:6].expand(k, 3, h, w)  # the shaded render, grey
        rgb = F.interpolate(rgb, size=(side, side), mode="bilinear", align_corners=False)
        mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
        std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
        out = self.model(pixel_values=((rgb - mean) / std).to(self.device)).last_hidden_state
        grid = side // self.patch
        tokens = out[:, -grid * grid :, :]  # drop CLS (and registers, if any)
        return tokens.transpose(1, 2).reshape(k, -1, grid, grid).float().cpu()


class StableDiffusionBackbone:
    """Stable Diffusion UNet decoder features of the noised render (Diff3F / DIFT style), local weights."""

    def __init__(self, weights_path: str, *, device: str, timestep: int = 261, up_block: int = 1) -> None:
        folder = _check_weights(weights_path, "stable_diffusion")
        try:
            from diffusers import StableDiffusionPipeline
        except ImportError:
            raise ConfigError(f"backbone=stable_diffusion needs `diffusers` and `transformers`, not installed. {WEIGHTS_HELP}") from None
        os.environ["HF_HUB_OFFLINE"] = "1"
        pipe = StableDiffusionPipeline.from_pretrained(str(folder), local_files_only=True, safety_checker=None)
        self.pipe = pipe.to(device)
        self.device = device
        self.timestep = timestep
        self._captured: list[torch.Tensor] = []
        self.pipe.unet.up_blocks[up_block].register_forward_hook(lambda _m, _i, out: self._captured.append(out))
        tokens = self.pipe.tokenizer([""], padding="max_length", max_length=self.pipe.tokenizer.model_max_length, return_tensors="pt")
        with torch.no_grad():
            self.empty = self.pipe.text_encoder(tokens.input_ids.to(device))[0]

    @torch.no_grad()
    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        k, _, h, w = images.shape
        rgb = images[:, 5:6].expand(k, 3, h, w)
        rgb = F.interpolate(rgb, size=(512, 512), mode="bilinear", align_corners=False) * 2 - 1
        latents = self.pipe.vae.encode(rgb.to(self.device)).latent_dist.mean * self.pipe.vae.config.scaling_factor
        t = torch.tensor([self.timestep], device=self.device)
        gen = torch.Generator(device=self.device).manual_seed(0)
        noisy = self.pipe.scheduler.add_noise(latents, torch.randn(latents.shape, generator=gen, device=self.device), t)
        self._captured.clear()
        self.pipe.unet(noisy, t, encoder_hidden_states=self.empty.expand(k, -1, -1))
        return self._captured[-1].float().cpu()


def sample_feature_maps(feature_map: torch.Tensor, pixel: np.ndarray, resolution: int) -> np.ndarray:
    """Features at vertex pixels.

    Args:
        feature_map: (D, h, w) features of one view.
        pixel: (V, 2) (column, row) pixel coordinates in the render of size ``resolution``.
        resolution: render size [px].

    Returns:
        (V, D): the exact pixel's feature when the map has the render's resolution, else a bilinear
        sample of the coarser map.
    """
    d, h, w = feature_map.shape
    if h == resolution and w == resolution:
        iu = np.clip(np.floor(pixel[:, 0]).astype(np.int64), 0, w - 1)
        iv = np.clip(np.floor(pixel[:, 1]).astype(np.int64), 0, h - 1)
        return feature_map[:, iv, iu].T.numpy().astype(np.float64)
    grid = torch.from_numpy(pixel / resolution * 2 - 1).float().view(1, 1, -1, 2)
    out = F.grid_sample(feature_map[None].float(), grid, mode="bilinear", align_corners=False)
    return out[0, :, 0].T.numpy().astype(np.float64)


def fill_unseen(
    features: np.ndarray, seen: np.ndarray, adjacency: sp.csr_matrix, points: np.ndarray, *, max_iters: int = 200
) -> np.ndarray:
    """Give vertices that no view saw the features of their neighbours.

    Fronts grow from the seen vertices over the graph: each round, every unseen vertex with at least one
    filled neighbour takes the mean of its filled neighbours. Vertices never reached (components with no
    seen vertex) take the feature of the nearest seen vertex in space.

    Args:
        features: (V, D) back-projected features; rows of unseen vertices are ignored.
        seen: (V,) bool.
        adjacency: (V, V) symmetric 0/1 graph (mesh edges or kNN).
        points: (V, 3) positions, for the nearest-seen fallback.

    Returns:
        (V, D) features with every row filled; seen rows unchanged.
    """
    if not seen.any():
        raise ConfigError("features.diff3f: no vertex is visible in any view; check the views (n_views) and resolution")
    out = np.where(seen[:, None], features, 0.0)
    known = seen.copy()
    for _ in range(max_iters):
        if known.all():
            break
        counts = adjacency @ known.astype(np.float64)
        frontier = (~known) & (counts > 0)
        if not frontier.any():
            break
        sums = adjacency @ (out * known[:, None])
        out[frontier] = sums[frontier] / counts[frontier, None]
        known = known | frontier
    if not known.all():
        _, nearest = cKDTree(points[known]).query(points[~known])
        out[~known] = out[known][nearest]
    return out


@register("features", "diff3f")
class Diff3FFeatures:
    """Render K views, run a 2D backbone, average the features of visible pixels per vertex, fill the rest."""

    @dataclass
    class Config:
        backbone: str = "shading_fourier"   # shading_fourier | dinov2 | stable_diffusion
        weights_path: str = ""              # local folder of the pretrained backbone (never downloaded)
        n_views: int = 12                   # views around the shape, alternating +/- elevation
        elevation_deg: float = 25.0         # camera elevation of the view rings [deg]
        resolution: int = 128               # render size H = W [px]
        samples_per_pixel: float = 2.0      # surface samples per image pixel (meshes)
        splat_radius_px: float = 1.0        # footprint of a surface sample [px]
        depth_tolerance_px: float = 3.0     # visibility test slack, in pixel sizes
        feature_dims: int = 64              # shading_fourier output channels D
        scales: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0)  # shading_fourier filter scales [px]
        bandwidth: float = 2.0              # shading_fourier random-feature kernel width
        seed: int = 0                       # sampling and projection seed (shared by both shapes)

        def validate(self) -> None:
            if self.backbone not in BACKBONES:
                raise ConfigError(f"features.backbone={self.backbone!r}: use one of {', '.join(BACKBONES)}")
            if self.n_views < 1 or self.resolution < 16:
                raise ConfigError("features.n_views must be >= 1 and features.resolution >= 16")

    def __init__(self, config: Config, *, device: str = "cpu") -> None:
        self.config = config
        self.device = device
        if config.backbone == "shading_fourier":
            self.backbone: Backbone = ShadingFourierBackbone(
                scales=tuple(config.scales), dims=config.feature_dims, bandwidth=config.bandwidth, seed=config.seed
            )
        elif config.backbone == "dinov2":
            self.backbone = Dinov2Backbone(config.weights_path, device=device)
        else:
            self.backbone = StableDiffusionBackbone(config.weights_path, device=device)

    def view_rotations(self) -> np.ndarray:
        """(K, 3, 3) view rotations of the configured cameras."""
        dirs = view_directions(self.config.n_views, self.config.elevation_deg)
        return np.stack([look_at_rotation(d) for d in dirs])

    def render_views(self, points: np.ndarray, faces: np.ndarray | None) -> tuple[list, torch.Tensor]:
        """Render every view; returns the renders and the (K, 6, H, W) backbone input images."""
        config = self.config
        centre = 0.5 * (points.max(axis=0) + points.min(axis=0))
        pts = points - centre
        extent = 1.05 * float(np.linalg.norm(pts, axis=1).max())  # bounding sphere: fits every view
        pix = 2 * extent / config.resolution
        n_samples = int(config.samples_per_pixel * config.resolution**2)
        samples, normals = surface_samples(pts, faces, n_samples, seed=config.seed)
        radius = config.splat_radius_px
        if faces is None:  # a point cloud must cover its gaps itself
            radius = max(radius, 0.75 * point_spacing(pts) / pix)
        renders, images = [], []
        for rot in self.view_rotations():
            view = render_view(
                pts, samples, normals, rot, resolution=config.resolution, extent=extent,
                splat_radius_px=radius, depth_tolerance_px=config.depth_tolerance_px,
            )
            depth = np.where(view.mask, (view.depth + extent) / (2 * extent), 1.0)
            img = np.concatenate(
                [view.normal, depth[..., None], view.mask[..., None].astype(np.float64), view.shading[..., None]], axis=2
            )
            renders.append(view)
            images.append(torch.from_numpy(img).permute(2, 0, 1).float())
        return renders, torch.stack(images)

    def backproject(self, renders: list, feature_maps: torch.Tensor, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
        """Mean feature over the views where each vertex is visible.

        Returns:
            features (V, D) (zeros where unseen), seen (V,) bool.
        """
        total = np.zeros((n_vertices, feature_maps.shape[1]))
        count = np.zeros(n_vertices)
        for view, fmap in zip(renders, feature_maps):
            vis = view.vertex_visible
            total[vis] += sample_feature_maps(fmap, view.vertex_pixel[vis], self.config.resolution)
            count[vis] += 1
        seen = count > 0
        total[seen] /= count[seen, None]
        return total, seen

    def extract(self, points: np.ndarray, faces: np.ndarray | None) -> np.ndarray:
        """Per-vertex multi-view features.

        Args:
            points: (V, 3) vertices in the common aligned frame (views are fixed in that frame, so both
                shapes are seen from the same directions).
            faces: (F, 3) triangles or None.

        Returns:
            (V, D) float32.
        """
        pts, fcs = check_shape(points, faces)
        renders, images = self.render_views(pts, fcs)
        with torch.no_grad():
            fmaps = self.backbone(images)
        feats, seen = self.backproject(renders, fmaps, len(pts))
        log.debug("diff3f: %d/%d vertices seen in %d views", int(seen.sum()), len(pts), len(renders))
        filled = fill_unseen(feats, seen, neighbour_graph(pts, fcs), pts)
        return filled.astype(np.float32)
