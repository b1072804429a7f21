"""sync4d.sim: the simulators a transfer steps (group ``sim``): ``mpm_warp`` (differentiable MLS-MPM on Warp: the
material, the held drive, velocity fields per group of touching parts), ``kinematic`` (each part moved rigidly by
its drive: the physics-free reference) and ``lbs`` (linear blend skinning: point-wise deformation); plus control
points, the Gaussians' deformation from a simulated particle set, and the shared physics helpers (grids, Lame
parameters, volumes)."""
