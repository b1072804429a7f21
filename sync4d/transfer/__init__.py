"""The transfer stage: frame-pair training of a delta-velocity field through the simulator (paper Sec. 3.4).

The simulator prepares and rolls out (:mod:`sync4d.sim`); this stage owns the loop: initial velocities,
the loss, the optimiser and the advance from one frame pair to the next (:mod:`sync4d.transfer.loop`).
"""

from sync4d.transfer.config import PAPER, TransferConfig
from sync4d.transfer.loop import (
    Particles,
    PartLoss,
    anchor_points,
    anchor_weights,
    apply_rigid,
    initial_velocity,
    make_particles,
    run_mpm_transfer,
)

__all__ = ["PAPER", "Particles", "PartLoss", "TransferConfig", "anchor_points", "anchor_weights", "apply_rigid",
           "initial_velocity", "make_particles", "run_mpm_transfer"]
