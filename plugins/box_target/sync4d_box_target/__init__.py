"""Example plugin: ``target=box``, a solid axis-aligned box sampled into 3D Gaussians.

Installed (``pip install plugins/box_target``), sync4d imports this module through the entry point in
``pyproject.toml``; its option ``conf/target/box.yaml`` ships inside the package.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from sync4d.errors import ConfigError
from sync4d.io.mesh import mesh_to_gaussians
from sync4d.registry import register
from sync4d.types import TargetGaussians


@register("target", "box")
class BoxTarget:
    """A box of the given size [m], bottom face on y = 0, as surface and interior Gaussians."""

    @dataclass
    class Config:
        size: list[float] = field(default_factory=lambda: [0.3, 0.1, 0.2])  # extents along x, y, z [m]
        num_surface: int = 1000
        num_interior: int = 500
        color: list[float] = field(default_factory=lambda: [0.3, 0.6, 0.9])  # RGB in [0, 1]

        def validate(self) -> None:
            if len(self.size) != 3 or min(self.size) <= 0:
                raise ConfigError(f"target.size={list(self.size)}: three positive extents [m] expected")

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.config, self.seed = config, seed
        box = trimesh.creation.box(extents=list(config.size)).subdivide().subdivide()  # 98 vertices to match on
        box.apply_translation([0.0, config.size[1] / 2, 0.0])
        self.vertices, self.faces = np.asarray(box.vertices), np.asarray(box.faces)

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """The box's triangle mesh: (V, 3) vertices [m], (F, 3) faces (matching uses it)."""
        return self.vertices, self.faces

    def load(self) -> TargetGaussians:
        r, g, b = self.config.color
        return mesh_to_gaussians(
            self.vertices, self.faces, num_surface=self.config.num_surface, num_interior=self.config.num_interior,
            default_color=(r, g, b), seed=self.seed, name="box",
        )
