"""The embedded default reference: a procedural laptop (base and lid on one hinge) opening and closing.

World frame: Y up, metres. The base slab spans x in [-W/2, W/2], y in [0, h_base], z in [-D/2, D/2];
the hinge axis is the x axis through the pivot (0, h_base, -D/2). A lid angle of 0 deg lies closed on
the base; the angle grows as the lid opens (90 deg = upright). Bone 0 is the base, bone 1 the lid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import trimesh

from sync4d.frontend.config import FrontEndConfig
from sync4d.registry import register
from sync4d.scenes.reference_video import FilmSettings, film_reference
from sync4d.types import Camera, Reference, ReferenceInput, VideoClip


def rotation_x(angle_rad: float) -> np.ndarray:
    """(3, 3) rotation about +x by ``angle_rad`` (right-handed)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rigid(rotation: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """(4, 4) transform rotating by ``rotation`` about the point ``pivot`` [m]."""
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = pivot - rotation @ pivot
    return out


def hinge_pivot(depth: float, base_thickness: float) -> np.ndarray:
    """(3,) a point on the hinge axis [m]."""
    return np.array([0.0, base_thickness, -depth / 2.0])


def lid_transform(lid_angle_deg: float, depth: float, base_thickness: float) -> np.ndarray:
    """(4, 4) transform taking the closed lid (angle 0) to ``lid_angle_deg`` about the hinge.

    Rotating by -angle about +x lifts the lid's front edge (+z) upwards (+y).
    """
    return rigid(rotation_x(-np.deg2rad(lid_angle_deg)), hinge_pivot(depth, base_thickness))


def _box(extents: np.ndarray, center: np.ndarray, subdivisions: int) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=extents)
    for _ in range(subdivisions):
        box = box.subdivide()
    box.apply_translation(center)
    return box


