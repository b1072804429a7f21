"""``sim=mpm_warp``: differentiable MLS-MPM on NVIDIA Warp.

model (what a rollout does not change; particle state; scratch) <- kernels (the Warp kernels) <- solver (a
substep forward and in reverse; a rollout) <- bridge (the rollout as a torch autograd Function) <- budget
(CFL, substeps, checkpoints, threads) <- simulator (the registered component).
"""

from sync4d.sim.mpm_warp.model import MPMModel, WarpState
from sync4d.sim.mpm_warp.simulator import MPMWarp

__all__ = ["MPMModel", "MPMWarp", "WarpState"]
