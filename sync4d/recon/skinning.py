"""Pure maths of Gaussian bones and linear blend skinning (NumPy and torch).

Conventions (see :mod:`sync4d.types`): rigid transforms are (4, 4) matrices acting on column vectors;
bone transforms map the rest pose to frame t. A Gaussian bone b has a centre c_b [m] and a covariance
Sigma_b = R_b diag(sigma_b^2) R_b^T [m^2]; the skinning weights of a point x are
``W(x) = softmax_b(-d_M(x, b) + W_delta(x))`` with the squared Mahalanobis distance
``d_M(x, b) = (x - c_b)^T Sigma_b^{-1} (x - c_b)`` (paper Eq. 3, following BANMo).
"""

from __future__ import annotations

import numpy as np
import torch

from sync4d.rng import init_linear_layers, torch_generator

# ----------------------------------------------------------------------------------------------------
# Point-set clustering and rigid alignment (NumPy)
# ----------------------------------------------------------------------------------------------------


def farthest_point_sample(points: np.ndarray, k: int, *, start: int = 0) -> np.ndarray:
    """Indices of ``k`` points chosen by greedy farthest-point sampling.

    Args:
        points: (N, 3) points [m].
        k: how many to pick, 1 <= k <= N.
        start: index of the first pick (deterministic).

    Returns:
        (k,) int64 indices into ``points``, all distinct.
    """
    n = len(points)
    if not 1 <= k <= n:
        raise ValueError(f"farthest_point_sample: k={k} must lie in [1, {n}]")
    chosen = np.empty(k, dtype=np.int64)
    chosen[0] = start
    dist = np.linalg.norm(points - points[start], axis=1)
    for i in range(1, k):
        chosen[i] = int(np.argmax(dist))
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[i]], axis=1))
    return chosen


def kmeans(points: np.ndarray, k: int, *, iterations: int = 30, features: np.ndarray | None = None) -> np.ndarray:
    """Lloyd's k-means seeded by farthest-point sampling (deterministic).

    Args:
        points: (N, 3) points [m].
        k: number of clusters.
        iterations: Lloyd iterations.
        features: (N, D) vectors to cluster instead of ``points`` (e.g. positions concatenated with
            per-frame displacements, so that parts which move differently separate); default ``points``.

    Returns:
        (N,) int64 cluster label in [0, k); every cluster is non-empty.
    """
    feats = points if features is None else features
    centres = feats[farthest_point_sample(feats, k)].copy()
    labels = np.zeros(len(feats), dtype=np.int64)
    for _ in range(iterations):
        d2 = ((feats[:, None, :] - centres[None]) ** 2).sum(-1) if len(feats) * k < 4_000_000 else _chunked_d2(feats, centres)
        labels = np.argmin(d2, axis=1)
        for j in range(k):
            members = labels == j
            if members.any():
                centres[j] = feats[members].mean(0)
            else:  # re-seed an empty cluster at the worst-fit point so every bone owns points
                worst = int(np.argmax(d2[np.arange(len(feats)), labels]))
                centres[j] = feats[worst]
                labels[worst] = j
    return labels


def _chunked_d2(feats: np.ndarray, centres: np.ndarray, chunk: int = 20000) -> np.ndarray:
    out = np.empty((len(feats), len(centres)))
    for s in range(0, len(feats), chunk):
        out[s : s + chunk] = ((feats[s : s + chunk, None, :] - centres[None]) ** 2).sum(-1)
    return out


