"""File formats in and out, with no algorithm: 3DGS ``.ply``, meshes, video clips and masks, mocap (BVH, joint
positions, DeepMimic), Lab4D exports, glTF, the compact ``.s4d`` 4D sequence, the exports of a run (USD, glb,
npz), and atomic writes."""
