"""The transfer stage's options: how each frame pair is initialised and supervised (paper Sec. 3.4)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass
class TransferConfig:
    """Options of the frame-pair optimisation; the one source of their defaults (``transfer.*`` in the config).

    Attributes:
        init: initial velocities: ``rigid`` (each particle on its bone's rigid velocity field
            (T_rel x - x) / (N dt), with the matching APIC matrix) or ``centroid`` (the paper: one velocity per
            part from its bone centre's displacement, which turns no part).
        loss_points: what the L1 loss compares: ``particles`` (every particle with its part's pose),
            ``anchors`` (the part centroid and six half-space centroids) or ``centroid`` (the paper).
        target_mode: ``absolute`` (the rest anchors moved by the reference's pose at t+1: drift is corrected)
            or ``relative`` (the paper: the current anchors moved by the reference's step; errors accumulate).
    """

    init: Literal["rigid", "centroid"] = "rigid"
    loss_points: Literal["particles", "anchors", "centroid"] = "particles"
    target_mode: Literal["absolute", "relative"] = "absolute"

    def validate(self) -> TransferConfig:
        return self


#: The paper's form (the ablation people ask for): ``transfer.init=centroid transfer.loss_points=centroid
#: transfer.target_mode=relative``.
PAPER = TransferConfig(init="centroid", loss_points="centroid", target_mode="relative")
