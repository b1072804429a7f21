"""A bounded, well-spread sample of a splat's centres: the target "surface" for matching and motion.

Feature extraction costs O(V) to O(V^1.5) in the surface points V, so a splat of millions of Gaussians
must not pass every centre (a 1.5 M-Gaussian target was still computing features after 9 minutes at
13.7 GB). Random subsampling follows the density (dense regions crowd the sample, thin limbs vanish);
a voxel-grid sample keeps one point per occupied voxel instead, so the sample covers the shape evenly:
the voxel side is searched (bisection on its log) until the occupied voxels number about ``max_points``,
and each voxel is represented by its most opaque Gaussian (deterministic; faint fill is not surface).
"""

from __future__ import annotations

import numpy as np

from sync4d.interfaces import TargetWithSurface
from sync4d.types import TargetGaussians

#: Surface points handed to matching for a target without a mesh (``match_parts``'s own bound).
SURFACE_POINTS = 6000
#: Points per sample point kept before the voxel search (by stride).
PRESAMPLE = 30
#: Gaussians fainter than this are not surface when enough brighter ones exist (as in ``match``).
MIN_OPACITY = 0.1


def area_samples(tri: np.ndarray, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
    """``count`` points uniform by area on triangles ``tri`` (F, 3, 3): their face index (count,) and
    barycentric weights (count, 3) (a point is ``bary @ tri[face]``; the same samples follow a deforming mesh).
    None when the triangles have no area (the caller says what that means for its input)."""
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not area.sum() > 0:
        return None
    face = rng.choice(len(tri), size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    return face, np.stack([1 - s, s * (1 - r2), s * r2], axis=1)


def area_points(tri: np.ndarray, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
    """``count`` points (count, 3) uniform by area on triangles ``tri`` (F, 3, 3) and the face (count,) each lies
    on (:func:`area_samples` placed on the triangles); None when the triangles have no area."""
    sampled = area_samples(tri, count, rng)
    if sampled is None:
        return None
    face, bary = sampled
    return np.einsum("sk,skd->sd", bary, tri[face]), face


def _occupied(points: np.ndarray, cell: float) -> tuple[np.ndarray, int]:
    """Voxel index of each point (N,) and the number of occupied voxels, for voxels of side ``cell``."""
    coords = np.floor((points - points.min(axis=0)) / cell).astype(np.int64)
    span = coords.max(axis=0) + 1
    keys = (coords[:, 0] * span[1] + coords[:, 1]) * span[2] + coords[:, 2]
    _, inverse = np.unique(keys, return_inverse=True)
    return inverse.reshape(-1), int(inverse.max()) + 1


def spread_sample(points: np.ndarray, weights: np.ndarray, max_points: int) -> np.ndarray:
    """Indices of at most ``max_points`` points spread evenly over (N, 3) ``points``.

    Args:
        points: (N, 3) positions [m].
        weights: (N,) preference within a voxel (the highest is kept), e.g. opacity.
        max_points: the bound (>= 1).

    Returns:
        (M,) sorted int64 indices, M <= max_points (all N when N <= max_points).
    """
    n = len(points)
    if n <= max_points:
        return np.arange(n, dtype=np.int64)
    if n > PRESAMPLE * max_points:
        # every k-th point first: the voxel search then costs the same for 50 k or 5 M points, and a
        # stride keeps the result deterministic without a random generator
        stride = -(-n // (PRESAMPLE * max_points))  # ceil: the strided set is within the bound
        return np.arange(0, n, stride)[spread_sample(points[::stride], weights[::stride], max_points)]
    extent = float(np.ptp(points, axis=0).max())
    if extent <= 0:
        return np.array([int(np.argmax(weights))], dtype=np.int64)
    lo, hi = np.log(extent / 4096.0), np.log(extent)  # voxel sides bracketing max_points
    best = None
    for _ in range(24):
        mid = 0.5 * (lo + hi)
        voxel, count = _occupied(points, float(np.exp(mid)))
        if count > max_points:
            lo = mid
        else:
            hi, best = mid, (voxel, count)
            if count > 0.9 * max_points:
                break
    voxel, count = best if best is not None else _occupied(points, extent)
    order = np.lexsort((-np.asarray(weights, dtype=np.float64), voxel))  # by voxel, most weight first
    first = np.ones(n, dtype=bool)
    first[1:] = voxel[order][1:] != voxel[order][:-1]
    return np.sort(order[first]).astype(np.int64)


def splat_surface(means: np.ndarray, opacities: np.ndarray, *, max_points: int = SURFACE_POINTS) -> np.ndarray:
    """(M, 3) surface points of a splat [m]: a :func:`spread_sample` of its opaque centres, M <= max_points."""
    means = np.asarray(means, dtype=np.float64)
    index = np.flatnonzero(opacities >= MIN_OPACITY)
    if len(index) < 8:
        index = np.arange(len(means))
    return means[index[spread_sample(means[index], opacities[index], max_points)]]


def target_surface(target: TargetGaussians, source: object) -> tuple[np.ndarray, np.ndarray | None]:
    """The target's surface for matching and motion: its source's mesh (vertices (V, 3) [m], faces (F, 3))
    when it has one, else a bounded, evenly spread sample of its opaque Gaussian centres (at most
    ``SURFACE_POINTS``, however many Gaussians) and no faces."""
    if isinstance(source, TargetWithSurface):
        return source.surface()
    return splat_surface(target.means, target.opacities), None
