"""Target sources read from files: a mesh (``target=mesh``) and a 3DGS ``.ply`` with its floaters removed
(``target=ply``); the checks every target passes."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from sync4d.errors import ConfigError, DataMissingError, InputError
from sync4d.io.mesh import load_mesh, mesh_to_gaussians
from sync4d.io.ply import read_gaussians_ply
from sync4d.paths import resolve_path
from sync4d.registry import register
from sync4d.sources.floaters import FloaterConfig, remove_floaters
from sync4d.types import FloaterReport, TargetGaussians


#: Fewest Gaussians a target can have: matching aligns shapes by their principal axes and the simulation
#: needs a body with an extent.
MIN_TARGET_GAUSSIANS = 4


def check_target_extent(means: np.ndarray, label: str) -> None:
    """Refuse (N, 3) Gaussian centres ``means`` [m] too few to match or simulate, or spanning no surface."""
    if len(means) < MIN_TARGET_GAUSSIANS:
        raise InputError(f"{label}: {len(means)} Gaussian(s); a target needs at least {MIN_TARGET_GAUSSIANS} "
                         "spread over a surface or volume")
    centred = means.astype(np.float64) - means.mean(axis=0)
    spread = np.linalg.svd(centred, compute_uv=False)
    if spread[0] <= 1e-9 * max(float(np.abs(means).max()), 1.0) or spread[1] <= 1e-9 * spread[0]:
        raise InputError(f"{label}: the {len(means)} Gaussian centres coincide or lie on one line; "
                         "a target needs a surface or a volume")


def fit_to_size(vertices: np.ndarray, size: float | None, up_axis: Literal["y", "z"]) -> np.ndarray:
    """Re-orient a mesh to Y-up, centre its footprint at the origin with its bottom at y = 0, and scale
    its bounding-box diagonal to ``size`` [m] (None keeps the file's units)."""
    v = np.asarray(vertices, dtype=np.float64)
    if up_axis == "z":
        v = v[:, [0, 2, 1]] * np.array([1.0, 1.0, -1.0])
    elif up_axis != "y":
        raise ConfigError(f"target.up_axis={up_axis}: use 'y' or 'z'")
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = v - np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
    if size is not None:
        v = v * (size / np.linalg.norm(hi - lo))
    return v


@register("target", "mesh")
class MeshTarget:
    """Any triangle mesh file (.obj/.ply/.stl/.off/.glb) sampled into Gaussians."""

    @dataclass
    class Config:
        path: str = "???"              # mesh file
        size: float | None = 0.4       # bounding-box diagonal after loading [m]; null keeps file units
        up_axis: Literal["y", "z"] = "y"  # the file's up axis
        num_surface: int = 3000
        num_interior: int = 1500
        color: list[float] = field(default_factory=lambda: [0.75, 0.7, 0.65])

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.config, self.seed = config, seed
        path = resolve_path(config.path, what="target.path: mesh file")
        if not path.is_file():
            raise DataMissingError(f"target.path={config.path}: {path} is not a mesh file")
        vertices, self.faces, self.colors = load_mesh(path)
        self.vertices = fit_to_size(vertices, config.size, config.up_axis)
        self.name = path.stem

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices, self.faces

    def load(self) -> TargetGaussians:
        return mesh_to_gaussians(
            self.vertices, self.faces, num_surface=self.config.num_surface, num_interior=self.config.num_interior,
            vertex_colors=self.colors, default_color=(self.config.color[0], self.config.color[1], self.config.color[2]), seed=self.seed, name=self.name,
        )


@register("target", "ply")
class PlyTarget:
    """A trained or generated 3D Gaussian Splatting ``.ply`` (Inria layout), floaters removed.

    :meth:`load_checked` also returns what floater removal did (:class:`sync4d.types.FloaterReport`),
    for the run's log and metrics.
    """

    @dataclass
    class Config:
        path: str = "???"        # .ply file
        max_gaussians: int | None = None  # keep a random subset of this size (None keeps all)
        floaters: FloaterConfig = field(default_factory=FloaterConfig)  # statistical outlier removal

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.config, self.seed = config, seed
        config.floaters.validate()

    def load_checked(self) -> tuple[TargetGaussians, FloaterReport | None]:
        """The splat without its floaters, and the removal's report (None when removal is off)."""
        path = resolve_path(self.config.path, what="target.path: .ply file")
        if not path.is_file():
            raise DataMissingError(f"target.path={self.config.path}: {path} is not a .ply file")
        gaussians = read_gaussians_ply(path)
        check_target_extent(gaussians.means, str(path))
        keep, report = remove_floaters(gaussians.means, self.config.floaters, source=str(path))
        if not keep.all():
            gaussians = gaussians.subset(keep)
        if self.config.max_gaussians is not None and gaussians.num > self.config.max_gaussians:
            keep = np.sort(np.random.default_rng(self.seed).choice(gaussians.num, self.config.max_gaussians, replace=False))
            gaussians = gaussians.subset(keep)
        return gaussians, report

    def load(self) -> TargetGaussians:
        return self.load_checked()[0]
