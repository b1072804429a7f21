"""The transfer stage (paper Sec. 3.4): it owns the frame-pair loop; a simulator only steps.

config (the stage's options) <- motion (the driving motion in the target's frame) <- particles (control
points, bone cores) <- loss (anchors, targets, initial velocities) <- loop (the loop and its optimiser) <-
budget (the simulation's size and cost, before it runs).
"""

from sync4d.transfer.config import PAPER, TransferConfig
from sync4d.transfer.loop import run_transfer

__all__ = ["PAPER", "TransferConfig", "run_transfer"]
