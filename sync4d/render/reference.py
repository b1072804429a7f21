"""The reconstructed reference as Gaussians, posed by its own bones: what the run's renders, the viewer and
the project's own filming of a reference show."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from sync4d.geometry import rgb_to_sh_dc, skinned_positions
from sync4d.io.mesh import mesh_to_gaussians
from sync4d.types import Reference, TargetGaussians


def reference_gaussians(reference: Reference, num_frames: int, *, count: int = 3000) -> tuple[TargetGaussians, np.ndarray, np.ndarray]:
    """The reference's rest surface as Gaussians, posed for every output frame (looped) by its own skinning.

    Returns:
        The rest Gaussians, world means (T, N, 3) and covariances (T, N, 3, 3).
    """
    if reference.rest_faces is not None and len(reference.rest_faces):
        rest = mesh_to_gaussians(reference.rest_vertices, reference.rest_faces, num_surface=count,
                                 vertex_colors=reference.vertex_colors, name=reference.name)
    else:
        n = len(reference.rest_vertices)
        size = 0.01 * np.linalg.norm(np.ptp(reference.rest_vertices, axis=0))
        colors = reference.vertex_colors if reference.vertex_colors is not None else np.full((n, 3), 0.6)
        rest = TargetGaussians(
            means=reference.rest_vertices.astype(np.float32), quats=np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (n, 1)),
            log_scales=np.full((n, 3), np.log(size), np.float32), opacity_logits=np.full(n, 2.0, np.float32),
            sh=rgb_to_sh_dc(colors).astype(np.float32),
        )
    weights = reference.skinning[reference_nearest(reference, rest.means)]
    means, covs = [], []
    rest_cov = rest.covariances()
    for t in range(num_frames):
        i = t % reference.num_frames
        x = skinned_positions(rest.means.astype(np.float64), weights, reference.bone_transforms[i])
        blended = np.einsum("nb,bij->nij", weights, reference.bone_transforms[i][:, :3, :3])
        G = reference.global_transforms[i]
        means.append(x @ G[:3, :3].T + G[:3, 3])
        R = G[:3, :3] @ blended
        covs.append(R @ rest_cov @ np.swapaxes(R, 1, 2))
    return rest, np.stack(means), np.stack(covs)


def reference_nearest(reference: Reference, points: np.ndarray) -> np.ndarray:
    """(M,) index of the nearest reference rest vertex of each of (M, 3) rest points [m]."""
    return cKDTree(reference.rest_vertices).query(points)[1]
