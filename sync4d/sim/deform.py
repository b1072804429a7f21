"""Move 3D Gaussians by simulated positions and deformation gradients (PhysGaussian's update).

A Gaussian carried by a deformation gradient F has covariance F Sigma F^T; we store it back in the
3DGS parameterisation (rotation quaternion + log scales) by a symmetric eigendecomposition. Its
view-dependent colour turns with the rotation part of F (the polar decomposition F = R U, as
PhysGaussian does) and with the global transform: spherical harmonics of degree 1-3 are rotated by
:func:`sync4d.render.sh.rotate_sh`, so a turning part shows its highlights where they belong.

Deformation gradients may be given once per control point with an ``index`` from each Gaussian to its
point: the rotations and SH rotation matrices are then built per point, which keeps a frame of millions
of Gaussians at a few seconds.
"""

from __future__ import annotations

import numpy as np

from sync4d.errors import InputError
from sync4d.render.sh import rotate_sh
from sync4d.types import TargetGaussians
from sync4d.geometry import matrix_to_quat, nearest_rotation


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
    *,
    index: np.ndarray | None = None,
) -> TargetGaussians:
    """The Gaussians moved to ``positions``, shaped by ``deformation``, then moved by ``global_transform``.

    Args:
        gaussians: the rest Gaussians (N of them).
        positions: (N, 3) new centres [m] (before the global transform).
        deformation: (N, 3, 3) deformation gradients F, or (P, 3, 3) with ``index``; None keeps the rest
            shapes.
        global_transform: (4, 4) rigid G_t applied last, or None.
        index: (N,) int, the row of ``deformation`` of each Gaussian (e.g. its control point), or None.

    Returns:
        A new :class:`TargetGaussians` (float32 arrays; SH rotated with R(F) and G_t; opacities unchanged).
    """
    means = np.asarray(positions, dtype=np.float64)
    if means.shape != (gaussians.num, 3):
        raise InputError(f"deform_gaussians: positions must be ({gaussians.num}, 3), got {means.shape}")
    quats, log_scales, sh = gaussians.quats, gaussians.log_scales, gaussians.sh
    cov = None
    turn = None  # (P, 3, 3) rotation of each row of ``deformation`` (or one shared (1, 3, 3))
    pick = np.zeros(gaussians.num, dtype=np.int64)
    if deformation is not None:
        F = np.asarray(deformation, dtype=np.float64)
        pick = np.arange(gaussians.num) if index is None else np.asarray(index, dtype=np.int64)
        Fg = F[pick] if index is not None else F
        cov = Fg @ gaussians.covariances() @ np.swapaxes(Fg, 1, 2)
        turn = nearest_rotation(F)
    if global_transform is not None:
        rot = np.asarray(global_transform, dtype=np.float64)[:3, :3]
        means = means @ rot.T + global_transform[:3, 3]
        if cov is None:
            cov = gaussians.covariances()
        cov = rot @ cov @ rot.T
        turn = rot[None] if turn is None else rot @ turn
    if cov is not None:
        q, s = covariance_to_quat_scale(cov)
        quats, log_scales = q.astype(np.float32), np.log(s).astype(np.float32)
    if turn is not None and gaussians.sh.shape[1] > 1:
        sh = rotate_sh(gaussians.sh, turn, index=pick)
    return gaussians.replace(means=means.astype(np.float32), quats=quats, log_scales=log_scales, sh=sh)
