"""``sim=kinematic``: the physics-free baseline of the MPM transfer (free flight, no grid, no stress).

The same particles as ``sim=mpm_warp`` (control points split by part, :func:`sync4d.transfer.make_particles`)
start every frame pair on the same initial velocities (:func:`sync4d.transfer.initial_velocity`) and fly
freely for the frame: x <- x + N dt v, F <- (I + N dt C) F. With ``transfer.init=rigid`` that is exactly each
part's rigid step, so every particle moves with its part's rigid motion. Whatever ``sim=mpm_warp``
does beyond this comes from the grid and the stress; this is the reference point that shows it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from sync4d.errors import ConfigError
from sync4d.registry import register
from sync4d.sim.control import carry_gaussians, gaussian_covariances
from sync4d.transfer.config import TransferConfig
from sync4d.types import DrivingMotion, PartMap, TargetGaussians, Trajectory


@register("sim", "kinematic")
class Kinematic:
    """Each particle moved by its part's rigid motion (free flight of the MPM's initial state)."""

    @dataclass
    class Config:
        """Attributes:
        control_grid: control-point lattice cells per axis (as ``sim=mpm_warp``), or null for every Gaussian.
        (The initial velocities follow ``transfer.init``, as the MPM's do.)
        """

        control_grid: int | None = 40

        def validate(self) -> None:
            if self.control_grid is not None and self.control_grid < 1:
                raise ConfigError(f"sim.control_grid={self.control_grid}: must be >= 1, or null for every Gaussian")

    def __init__(self, cfg: Config, *, device: str = "cpu") -> None:
        cfg.validate()
        self.cfg = cfg

    def run(
        self,
        target: TargetGaussians,
        part_map: PartMap,
        motion: DrivingMotion,
        *,
        velocity_cfg: Any = None,
        num_frames: int,
        transfer: TransferConfig | None = None,
        seed: int = 0,
        on_frame: Callable[..., None] | None = None,
        resume: dict[str, Any] | None = None,
    ) -> Trajectory:
        """Free flight of every frame pair from ``transfer.init``'s velocities; nothing is optimised, so
        ``velocity_cfg`` and ``seed`` are unused."""
        from sync4d.transfer import initial_velocity, make_particles

        init = (transfer or TransferConfig()).init

        particles = make_particles(target, part_map, self.cfg.control_grid)
        rest = particles.points
        means0 = target.means.astype(np.float64)
        cov0 = gaussian_covariances(target.scales, target.quats)
        x, F = rest.copy(), np.tile(np.eye(3), (len(rest), 1, 1))
        frame_time = 1.0 / motion.fps  # any value: free flight of N dt v does not depend on it
        xs, fs = [], []
        for t in range(num_frames):
            started = time.perf_counter()
            if t > 0:
                P_t, P_next = motion.part_transforms[t - 1], motion.part_transforms[t]
                step = P_next @ np.linalg.inv(P_t)
                v0, C0 = initial_velocity(x, particles.part, step, motion.part_displacements[t - 1], frame_time,
                                          init)
                x = x + frame_time * v0
                F = (np.eye(3)[None] + frame_time * C0) @ F
            means_t, _ = carry_gaussians(means0, cov0, particles.gaussian_to_point, rest, x, F)
            Fg = F[particles.gaussian_to_point]
            xs.append(means_t)
            fs.append(Fg)
            if on_frame is not None:
                on_frame(t, means_t, Fg, {"time/frame_s": time.perf_counter() - started})
        return Trajectory(x=np.stack(xs), F=np.stack(fs), frame_dt=1.0 / motion.fps,
                          global_transforms=motion.global_transforms[:num_frames]).validate()
