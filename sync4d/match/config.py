"""Every option of part matching and its default (:class:`MatchConfig`), checked by ``validate``."""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Literal

from sync4d.errors import ConfigError
from sync4d.match.structure import StructureConfig
from sync4d.registry import literal_options

#: The option sets, each written once: the fields below are typed with them, the tuples are read from them.
Method = Literal["auto", "features", "structure"]
TieBreak = Literal["centroid", "nearest_vertex"]
BoxFrame = Literal["aligned", "pca"]
BOX_FRAMES: tuple[str, ...] = typing.get_args(BoxFrame)
TIE_BREAKS: tuple[str, ...] = typing.get_args(TieBreak)
METHODS: tuple[str, ...] = typing.get_args(Method)


def prototype_count(spec: int | str) -> int:
    """``match.prototypes`` as a count: ``"all"`` -> 0 (every reference vertex), else an int >= 1."""
    if isinstance(spec, str) and spec.strip().lower() == "all":
        return 0
    try:
        count = int(spec)
    except (TypeError, ValueError):
        count = -1
    if count < 1:
        raise ConfigError(
            f"match.prototypes={spec!r}: use 1 (the paper's part mean), k > 1 (k prototypes per part) or 'all'"
        )
    return count




@dataclass
class MatchConfig:
    """Every option of part matching, with its defaults (the single source of them).

    Attributes:
        method: ``structure`` (curve skeletons matched branch by branch, :mod:`sync4d.match.structure`;
            shapes given upright along ``up_axis``, facing any way), ``features`` (the paper's cosine
            assignment of per-vertex features, then part boxes) or ``auto``: both, keeping the map that
            agrees better with the reference's structure (:mod:`sync4d.match.auto`).
        up_axis: the up axis shared by the reference and the (aligned) target.
        align: ``none`` | ``pca`` | ``pca_icp`` | ``upright_icp`` (:func:`sync4d.match.align.align_shapes`). With
            ``structure``, ``pca``/``pca_icp`` first bring an arbitrarily turned target into the
            reference's frame; ``none``/``upright_icp`` trust that both are upright (the turn about the up
            axis is searched by the structure match itself).
        icp_iterations: ICP iterations of the alignment.
        outlier_sigma: (features) robust spreads beyond which a target vertex is an outlier (<= 0 disables).
        prototypes: (features) ``"1"`` (the paper's part mean), ``"k"`` (k-means prototypes) or ``"all"``.
        smooth_neighbours: (features) k of the label vote after the cosine assignment (0 = off).
        tie_break: (features) ``centroid`` | ``nearest_vertex``: the part of a Gaussian in several boxes.
        box_frame: (features) ``aligned`` | ``pca`` part boxes.
        box_padding: (features) box growth as a fraction of its size per side.
        max_target_vertices: Gaussian means used as the surface when the target has no mesh.
        min_opacity: Gaussians below this opacity are not surface points.
        structure: options of the structure match.
    """

    method: Method = "auto"
    up_axis: Literal["x", "y", "z"] = "y"
    align: Literal["none", "pca", "pca_icp", "upright_icp"] = "upright_icp"
    icp_iterations: int = 100
    outlier_sigma: float = 2.5
    prototypes: str = "all"
    smooth_neighbours: int = 0
    tie_break: TieBreak = "nearest_vertex"
    box_frame: BoxFrame = "aligned"
    box_padding: float = 0.02
    max_target_vertices: int = 6000
    min_opacity: float = 0.1
    structure: StructureConfig = field(default_factory=StructureConfig)

    def validate(self) -> MatchConfig:
        """Raise ConfigError naming the first bad option."""
        hints = typing.get_type_hints(MatchConfig)
        for f in dataclasses.fields(self):
            allowed, value = literal_options(hints[f.name]), getattr(self, f.name)
            if allowed is not None and value not in allowed:
                raise ConfigError(f"match.{f.name}={value!r}: use one of {', '.join(map(str, allowed))}")
        prototype_count(self.prototypes)
        if self.icp_iterations < 1 or self.max_target_vertices < 16 or self.structure.yaw_steps < 1:
            raise ConfigError(
                "match.icp_iterations, match.structure.yaw_steps must be >= 1 and " "match.max_target_vertices >= 16"
            )
        if self.structure.skeleton.samples < 64 or self.structure.skeleton.neighbours < 3:
            raise ConfigError("match.structure.skeleton.samples must be >= 64 and .neighbours >= 3")
        return self
