"""The transfer stage's options: the particle set, how each frame pair is initialised, driven and supervised,
and the optimiser of the velocity field (paper Sec. 3.4)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from sync4d.errors import ConfigError


@dataclass
class TransferConfig:
    """Options of the frame-pair transfer; the one source of their defaults (``transfer.*`` in the config).

    Attributes:
        control_grid: cells per axis of the control-point lattice the target is simulated through (paper:
            41 for millions of Gaussians), or null to simulate every Gaussian: 40 against the MPM's default
            48-node grid (27 cells across the object) is 1.5 lattice cells per grid cell. Cells that
            straddle a part boundary are split per part, so a particle never mixes parts.
        init: initial velocities: ``drive`` (each part's rigid step as a screw: its centroid's velocity plus a constant
            angular velocity, with C = [w]x; what the simulator's held drive follows through the frame), ``rigid`` (each particle on its bone's rigid velocity field
            (T_rel x - x) / (N dt), with the matching APIC matrix), ``pose`` (towards where its part's pose at t+1
            puts its rest position, (P_{t+1} P_0^-1 X - x) / (N dt): the rigid step plus the particle's offset from
            its pose, so drift is closed every frame) or ``centroid`` (the paper: one velocity per part from its
            bone centre's displacement, which turns no part).
        loss_points: what the L1 loss compares: ``particles`` (every particle with its part's pose),
            ``anchors`` (the part centroid and six half-space centroids) or ``centroid`` (the paper).
        target_mode: ``absolute`` (the rest anchors moved by the reference's pose at t+1: drift is corrected)
            or ``relative`` (the paper: the current anchors moved by the reference's step; errors accumulate).
        lr: Adam learning rate of a trainable velocity field.
        iterations: most optimisation steps per frame pair (0 = none, whatever the field).
        patience: stop after this many steps without improvement.
        min_improvement: relative loss improvement that counts.
        reset_each_frame: re-initialise the field at every frame pair (else it starts from the last one).
    """

    control_grid: int | None = 40
    init: Literal["drive", "rigid", "pose", "centroid"] = "drive"
    loss_points: Literal["particles", "anchors", "centroid"] = "particles"
    target_mode: Literal["absolute", "relative"] = "absolute"
    lr: float = 1e-2
    iterations: int = 12
    patience: int = 4
    min_improvement: float = 1e-3
    reset_each_frame: bool = False

    def validate(self) -> TransferConfig:
        """Raise :class:`ConfigError` naming the offending ``transfer.*`` key."""
        if self.control_grid is not None and self.control_grid < 1:
            raise ConfigError(f"transfer.control_grid={self.control_grid}: must be >= 1, or null for every Gaussian")
        if not self.lr > 0:
            raise ConfigError(f"transfer.lr={self.lr}: must be > 0")
        if self.iterations < 0 or self.patience < 1:
            raise ConfigError("transfer.iterations must be >= 0 and transfer.patience >= 1")
        if not 0.0 <= self.min_improvement < 1.0:
            raise ConfigError(f"transfer.min_improvement={self.min_improvement}: must be in [0, 1)")
        return self


#: The paper's form (the ablation people ask for): ``transfer.init=centroid transfer.loss_points=centroid
#: transfer.target_mode=relative``.
PAPER = TransferConfig(init="centroid", loss_points="centroid", target_mode="relative")
