"""Similarity alignment of two shapes: normalise, principal axes, 24 proper axis/sign candidates, ICP.

The paper's stated limitation is that reference and target must start in similar poses. Here the
target is brought into the reference's frame before any coordinate feature is computed:

1. both shapes are normalised (centroid at the origin, unit RMS radius or unit bounding-box diagonal);
2. each is expressed in its principal axes, the axis signs fixed by the third moments (skewness);
3. because principal axes swap when two variances are close and skewness is weak on near-symmetric
   shapes, every one of the 24 proper rotations of the axis frame (axis permutations with sign flips,
   determinant +1, so no mirror image that would swap left and right limbs) is scored by the chamfer
   distance, and the best few are refined by similarity ICP (Umeyama); the lowest residual wins.

The result is a :class:`Similarity` ``x -> s R x + t`` mapping the source into the target's frame.
All functions are pure NumPy/SciPy on (N, 3) float arrays in metres.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from sync4d.errors import ConfigError, InputError

log = logging.getLogger(__name__)

ALIGN_METHODS: tuple[str, ...] = ("none", "pca", "pca_icp", "upright_icp")


@dataclass(frozen=True)
class Similarity:
    """A similarity transform ``x -> scale * rotation @ x + translation``.

    Attributes:
        rotation: (3, 3) proper rotation (det +1).
        scale: positive uniform scale (dimensionless).
        translation: (3,) translation [m].
    """

    rotation: np.ndarray
    scale: float
    translation: np.ndarray

    @staticmethod
    def identity() -> Similarity:
        return Similarity(np.eye(3), 1.0, np.zeros(3))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) -> (N, 3) transformed points."""
        return self.scale * np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation

    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix acting on column vectors."""
        out = np.eye(4)
        out[:3, :3] = self.scale * self.rotation
        out[:3, 3] = self.translation
        return out

    def inverse(self) -> Similarity:
        rot_t = self.rotation.T
        return Similarity(rot_t, 1.0 / self.scale, -(rot_t @ self.translation) / self.scale)

    def then(self, other: Similarity) -> Similarity:
        """The composition ``other(self(x))``."""
        return Similarity(
            other.rotation @ self.rotation,
            other.scale * self.scale,
            other.scale * other.rotation @ self.translation + other.translation,
        )

    @property
    def rotation_angle_deg(self) -> float:
        """Angle of the rotation about its axis [deg], in [0, 180]."""
        cos = (np.trace(self.rotation) - 1.0) / 2.0
        return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


@dataclass(frozen=True)
class AlignResult:
    """Outcome of :func:`align_shapes`.

    Attributes:
        transform: similarity mapping source points into the target's frame.
        residual: symmetric chamfer distance (mean of both directions) after alignment, in units of the
            target's normalisation radius (dimensionless; 0 = perfect overlap).
        candidate_residuals: (K,) chamfer residual of every rotation candidate before ICP (normalised),
            or an empty array for ``method="none"``.
        method: the method used.
    """

    transform: Similarity
    residual: float
    candidate_residuals: np.ndarray
    method: str

    def summary(self) -> str:
        t = self.transform
        return (
            f"align[{self.method}]: rotation {t.rotation_angle_deg:.1f} deg, scale {t.scale:.4g}, "
            f"residual {self.residual:.4f} (chamfer / target radius)"
        )


def _as_points(points: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) < 4:
        raise InputError(f"{name}: expected (N >= 4, 3) points, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise InputError(f"{name}: contains NaN/inf")
    return arr


def normalization(points: np.ndarray, *, mode: str = "rms") -> Similarity:
    """The similarity that centres ``points`` at the origin and scales them to unit size.

    Args:
        points: (N, 3) [m].
        mode: ``"rms"`` (unit root-mean-square distance to the centroid) or ``"bbox"`` (unit diagonal of
            the axis-aligned bounding box).

    Returns:
        Similarity with identity rotation; apply it to get the normalised points.
    """
    pts = _as_points(points, "normalization.points")
    centroid = pts.mean(axis=0)
    if mode == "rms":
        size = float(np.sqrt(((pts - centroid) ** 2).sum(axis=1).mean()))
    elif mode == "bbox":
        size = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    else:
        raise ConfigError(f"normalization mode '{mode}': use 'rms' or 'bbox'")
    if size <= 1e-12:
        raise InputError("normalization.points: all points coincide; cannot normalise a degenerate shape")
    return Similarity(np.eye(3), 1.0 / size, -centroid / size)


def principal_frame(points: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose rows are the principal axes of ``points``, largest variance first.

    Each axis sign is chosen so that the third moment (skewness) of the projections is positive, which
    makes the frame follow the shape under rotation when the distribution is not symmetric. The third
    row is flipped if needed so that the frame is a proper rotation (det +1).

    Args:
        points: (N, 3) points, ideally already centred [m].
    """
    pts = _as_points(points, "principal_frame.points")
    centred = pts - pts.mean(axis=0)
    cov = centred.T @ centred / len(centred)
    _, vecs = np.linalg.eigh(cov)
    axes = vecs[:, ::-1].T.copy()  # rows, descending variance
    for i in range(2):
        skew = float(((centred @ axes[i]) ** 3).mean())
        if skew < 0:
            axes[i] = -axes[i]
    if np.linalg.det(axes) < 0:
        axes[2] = -axes[2]
    return axes