def laptop_mesh(
    width: float = 0.34,
    depth: float = 0.24,
    base_thickness: float = 0.02,
    lid_thickness: float = 0.012,
    lid_angle_deg: float = 110.0,
    subdivisions: int = 3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle mesh of a laptop with its lid at ``lid_angle_deg``.

    Args:
        width: size along x [m].
        depth: size along z [m].
        base_thickness: base slab height [m].
        lid_thickness: lid slab thickness [m].
        lid_angle_deg: opening angle (0 closed, 90 upright) [deg].
        subdivisions: midpoint subdivisions of each box (4^k triangles per face), for dense vertices.

    Returns:
        vertices (V, 3) [m], faces (F, 3) int64, part (V,) int64 with 0 = base, 1 = lid.
    """
    base = _box(np.array([width, base_thickness, depth]), np.array([0.0, base_thickness / 2, 0.0]), subdivisions)
    # Closed lid: lies on the base, inset by a hair so that the closed pose does not self-touch.
    lid = _box(
        np.array([width, lid_thickness, depth]),
        np.array([0.0, base_thickness + lid_thickness / 2 + 1e-4, 0.0]),
        subdivisions,
    )
    lid.apply_transform(lid_transform(lid_angle_deg, depth, base_thickness))
    vertices = np.concatenate([base.vertices, lid.vertices]).astype(np.float64)
    faces = np.concatenate([base.faces, lid.faces + len(base.vertices)]).astype(np.int64)
    part = np.concatenate([np.zeros(len(base.vertices)), np.ones(len(lid.vertices))]).astype(np.int64)
    return vertices, faces, part


def lid_angle_schedule(num_frames: int, rest_deg: float, min_deg: float, period_frames: int) -> np.ndarray:
    """(T,) lid angle per frame [deg]: starts at ``rest_deg``, closes to ``min_deg`` and reopens (cosine)."""
    t = np.arange(num_frames, dtype=np.float64)
    amplitude = (rest_deg - min_deg) / 2.0
    return min_deg + amplitude + amplitude * np.cos(2.0 * np.pi * t / period_frames)


def box_covariance(extents: np.ndarray, rotation: np.ndarray | None = None) -> np.ndarray:
    """(3, 3) covariance of a uniform solid box with the given extents [m^2], optionally rotated."""
    cov = np.diag(np.asarray(extents, dtype=np.float64) ** 2 / 12.0)
    if rotation is not None:
        cov = rotation @ cov @ rotation.T
    return cov


def laptop_reference(
    num_frames: int = 24,
    *,
    width: float = 0.34,
    depth: float = 0.24,
    base_thickness: float = 0.02,
    lid_thickness: float = 0.012,
    rest_angle_deg: float = 110.0,
    min_angle_deg: float = 40.0,
    period_frames: int = 24,
    fps: float = 12.0,
    subdivisions: int = 3,
) -> Reference:
    """The exact articulated laptop: rest shape at ``rest_angle_deg``, 2 bones, hard skinning, motion.

    The lid's bone transform at frame t rotates the lid about the hinge from the rest angle to the
    scheduled angle; the base stays put; the global transform is the identity.
    """
    vertices, faces, part = laptop_mesh(width, depth, base_thickness, lid_thickness, rest_angle_deg, subdivisions)
    skinning = np.eye(2)[part]
    lid_rest = lid_transform(rest_angle_deg, depth, base_thickness)
    base_center = np.array([0.0, base_thickness / 2, 0.0])
    lid_center = (lid_rest @ np.array([0.0, base_thickness + lid_thickness / 2, 0.0, 1.0]))[:3]
    covariances = np.stack(
        [
            box_covariance(np.array([width, base_thickness, depth])),
            box_covariance(np.array([width, lid_thickness, depth]), lid_rest[:3, :3]),
        ]
    )
    angles = lid_angle_schedule(num_frames, rest_angle_deg, min_angle_deg, period_frames)
    transforms = np.tile(np.eye(4), (num_frames, 2, 1, 1))
    pivot = hinge_pivot(depth, base_thickness)
    for t, angle in enumerate(angles):
        transforms[t, 1] = rigid(rotation_x(-np.deg2rad(angle - rest_angle_deg)), pivot)
    colors = np.where(part[:, None] == 0, [[0.55, 0.57, 0.62]], [[0.25, 0.27, 0.32]])
    return Reference(
        rest_vertices=vertices,
        rest_faces=faces,
        bone_centers=np.stack([base_center, lid_center]),
        bone_covariances=covariances,
        skinning=skinning,
        bone_transforms=transforms,
        global_transforms=np.tile(np.eye(4), (num_frames, 1, 1)),
        fps=fps,
        vertex_colors=colors.astype(np.float64),
        bone_names=("base", "lid"),
        name="laptop",
    ).validate()


def lid_angles_of(reference: Reference, depth: float = 0.24, base_thickness: float = 0.02) -> np.ndarray:
    """(T,) the lid's rotation about the hinge relative to the rest pose, per frame [deg] (for tests)."""
    rot = reference.bone_transforms[:, 1, :3, :3] @ np.linalg.inv(reference.bone_transforms[:, 0, :3, :3])
    return -np.rad2deg(np.arctan2(rot[:, 2, 1], rot[:, 1, 1]))


@register("reference", "laptop")
class LaptopReference:
    """The project's own default reference: a procedural laptop opening and closing (exact ground truth)."""

    @dataclass
    class Config:
        num_frames: int = 24           # length of the reference motion T
        width: float = 0.34            # [m]
        depth: float = 0.24            # [m]
        base_thickness: float = 0.02   # [m]
        lid_thickness: float = 0.012   # [m]
        rest_angle_deg: float = 110.0  # lid angle at frame 0 (the rest pose) [deg]
        min_angle_deg: float = 40.0    # most closed lid angle [deg]
        period_frames: int = 24        # frames per open-close cycle
        fps: float = 12.0              # [1/s]
        subdivisions: int = 3          # mesh density (vertices grow 4x per step)
        video: bool = True             # also film the laptop (textured) for recon=video, as the default run reconstructs from the film
        # how it is filmed: handheld = a slow 30 deg arc about it in a textured room (bob, jitter, roll; seeded by
        # the run's seed), as a phone user films an object; static = one fixed camera before a white backdrop
        video_camera: Literal["handheld", "static"] = "handheld"
        video_width: int = 160         # [px]
        video_height: int = 120        # [px]
        video_gaussians: int = 6000    # surface Gaussians rendered
        video_texture_cell: float = 0.02  # checker texture cell [m] (optical flow needs texture; 0 = none)
        # what the film hands recon=video besides its frames; the rest is found by the video front end:
        # masks_intrinsics = the renderer's exact masks and the lens's intrinsics (as a phone records its focal
        # length; the per-frame camera poses found), masks = the masks only (the intrinsics guessed from a
        # 66 deg field of view, then refined), none = the video alone, masks_camera = masks and camera exact
        video_exact: Literal["none", "masks", "masks_intrinsics", "masks_camera"] = "masks_intrinsics"
        frontend: FrontEndConfig = field(default_factory=FrontEndConfig)  # the front end's options

        def validate(self) -> None:
            from sync4d.errors import ConfigError

            if self.num_frames < 2:
                raise ConfigError(f"reference.num_frames={self.num_frames}: needs at least 2 frames")
            if min(self.width, self.depth, self.base_thickness, self.lid_thickness) <= 0:
                raise ConfigError("reference: laptop dimensions must be > 0 m")
            if not 0.0 <= self.min_angle_deg <= self.rest_angle_deg <= 180.0:
                raise ConfigError("reference: need 0 <= min_angle_deg <= rest_angle_deg <= 180")

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.config = config
        self.device = device
        self.seed = seed

    def film_settings(self) -> FilmSettings:
        """The camera, background and texture the laptop is filmed with (its ``up`` is the world's up)."""
        c = self.config
        hand = c.video_camera == "handheld"
        return FilmSettings(width=c.video_width, height=c.video_height, gaussians=c.video_gaussians,
                            texture_cell=c.video_texture_cell, path="arc" if hand else "static",
                            background="room" if hand else "plain", seed=self.seed)

    def film(self, reference: Reference) -> tuple[VideoClip, Camera]:
        """The laptop filmed by the project's renderer (see :mod:`sync4d.scenes.reference_video`)."""
        from sync4d.registry import build

        c = self.config
        renderer = build("render", {"type": "splat_torch", "width": c.video_width, "height": c.video_height},
                         device=self.device)
        clip, camera, *_ = film_reference(reference, renderer, self.film_settings())
        return clip, camera

    def load(self) -> ReferenceInput:
        c = self.config
        reference = laptop_reference(
            c.num_frames,
            width=c.width,
            depth=c.depth,
            base_thickness=c.base_thickness,
            lid_thickness=c.lid_thickness,
            rest_angle_deg=c.rest_angle_deg,
            min_angle_deg=c.min_angle_deg,
            period_frames=c.period_frames,
            fps=c.fps,
            subdivisions=c.subdivisions,
        )
        sequence = np.stack([reference.posed_vertices(t) for t in range(reference.num_frames)])
        clip, camera = self.film(reference) if c.video else (None, None)
        up = np.asarray(self.film_settings().up, dtype=np.float64)
        if clip is not None and c.video_exact != "masks_camera":  # the camera (and the masks) from the film alone
            from dataclasses import replace

            from sync4d.frontend import complete_video_up

            masks = c.video_exact != "none"
            lens = clip.intrinsics if c.video_exact == "masks_intrinsics" else None
            clip, camera, ground = complete_video_up(replace(clip, intrinsics=lens, extrinsics=None, masks=clip.masks
                                                             if masks else np.zeros_like(clip.masks)), None, c.frontend,
                                                     masks_given=masks)
            # the front end's world: the first camera turned to Y up (an upright phone); up is the ground's normal
            # when a moving camera found the floor
            up = np.array([0.0, 1.0, 0.0]) if ground is None else ground
        return ReferenceInput(
            name="laptop",
            fps=c.fps,
            mesh_sequence=sequence,
            faces=reference.rest_faces,
            ground_truth=reference,
            video=clip,
            camera=camera,
            world_up=up / np.linalg.norm(up) if c.video else None,
        )


def hinge_angles_rad(reference: Reference, base: int = 0, lid: int = 1) -> np.ndarray:
    """(T,) angle [rad] of bone ``lid`` relative to bone ``base``, measured from frame 0's relative pose."""
    from scipy.spatial.transform import Rotation

    j = reference.bone_transforms[:, :, :3, :3]
    rel = np.swapaxes(j[:, base], 1, 2) @ j[:, lid]
    change = np.swapaxes(rel[0], 0, 1)[None] @ rel
    return np.linalg.norm(Rotation.from_matrix(change).as_rotvec(), axis=1)


def filmed_laptop_case(settings: FilmSettings | None = None, *, num_frames: int = 24, device: str = "cpu"
                       ) -> tuple[ReferenceInput, dict[str, np.ndarray]]:
    """The default scene's laptop filmed, with ground truth in the layout of the hinge renders' ``gt.npz``.

    Returns:
        (ReferenceInput with video and camera, gt dict: ``hinge_angle_rad`` (T,), ``part_labels``
        (T, H, W) uint8 with 0 background, 1 base, 2 lid, and ``K`` (3, 3)).
    """
    from sync4d.registry import build

    settings = settings or FilmSettings()
    reference = laptop_reference(num_frames)
    renderer = build("render", {"type": "splat_torch", "width": settings.width, "height": settings.height}, device=device)
    clip, camera, labels = film_reference(reference, renderer, settings, with_labels=True)  # type: ignore[misc]
    up = np.asarray(settings.up, dtype=np.float64)
    source = ReferenceInput(name="laptop_filmed", fps=reference.fps, video=clip, camera=camera,
                            world_up=up / np.linalg.norm(up))
    gt = {"hinge_angle_rad": hinge_angles_rad(reference), "part_labels": labels, "K": camera.K}
    return source, gt
