"""Render an articulated reference as a casual video (frames, masks, camera), for ``recon=video``.

The paper starts from a video of the reference; the project's default scene is procedural, so it is
filmed here with the project's own splatting renderer: the rest surface as Gaussians, posed every frame
by the reference's own skinning, seen by one static camera or by a hand-held one (a slow arc about the
object with bob, jitter and roll, as a phone user films an object: :func:`camera_path`). The surface gets a
procedural texture fixed to the material (a 3D checker in rest coordinates), because optical flow needs
texture and a real object has some (keys, bezels, logos). Behind it: a plain backdrop, or a textured room
(floor and walls, :func:`room_image`) from which a moving camera can be found. Masks are the rendered
opacity above one half.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

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
        path: ``static`` (one camera) or ``arc`` (hand-held: ``arc_deg`` of azimuth about the up axis over
            the clip, a few degrees of elevation bob, jitter of the aim and about 1 deg of roll per frame).
        arc_deg: azimuth swept by the hand-held arc [deg].
        background: ``plain`` (the renderer's backdrop) or ``room`` (textured floor and walls).
        seed: the hand-held camera's jitter and roll.
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
    path: Literal["static", "arc"] = "static"
    arc_deg: float = 30.0
    background: Literal["plain", "room"] = "plain"
    seed: int = 0

    def validate(self) -> FilmSettings:
        if self.width < 16 or self.height < 16:
            raise ConfigError(f"reference.video_size={self.width}x{self.height}: needs at least 16x16 px")
        if self.gaussians < 100:
            raise ConfigError(f"reference.video_gaussians={self.gaussians}: needs at least 100")
        if self.texture_cell < 0 or not 0.0 <= self.texture_contrast < 1.0:
            raise ConfigError("reference.video_texture_cell must be >= 0 and video_texture_contrast in [0, 1)")
        if self.path not in ("static", "arc") or self.background not in ("plain", "room"):
            raise ConfigError(f"reference video: path {self.path!r} (static | arc), background {self.background!r} "
                              "(plain | room)")
        return self


def camera_path(points: np.ndarray, settings: FilmSettings, frames: int) -> list[Camera]:
    """Per-frame cameras framing ``points`` (..., 3) [m]: the static camera of ``settings.direction`` in every
    frame, or a hand-held arc starting there (:func:`handheld_path`, seeded by ``settings.seed``)."""
    from sync4d.render.camera import bounding_sphere, frame_object, look_at

    first = frame_object(points.reshape(-1, 3), direction=settings.direction, up=settings.up, fov_deg=settings.fov_deg,
                         width=settings.width, height=settings.height, margin=settings.margin)
    if settings.path == "static":
        return [first] * frames
    centre, radius = bounding_sphere(points)
    eye = np.linalg.inv(first.world_to_cam)[:3, 3]
    rng = np.random.default_rng([settings.seed, 0x5EED])
    path = handheld_path(eye, centre, radius, settings.up, settings.arc_deg, frames, rng)
    return [look_at(pos, aim, tilt, settings.fov_deg, settings.width, settings.height) for pos, aim, tilt in path]


def handheld_path(eye: np.ndarray, centre: np.ndarray, radius: float, up: tuple[float, float, float] | np.ndarray,
                  arc_deg: float, frames: int, rng: np.random.Generator
                  ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per frame (eye (3,), aim (3,), the camera's up (3,)) of a phone user's arc about an object at ``centre``
    of ``radius`` [m], starting at ``eye`` (frame 0 exactly there, aimed at the centre): azimuth swept
    smoothly by ``arc_deg`` about ``up``, elevation +-3 deg, distance +-5 %, the aim jittered by 2 % of the
    radius, roll ~1 deg (drawn from ``rng``)."""
    from scipy.spatial.transform import Rotation

    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    s = np.linspace(0.0, 1.0, frames)
    out = []
    for t in range(frames):
        offset = Rotation.from_rotvec(np.radians(arc_deg * (3 * s[t] ** 2 - 2 * s[t] ** 3)) * up).apply(eye - centre)
        side = np.cross(up, offset)
        offset = Rotation.from_rotvec(np.radians(3.0 * np.sin(2 * np.pi * s[t])) * side / np.linalg.norm(side)).apply(offset)
        offset = offset * (1.0 + 0.05 * np.sin(3.0 * s[t]))
        aim = centre + (rng.normal(0.0, 0.02 * radius, 3) if t else 0.0)
        roll = np.radians(rng.normal(0.0, 1.0)) if t else 0.0
        fwd = (aim - centre - offset) / np.linalg.norm(aim - centre - offset)
        tilt = Rotation.from_rotvec(roll * fwd).apply(up)
        out.append((centre + offset, aim, tilt))
    return out


def room_texture(uv: np.ndarray, salt: int, tile: float) -> np.ndarray:
    """(N, 3) colours of a tiled pattern at plane coordinates uv (N, 2) [m]: tiles of edge ``tile`` [m] in
    random muted colours, a checker of a third of that and a slow shading gradient."""
    cell = np.floor(uv / tile).astype(np.int64)
    h = (cell[:, 0] * 73856093 ^ cell[:, 1] * 19349663 ^ salt * 83492791) % 1000003
    base = np.stack([(h % 97) / 97.0, (h % 89) / 89.0, (h % 83) / 83.0], axis=1) * 0.55 + 0.25
    fine = np.where((np.floor(3 * uv / tile).astype(np.int64).sum(1) % 2) == 0, 1.0, 0.8)
    shade = 0.85 + 0.15 * np.sin(uv[:, 0] / tile + salt) * np.cos(uv[:, 1] / tile)
    return np.clip(base * (fine * shade)[:, None], 0.0, 1.0)


