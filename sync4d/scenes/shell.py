"""The embedded default target: a procedural clam shell (two dome halves hinged along their back edge).

Mirrors the paper's laptop-to-shell pair. World frame: Y up, metres. The bottom half is the lower half
of an ellipsoid with semi-axes (a, b_bottom, c) under the plane y = 0; the top half is the upper half of
an ellipsoid (a, b_top, c) hinged about the x axis through (0, 0, -c) and opened by ``open_angle_deg``
(0 = closed, as for the laptop lid).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sync4d.io.mesh import mesh_to_gaussians
from sync4d.registry import register
from sync4d.scenes.laptop import rigid, rotation_x
from sync4d.types import TargetGaussians


def half_ellipsoid_mesh(a: float, b: float, c: float, *, up: bool, n_lat: int = 12, n_lon: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A closed half-ellipsoid solid: the dome plus a flat elliptical disk on the plane y = 0.

    Args:
        a, b, c: semi-axes along x, y, z [m].
        up: dome above the plane (True) or below it (False).
        n_lat: rings from the equator to the pole; n_lon: segments around.

    Returns:
        vertices (V, 3) [m], faces (F, 3) int64 with outward normals.
    """
    sign = 1.0 if up else -1.0
    theta = np.linspace(0.0, np.pi / 2, n_lat + 1)[:-1]  # elevation from the equator, pole added apart
    phi = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    dome = np.stack([a * np.cos(th) * np.cos(ph), sign * b * np.sin(th), c * np.cos(th) * np.sin(ph)], -1).reshape(-1, 3)
    pole = np.array([[0.0, sign * b, 0.0]])
    # Disk: rings scaled towards the centre on y = 0 (the equator ring is shared with the dome).
    radii = np.linspace(1.0, 0.0, n_lat // 2 + 1)[1:-1]
    disk = np.concatenate([np.stack([r * a * np.cos(phi), np.zeros_like(phi), r * c * np.sin(phi)], -1) for r in radii])
    center = np.array([[0.0, 0.0, 0.0]])
    vertices = np.concatenate([dome, pole, disk, center])
    idx = lambda i, j: i * n_lon + (j % n_lon)  # noqa: E731 - ring i, segment j of the dome
    faces = []
    for i in range(n_lat - 1):
        for j in range(n_lon):
            faces += [[idx(i, j), idx(i + 1, j), idx(i, j + 1)], [idx(i, j + 1), idx(i + 1, j), idx(i + 1, j + 1)]]
    pole_i = n_lat * n_lon
    faces += [[idx(n_lat - 1, j), pole_i, idx(n_lat - 1, j + 1)] for j in range(n_lon)]
    disk0 = pole_i + 1
    rings = [list(range(n_lon))] + [list(range(disk0 + k * n_lon, disk0 + (k + 1) * n_lon)) for k in range(len(radii))]
    for outer, inner in zip(rings[:-1], rings[1:]):
        for j in range(n_lon):
            j1 = (j + 1) % n_lon
            faces += [[outer[j], outer[j1], inner[j]], [inner[j], outer[j1], inner[j1]]]
    center_i = len(vertices) - 1
    last = rings[-1]
    faces += [[last[j], last[(j + 1) % n_lon], center_i] for j in range(n_lon)]
    triangles = np.array(faces, dtype=np.int64)
    if not up:
        triangles = triangles[:, ::-1]  # mirrored dome: flip winding so normals stay outward
    # Orientation check: the signed volume must be positive for outward normals.
    tri = vertices[triangles]
    if np.einsum("fi,fi->f", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() < 0:
        triangles = triangles[:, ::-1]
    return vertices, triangles


def shell_mesh(
    half_width: float = 0.15,
    half_depth: float = 0.12,
    bottom_height: float = 0.045,
    top_height: float = 0.03,
    open_angle_deg: float = 110.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clam shell mesh with its top half opened by ``open_angle_deg`` about the back hinge.

    Returns:
        vertices (V, 3) [m], faces (F, 3), part (V,) with 0 = bottom half, 1 = top half.
    """
    bv, bf = half_ellipsoid_mesh(half_width, bottom_height, half_depth, up=False)
    tv, tf = half_ellipsoid_mesh(half_width, top_height, half_depth, up=True)
    tv = tv + np.array([0.0, 1e-3, 0.0])  # a hair above the bottom half so the closed shell does not overlap
    hinge = rigid(rotation_x(-np.deg2rad(open_angle_deg)), np.array([0.0, 0.0, -half_depth]))
    tv = tv @ hinge[:3, :3].T + hinge[:3, 3]
    vertices = np.concatenate([bv, tv])
    faces = np.concatenate([bf, tf + len(bv)])
    part = np.concatenate([np.zeros(len(bv), np.int64), np.ones(len(tv), np.int64)])
    return vertices, faces, part


def shell_colors(vertices: np.ndarray, part: np.ndarray) -> np.ndarray:
    """(V, 3) RGB: sandy bottom, coral top, with radial ribs so rotation is visible in renders."""
    angle = np.arctan2(vertices[:, 2], vertices[:, 0])
    ribs = 0.5 + 0.5 * np.cos(18.0 * angle)
    bottom = np.array([0.85, 0.72, 0.52])
    top = np.array([0.93, 0.52, 0.45])
    base = np.where(part[:, None] == 0, bottom, top)
    return np.clip(base * (0.75 + 0.25 * ribs[:, None]), 0.0, 1.0)


@register("target", "shell")
class ShellTarget:
    """The project's own default target: a procedural clam shell as 3D Gaussians."""

    @dataclass
    class Config:
        half_width: float = 0.15      # semi-axis along x [m]
        half_depth: float = 0.12      # semi-axis along z [m]
        bottom_height: float = 0.045  # depth of the bottom dome [m]
        top_height: float = 0.03      # height of the top dome [m]
        open_angle_deg: float = 110.0  # initial opening; keep close to the reference's rest pose [deg]
        num_surface: int = 3000       # surface Gaussians
        num_interior: int = 1500      # interior Gaussians (volume for the simulation)

        def validate(self) -> None:
            from sync4d.errors import ConfigError

            if min(self.half_width, self.half_depth, self.bottom_height, self.top_height) <= 0:
                raise ConfigError("target: shell dimensions must be > 0 m")
            if self.num_surface < 1 or self.num_interior < 0:
                raise ConfigError("target: num_surface must be >= 1 and num_interior >= 0")

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.config = config
        self.seed = seed
        c = config
        self.vertices, self.faces, self.part = shell_mesh(
            c.half_width, c.half_depth, c.bottom_height, c.top_height, c.open_angle_deg
        )

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """The shell's surface mesh (vertices (V, 3) [m], faces (F, 3)) for feature extraction."""
        return self.vertices, self.faces

    def load(self) -> TargetGaussians:
        return mesh_to_gaussians(
            self.vertices,
            self.faces,
            num_surface=self.config.num_surface,
            num_interior=self.config.num_interior,
            vertex_colors=shell_colors(self.vertices, self.part),
            seed=self.seed,
            name="shell",
        )
