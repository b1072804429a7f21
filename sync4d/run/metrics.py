"""Transfer metrics (pure functions). Lengths are reported in % of the target's bounding-box diagonal.

``metrics.json`` keys: ``pose_error_pct`` (null without ground truth), ``displacement_error_pct``,
``drift_pct``, ``rigidity_residual_pct``, ``det_f_deviation``, ``jitter_ratio``, ``seconds_per_frame``,
``peak_memory_mb``, ``frames``, and ``per_frame`` with the same per frame.
"""

from __future__ import annotations

import resource
import sys
from dataclasses import dataclass

import numpy as np

from sync4d.geometry import SEAM_BAND_OF_DIAGONAL, part_centroids, rigid_fit, rotation_angle_deg


def displacement_error(
    x_start: np.ndarray, x_end: np.ndarray, parts: np.ndarray, target_displacement: np.ndarray, diagonal: float
) -> float:
    """Mean over parts of |delta_b - (s_t/s_o) delta_hat_b| in % of ``diagonal`` (one frame pair).

    Args:
        x_start, x_end: (N, 3) positions before and after the step [m].
        parts: (N,) part of each point.
        target_displacement: (B, 3) scaled reference displacement per part [m].
    """
    b = len(target_displacement)
    delta = part_centroids(x_end, parts, b) - part_centroids(x_start, parts, b)
    err = np.linalg.norm(delta - target_displacement, axis=1)
    return float(np.nanmean(err) / diagonal * 100.0)


def drift(x_t: np.ndarray, x_0: np.ndarray, parts: np.ndarray, accumulated_target: np.ndarray, diagonal: float) -> float:
    """Mean over parts of |(c_b(t) - c_b(0)) - sum_{s<t} delta_hat_b(s)| in % of ``diagonal``."""
    b = len(accumulated_target)
    moved = part_centroids(x_t, parts, b) - part_centroids(x_0, parts, b)
    return float(np.nanmean(np.linalg.norm(moved - accumulated_target, axis=1)) / diagonal * 100.0)


def pose_error(x_t: np.ndarray, x_true: np.ndarray, diagonal: float) -> float:
    """Mean distance of each point to its ground-truth position, in % of ``diagonal``."""
    return float(np.linalg.norm(x_t - x_true, axis=1).mean() / diagonal * 100.0)


def procrustes_residual(source: np.ndarray, moved: np.ndarray) -> float:
    """RMS residual [m] of the best rigid fit (rotation + translation, Kabsch) of ``source`` onto ``moved``."""
    if len(source) < 3:
        return 0.0
    fit = rigid_fit(source, moved)
    residual = moved - (source @ fit[:3, :3].T + fit[:3, 3])
    return float(np.sqrt((residual**2).sum(axis=1).mean()))


def rigidity_residual(x_0: np.ndarray, x_t: np.ndarray, parts: np.ndarray, num_parts: int, diagonal: float) -> float:
    """Mean over parts of the Procrustes residual from rest to frame t, in % of ``diagonal``."""
    values = [procrustes_residual(x_0[parts == b], x_t[parts == b]) for b in range(num_parts) if (parts == b).sum() >= 3]
    return float(np.mean(values) / diagonal * 100.0) if values else 0.0


def det_f_deviation(F: np.ndarray | None) -> float:
    """Mean |det F - 1| over (N, 3, 3) deformation gradients (0 when F is not tracked)."""
    return 0.0 if F is None else float(np.abs(np.linalg.det(F) - 1.0).mean())


def second_difference(x: np.ndarray) -> np.ndarray:
    """(T-2,) mean |x_{t+1} - 2 x_t + x_{t-1}| over points of a (T, N, 3) sequence [m]."""
    if len(x) < 3:
        return np.zeros(0)
    return np.linalg.norm(x[2:] - 2 * x[1:-1] + x[:-2], axis=2).mean(axis=1)