def proper_axis_rotations() -> np.ndarray:
    """(24, 3, 3) the rotations of the cube: signed axis permutations with determinant +1.

    The first entry is the identity (the skewness-disambiguated principal frame).
    """
    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[np.arange(3), perm] = signs
            if np.linalg.det(m) > 0:
                mats.append(m)
    mats.sort(key=lambda m: -np.trace(m))  # identity first
    return np.stack(mats)


def axis_rotation(axis: int, angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_rad`` about coordinate axis ``axis`` (0, 1, 2)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    i, j = [k for k in range(3) if k != axis]
    m = np.eye(3)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


def candidate_rotations(half_steps: bool = True) -> np.ndarray:
    """(K, 3, 3) rotations tried in the principal frame: the 24 cube rotations, each optionally
    followed by +/-45 deg about each principal axis (K = 24 x 7 = 168).

    Why the half steps: when two principal variances are nearly equal (a body seen from above is about
    as wide as deep), the principal axes themselves are arbitrary within that plane, and the nearest
    cube rotation can be 45 deg away from the truth, too far for ICP to recover reliably.
    """
    cube = proper_axis_rotations()
    if not half_steps:
        return cube
    turns = [np.eye(3)] + [axis_rotation(a, sgn * np.pi / 4) for a in range(3) for sgn in (1.0, -1.0)]
    return np.stack([t @ g for g in cube for t in turns])


def chamfer_distance(a: np.ndarray, b: np.ndarray, *, tree_b: cKDTree | None = None) -> float:
    """Symmetric chamfer distance: mean of the mean nearest-neighbour distances a->b and b->a [m]."""
    tree_b = tree_b if tree_b is not None else cKDTree(b)
    d_ab = tree_b.query(a)[0]
    d_ba = cKDTree(a).query(b)[0]
    return float(0.5 * (d_ab.mean() + d_ba.mean()))


def umeyama(source: np.ndarray, target: np.ndarray, *, with_scale: bool = True) -> Similarity:
    """Least-squares similarity mapping paired ``source`` points onto ``target`` points (Umeyama 1991).

    Args:
        source: (N, 3) points.
        target: (N, 3) corresponding points.
        with_scale: estimate the scale (else fixed to 1).
    """
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    xs, xt = source - mu_s, target - mu_t
    cov = xt.T @ xs / len(source)
    u, sig, vt = np.linalg.svd(cov)
    d = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[2] = -1.0
    rot = u @ np.diag(d) @ vt
    var_s = float((xs**2).sum(axis=1).mean())
    scale = float((sig * d).sum() / var_s) if with_scale and var_s > 0 else 1.0
    return Similarity(rot, scale, mu_t - scale * rot @ mu_s)


def icp(
    source: np.ndarray,
    target: np.ndarray,
    init: Similarity,
    *,
    iterations: int = 30,
    with_scale: bool = True,
    trim: float = 0.9,
    tol: float = 1e-6,
) -> Similarity:
    """Trimmed similarity ICP: iterate nearest neighbours and Umeyama from ``init``.

    Correspondences are taken both ways (source->target and target->source) so that a part missing
    in one shape does not pull the fit, and the worst ``1 - trim`` fraction of pairs is dropped.

    Args:
        source: (N, 3) points to move.
        target: (M, 3) fixed points.
        init: initial similarity mapping source into target.
        iterations: maximum iterations.
        with_scale: estimate scale too.
        trim: fraction of correspondences kept per iteration (by distance).
        tol: stop when the mean squared pair distance changes less than this (relative).
    """
    tree_t = cKDTree(target)
    current = init
    previous = np.inf
    for _ in range(iterations):
        moved = current.apply(source)
        d_st, j = tree_t.query(moved)
        d_ts, i = cKDTree(moved).query(target)
        src = np.concatenate([source, source[i]])
        dst = np.concatenate([target[j], target])
        dist = np.concatenate([d_st, d_ts])
        keep = dist <= np.quantile(dist, trim)
        current = umeyama(src[keep], dst[keep], with_scale=with_scale)
        err = float((dist[keep] ** 2).mean())
        if abs(previous - err) <= tol * max(err, 1e-12):
            break
        previous = err
    return current


def _subsample(points: np.ndarray, max_points: int, rng: np.random.Generator) -> np.ndarray:
    if len(points) <= max_points:
        return points
    return points[rng.choice(len(points), size=max_points, replace=False)]


def align_shapes(
    source: np.ndarray,
    target: np.ndarray,
    *,
    method: str = "pca_icp",
    icp_iterations: int = 100,
    refine_top: int = 4,
    normalize_mode: str = "rms",
    max_points: int = 3000,
    score_points: int = 1500,
    half_steps: bool = True,
    seed: int = 0,
) -> AlignResult:
    """Similarity taking ``source`` into the frame of ``target``, robust to any initial rotation.

    Args:
        source: (N, 3) points of the shape to move [m].
        target: (M, 3) points of the fixed shape [m].
        method: ``"none"`` (identity), ``"pca"`` (normalise + best of the principal-axis candidates,
            see :func:`candidate_rotations`), ``"pca_icp"`` (then similarity ICP on the best
            ``refine_top`` candidates) or ``"upright_icp"`` (normalise, then similarity ICP from the
            identity rotation: for shapes given in the same upright pose, as the paper assumes, where
            a near-symmetric shape could otherwise be matched upside down).
        icp_iterations: maximum ICP iterations per refined candidate (point-to-point ICP converges
            slowly along weakly constrained rotations: ~100 are needed on a human body).
        refine_top: how many of the best-scoring axis candidates ICP refines (more is more robust).
        normalize_mode: ``"rms"`` or ``"bbox"`` (see :func:`normalization`).
        max_points: random subsample size used for ICP (speed).
        score_points: smaller subsample used to score the rotation candidates.
        half_steps: also try +/-45 deg turns about each principal axis (168 candidates instead of 24).
        seed: seed of the subsampling.

    Returns:
        AlignResult; ``result.transform.apply(source)`` lies on ``target``.
    """
    if method not in ALIGN_METHODS:
        raise ConfigError(f"match.align={method!r}: use one of {', '.join(ALIGN_METHODS)}")
    src = _as_points(source, "align_shapes.source")
    dst = _as_points(target, "align_shapes.target")
    norm_t = normalization(dst, mode=normalize_mode)
    radius_t = 1.0 / norm_t.scale
    if method == "none":
        res = chamfer_distance(src, dst) / radius_t
        result = AlignResult(Similarity.identity(), res, np.zeros(0), method)
        log.info(result.summary())
        return result

    rng = np.random.default_rng(seed)
    norm_s = normalization(src, mode=normalize_mode)
    ns = _subsample(norm_s.apply(src), max_points, rng)
    nt = _subsample(norm_t.apply(dst), max_points, rng)
    frame_s, frame_t = principal_frame(ns), principal_frame(nt)
    tree_t = cKDTree(nt)

    # Candidate rotation in normalised space: source -> its principal frame -> a cube rotation of it
    # -> the target's principal frame expressed back in target coordinates.
    candidates = [Similarity(frame_t.T @ g @ frame_s, 1.0, np.zeros(3)) for g in candidate_rotations(half_steps)]
    ns_score, nt_score = _subsample(ns, score_points, rng), _subsample(nt, score_points, rng)
    tree_score = cKDTree(nt_score)
    scores = np.array([chamfer_distance(c.apply(ns_score), nt_score, tree_b=tree_score) for c in candidates])
    order = np.argsort(scores, kind="stable")
    best, best_res = candidates[int(order[0])], float(scores[order[0]])
    if method == "upright_icp":
        best = icp(ns, nt, Similarity(np.eye(3), 1.0, np.zeros(3)), iterations=icp_iterations)
        best_res = chamfer_distance(best.apply(ns), nt, tree_b=tree_t)
    if method == "pca_icp":
        best_res = np.inf
        for k in order[: max(1, refine_top)]:
            refined = icp(ns, nt, candidates[int(k)], iterations=icp_iterations)
            res = chamfer_distance(refined.apply(ns), nt, tree_b=tree_t)
            if res < best_res:
                best, best_res = refined, res
    # Compose: source -> normalised source -> aligned (normalised target frame) -> target.
    transform = norm_s.then(best).then(norm_t.inverse())
    result = AlignResult(transform, float(best_res), scores, method)
    log.info(result.summary())
    return result
