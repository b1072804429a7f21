"""Real spherical harmonics for view-dependent Gaussian colours (the Inria 3DGS convention).

Colour of a Gaussian seen along the unit direction ``d`` (from the camera centre to the Gaussian's mean,
in world coordinates) is ``RGB = max(0, 0.5 + sum_k c_k Y_k(d))`` with K = (degree + 1)^2 coefficients
per channel, ordered and signed exactly as in 3DGS / gsplat so that trained ``.ply`` files render the same.
"""

from __future__ import annotations

import numpy as np
import torch

from sync4d.geometry import SH_C0

SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_degree_from_count(num_coeffs: int) -> int:
    """Degree of a set of SH coefficients: K = (degree + 1)^2, K in (1, 4, 9, 16).

    Raises:
        ValueError: K is not a supported coefficient count.
    """
    for degree in range(4):
        if (degree + 1) ** 2 == num_coeffs:
            return degree
    raise ValueError(f"expected 1, 4, 9 or 16 SH coefficients (degree 0-3), got {num_coeffs}")


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor, degree: int | None = None) -> torch.Tensor:
    """Evaluate SH colours for view directions (without the +0.5 offset).

    Args:
        sh: (N, K, 3) coefficients, K = (d + 1)^2 for d in 0..3.
        dirs: (N, 3) unit view directions (camera centre -> Gaussian) in world coordinates.
        degree: highest degree to use (<= the degree held by ``sh``); None uses all coefficients.

    Returns:
        (N, 3) sum_k c_k Y_k(d); add 0.5 and clamp at 0 for RGB (see :func:`sh_to_rgb`).
    """
    held = sh_degree_from_count(sh.shape[1])
    degree = held if degree is None else min(int(degree), held)
    result = SH_C0 * sh[:, 0]
    if degree == 0:
        return result
    x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
    result = result - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
    if degree == 1:
        return result
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    result = (
        result
        + SH_C2[0] * xy * sh[:, 4]
        + SH_C2[1] * yz * sh[:, 5]
        + SH_C2[2] * (2.0 * zz - xx - yy) * sh[:, 6]
        + SH_C2[3] * xz * sh[:, 7]
        + SH_C2[4] * (xx - yy) * sh[:, 8]
    )
    if degree == 2:
        return result
    return (
        result
        + SH_C3[0] * y * (3.0 * xx - yy) * sh[:, 9]
        + SH_C3[1] * xy * z * sh[:, 10]
        + SH_C3[2] * y * (4.0 * zz - xx - yy) * sh[:, 11]
        + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[:, 12]
        + SH_C3[4] * x * (4.0 * zz - xx - yy) * sh[:, 13]
        + SH_C3[5] * z * (xx - yy) * sh[:, 14]
        + SH_C3[6] * x * (xx - 3.0 * yy) * sh[:, 15]
    )


def sh_to_rgb(sh: torch.Tensor, dirs: torch.Tensor, degree: int | None = None) -> torch.Tensor:
    """(N, 3) RGB = max(0, 0.5 + SH(d)) as in 3DGS (no upper clamp: compositing may exceed 1 only if
    the coefficients say so; images are clipped when encoded)."""
    return torch.clamp_min(eval_sh(sh, dirs, degree) + 0.5, 0.0)


def sh_basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """Real SH basis values in the 3DGS order and signs: (..., K) for unit directions (..., 3), K = (degree+1)^2.

    ``eval_sh(c, d) == sum_k c_k sh_basis(d)_k`` (the same polynomials, so rotation and rendering agree).
    """
    return np.moveaxis(sh_basis_first(np.ascontiguousarray(np.moveaxis(dirs, -1, 0)), degree), 0, -1)


def sh_basis_first(dirs: np.ndarray, degree: int) -> np.ndarray:
    """:func:`sh_basis` with the axes first: (3, ...) directions -> (K, ...) values (contiguous, fast)."""
    x, y, z = dirs[0], dirs[1], dirs[2]
    out = [np.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * x * z,
                SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3.0 * xx - yy), SH_C3[1] * x * y * z, SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3.0 * yy),
        ]  # fmt: skip
    return np.stack(out, axis=0)


