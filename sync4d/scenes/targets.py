"""The laptop's own Gaussians as the target (``target=laptop``): a self-transfer, whose answer is known exactly."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sync4d.io.mesh import mesh_to_gaussians
from sync4d.registry import register
from sync4d.scenes.laptop import laptop_mesh
from sync4d.types import TargetGaussians



@register("target", "laptop")
class LaptopTarget:
    """The default laptop itself as Gaussians, for self-transfer (the answer is known exactly)."""

    @dataclass
    class Config:
        width: float = 0.34            # [m] (match reference=laptop for a self-transfer)
        depth: float = 0.24            # [m]
        base_thickness: float = 0.02   # [m]
        lid_thickness: float = 0.012   # [m]
        rest_angle_deg: float = 110.0  # [deg]
        subdivisions: int = 3
        num_surface: int = 3000
        num_interior: int = 1500

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.config, self.seed = config, seed
        c = config
        self.vertices, self.faces, self.part = laptop_mesh(
            c.width, c.depth, c.base_thickness, c.lid_thickness, c.rest_angle_deg, c.subdivisions
        )

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices, self.faces

    def load(self) -> TargetGaussians:
        colors = np.where(self.part[:, None] == 0, [[0.55, 0.57, 0.62]], [[0.25, 0.27, 0.32]])
        return mesh_to_gaussians(
            self.vertices, self.faces, num_surface=self.config.num_surface, num_interior=self.config.num_interior,
            vertex_colors=colors, seed=self.seed, name="laptop",
        )