def jitter_ratio(x_target: np.ndarray, x_reference: np.ndarray, coverage_ratio: float) -> float:
    """Mean second difference of the target against the reference's own (scaled to the target's size).

    1 means as smooth as the reference; much more than 1 means added jitter. NaN for fewer than 3 frames.
    """
    tgt, ref = second_difference(x_target), second_difference(x_reference) * coverage_ratio
    if len(tgt) == 0:
        return float("nan")
    return float(tgt.mean() / max(ref.mean(), 1e-12))


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far [MB]."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1024.0 if sys.platform != "darwin" else peak / (1024.0 * 1024.0)


# ----------------------------------------------------------------------------------------------------
# Shape integrity: does the target stay whole? (rest neighbour pairs, fragments, part volumes)
# ----------------------------------------------------------------------------------------------------

#: relative length change of a rest neighbour pair beyond which it counts as torn (stretched or compressed)
TORN_STRAIN = 0.10


def rest_neighbour_pairs(rest: np.ndarray, k: int = 8) -> np.ndarray:
    """(M, 2) unique pairs (i < j) of each rest point with its ``k`` nearest neighbours.

    Args:
        rest: (N, 3) rest positions [m].
        k: neighbours per point.
    """
    from scipy.spatial import cKDTree

    rest = np.asarray(rest, dtype=np.float64)
    kk = min(k + 1, len(rest))
    _, idx = cKDTree(rest).query(rest, k=kk)
    i = np.repeat(np.arange(len(rest)), kk - 1)
    j = idx[:, 1:].reshape(-1)
    pairs = np.sort(np.stack([i, j], axis=1), axis=1)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    return np.unique(pairs, axis=0)


