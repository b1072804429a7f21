"""``sim=lbs``: the point-wise deformation baseline the paper argues against.

Every particle is moved by linear blend skinning with its matched parts' rigid transforms (paper-style
"point-wise deformation"): weights are the part labels of its k nearest particles (so seams blend instead of
tearing; ``neighbours=1`` = hard parts), transforms are the frame's part poses. No physics, no optimisation;
the same protocol as ``sim=mpm_warp`` for side-by-side charts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from sync4d.errors import ConfigError, InputError
from sync4d.geometry import skinned_positions
from sync4d.registry import register
from sync4d.sim.kinematic import padded_box
from sync4d.types import FramePose


def smoothed_part_weights(points: np.ndarray, parts: np.ndarray, num_parts: int, neighbours: int) -> np.ndarray:
    """(N, B) skinning weights: the share of each part among a point's ``neighbours`` nearest points."""
    onehot = np.eye(num_parts)[parts]
    if neighbours <= 1:
        return onehot
    _, idx = cKDTree(points).query(points, k=min(neighbours, len(points)))
    return onehot[idx].mean(axis=1)


@dataclass(frozen=True)
class SkinningModel:
    """Rest particles (P, 3) [m] and their (P, B) blend weights over the parts."""

    rest_points: np.ndarray
    weights: np.ndarray


@register("sim", "lbs")
class LinearBlendSkinning:
    """Point-wise deformation of the target by its matched parts' transforms (baseline)."""

    @dataclass
    class Config:
        neighbours: int = 16   # k nearest particles averaged into each particle's weights (1 = hard parts)

        def validate(self) -> None:
            if self.neighbours < 1:
                raise ConfigError(f"sim.neighbours={self.neighbours}: must be >= 1")

    differentiable = False
    dtype = torch.float64  # point-wise: exact in double precision

    def __init__(self, config: Config, *, device: str = "cpu") -> None:
        config.validate()
        self.config = config

    def prepare(self, points: np.ndarray, *, volume: np.ndarray | None = None,
                part: np.ndarray | None = None, parent: np.ndarray | None = None) -> SkinningModel:
        """Blend weights of the rest particles from their parts (``part`` is required)."""
        if part is None:
            raise InputError("sim=lbs: prepare needs the particles' parts")
        rest = np.asarray(points, dtype=np.float64)
        parts = np.asarray(part, dtype=np.int64)
        return SkinningModel(rest, smoothed_part_weights(rest, parts, int(parts.max()) + 1, self.config.neighbours))

    def domain(self, model: SkinningModel) -> tuple[np.ndarray, np.ndarray]:
        return padded_box(model.rest_points)

    def frame_time_for(self, fps: float | None) -> float:
        return 1.0 / float(fps) if fps else 1.0

    def substeps_for(self, model: SkinningModel, v_max: float = 0.0, *,
                     fps: float | None = None) -> tuple[int, float]:
        return 1, self.frame_time_for(fps)

    def rollout(
        self, model: SkinningModel, x: torch.Tensor, v: torch.Tensor, F: torch.Tensor, C: torch.Tensor, *,
        substeps: int, dt: float, frame_index: int = 0, pose: FramePose | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every particle skinned to ``pose.end`` (its blend of the parts' rest -> t+1 transforms); F is the
        blend of their rotations. The incoming state is not used: skinning is point-wise, from rest."""
        if pose is None:
            raise InputError("sim=lbs: rollout needs the frame's pose")
        weights = pad_columns(model.weights, pose.num_parts)
        x1 = skinned_positions(model.rest_points, weights, pose.end)
        F1 = np.einsum("nb,bij->nij", weights, pose.end[:, :3, :3])
        horizon = float(substeps) * float(dt)
        x1_t = torch.as_tensor(x1, dtype=self.dtype)
        return x1_t, (x1_t - x) / horizon, torch.as_tensor(F1, dtype=self.dtype), torch.zeros_like(C)


def pad_columns(weights: np.ndarray, columns: int) -> np.ndarray:
    """(N, B') weights widened with zero columns to (N, columns) (parts with no particle of their own)."""
    if weights.shape[1] >= columns:
        return weights[:, :columns]
    return np.concatenate([weights, np.zeros((len(weights), columns - weights.shape[1]))], axis=1)
