"""Example plugin: ``target=box``, a solid axis-aligned box sampled into 3D Gaussians."""

from __future__ import annotations

from dataclasses import dataclass

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
        size: list[float] = (0.3, 0.1, 0.2)  # type: ignore[assignment] - extents along x, y, z [m]
        num_surface: int = 1000
        num_interior: int = 500
        color: list[float] = (0.3, 0.6, 0.9)  # type: ignore[assignment]

        def validate(self) -> None:
            if len(self.size) != 3 or min(self.size) <= 0:
                raise ConfigError(f"target.size={list(self.size)}: three positive extents [m] expected")

    def __init__(self, cfg: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.cfg, self.seed = cfg, seed
        box = trimesh.creation.box(extents=list(cfg.size))
        box.apply_translation([0.0, cfg.size[1] / 2, 0.0])
        self.vertices, self.faces = np.asarray(box.vertices), np.asarray(box.faces)

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices, self.faces

    def load(self) -> TargetGaussians:
        return mesh_to_gaussians(
            self.vertices, self.faces, num_surface=self.cfg.num_surface, num_interior=self.cfg.num_interior,
            default_color=tuple(self.cfg.color), seed=self.seed, name="box",
        )
