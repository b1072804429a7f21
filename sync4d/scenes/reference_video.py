"""Render an articulated reference as a casual video (frames, masks, camera), for ``recon=video``.

The paper starts from a video of the reference; the project's default scene is procedural, so it is
filmed here with the project's own splatting renderer: the rest surface as Gaussians, posed every frame
by the reference's own skinning, seen by one static camera. The surface gets a procedural texture
fixed to the material (a 3D checker in rest coordinates), because optical flow needs texture and a real
object has some (keys, bezels, logos). Masks are the rendered opacity above one half.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from sync4d.errors import ConfigError
from sync4d.geometry import rgb_to_sh_dc
from sync4d.types import Camera, Reference, TargetGaussians, VideoClip


@dataclass(frozen=True)
class FilmSettings:
    """How to film a reference.

    Attributes:
        width, height: image size [px].
        gaussians: surface Gaussians sampled on the rest mesh.
        texture_cell: edge of the checker texture's cells [m] (0 = untextured).
        texture_contrast: checker brightness swing, fraction of the base colour.
        direction: from the object's centre towards the camera (world axes).
        up: world up.
        fov_deg: vertical field of view [deg].
        margin: the motion's bounding sphere fills 1/margin of the view.
    """

    width: int = 160
    height: int = 120
    gaussians: int = 6000
    texture_cell: float = 0.02
    texture_contrast: float = 0.35
    direction: tuple[float, float, float] = (0.9, 1.1, 1.6)
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_deg: float = 40.0
    margin: float = 1.15

    def validate(self) -> FilmSettings:
        if self.width < 16 or self.height < 16:
            raise ConfigError(f"reference.video_size={self.width}x{self.height}: needs at least 16x16 px")
        if self.gaussians < 100:
            raise ConfigError(f"reference.video_gaussians={self.gaussians}: needs at least 100")
        if self.texture_cell < 0 or not 0.0 <= self.texture_contrast < 1.0:
            raise ConfigError("reference.video_texture_cell must be >= 0 and video_texture_contrast in [0, 1)")
        return self


def checker(points: np.ndarray, cell: float) -> np.ndarray:
    """(N,) +1 / -1 of a 3D checkerboard with cells of edge ``cell`` [m] at ``points`` (N, 3)."""
    index = np.floor(np.asarray(points, dtype=np.float64) / cell).astype(np.int64)
    return np.where(index.sum(axis=1) % 2 == 0, 1.0, -1.0)


def textured(gaussians: TargetGaussians, cell: float, contrast: float) -> TargetGaussians:
    """The Gaussians with their colours scaled by (1 +- contrast) on a rest-frame checker."""
    if cell <= 0 or contrast <= 0:
        return gaussians
    colours = np.clip(gaussians.colors() * (1.0 + contrast * checker(gaussians.means, cell))[:, None], 0.0, 1.0)
    sh = rgb_to_sh_dc(colours).astype(np.float32)
    return TargetGaussians(
        means=gaussians.means, quats=gaussians.quats, log_scales=gaussians.log_scales,
        opacity_logits=gaussians.opacity_logits, sh=sh, name=gaussians.name,
    ).validate()


def film_reference(
    reference: Reference, renderer: object, settings: FilmSettings, *, with_labels: bool = False
) -> tuple[VideoClip, Camera] | tuple[VideoClip, Camera, np.ndarray]:
    """Render every frame of ``reference`` from one static camera.

    Args:
        reference: the articulated reference (rest mesh with faces, skinning, per-frame transforms).
        renderer: a built ``render`` component with ``render_full(means, covs, colours, opacities, camera)``.
        settings: image size, texture and framing.

        with_labels: also render the ground-truth part of every pixel.

    Returns:
        The clip (frames (T, H, W, 3) uint8, masks (T, H, W) bool, intrinsics, static camera), its
        camera, and with ``with_labels`` the (T, H, W) uint8 part labels: 0 background, b + 1 where
        bone b (the argmax skinning of the nearest rest vertex) is in front.
    """
    from sync4d.render.camera import frame_object
    from sync4d.render.reference import reference_gaussians

    settings.validate()
    if reference.rest_faces is None or not len(reference.rest_faces):
        raise ConfigError("reference video: the reference has no surface mesh to film")
    rest, means, covs = reference_gaussians(reference, reference.num_frames, count=settings.gaussians)
    rest = textured(rest, settings.texture_cell, settings.texture_contrast)
    camera = frame_object(
        means.reshape(-1, 3), direction=settings.direction, up=settings.up, fov_deg=settings.fov_deg,
        width=settings.width, height=settings.height, margin=settings.margin,
    )
    frames, masks, labels = [], [], []
    colours = np.clip(rest.colors(), 0.0, 1.0)
    onehot = None
    if with_labels:
        from scipy.spatial import cKDTree

        part = reference.part_labels()[cKDTree(reference.rest_vertices).query(rest.means)[1]]
        onehot = np.eye(reference.num_bones, dtype=np.float32)[part]
        if reference.num_bones == 3:  # three channels would be read as RGB (and composited on the background)
            onehot = np.concatenate([onehot, np.zeros((len(onehot), 1), np.float32)], axis=1)
    for t in range(reference.num_frames):
        out = renderer.render_full(means[t], covs[t], colours, rest.opacities, camera)  # type: ignore[attr-defined]
        rgb, alpha = (_numpy(out[k]) for k in ("rgb", "alpha"))
        frames.append(np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8))
        mask = alpha.reshape(settings.height, settings.width) > 0.5
        masks.append(mask)
        if onehot is not None:
            weights = _numpy(renderer.render_full(means[t], covs[t], onehot, rest.opacities, camera)["rgb"])  # type: ignore[attr-defined]
            labels.append(np.where(mask, np.argmax(weights[..., : reference.num_bones], axis=-1) + 1, 0).astype(np.uint8))
    clip = VideoClip(
        frames=np.stack(frames), masks=np.stack(masks), fps=reference.fps, intrinsics=camera.K.copy(),
        extrinsics=None, source=f"{reference.name} filmed by sync4d ({settings.width}x{settings.height})",
    ).validate()
    if with_labels:
        return clip, camera, np.stack(labels)
    return clip, camera


def _numpy(value: object) -> np.ndarray:
    """A renderer output (torch tensor or array) as a numpy array."""
    return np.asarray(value.detach().cpu() if isinstance(value, torch.Tensor) else value)
