"""Real spherical harmonics for view-dependent Gaussian colours (the Inria 3DGS convention).

Colour of a Gaussian seen along the unit direction ``d`` (from the camera centre to the Gaussian's mean,
in world coordinates) is ``RGB = max(0, 0.5 + sum_k c_k Y_k(d))`` with K = (degree + 1)^2 coefficients
per channel, ordered and signed exactly as in 3DGS / gsplat so that trained ``.ply`` files render the same.
"""

from __future__ import annotations

import torch

SH_C0 = 0.28209479177387814
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


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """(N, 3) RGB -> (N, 1, 3) degree-0 coefficients such that ``sh_to_rgb`` gives back ``rgb``."""
    return ((rgb - 0.5) / SH_C0)[:, None, :]
