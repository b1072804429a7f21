"""Move 3D Gaussians by simulated positions and deformation gradients (PhysGaussian's update).

A Gaussian carried by a deformation gradient F has covariance F Sigma F^T; we store it back in the
3DGS parameterisation (rotation quaternion + log scales) by a symmetric eigendecomposition.
"""

from __future__ import annotations

import numpy as np

from sync4d.types import TargetGaussians, matrix_to_quat


def covariance_to_quat_scale(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) SPD covariances -> (N, 4) wxyz quats and (N, 3) standard deviations [m].

    Eigenvectors form the rotation (a column is flipped where needed so det = +1).
    """
    sym = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    eigval, eigvec = np.linalg.eigh(sym)
    flip = np.linalg.det(eigvec) < 0
    eigvec[flip, :, 2] *= -1.0
    return matrix_to_quat(eigvec), np.sqrt(np.maximum(eigval, 1e-20))


def deform_gaussians(
    gaussians: TargetGaussians,
    positions: np.ndarray,
    deformation: np.ndarray | None = None,
    global_transform: np.ndarray | None = None,
) -> TargetGaussians:
    """The Gaussians moved to ``positions``, shaped by ``deformation``, then moved by ``global_transform``.

    Args:
        gaussians: the rest Gaussians (N of them).
        positions: (N, 3) new centres [m] (before the global transform).
        deformation: (N, 3, 3) deformation gradients F, or None to keep the rest shapes.
        global_transform: (4, 4) rigid G_t applied last, or None.

    Returns:
        A new :class:`TargetGaussians` (float32 arrays, colours and opacities unchanged).
    """
    means = np.asarray(positions, dtype=np.float64)
    quats, log_scales = gaussians.quats, gaussians.log_scales
    cov = None
    if deformation is not None:
        cov = deformation @ gaussians.covariances() @ np.swapaxes(deformation, 1, 2)
    if global_transform is not None:
        rot = global_transform[:3, :3]
        means = means @ rot.T + global_transform[:3, 3]
        if cov is None:
            cov = gaussians.covariances()
        cov = rot @ cov @ rot.T
    if cov is not None:
        q, s = covariance_to_quat_scale(cov)
        quats, log_scales = q.astype(np.float32), np.log(s).astype(np.float32)
    return gaussians.replace(means=means.astype(np.float32), quats=quats, log_scales=log_scales)