def room_image(camera: Camera, centre: np.ndarray, floor_y: float, half: float) -> np.ndarray:
    """(H, W, 3) the room behind the subject: floor at ``floor_y``, walls at centre +- ``half`` (x, z),
    ceiling ``2 half`` above the floor; each pixel's ray hits the first plane it leaves the box through."""
    w2c = camera.world_to_cam
    c2w = np.linalg.inv(w2c)
    vv, uu = np.mgrid[0:camera.height, 0:camera.width] + 0.5
    pix = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], axis=1) @ np.linalg.inv(camera.K).T
    d = pix @ c2w[:3, :3].T
    o = c2w[:3, 3]
    lo = np.array([centre[0] - half, floor_y, centre[2] - half])
    hi = np.array([centre[0] + half, floor_y + 2 * half, centre[2] + half])
    with np.errstate(divide="ignore", invalid="ignore"):
        t_exit = np.where(d > 0, (hi - o) / d, (lo - o) / d)
    t_exit = np.where(np.isfinite(t_exit) & (t_exit > 0), t_exit, np.inf)
    axis = np.argmin(t_exit, axis=1)
    hit = o + d * t_exit[np.arange(len(d)), axis][:, None]
    keep = [(1, 2), (0, 2), (0, 1)]  # in-plane coordinates of the plane crossed on each axis
    colours = np.zeros((len(d), 3))
    for a in range(3):
        sel = axis == a
        colours[sel] = room_texture(hit[sel][:, keep[a]], salt=a, tile=half / 6)
    return colours.reshape(camera.height, camera.width, 3)


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
    """Render every frame of ``reference`` from the cameras of ``settings`` (:func:`camera_path`).

    Args:
        reference: the articulated reference (rest mesh with faces, skinning, per-frame transforms).
        renderer: a built ``render`` component with ``render_full(means, covs, colours, opacities, camera)``.
        settings: image size, texture and framing.

        with_labels: also render the ground-truth part of every pixel.

    Returns:
        The clip (frames (T, H, W, 3) uint8, masks (T, H, W) bool, intrinsics, and the (T, 4, 4)
        world-to-camera poses when the camera moves), its first frame's camera, and with ``with_labels`` the (T, H, W) uint8 part labels: 0 background, b + 1 where
        bone b (the argmax skinning of the nearest rest vertex) is in front.
    """
    from sync4d.render.camera import bounding_sphere
    from sync4d.render.reference import reference_gaussians

    settings.validate()
    if reference.rest_faces is None or not len(reference.rest_faces):
        raise ConfigError("reference video: the reference has no surface mesh to film")
    rest, means, covs = reference_gaussians(reference, reference.num_frames, count=settings.gaussians)
    rest = textured(rest, settings.texture_cell, settings.texture_contrast)
    cameras = camera_path(means, settings, reference.num_frames)
    camera = cameras[0]
    centre, radius = bounding_sphere(means.reshape(-1, 3))
    floor_y = float(means[..., 1].min())
    frames, masks, labels = [], [], []
    colours = np.clip(rest.colors(), 0.0, 1.0)
    onehot = None
    if with_labels:
        from scipy.spatial import cKDTree

        part = reference.part_labels()[cKDTree(reference.rest_vertices).query(rest.means)[1]]
        onehot = np.eye(reference.num_bones, dtype=np.float32)[part]
        if reference.num_bones == 3:  # three channels would be read as RGB (and composited on the background)
            onehot = np.concatenate([onehot, np.zeros((len(onehot), 1), np.float32)], axis=1)
    room = settings.background == "room"
    for t in range(reference.num_frames):
        cam = cameras[t]
        out = renderer.render_full(means[t], covs[t], colours, rest.opacities, cam,  # type: ignore[attr-defined]
                                   **({"background": np.zeros(3)} if room else {}))
        rgb, alpha = (_numpy(out[k]) for k in ("rgb", "alpha"))
        alpha = alpha.reshape(settings.height, settings.width)
        if room:
            rgb = rgb + (1.0 - alpha[..., None]) * room_image(cam, centre, floor_y, 4.0 * radius)
        frames.append(np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8))
        mask = alpha > 0.5
        masks.append(mask)
        if onehot is not None:
            weights = _numpy(renderer.render_full(means[t], covs[t], onehot, rest.opacities, cam)["rgb"])  # type: ignore[attr-defined]
            labels.append(np.where(mask, np.argmax(weights[..., : reference.num_bones], axis=-1) + 1, 0).astype(np.uint8))
    moving = settings.path != "static"
    clip = VideoClip(
        frames=np.stack(frames), masks=np.stack(masks), fps=reference.fps, intrinsics=camera.K.copy(),
        extrinsics=np.stack([c.world_to_cam for c in cameras]) if moving else None,
        source=f"{reference.name} filmed by sync4d ({settings.width}x{settings.height}, {settings.path} camera)",
    ).validate()
    if with_labels:
        return clip, camera, np.stack(labels)
    return clip, camera


def _numpy(value: object) -> np.ndarray:
    """A renderer output (torch tensor or array) as a numpy array."""
    return np.asarray(value.detach().cpu() if isinstance(value, torch.Tensor) else value)
