"""Order-free soft splatting of isotropic Gaussians at sampled pixels, for ``recon=video``'s losses.

Why not the project's full renderer (``render=splat_torch``): the fit evaluates its losses on a few
thousand sampled pixels per frame for many frames per step, and needs two order-free quantities that
a front-to-back compositor does not give directly:

* a soft silhouette ``S(p) = 1 - prod_i (1 - alpha_i(p))`` (independent of depth order), and
* soft front-most weights ``w_i(p) ∝ alpha_i(p) exp(-z_i / tau)`` (a SoftRas-style soft z-buffer) used
  to render per-Gaussian quantities such as 2D motion or part labels.

``alpha_i(p) = o_i exp(-|p - u_i|^2 / (2 s_i^2))`` with ``s_i = f sigma_i / z_i`` the projected
standard deviation [px] (floored at ``min_sigma_px``).
"""

from __future__ import annotations

import torch


def project_points(points_world: torch.Tensor, K: torch.Tensor, world_to_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pinhole projection (OpenCV axes).

    Args:
        points_world: (..., N, 3) [m].
        K: (3, 3) intrinsics [px].
        world_to_cam: (4, 4).

    Returns:
        (uv (..., N, 2) pixel coordinates [px], z (..., N) camera depth [m]).
    """
    pc = points_world @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    z = pc[..., 2].clamp_min(1e-6)
    u = K[0, 0] * pc[..., 0] / z + K[0, 2]
    v = K[1, 1] * pc[..., 1] / z + K[1, 2]
    return torch.stack([u, v], -1), pc[..., 2]


def splat_alpha(
    uv: torch.Tensor, sigma_px: torch.Tensor, opacity: torch.Tensor, pixels: torch.Tensor
) -> torch.Tensor:
    """Per-Gaussian opacity at sampled pixels.

    Args:
        uv: (F, N, 2) projected centres [px].
        sigma_px: (F, N) projected std-devs [px].
        opacity: (N,) in (0, 1).
        pixels: (F, P, 2) sampled pixel coordinates [px].

    Returns:
        (F, N, P) alpha in [0, 0.99].
    """
    # |p - u|^2 = |p|^2 + |u|^2 - 2 u.p as one batched matmul: no (F, N, P, 2) temporary.
    d2 = ((uv**2).sum(-1)[..., None] + (pixels**2).sum(-1)[:, None, :] - 2.0 * uv @ pixels.transpose(1, 2)).clamp_min(0.0)
    return (opacity[None, :, None] * torch.exp(-0.5 * d2 / sigma_px[..., None] ** 2)).clamp_max(0.99)


def front_weights(alpha: torch.Tensor, z: torch.Tensor, tau: float) -> torch.Tensor:
    """(F, N, P) soft front-most weights: alpha_i exp(-(z_i - z_min) / tau), normalised over i.

    Args:
        alpha: (F, N, P).
        z: (F, N) depths [m].
        tau: depth softness [m]; smaller approaches a hard z-buffer.
    """
    logit = torch.log(alpha + 1e-12) - (z - z.min(dim=1, keepdim=True).values)[..., None] / tau
    return torch.softmax(logit, dim=1)


def composite_weights(alpha: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """(F, N, P) front-to-back alpha-compositing weights T_i alpha_i, as a 3DGS rasteriser blends.

    T_i = prod over the Gaussians j nearer than i of (1 - alpha_j). Unlike :func:`front_weights`, a
    surface hidden behind an opaque one gets (almost) no weight however many Gaussians it has; the
    order is each frame's global depth order of the Gaussian centres, as in 3DGS.

    Args:
        alpha: (F, N, P) in [0, 0.99].
        z: (F, N) depths [m].
    """
    order = torch.argsort(z, dim=1)
    a = torch.take_along_dim(alpha, order[..., None], dim=1)
    log_t = torch.cumsum(torch.log1p(-a), dim=1)
    log_t = torch.cat([torch.zeros_like(log_t[:, :1]), log_t[:, :-1]], dim=1)  # exclusive: light reaching i
    w_sorted = torch.exp(log_t) * a
    return torch.zeros_like(alpha).scatter_(1, order[..., None].expand_as(alpha), w_sorted)
