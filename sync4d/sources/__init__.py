"""Sources read from files (groups ``reference`` and ``target``): reference inputs (mesh sequences, Lab4D
exports, BVH / joint positions / DeepMimic mocap, glTF animations, videos with their front end) and targets
(a mesh, a 3DGS ``.ply`` with floater removal)."""