def pair_strain(rest: np.ndarray, x: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(M,) relative length change |l_t / l_0 - 1| of each pair from ``rest`` (N, 3) to ``x`` (N, 3)."""
    l0 = np.linalg.norm(rest[pairs[:, 0]] - rest[pairs[:, 1]], axis=1)
    lt = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)
    return np.abs(lt / np.maximum(l0, 1e-12) - 1.0)


def torn_pairs_pct(strain: np.ndarray, mask: np.ndarray | None = None, threshold: float = TORN_STRAIN) -> float:
    """Share [%] of pairs (optionally only those in ``mask``) strained beyond ``threshold``; 0 without pairs."""
    s = strain if mask is None else strain[mask]
    return float((s > threshold).mean() * 100.0) if len(s) else 0.0


def strain_p99_pct(strain: np.ndarray) -> float:
    """99th percentile of the pair strain [%]."""
    return float(np.percentile(strain, 99) * 100.0) if len(strain) else 0.0


def seam_pairs(pairs: np.ndarray, parts: np.ndarray) -> np.ndarray:
    """(M,) bool: the pair joins two different parts (a seam)."""
    return parts[pairs[:, 0]] != parts[pairs[:, 1]]


def count_fragments(
    x: np.ndarray, pairs: np.ndarray, strain: np.ndarray, gap: float, threshold: float = TORN_STRAIN
) -> int:
    """Pieces of the rest neighbour graph, cut at torn pairs, lying more than ``gap`` from the rest of the body.

    The graph's largest component after cutting is the body; every other component whose nearest point
    is farther than ``gap`` [m] from every point outside it has come off. A torn but touching seam is
    not a fragment; a limb or a few scattered Gaussians floating free are.

    Args:
        x: (N, 3) positions at frame t [m].
        pairs: (M, 2) rest neighbour pairs; strain: (M,) their strain at t.
        gap: distance [m] (two grid cells of the simulator).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(x)
    keep = strain <= threshold
    a, b = pairs[keep, 0], pairs[keep, 1]
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    n_comp, label = connected_components(graph, directed=False)
    if n_comp <= 1:
        return 0
    sizes = np.bincount(label, minlength=n_comp)
    count = 0
    order = np.argsort(label, kind="stable")
    starts = np.concatenate([[0], np.cumsum(sizes)])
    main = int(np.argmax(sizes))
    # Pieces of at most SMALL_PIECE points, all at once: a point's nearest point outside its piece is
    # among its (size + 1) nearest, so one tree answers them (a tree per piece cost minutes for the
    # thousands of small pieces of a large splat). Larger pieces: a tree of the points outside each.
    small = (sizes <= SMALL_PIECE) & (np.arange(n_comp) != main)
    points = np.flatnonzero(small[label])
    if len(points):
        d, j = cKDTree(x).query(x[points], k=min(SMALL_PIECE + 1, n), distance_upper_bound=gap)
        outside = np.isfinite(d) & (label[np.minimum(j, n - 1)] != label[points][:, None])
        touching = np.zeros(n_comp, dtype=bool)
        touching[label[points][outside.any(axis=1)]] = True
        count += int((small & ~touching).sum())
    for c in np.flatnonzero(~small):
        if c == main:
            continue
        inside = order[starts[c]: starts[c + 1]]
        others = np.ones(n, dtype=bool)
        others[inside] = False
        d, _ = cKDTree(x[others]).query(x[inside], k=1, distance_upper_bound=gap)
        if np.all(~np.isfinite(d)):
            count += 1
    return count


#: Pieces up to this many points are tested for contact in one neighbour query (count_fragments).
SMALL_PIECE = 32


def part_volumes(x: np.ndarray, parts: np.ndarray, num_parts: int) -> np.ndarray:
    """(B,) convex-hull volume [m^3] of each part's points (NaN for parts with < 4 points or flat ones).

    Measured from positions alone, so methods that carry no deformation gradient (or a wrong one) are
    judged alike; a rigid motion keeps it exactly, a shrunk or collapsed part loses volume.
    """
    from scipy.spatial import ConvexHull, QhullError

    out = np.full(num_parts, np.nan)
    for b in range(num_parts):
        pts = x[parts == b]
        if len(pts) >= 4:
            try:
                out[b] = ConvexHull(pts).volume
            except (QhullError, ValueError):
                pass
    return out


def part_volume_change_pct(volume: np.ndarray, rest_volume: np.ndarray, true_volume: np.ndarray | None = None) -> np.ndarray:
    """(B,) change of each part's volume against the truth's at the same frame (or the rest), in % of its rest volume.

    Dividing by the rest volume (not the truth's) keeps parts that the truth flattens from blowing up the ratio.
    NaN where a volume is unknown.
    """
    ref = rest_volume if true_volume is None else true_volume
    with np.errstate(invalid="ignore", divide="ignore"):
        return (volume - ref) / rest_volume * 100.0


def body_volume_change_pct(change_pct: np.ndarray, rest_volume: np.ndarray) -> float:
    """Rest-volume-weighted mean of |per-part change| [%]: how much of the body's volume went wrong."""
    ok = np.isfinite(change_pct) & np.isfinite(rest_volume)
    if not ok.any():
        return 0.0
    return float((np.abs(change_pct[ok]) * rest_volume[ok]).sum() / rest_volume[ok].sum())


@dataclass(frozen=True)
class IntegrityFrame:
    """Shape integrity of one frame (see :func:`integrity_frame`).

    Attributes:
        torn_pairs_pct: rest k-NN pairs strained > 10% [% of pairs].
        torn_seam_pairs_pct: the same among pairs that join two parts [%].
        strain_p99_pct: 99th percentile pair strain [%].
        volume_change_pct: (B,) per-part convex-hull volume change (against the truth's, else the rest),
            in % of the part's rest volume, signed.
        body_volume_change_pct: rest-volume-weighted mean of the parts' |change| [%].
        fragments: pieces more than ``gap`` from the rest of the body.
    """

    torn_pairs_pct: float
    torn_seam_pairs_pct: float
    strain_p99_pct: float
    volume_change_pct: np.ndarray
    body_volume_change_pct: float
    fragments: int


@dataclass(frozen=True)
class IntegrityModel:
    """What integrity is measured against: the rest shape, its neighbour graph, parts and the fragment gap.

    Attributes:
        rest: (N, 3) rest positions [m]; parts: (N,) part labels; num_parts: B.
        pairs: (M, 2) rest k-NN pairs; seam: (M,) bool pairs joining two parts.
        rest_volume: (B,) rest convex-hull volume per part [m^3]; gap: fragment distance [m].
    """

    rest: np.ndarray
    parts: np.ndarray
    num_parts: int
    pairs: np.ndarray
    seam: np.ndarray
    rest_volume: np.ndarray
    gap: float


def integrity_model(
    rest: np.ndarray, parts: np.ndarray, num_parts: int, *, gap: float, k: int = 8, truth: np.ndarray | None = None
) -> IntegrityModel:
    """Build the rest neighbour graph once per run (k = 8 nearest neighbours, ``gap`` [m]).

    With a ``truth`` (T, N, 3), pairs that the correct motion itself strains beyond 10% in some frame
    (two limbs side by side at rest that walk apart, a lid edge leaving the base) are left out: what
    remains are the pairs a correct transfer keeps together, so the metrics count only what the method
    tore. Without a truth every rest pair counts.
    """
    rest = np.asarray(rest, dtype=np.float64)
    parts = np.asarray(parts)
    pairs = rest_neighbour_pairs(rest, k)
    if truth is not None:
        worst = np.max([pair_strain(rest, xt, pairs) for xt in truth], axis=0)
        pairs = pairs[worst <= TORN_STRAIN]
    return IntegrityModel(rest, parts, int(num_parts), pairs, seam_pairs(pairs, parts),
                          part_volumes(rest, parts, num_parts), float(gap))


def integrity_frame(model: IntegrityModel, x: np.ndarray, *, true_volume: np.ndarray | None = None) -> IntegrityFrame:
    """All shape-integrity metrics of positions ``x`` (N, 3) [m] against ``model``.

    ``true_volume`` (B,) [m^3]: each part's volume in the truth at this frame; the volume change is then
    measured against it (a correct motion's own volume change is no error), else against the rest.
    """
    strain = pair_strain(model.rest, x, model.pairs)
    change = part_volume_change_pct(part_volumes(x, model.parts, model.num_parts), model.rest_volume, true_volume)
    return IntegrityFrame(
        torn_pairs_pct=torn_pairs_pct(strain),
        torn_seam_pairs_pct=torn_pairs_pct(strain, model.seam),
        strain_p99_pct=strain_p99_pct(strain),
        volume_change_pct=change,
        body_volume_change_pct=body_volume_change_pct(change, model.rest_volume),
        fragments=count_fragments(x, model.pairs, strain, model.gap),
    )


def integrity_summary(frames: list[IntegrityFrame]) -> dict[str, float | int | list[float]]:
    """Overall integrity over frames 1..T (frame 0 is the rest shape and stays out of every mean).

    Returns ``torn_pairs_pct`` / ``torn_seam_pairs_pct`` / ``strain_p99_pct`` (means over frames),
    ``strain_p99_max_pct`` (worst frame), ``volume_change_pct`` (mean over frames of the body's
    volume-weighted |part change|), ``volume_change_per_part_pct`` (B,, signed means over frames),
    ``fragments`` (most in any frame).
    """
    import warnings

    use = frames[1:] if len(frames) > 1 else frames
    vol = np.stack([f.volume_change_pct for f in use])  # (T, B)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # parts too small for a hull are NaN in every frame
        per_part = np.nanmean(vol, axis=0)
    return {
        "torn_pairs_pct": float(np.mean([f.torn_pairs_pct for f in use])),
        "torn_seam_pairs_pct": float(np.mean([f.torn_seam_pairs_pct for f in use])),
        "strain_p99_pct": float(np.mean([f.strain_p99_pct for f in use])),
        "strain_p99_max_pct": float(np.max([f.strain_p99_pct for f in use])),
        "volume_change_pct": float(np.mean([f.body_volume_change_pct for f in use])),
        "volume_change_per_part_pct": [float(v) for v in per_part],
        "fragments": int(max(f.fragments for f in use)),
    }


# ----------------------------------------------------------------------------------------------------
# Tearing over thresholds: the verdict must not hang on one constant
# ----------------------------------------------------------------------------------------------------

#: tear thresholds of the integrity curves (relative pair length change)
TEAR_THRESHOLDS = (0.05, 0.10, 0.20, 0.30)


def threshold_key(threshold: float) -> str:
    """``0.1`` -> ``"10"``: a tear threshold as the JSON key of its curve point (whole percent)."""
    return f"{round(threshold * 100):d}"


def tear_curve(
    rest: np.ndarray, x: np.ndarray, gap: float, *, truth: np.ndarray | None = None,
    thresholds: tuple[float, ...] = TEAR_THRESHOLDS, k: int = 8,
) -> dict[str, dict[str, float]]:
    """Torn pairs and fragments at each tear threshold, over frames 1..T (frame 0 is the rest shape).

    At threshold tau a rest k-NN pair is torn when its length changes by more than tau; with a ``truth``
    (T, N, 3) the pairs that the correct motion itself strains beyond tau in some frame are left out (as
    :func:`integrity_model` does at 10%), so each point of the curve counts only what the method tore.

    Args:
        rest: (N, 3) rest positions [m]; x: (T, N, 3) the method's positions [m].
        gap: fragment distance [m] (:func:`count_fragments`).

    Returns:
        ``{"torn_pairs_pct": {"5": ..., "10": ...}, "fragments": {"5": ..., ...}}``: torn pairs as the mean
        over frames of the share of kept pairs [%], fragments as the most in any frame.
    """
    rest = np.asarray(rest, dtype=np.float64)
    pairs = rest_neighbour_pairs(rest, k)
    strain = np.stack([pair_strain(rest, xt, pairs) for xt in x])  # (T, M)
    worst_true = None if truth is None else np.max([pair_strain(rest, xt, pairs) for xt in truth], axis=0)
    frames = range(1, len(x)) if len(x) > 1 else range(len(x))
    torn: dict[str, float] = {}
    fragments: dict[str, float] = {}
    for tau in thresholds:
        keep = np.ones(len(pairs), dtype=bool) if worst_true is None else worst_true <= tau
        key = threshold_key(tau)
        torn[key] = float(np.mean([torn_pairs_pct(strain[t, keep], threshold=tau) for t in frames]))
        fragments[key] = float(max(count_fragments(x[t], pairs[keep], strain[t, keep], gap, threshold=tau)
                                   for t in frames))
    return {"torn_pairs_pct": torn, "fragments": fragments}


# ----------------------------------------------------------------------------------------------------
# Follow error: does each part move the way its reference part does? (no truth needed)
# ----------------------------------------------------------------------------------------------------


def fit_is_determined(points: np.ndarray, *, min_points: int = 4) -> bool:
    """A rigid fit of these (n, 3) rest points fixes the rotation: enough points, not all on one line."""
    if len(points) < min_points:
        return False
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return bool(s[1] > 1e-3 * s[0])




@dataclass(frozen=True)
class FollowError:
    """Each part's follow error per frame, and how much each part weighs in the means.

    Attributes:
        rotation_deg: (T, B) angle of R_fit R_drive^T [deg] (NaN where the fit is undetermined).
        translation_pct: (T, B) distance between where the fit and the drive take the core's rest centroid [% of
            the diagonal] (NaN likewise).
        weight: (B,) the points of each part's core (its mass share; 0 where undetermined).
    """

    rotation_deg: np.ndarray
    translation_pct: np.ndarray
    weight: np.ndarray

    def frame_means(self) -> tuple[np.ndarray, np.ndarray]:
        """(T,) weighted means over parts of the rotation [deg] and translation [%] errors (NaN when no part)."""
        return weighted_nanmean(self.rotation_deg, self.weight), weighted_nanmean(self.translation_pct, self.weight)


def weighted_nanmean(values: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(T,) mean of (T, B) ``values`` over B, weighted by (B,) ``weight``, NaN entries left out."""
    w = np.where(np.isfinite(values), weight[None], 0.0)
    total = w.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, (np.nan_to_num(values) * w).sum(axis=1) / total, np.nan)


def part_cores(rest: np.ndarray, parts: np.ndarray, num_parts: int, band: float) -> list[np.ndarray]:
    """Per part, the indices of its points farther than ``band`` [m] from every point of another part (all of
    the part's points when fewer than 4 or a tenth of them would remain)."""
    from scipy.spatial import cKDTree

    cores = []
    for b in range(num_parts):
        idx = np.flatnonzero(parts == b)
        others = rest[(parts != b) & (parts >= 0)]
        if len(idx) == 0 or len(others) == 0 or band <= 0:
            cores.append(idx)
            continue
        distance, _ = cKDTree(others).query(rest[idx], distance_upper_bound=band)
        core = idx[~np.isfinite(distance)]
        cores.append(core if len(core) >= max(4, len(idx) // 10) else idx)
    return cores


def follow_error(
    rest: np.ndarray, x: np.ndarray, parts: np.ndarray, part_transforms: np.ndarray, diagonal: float,
    *, band: float | None = None,
) -> FollowError:
    """Each part's best rigid motion (rest -> frame t) on its core against the driving motion it was given.

    The driving motion of part b at frame t is ``part_transforms[t, b] @ inv(part_transforms[0, b])``
    (frame 0 is the rest pose, as every simulator uses it). The fit uses the part's core only: the points
    farther than ``band`` (default ``SEAM_BAND_OF_DIAGONAL`` of ``diagonal``) from any other part, since a joint's
    blend moves with neither part rigidly. The rotation error is the angle of ``R_fit R_drive^T``; the
    translation error is the distance between where the fit and the drive take the core's rest centroid, in %
    of ``diagonal``. A frozen part scores the drive's own rotation and displacement; a torn or detached part
    scores the gap. Means weigh each part by its core's points (:meth:`FollowError.frame_means`), so a part of
    three Gaussians does not count as much as the torso.

    Args:
        rest: (N, 3) rest positions [m]; x: (T, N, 3) positions (before the global transform) [m].
        parts: (N,) part of each point; part_transforms: (T, B, 4, 4) DrivingMotion.part_transforms.
        diagonal: the target's bounding-box diagonal [m].
        band: the seam band [m].

    Returns:
        The errors; NaN for parts whose fit is undetermined (fewer than 4 points or all on a line).
    """
    rest = np.asarray(rest, dtype=np.float64)
    T, B = len(x), part_transforms.shape[1]
    rot_err, trans_err, weight = np.full((T, B), np.nan), np.full((T, B), np.nan), np.zeros(B)
    drive = part_transforms[:T] @ np.linalg.inv(part_transforms[0])[None]
    width = SEAM_BAND_OF_DIAGONAL * diagonal if band is None else band
    for b, idx in enumerate(part_cores(rest, parts, B, width)):
        if not fit_is_determined(rest[idx]):
            continue
        weight[b] = len(idx)
        centroid = rest[idx].mean(axis=0)
        for t in range(T):
            rot = rigid_fit(rest[idx], x[t][idx])[:3, :3]
            r_drive, t_drive = drive[t, b, :3, :3], drive[t, b, :3, 3]
            rot_err[t, b] = float(rotation_angle_deg(rot @ r_drive.T))
            trans_err[t, b] = np.linalg.norm(x[t][idx].mean(axis=0) - (r_drive @ centroid + t_drive))
    return FollowError(rot_err, trans_err / diagonal * 100.0, weight)


def follow_summary(follow: FollowError) -> dict[str, float | None]:
    """``follow_rotation_deg`` / ``follow_translation_pct`` (frames 1..T, each frame's parts weighted by their
    cores' points) and the worst part-frame (``..._max_...``); None when no part could be measured."""
    rot, trans = follow.rotation_deg[1:], follow.translation_pct[1:]
    if rot.size == 0 or not np.isfinite(rot).any():
        return {"follow_rotation_deg": None, "follow_rotation_max_deg": None,
                "follow_translation_pct": None, "follow_translation_max_pct": None}
    mean_rot, mean_trans = (m[1:] for m in follow.frame_means())
    return {
        "follow_rotation_deg": float(np.nanmean(mean_rot)),
        "follow_rotation_max_deg": float(np.nanmax(rot)),
        "follow_translation_pct": float(np.nanmean(mean_trans)),
        "follow_translation_max_pct": float(np.nanmax(trans)),
    }

