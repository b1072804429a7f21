"""``sim=mpm_warp``: differentiable MLS-MPM on NVIDIA Warp.

drive (each part's rest geometry and its rig at every substep: the drive held through the frame) and fields (which
velocity field each particle uses: touching parts that are not joined do not glue) <- model (what a rollout does
not change; particle state; scratch) <- kernels (the Warp kernels) <- solver (a substep forward and in reverse; a
rollout) <- bridge (the rollout as a torch autograd Function) <- budget (CFL, substeps, checkpoints, threads) <-
simulator (the registered component).
"""

from sync4d.sim.mpm_warp.model import MPMModel, WarpState
from sync4d.sim.mpm_warp.simulator import MPMWarp

__all__ = ["MPMModel", "MPMWarp", "WarpState"]