def rigid_inverse(transform: np.ndarray) -> np.ndarray:
    """(..., 4, 4) inverse of rigid transforms (rotation transposed, no general matrix inverse)."""
    out = np.zeros_like(transform)
    rot_t = np.swapaxes(transform[..., :3, :3], -1, -2)
    out[..., :3, :3] = rot_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rot_t, transform[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def project_to_rigid(transforms: np.ndarray) -> np.ndarray:
    """(..., 4, 4) the nearest rigid transforms (rotation part projected onto SO(3) by SVD)."""
    u, _, vt = np.linalg.svd(transforms[..., :3, :3])
    d = np.sign(np.linalg.det(u @ vt))
    fix = np.ones(u.shape[:-2] + (3,))
    fix[..., 2] = d
    out = np.array(transforms, dtype=np.float64, copy=True)
    out[..., :3, :3] = (u * fix[..., None, :]) @ vt
    out[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
    return out


# ----------------------------------------------------------------------------------------------------
# Gaussian bones and skinning (NumPy)
# ----------------------------------------------------------------------------------------------------


def bone_covariances(rotations: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """(B, 3, 3) covariances R diag(s^2) R^T [m^2] from (B, 3, 3) rotations and (B, 3) std devs [m]."""
    scaled = rotations * scales[:, None, :]
    return scaled @ np.swapaxes(scaled, 1, 2)


def mahalanobis_sq(points: np.ndarray, centers: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distances of points to Gaussian bones.

    Args:
        points: (V, 3) [m].
        centers: (B, 3) bone centres [m].
        covariances: (B, 3, 3) SPD bone covariances [m^2].

    Returns:
        (V, B) dimensionless squared distances.
    """
    inv = np.linalg.inv(covariances)
    diff = points[:, None, :] - centers[None]
    return np.einsum("vbi,bij,vbj->vb", diff, inv, diff)


def softmax_weights(logits: np.ndarray) -> np.ndarray:
    """(V, B) row-wise softmax of (V, B) logits (stable; rows sum to 1)."""
    z = logits - logits.max(axis=1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=1, keepdims=True)


def gaussian_skinning(
    points: np.ndarray, centers: np.ndarray, covariances: np.ndarray, delta: np.ndarray | None = None
) -> np.ndarray:
    """Skinning weights W = softmax(-d_M(x, bones) + delta) (paper Eq. 3).

    Args:
        points: (V, 3) [m].
        centers: (B, 3) [m].
        covariances: (B, 3, 3) [m^2].
        delta: (V, B) additive logits (the MLP correction), or None.

    Returns:
        (V, B) weights, non-negative, rows sum to 1.
    """
    logits = -mahalanobis_sq(points, centers, covariances)
    if delta is not None:
        logits = logits + delta
    return softmax_weights(logits)


def linear_blend(points: np.ndarray, weights: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """Linear blend skinning of rest points.

    Args:
        points: (V, 3) rest points [m].
        weights: (V, B) skinning weights (rows sum to 1).
        transforms: (B, 4, 4) or (T, B, 4, 4) bone transforms rest -> frame.

    Returns:
        (V, 3) or (T, V, 3) posed points [m].
    """
    blended = np.einsum("vb,...bij->...vij", weights, transforms[..., :3, :])
    return np.einsum("...vij,vj->...vi", blended[..., :3], points) + blended[..., 3]


# ----------------------------------------------------------------------------------------------------
# Torch versions used inside optimisation loops
# ----------------------------------------------------------------------------------------------------


def rot6d_to_matrix(d6: torch.Tensor) -> torch.Tensor:
    """(..., 6) continuous 6D rotation representation (Zhou et al. 2019) -> (..., 3, 3) rotation.

    The 6 numbers are the first two columns of the matrix, Gram-Schmidt orthonormalised.
    """
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = torch.nn.functional.normalize(a1, dim=-1)
    b2 = torch.nn.functional.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def matrix_to_rot6d(rot: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation -> (..., 6): its first two columns (inverse of :func:`rot6d_to_matrix`)."""
    return np.concatenate([rot[..., :, 0], rot[..., :, 1]], axis=-1)


def mahalanobis_sq_torch(
    points: torch.Tensor, centers: torch.Tensor, rotations: torch.Tensor, log_scales: torch.Tensor
) -> torch.Tensor:
    """(V, B) squared Mahalanobis distances to Gaussian bones, differentiable.

    Args:
        points: (V, 3) [m].
        centers: (B, 3) [m].
        rotations: (B, 3, 3) bone axes (columns).
        log_scales: (B, 3) natural log of the per-axis standard deviations [log m].
    """
    diff = points[:, None, :] - centers[None]  # (V, B, 3)
    local = torch.einsum("vbi,bij->vbj", diff, rotations)  # coordinates along each bone's axes
    return ((local * torch.exp(-log_scales)[None]) ** 2).sum(-1)


def linear_blend_torch(points: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """LBS: (V, 3) rest points, (V, B) weights, (T, B, 3, 4) transforms -> (T, V, 3) posed points."""
    blended = torch.einsum("vb,tbij->tvij", weights, transforms)
    return torch.einsum("tvij,vj->tvi", blended[..., :3], points) + blended[..., 3]


class SkinningDelta(torch.nn.Module):
    """Coordinate MLP giving the skinning logit correction W_delta(x) (paper Eq. 3).

    Input points are normalised by a fixed centre and scale, encoded with sin/cos at ``frequencies``
    octaves, passed through ``layers`` hidden layers of ``width`` (softplus), and mapped to B logits.
    The last layer starts at zero so the initial weights are the pure Gaussian-bone weights.
    """

    center: torch.Tensor  # a registered buffer (moves with .to(), not trained)

    def __init__(self, bones: int, *, center: np.ndarray, scale: float, width: int = 64, layers: int = 2,
                 frequencies: int = 4, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.register_buffer("center", torch.as_tensor(np.asarray(center, dtype=np.float32)))
        self.scale = float(scale)
        self.frequencies = int(frequencies)
        in_dim = 3 + 6 * self.frequencies
        mods: list[torch.nn.Module] = []
        for _ in range(layers):
            mods += [torch.nn.Linear(in_dim, width), torch.nn.Softplus(beta=10.0)]
            in_dim = width
        self.body = torch.nn.Sequential(*mods)
        self.head = torch.nn.Linear(in_dim, bones)
        init_linear_layers(self.body, generator if generator is not None else torch_generator(0))
        torch.nn.init.zeros_(self.head.weight)
        torch.nn.init.zeros_(self.head.bias)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """(V, 3) points [m] -> (V, B) logit corrections."""
        x = (points - self.center) / self.scale
        feats = [x]
        for k in range(self.frequencies):
            feats += [torch.sin((2.0**k) * np.pi * x), torch.cos((2.0**k) * np.pi * x)]
        return self.head(self.body(torch.cat(feats, dim=-1)))
