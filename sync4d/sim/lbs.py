"""``sim=lbs``: the point-wise deformation baseline the paper argues against.

Every target Gaussian is moved by linear blend skinning with its matched parts' rigid transforms
(paper-style "point-wise deformation"): weights are the part labels of its k nearest Gaussians
(so seams blend instead of tearing), transforms are the driving motion's part transforms.
No physics, no optimisation; same interface as ``sim=mpm_warp`` for side-by-side charts.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from sync4d.errors import ConfigError
from sync4d.metrics import skinned_positions
from sync4d.registry import register
from sync4d.types import DrivingMotion, PartMap, TargetGaussians, Trajectory


def smoothed_part_weights(points: np.ndarray, parts: np.ndarray, num_parts: int, neighbours: int) -> np.ndarray:
    """(N, B) skinning weights: the share of each part among a point's ``neighbours`` nearest points."""
    onehot = np.eye(num_parts)[parts]
    if neighbours <= 1:
        return onehot
    _, idx = cKDTree(points).query(points, k=min(neighbours, len(points)))
    return onehot[idx].mean(axis=1)


@register("sim", "lbs")
class LinearBlendSkinning:
    """Point-wise deformation of the target by its matched parts' transforms (baseline)."""

    @dataclass
    class Config:
        neighbours: int = 16   # k nearest Gaussians averaged into each Gaussian's weights (1 = hard parts)

        def validate(self) -> None:
            if self.neighbours < 1:
                raise ConfigError(f"sim.neighbours={self.neighbours}: must be >= 1")

    def __init__(self, cfg: Config, *, device: str = "cpu") -> None:
        self.cfg = cfg

    def run(
        self,
        target: TargetGaussians,
        part_map: PartMap,
        motion: DrivingMotion,
        *,
        velocity_cfg: Any = None,
        num_frames: int,
        transfer: Any = None,
        seed: int = 0,
        on_frame: Callable[..., None] | None = None,
        resume: dict[str, Any] | None = None,
    ) -> Trajectory:
        """Point-wise skinning of every frame; nothing is simulated or optimised (``velocity_cfg``,
        ``transfer`` and ``seed`` are unused)."""
        rest = target.means.astype(np.float64)
        weights = smoothed_part_weights(rest, part_map.tgt_part, part_map.num_parts, self.cfg.neighbours)
        xs, fs = [], []
        for t in range(num_frames):
            started = time.perf_counter()
            # Part transforms map rest -> t; the target's rest pose is the reference's rest pose.
            relative = motion.part_transforms[t] @ np.linalg.inv(motion.part_transforms[0])
            x = skinned_positions(rest, weights, relative)
            blended = np.einsum("nb,bij->nij", weights, relative[:, :3, :3])
            xs.append(x)
            fs.append(blended)
            if on_frame is not None:
                on_frame(t, x, blended, {"time/frame_s": time.perf_counter() - started})
        return Trajectory(
            x=np.stack(xs), F=np.stack(fs), frame_dt=1.0 / motion.fps, global_transforms=motion.global_transforms
        ).validate()
