"""``features=concat``: concatenation of several extractors (the paper's f_diff || f_geo).

Each part's features are L2-normalised per vertex, then multiplied by the part's weight, so a block's
share of the cosine similarity is set by its weight and not by its dimension or its raw magnitude.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sync4d.errors import ConfigError
from sync4d.features._common import l2_rows
from sync4d.registry import make_config, register


@register("features", "concat")
class ConcatFeatures:
    """[w_1 f_1 / |f_1|, w_2 f_2 / |f_2|, ...] per vertex."""

    @dataclass
    class Config:
        # Sub-configs, each with its own ``type`` (e.g. [{type: diff3f}, {type: geometric}]).
        parts: list[Any] = field(default_factory=lambda: [{"type": "diff3f", "backbone": "shading_fourier"}, {"type": "geometric"}])
        weights: list[float] = field(default_factory=lambda: [0.5, 1.0])  # one per part; empty = all 1

        def validate(self) -> None:
            if not self.parts:
                raise ConfigError("features.parts: concat needs at least one sub-extractor")
            if self.weights and len(self.weights) != len(self.parts):
                raise ConfigError(
                    f"features.weights: {len(self.weights)} weights for {len(self.parts)} parts; give one per part"
                )
            if any(w < 0 for w in self.weights):
                raise ConfigError("features.weights: weights must be >= 0")

    def __init__(self, config: Config, *, device: str = "cpu") -> None:
        self.config = config
        self.extractors = []
        for i, part in enumerate(config.parts):
            if not isinstance(part, dict) or "type" not in part:
                raise ConfigError(f"features.parts[{i}]: each part needs a 'type' (e.g. {{type: geometric}})")
            if part["type"] == "concat":
                raise ConfigError(f"features.parts[{i}]: nested concat is not supported; list the parts flat")
            cls, typed = make_config("features", part)
            self.extractors.append(cls(typed, device=device))
        self.weights = list(config.weights) if config.weights else [1.0] * len(self.extractors)

    def extract(self, points: np.ndarray, faces: np.ndarray | None) -> np.ndarray:
        """(V, sum D_i) float32 concatenation of the per-vertex L2-normalised, weighted parts."""
        blocks = [w * l2_rows(np.asarray(ex.extract(points, faces), dtype=np.float64)) for ex, w in zip(self.extractors, self.weights)]
        return np.concatenate(blocks, axis=1).astype(np.float32)
