"""A procedural cross target (``target=cross``): two boxes forming an upright cross, like a person with
arms out (the paper's human-to-cross pair).

World frame: Y up, metres. A vertical bar (``bar_width`` x ``height`` x ``depth``) stands on y = 0
centred in x and z; a horizontal bar (``arm_span`` x ``arm_height`` x ``depth``) crosses it with its
centre at height ``arm_center_y``. The solid is built as ONE closed surface (the cross-shaped outline
extruded along z, no faces inside), so surface samples stay on the outside and inside/outside tests
for interior samples are exact.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from sync4d.errors import ConfigError
from sync4d.io.mesh import mesh_to_gaussians
from sync4d.registry import register
from sync4d.types import TargetGaussians


def cross_outline(height: float, bar_width: float, arm_span: float, arm_height: float, arm_center_y: float) -> np.ndarray:
    """The 12 corners (x, y) [m] of the cross outline, clockwise seen from +z.

    Corners 0, 3, 6, 9 are the concave (inner) ones; together they bound the square where the bars meet.
    """
    w, a = bar_width / 2, arm_span / 2
    lo, hi = arm_center_y - arm_height / 2, arm_center_y + arm_height / 2
    return np.array([
        [w, lo], [w, 0.0], [-w, 0.0], [-w, lo],     # inner lower-right, foot right, foot left, inner lower-left
        [-a, lo], [-a, hi], [-w, hi],               # left arm
        [-w, height], [w, height], [w, hi],         # head
        [a, hi], [a, lo],                           # right arm
    ])


def cross_mesh(
    height: float = 0.6,
    bar_width: float = 0.12,
    arm_span: float = 0.5,
    arm_height: float = 0.1,
    arm_center_y: float = 0.42,
    depth: float = 0.1,
    subdivisions: int = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """A closed, outward-oriented triangle mesh of the cross.

    Args:
        height: vertical bar height [m]; bar_width: its width along x [m].
        arm_span: horizontal bar length along x [m]; arm_height: its thickness along y [m].
        arm_center_y: height of the horizontal bar's centre [m].
        depth: thickness of both bars along z [m].
        subdivisions: midpoint subdivisions (4^k triangles per face) for dense vertices.

    Returns:
        vertices (V, 3) [m], faces (F, 3) int64.
    """
    outline = cross_outline(height, bar_width, arm_span, arm_height, arm_center_y)
    n = len(outline)
    front = np.column_stack([outline, np.full(n, depth / 2)])
    back = np.column_stack([outline, np.full(n, -depth / 2)])
    vertices = np.concatenate([front, back])
    # Caps: the central square and the four arms, each a quad of outline corners, ordered like the
    # outline (clockwise from +z) so that caps and side walls share edges in opposite directions.
    quads = [[3, 6, 9, 0], [0, 1, 2, 3], [4, 5, 6, 3], [6, 7, 8, 9], [0, 9, 10, 11]]
    faces = []
    for q in quads:
        faces += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]                       # front (z = +depth/2)
        faces += [[n + q[0], n + q[2], n + q[1]], [n + q[0], n + q[3], n + q[2]]]  # back (z = -depth/2), reversed
    for i in range(n):
        j = (i + 1) % n
        faces += [[i, n + i, n + j], [i, n + j, j]]                             # side walls
    mesh = trimesh.Trimesh(vertices, np.array(faces, dtype=np.int64), process=True)
    if mesh.volume < 0:  # orient outward
        mesh.invert()
    for _ in range(subdivisions):
        mesh = mesh.subdivide()
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


@register("target", "cross")
class CrossTarget:
    """A procedural upright cross as 3D Gaussians (a human-like shape with arms out)."""

    @dataclass
    class Config:
        height: float = 0.6         # vertical bar height [m]
        bar_width: float = 0.12     # vertical bar width along x [m]
        arm_span: float = 0.5       # horizontal bar length along x [m]
        arm_height: float = 0.1     # horizontal bar thickness along y [m]
        arm_center_y: float = 0.42  # height of the horizontal bar's centre [m]
        depth: float = 0.1          # thickness of both bars along z [m]
        subdivisions: int = 3       # mesh density (triangles grow 4x per step)
        num_surface: int = 3000     # surface Gaussians
        num_interior: int = 1500    # interior Gaussians (volume for the simulation)
        color: list[float] = field(default_factory=lambda: [0.8, 0.55, 0.3])

        def validate(self) -> None:
            if min(self.height, self.bar_width, self.arm_span, self.arm_height, self.depth) <= 0:
                raise ConfigError("target: cross sizes (height, bar_width, arm_span, arm_height, depth) must be > 0 m")
            if self.arm_span <= self.bar_width:
                raise ConfigError(f"target.arm_span={self.arm_span}: must exceed bar_width={self.bar_width} m")
            lo, hi = self.arm_center_y - self.arm_height / 2, self.arm_center_y + self.arm_height / 2
            if not (0.0 < lo and hi < self.height):
                raise ConfigError(
                    f"target.arm_center_y={self.arm_center_y}: the arms ({lo:.3g}..{hi:.3g} m) must lie strictly "
                    f"inside the vertical bar (0..{self.height} m)"
                )
            if self.subdivisions < 0 or self.num_surface < 1 or self.num_interior < 0:
                raise ConfigError("target: need subdivisions >= 0, num_surface >= 1, num_interior >= 0")

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.config, self.seed = config, seed
        c = config
        self.vertices, self.faces = cross_mesh(
            c.height, c.bar_width, c.arm_span, c.arm_height, c.arm_center_y, c.depth, c.subdivisions
        )

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """The cross's surface mesh (vertices (V, 3) [m], faces (F, 3)) for feature extraction."""
        return self.vertices, self.faces

    def load(self) -> TargetGaussians:
        colors = np.tile(np.asarray(self.config.color, dtype=np.float64), (len(self.vertices), 1))
        return mesh_to_gaussians(
            self.vertices, self.faces, num_surface=self.config.num_surface, num_interior=self.config.num_interior,
            vertex_colors=colors, seed=self.seed, name="cross",
        )
