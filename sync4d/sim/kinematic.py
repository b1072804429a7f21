"""``sim=kinematic``: the physics-free baseline of the MPM transfer (free flight, no grid, no stress).

The same particles as ``sim=mpm_warp`` start every frame pair on the same initial velocities and fly freely
for the frame: x <- x + N dt v, F <- (I + N dt C) F. With
``transfer.init=rigid`` that is exactly each part's rigid step, so every particle moves with its part's rigid
motion. Whatever ``sim=mpm_warp`` does beyond this comes from the grid and the stress; this is the reference
point that shows it. Written in torch, so it is differentiable too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from sync4d.registry import register
from sync4d.types import FramePose


@dataclass(frozen=True)
class KinematicModel:
    """Rest particles (P, 3) [m] and their parts (P,), or None."""

    rest_points: np.ndarray
    part: np.ndarray | None = None


@register("sim", "kinematic")
class Kinematic:
    """Each particle moved by its part's rigid motion (free flight of the MPM's initial state)."""

    @dataclass
    class Config:
        """No settings: the initial velocities follow ``transfer.init``, as the MPM's do."""

    differentiable = True
    dtype = torch.float64  # point-wise: exact in double precision

    def __init__(self, config: Config, *, device: str = "cpu") -> None:
        self.config = config

    def prepare(self, points: np.ndarray, *, volume: np.ndarray | None = None,
                part: np.ndarray | None = None, parent: np.ndarray | None = None) -> KinematicModel:
        """The particles as given, with their parts (volumes play no part)."""
        return KinematicModel(np.asarray(points, dtype=np.float64), None if part is None else np.asarray(part))

    def domain(self, model: KinematicModel) -> tuple[np.ndarray, np.ndarray]:
        return padded_box(model.rest_points)

    def frame_time_for(self, fps: float | None) -> float:
        return 1.0 / float(fps) if fps else 1.0  # any value: free flight of N dt v does not depend on it

    def substeps_for(self, model: KinematicModel, v_max: float = 0.0, *,
                     fps: float | None = None) -> tuple[int, float]:
        return 1, self.frame_time_for(fps)

    def rollout(
        self, model: KinematicModel, x: torch.Tensor, v: torch.Tensor, F: torch.Tensor, C: torch.Tensor, *,
        substeps: int, dt: float, frame_index: int = 0, pose: FramePose | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Each particle on its part's rigid step of ``pose``; without a pose or parts, free flight for
        ``substeps * dt``: x + T v, F <- (I + T C) F."""
        horizon = float(substeps) * float(dt)
        if pose is None or model.part is None:
            x1 = x + horizon * v
            return x1, v, (torch.eye(3, dtype=F.dtype) + horizon * C) @ F, C
        step = torch.as_tensor(pose.end @ np.linalg.inv(pose.start), dtype=x.dtype)[torch.as_tensor(model.part)]
        rot = step[:, :3, :3]
        x1 = torch.einsum("pij,pj->pi", rot, x) + step[:, :3, 3]
        return x1, (x1 - x) / horizon, rot @ F, C


def padded_box(points: np.ndarray, padding: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """The points' bounding box grown by ``padding`` of its longest side on every side [m]."""
    lo, hi = points.min(0), points.max(0)
    margin = padding * float(max((hi - lo).max(), 1e-9))
    return lo - margin, hi + margin


