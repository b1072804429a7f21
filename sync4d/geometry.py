"""Geometry used across the library, each in one place: rotations (quaternions, axis-angle), rigid
transforms and fits, linear blend skinning, the interpolation of a part's pose within a frame, and the
degree-0 spherical-harmonic constant that maps colours to 3DGS coefficients. NumPy functions, and a torch
twin (``..._torch``) where an optimiser needs the gradient (torch is imported only by those)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

if TYPE_CHECKING:
    import torch

#: A NumPy array or a torch tensor (functions written once for both).
ArrayT = TypeVar("ArrayT", bound=Any)

#: Y_0^0 = 1 / (2 sqrt(pi)): a 3DGS colour is RGB = 0.5 + SH_C0 * f_dc.
SH_C0 = 0.28209479177387814


#: The band either side of a seam between two parts, as a share of the target's bounding-box diagonal, that is the
#: joint's rather than either part's: the held drive's rig blends the two parts' motions over it
#: (``sim.blend_band``), and a part's follow fit leaves it out (:func:`sync4d.run.metrics.follow_error`).
SEAM_BAND_OF_DIAGONAL = 0.03


def rgb_to_sh_dc(rgb: ArrayT) -> ArrayT:
    """(N, 3) RGB in [0, 1] -> (N, 1, 3) degree-0 SH coefficients (inverse of 0.5 + SH_C0 * c); NumPy arrays
    and torch tensors alike (differentiable)."""
    return ((rgb - 0.5) / SH_C0)[:, None, :]


def quat_to_matrix(quats: np.ndarray) -> np.ndarray:
    """(N, 4) wxyz quaternions (any length) -> (N, 3, 3) rotation matrices (float64)."""
    q = np.asarray(quats, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def gaussian_covariances(scales: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """(N, 3, 3) covariances Sigma = R S S R^T [m^2] from per-axis scales (N, 3) [m] and wxyz quaternions (N, 4)."""
    scaled = quat_to_matrix(quats) * np.asarray(scales, dtype=np.float64)[:, None, :]
    return scaled @ np.swapaxes(scaled, 1, 2)


def matrix_to_quat(mats: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices -> (N, 4) wxyz unit quaternions with w >= 0 (float64)."""
    m = np.asarray(mats, dtype=np.float64)
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = np.stack(
        [
            np.stack([1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            np.stack([m[..., 2, 1] - m[..., 1, 2], 1 + 2 * m[..., 0, 0] - trace, m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            np.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 + 2 * m[..., 1, 1] - trace, m[..., 1, 2] + m[..., 2, 1]], -1),
            np.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 + 2 * m[..., 2, 2] - trace], -1),
        ],
        -2,
    )
    # Pick the numerically largest candidate (Shepperd's method) per matrix.
    diag = np.stack([trace, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    best = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def rotation_about_axis(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations by ``angles`` [rad] (any shape) about one unit ``axis`` (3,) (Rodrigues)."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    a = np.asarray(angles, dtype=np.float64)[..., None, None]
    return np.eye(3) + np.sin(a) * K + (1.0 - np.cos(a)) * (K @ K)


def rotation_vector_to_matrix(v: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors (axis times angle [rad]) -> (..., 3, 3) rotations, exact at zero."""
    v = np.asarray(v, dtype=np.float64)
    theta = np.linalg.norm(v, axis=-1)[..., None, None]
    zeros = np.zeros(v.shape[:-1])
    K = np.stack([np.stack([zeros, -v[..., 2], v[..., 1]], -1),
                  np.stack([v[..., 2], zeros, -v[..., 0]], -1),
                  np.stack([-v[..., 1], v[..., 0], zeros], -1)], -2)
    safe = np.where(theta > 1e-12, theta, 1.0)
    a = np.where(theta > 1e-12, np.sin(theta) / safe, 1.0)
    b = np.where(theta > 1e-12, (1.0 - np.cos(theta)) / safe**2, 0.5)
    return np.eye(3) + a * K + b * (K @ K)


def rotation_vector_to_matrix_torch(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) rotation vectors [rad] -> (..., 3, 3) rotations (Rodrigues), differentiable; the angle is
    clamped at 1e-8 rad so the axis (and the gradient) stays finite at zero."""
    import torch

    theta = v.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    k = v / theta
    kx, ky, kz = k.unbind(-1)
    zero = torch.zeros_like(kx)
    kmat = torch.stack([zero, -kz, ky, kz, zero, -kx, -ky, kx, zero], -1).reshape(v.shape[:-1] + (3, 3))
    th = theta[..., None]
    eye = torch.eye(3, dtype=v.dtype).expand(kmat.shape)
    return eye + torch.sin(th) * kmat + (1 - torch.cos(th)) * (kmat @ kmat)


def matrix_to_rotation_vector(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) rotation vectors (angle in [0, pi]), via the quaternion."""
    q = matrix_to_quat(R)  # w >= 0
    s = np.linalg.norm(q[..., 1:], axis=-1)
    angle = 2.0 * np.arctan2(s, q[..., 0])
    scale = np.where(s > 1e-12, angle / np.where(s > 1e-12, s, 1.0), 2.0)
    return q[..., 1:] * scale[..., None]


def skew_matrices(w: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices [w]x of (..., 3) vectors: [w]x a = w x a."""
    w = np.asarray(w, dtype=np.float64)
    out = np.zeros((*w.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    return out - np.swapaxes(out, -1, -2)


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """(..., 3, 3) the rotations closest to ``matrix`` (..., 3, 3) in the Frobenius norm: the R of the polar
    decomposition F = R U (U symmetric positive semi-definite).

    From the SVD F = W S V^T, R = W V^T; an improper result (det -1, e.g. an inverted F) has W's last column
    flipped so R stays a rotation.
    """
    W, _, Vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    flip = np.linalg.det(W @ Vt) < 0
    W[flip, :, 2] *= -1.0
    return W @ Vt


def best_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) rotation R minimising sum |b_i - R a_i|^2 over directions a, b (N, 3), no translation (Wahba's
    problem; :func:`rigid_fit` is the version with translation)."""
    return nearest_rotation(b.T @ a)


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """(...) the angle [deg] of rotations (..., 3, 3).

    From atan2(|skew part|, trace - 1) rather than arccos of the trace: arccos loses half the digits near 0 deg
    (a rounding of 1e-16 in the trace reads as 1.6e-6 deg), atan2 keeps them at every angle.
    """
    R = np.asarray(R, dtype=np.float64)
    cos2 = np.trace(R, axis1=-2, axis2=-1) - 1.0
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    return np.degrees(np.arctan2(np.linalg.norm(skew, axis=-1), cos2))


def bbox_diagonal(points: np.ndarray) -> float:
    """Length of the axis-aligned bounding-box diagonal of (N, 3) points [m]."""
    return float(np.linalg.norm(np.ptp(points, axis=0)))


def part_centroids(x: np.ndarray, parts: np.ndarray, num_parts: int, mass: np.ndarray | None = None) -> np.ndarray:
    """(B, 3) mass centroids of each part of (N, 3) points (NaN rows for empty parts)."""
    w = np.ones(len(x)) if mass is None else np.asarray(mass, dtype=np.float64)
    sums = np.zeros((num_parts, 3))
    np.add.at(sums, parts, x * w[:, None])
    totals = np.bincount(parts, weights=w, minlength=num_parts)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums / totals[:, None]


def apply_rigid(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) points [m] mapped by one (4, 4) transform."""
    return points @ transform[:3, :3].T + transform[:3, 3]


def rigid_fit(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Best rigid transform (rotation + translation, no scale) taking ``src`` onto ``dst`` (Kabsch).

    Args:
        src: (..., N, 3) source points [m].
        dst: (..., N, 3) target points [m], same correspondence.
        weights: (..., N) non-negative weights, or None for uniform.

    Returns:
        (..., 4, 4) transforms T with ``dst ~= R src + t``, det(R) = +1.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    w = np.ones(src.shape[:-1]) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / np.maximum(w.sum(-1, keepdims=True), 1e-12)
    mu_s = (w[..., None] * src).sum(-2)
    mu_d = (w[..., None] * dst).sum(-2)
    cov = np.einsum("...n,...ni,...nj->...ij", w, dst - mu_d[..., None, :], src - mu_s[..., None, :])
    u, _, vt = np.linalg.svd(cov)
    # Flip the last singular direction when needed so that R is a rotation, not a reflection.
    d = np.sign(np.linalg.det(u @ vt))
    d = np.where(d == 0, 1.0, d)
    fix = np.ones(u.shape[:-2] + (3,))
    fix[..., 2] = d
    rot = (u * fix[..., None, :]) @ vt
    out = np.zeros(src.shape[:-2] + (4, 4))
    out[..., :3, :3] = rot
    out[..., :3, 3] = mu_d - np.einsum("...ij,...j->...i", rot, mu_s)
    out[..., 3, 3] = 1.0
    return out


def skinned_positions(rest: np.ndarray, skinning: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """(N, 3) linear blend skinning of rest points [m] with (N, B) weights and (B, 4, 4) transforms."""
    blended = np.einsum("nb,bij->nij", skinning, transforms)
    return np.einsum("nij,nj->ni", blended[:, :3, :3], rest) + blended[:, :3, 3]