def _sample_directions(count: int) -> np.ndarray:
    """(count, 3) unit directions spread over the sphere (Fibonacci lattice): fixed, well conditioned."""
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


#: Directions at which a rotated colour function is sampled to solve for its coefficients (>= 2l+1 = 7).
_DIRS = _sample_directions(16)


def sh_rotation_blocks(rotations: np.ndarray, degree: int, *, chunk: int = 65536) -> list[np.ndarray]:
    """Per rotation and degree l = 1..degree, the (2l+1, 2l+1) matrix taking coefficients to turned ones.

    A Gaussian turned by R shows in world direction d the colour it showed in R^T d before, so the new
    coefficients c' satisfy sum_k c'_k Y_k(d) = sum_k c_k Y_k(R^T d) for every d. Each degree l is closed
    under rotation, so c'_l = D_l c_l with D_l = A_l^+ B_l(R), A_l = Y_l at fixed sample directions d_s
    and B_l(R) = Y_l at R^T d_s: exact (up to float rounding) since the 16 samples span every degree <= 3.

    Args:
        rotations: (P, 3, 3) rotation matrices.
        degree: highest SH degree (0-3).
        chunk: rotations per batch (bounds the (3, chunk, 16) temporaries).

    Returns:
        ``degree`` arrays, the l-th (P, 2l+1, 2l+1) float64.
    """
    rot = np.asarray(rotations, dtype=np.float64)
    p = len(rot)
    blocks = [np.empty((p, 2 * deg + 1, 2 * deg + 1)) for deg in range(1, degree + 1)]
    if degree == 0:
        return blocks
    pinv = [np.linalg.pinv(sh_basis(_DIRS, degree)[:, deg * deg:(deg + 1) ** 2]) for deg in range(1, degree + 1)]
    for start in range(0, p, chunk):
        stop = min(start + chunk, p)
        turned = np.einsum("nji,sj->ins", rot[start:stop], _DIRS)  # R^T d_s, (3, n, S)
        basis = sh_basis_first(turned, degree)  # (K, n, S)
        for deg in range(1, degree + 1):
            blocks[deg - 1][start:stop] = pinv[deg - 1][None] @ np.moveaxis(basis[deg * deg:(deg + 1) ** 2], 0, -1)
    return blocks


def rotate_sh(
    sh: np.ndarray, rotations: np.ndarray, *, index: np.ndarray | None = None, chunk: int = 262144
) -> np.ndarray:
    """Coefficients of each Gaussian's colour after the Gaussian turns (see :func:`sh_rotation_blocks`).

    The DC term (degree 0) is unchanged.

    Args:
        sh: (N, K, 3) coefficients, K in (1, 4, 9, 16).
        rotations: (P, 3, 3) rotation matrices: one per Gaussian (P = N, ``index`` None), or shared, e.g.
            one per control point, with ``index`` (N,) picking each Gaussian's (the matrices are then
            built P times, not N: millions of Gaussians turn at the cost of their control points).
        index: (N,) int rotation of each Gaussian, or None.
        chunk: Gaussians per batch (bounds the gathered (chunk, 7, 7) temporaries).

    Returns:
        (N, K, 3) rotated coefficients, the dtype of ``sh``.
    """
    degree = sh_degree_from_count(sh.shape[1])
    out = sh.copy()
    if degree == 0:
        return out
    rot = np.asarray(rotations, dtype=np.float64)
    if rot.shape == (3, 3):
        rot, index = rot[None], np.zeros(len(sh), dtype=np.int64)
    blocks = sh_rotation_blocks(rot, degree)
    n = sh.shape[0]
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        pick = slice(start, stop) if index is None else index[start:stop]
        for deg, D in enumerate(blocks, start=1):
            block = slice(deg * deg, (deg + 1) ** 2)
            out[start:stop, block] = D[pick] @ sh[start:stop, block].astype(np.float64)
    return out
