"""Part mapping with shape correspondence (paper Sec. 3.3).

Steps, each a small pure function:

1. reference labels ``y_ref = argmax_b W(x)`` (:meth:`Reference.part_labels`);
2. the target surface (its mesh, or the Gaussian means) is aligned to the reference
   (:func:`sync4d.match.align.align_shapes`) and both are put in the reference's normalised frame
   (centroid at 0, unit RMS radius), where the features are computed;
3. mean reference feature per part, ``f_b = mean_{y_ref = b} f_ref`` (:func:`part_mean_features`);
4. each target vertex takes the part of highest cosine similarity (:func:`assign_by_similarity`);
   with ``prototypes`` other than 1 a part is represented by several prototype features (k-means
   within the part) or by all its vertices (nearest-neighbour feature matching), and its similarity
   is that of its most similar prototype (:func:`part_prototype_features`; not in the paper, whose
   single mean loses to a compact neighbouring part at seams: measured in docs/results/matching.md);
5. outliers are dropped: vertices farther from their part's centre than ``outlier_sigma`` robust
   spreads (:func:`remove_outliers`);
6. a box per part around its kept vertices (:func:`part_boxes`), and every Gaussian is given the part
   whose box holds it; several boxes -> the nearest of their part centroids, no box -> the nearest part
   centroid overall (:func:`assign_to_boxes`);
7. confidence per Gaussian: the cosine margin (best minus second-best part) of the nearest kept target
   vertex of its part, clipped to [0, 1]; 0 for orphans (:func:`gaussian_confidence`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from sync4d.errors import ConfigError, InputError
from sync4d.interfaces import FeatureExtractor
from sync4d.match.align import AlignResult, align_shapes, normalization
from sync4d.match.config import BOX_FRAMES, MatchConfig, prototype_count
from sync4d.match.result import IN_ONE_BOX, IN_SEVERAL_BOXES, ORPHAN, MatchDiagnostics, MatchResult, finish_match
from sync4d.match.surface_points import target_points
from sync4d.types import Reference, TargetGaussians


def part_mean_features(features: np.ndarray, labels: np.ndarray, num_parts: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean feature of each part (paper eq. f_b = 1/N_b sum_{y_n = b} f_n).

    Args:
        features: (V, D) reference vertex features.
        labels: (V,) int part per vertex in [0, num_parts).
        num_parts: B.

    Returns:
        means (B, D) (zero rows for empty parts), present (B,) bool (the part owns >= 1 vertex).
    """
    labels = np.asarray(labels, dtype=np.int64)
    sums = np.zeros((num_parts, features.shape[1]))
    np.add.at(sums, labels, features)
    counts = np.bincount(labels, minlength=num_parts).astype(np.float64)
    present = counts > 0
    sums[present] /= counts[present, None]
    return sums, present


def part_prototype_features(
    features: np.ndarray, labels: np.ndarray, num_parts: int, per_part: int, *, iterations: int = 10, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Unit-length prototype features of every part, sorted by part.

    ``per_part = 1`` is the paper's part mean (normalised, which leaves its cosine unchanged);
    ``per_part = k > 1`` runs spherical k-means within each part, so that a part spanning
    different-looking regions (a torso's front and sides, a lid's two faces) is matched region by
    region; ``per_part = 0`` makes every reference vertex a prototype, i.e. nearest-neighbour feature
    matching, the way Diff3F transfers labels.

    Args:
        features: (V, D) reference features.
        labels: (V,) part per vertex in [0, num_parts).
        num_parts: B.
        per_part: prototypes per part (0 = all vertices).
        iterations: k-means rounds.
        seed: k-means initialisation seed.

    Returns:
        prototypes (P, D) unit rows, owner (P,) non-decreasing part of each prototype.
    """
    unit = features / np.maximum(np.linalg.norm(features, axis=1, keepdims=True), 1e-12)
    labels = np.asarray(labels, dtype=np.int64)
    rng = np.random.default_rng(seed)
    protos, owner = [], []
    for b in range(num_parts):
        members = unit[labels == b]
        if len(members) == 0:
            continue
        if per_part == 1:
            mean = features[labels == b].mean(axis=0)
            centres = (mean / max(np.linalg.norm(mean), 1e-12))[None]
        elif per_part == 0 or len(members) <= per_part:
            centres = members
        else:
            centres = members[rng.choice(len(members), per_part, replace=False)]
            for _ in range(iterations):
                assign = np.argmax(members @ centres.T, axis=1)
                sums = np.zeros_like(centres)
                np.add.at(sums, assign, members)
                norms = np.linalg.norm(sums, axis=1, keepdims=True)
                # An empty cluster keeps its previous centre rather than collapsing to zero.
                centres = np.where(norms > 1e-12, sums / np.maximum(norms, 1e-12), centres)
        protos.append(centres)
        owner.append(np.full(len(centres), b))
    return np.concatenate(protos), np.concatenate(owner)


def prototype_similarity(
    features: np.ndarray, prototypes: np.ndarray, owner: np.ndarray, num_parts: int, *, chunk: int = 2048
) -> np.ndarray:
    """(N, B) highest cosine similarity of each row of ``features`` to any prototype of each part.

    Args:
        features: (N, D) target features.
        prototypes: (P, D) unit rows sorted by ``owner``.
        owner: (P,) non-decreasing part of each prototype.
        num_parts: B; parts without a prototype get -inf.

    Cost O(N P D) in chunks of ``chunk`` rows (with ``prototypes=all``, P = the reference's vertex count:
    4.1 s measured for 6000 x 20000 x 544 on one core of this machine).
    """
    unit = features / np.maximum(np.linalg.norm(features, axis=1, keepdims=True), 1e-12)
    parts, starts = np.unique(owner, return_index=True)
    out = np.full((len(unit), num_parts), -np.inf)
    for s in range(0, len(unit), chunk):
        sims = unit[s : s + chunk] @ prototypes.T
        out[s : s + chunk, parts] = np.maximum.reduceat(sims, starts, axis=1)
    return out


def cosine_similarity(features: np.ndarray, means: np.ndarray) -> np.ndarray:
    """(N, B) cosine similarity of every row of ``features`` (N, D) with every row of ``means`` (B, D)."""
    a = features / np.maximum(np.linalg.norm(features, axis=1, keepdims=True), 1e-12)
    b = means / np.maximum(np.linalg.norm(means, axis=1, keepdims=True), 1e-12)
    return a @ b.T


def assign_by_similarity(similarity: np.ndarray, present: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Part of highest similarity per row, and the margin to the second-best part.

    Args:
        similarity: (N, B) cosine similarities.
        present: (B,) bool, parts that may be chosen (parts without reference vertices may not).

    Returns:
        labels (N,) int64, margin (N,) >= 0 (0 when only one part can be chosen).
    """
    sim = np.asarray(similarity, dtype=np.float64).copy()
    if present is not None:
        if not present.any():
            raise InputError("match: the reference has no labelled part (every skinning column is empty)")
        sim[:, ~present] = -np.inf
    order = np.argsort(-sim, axis=1)
    labels = order[:, 0]
    best = np.take_along_axis(sim, order[:, :1], axis=1)[:, 0]
    if sim.shape[1] > 1:
        second = np.take_along_axis(sim, order[:, 1:2], axis=1)[:, 0]
        margin = np.where(np.isfinite(second), best - second, 0.0)
    else:
        margin = np.zeros(len(sim))
    return labels.astype(np.int64), margin


def smooth_labels(
    points: np.ndarray,
    labels: np.ndarray,
    similarity: np.ndarray,
    num_parts: int,
    neighbours: int,
    *,
    iterations: int = 3,
) -> np.ndarray:
    """Relabel each point by the vote of its ``neighbours`` nearest points, weighted by their similarity.

    Args:
        points: (M, 3) target vertices (aligned frame).
        labels: (M,) current parts.
        similarity: (M, B) cosine similarity of each point to each part's mean reference feature.
        neighbours: k of the k-nearest-neighbour vote (the point itself included).
        iterations: vote rounds (labels spread at most this many neighbourhoods).

    Returns:
        (M,) smoothed parts.
    """
    from scipy.spatial import cKDTree

    k = min(int(neighbours), len(points))
    _, idx = cKDTree(points).query(points, k=k)
    weight = np.clip(similarity, 0.0, None) + 1e-6
    out = labels.copy()
    for _ in range(iterations):
        votes = np.zeros((len(points), num_parts))
        np.add.at(
            votes, (np.repeat(np.arange(len(points)), k), out[idx].ravel()), weight[idx.ravel(), out[idx].ravel()]
        )
        new = np.argmax(votes, axis=1)
        if np.array_equal(new, out):
            break
        out = new
    return out


def remove_outliers(points: np.ndarray, labels: np.ndarray, num_parts: int, sigma: float) -> np.ndarray:
    """Keep mask dropping points far from their part's centre.

    The centre is the coordinate-wise median of the part (a centroid that the outliers themselves
    cannot drag), the distance d_i of each point to it is compared with a robust spread,
    ``d_i > median(d) + sigma * 1.4826 * MAD(d)`` marks an outlier (the median absolute deviation
    scaled to a standard deviation; a plain standard deviation would be inflated by the very points to
    remove). For a straight limb of length L the farthest genuine point sits at ~1.9 spreads, so
    sigma >= 2 keeps every genuine point of such parts.

    Args:
        points: (N, 3) positions.
        labels: (N,) int part per point.
        num_parts: B.
        sigma: threshold in robust spreads; <= 0 or inf disables removal.

    Returns:
        (N,) bool, True for kept points.
    """
    keep = np.ones(len(points), dtype=bool)
    if not np.isfinite(sigma) or sigma <= 0:
        return keep
    for b in range(num_parts):
        idx = np.flatnonzero(labels == b)
        if len(idx) < 4:
            continue
        centre = np.median(points[idx], axis=0)
        d = np.linalg.norm(points[idx] - centre, axis=1)
        med = np.median(d)
        spread = 1.4826 * np.median(np.abs(d - med))
        spread = max(spread, 1e-3 * max(med, 1e-12))
        keep[idx[d > med + sigma * spread]] = False
    return keep


def part_boxes(
    points: np.ndarray,
    labels: np.ndarray,
    keep: np.ndarray,
    num_parts: int,
    *,
    frame: str = "aligned",
    padding: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bounding box of the kept points of each part.

    Args:
        points: (N, 3) target vertices in the common frame.
        labels: (N,) int part per vertex.
        keep: (N,) bool, vertices kept after outlier removal.
        num_parts: B.
        frame: ``"aligned"``: axis-aligned in the common (aligned) frame, as in the paper;
            ``"pca"``: oriented along each part's principal axes (tighter around slanted limbs).
        padding: boxes grow by this fraction of their size on every side (Gaussian centres sit slightly
            off the sampled surface).

    Returns:
        boxes (B, 2, 3) lo/hi corners in each box's frame, rotations (B, 3, 3) (box coordinates are
        ``R @ x``), valid (B,) bool, centroids (B, 3) of the kept points (NaN where invalid).
    """
    if frame not in BOX_FRAMES:
        raise ConfigError(f"match.box_frame={frame!r}: use one of {', '.join(BOX_FRAMES)}")
    boxes = np.zeros((num_parts, 2, 3))
    rots = np.tile(np.eye(3), (num_parts, 1, 1))
    valid = np.zeros(num_parts, dtype=bool)
    centroids = np.full((num_parts, 3), np.nan)
    for b in range(num_parts):
        pts = points[(labels == b) & keep]
        if len(pts) == 0:
            continue
        valid[b] = True
        centroids[b] = pts.mean(axis=0)
        if frame == "pca" and len(pts) >= 4:
            centred = pts - centroids[b]
            _, vecs = np.linalg.eigh(centred.T @ centred)
            rots[b] = vecs.T
        local = pts @ rots[b].T
        lo, hi = local.min(axis=0), local.max(axis=0)
        pad = padding * (hi - lo)
        boxes[b] = np.stack([lo - pad, hi + pad])
    return boxes, rots, valid, centroids


def points_in_boxes(points: np.ndarray, boxes: np.ndarray, rotations: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(N, B) bool: point n lies inside (or on) box b; invalid boxes hold nothing."""
    local = np.einsum("bij,nj->nbi", rotations, points)  # (N, B, 3)
    inside = np.all((local >= boxes[None, :, 0]) & (local <= boxes[None, :, 1]), axis=2)
    return inside & valid[None, :]


def part_distances(
    points: np.ndarray,
    centroids: np.ndarray,
    valid: np.ndarray,
    *,
    vertex_points: np.ndarray | None = None,
    vertex_labels: np.ndarray | None = None,
) -> np.ndarray:
    """(N, B) distance of each point to each part: to its centroid, or (when the part's kept vertices
    are given) to its nearest kept vertex; inf for invalid parts."""
    dist = np.full((len(points), len(valid)), np.inf)
    for b in np.flatnonzero(valid):
        if vertex_points is None or vertex_labels is None:
            dist[:, b] = np.linalg.norm(points - centroids[b], axis=1)
        else:
            dist[:, b] = cKDTree(vertex_points[vertex_labels == b]).query(points)[0]
    return dist


def assign_to_boxes(
    points: np.ndarray,
    boxes: np.ndarray,
    rotations: np.ndarray,
    valid: np.ndarray,
    centroids: np.ndarray,
    *,
    distances: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Part per Gaussian: the box that holds it; ties and orphans go to the nearest part centroid.

    Args:
        points: (N, 3) Gaussian centres in the common frame.
        boxes, rotations, valid, centroids: from :func:`part_boxes`.
        distances: (N, B) point-to-part distances used for ties and orphans instead of the distances to
            the centroids (see :func:`part_distances`).

    Returns:
        labels (N,) int64, status (N,) int8: 0 in one box, 1 in several boxes (nearest part among
        them), 2 in none (nearest part among all valid parts).
    """
    if not valid.any():
        raise InputError("match: no part kept any target vertex; lower match.outlier_sigma or check the features")
    inside = points_in_boxes(points, boxes, rotations, valid)
    dist = part_distances(points, centroids, valid) if distances is None else distances.copy()
    dist[:, ~valid] = np.inf
    count = inside.sum(axis=1)
    among_boxes = np.where(inside, dist, np.inf)
    labels = np.where(count >= 1, np.argmin(among_boxes, axis=1), np.argmin(dist, axis=1))
    status = np.where(count == 1, IN_ONE_BOX, np.where(count > 1, IN_SEVERAL_BOXES, ORPHAN)).astype(np.int8)
    return labels.astype(np.int64), status


def gaussian_confidence(
    points: np.ndarray,
    labels: np.ndarray,
    status: np.ndarray,
    vertex_points: np.ndarray,
    vertex_labels: np.ndarray,
    vertex_margin: np.ndarray,
    kept: np.ndarray,
) -> np.ndarray:
    """(N,) confidence in [0, 1]: the cosine margin of the nearest kept vertex of the Gaussian's part.

    A Gaussian has no feature of its own; the margin (best minus second-best cosine similarity) of the
    surface vertex nearest to it within its assigned part says how clearly that region belongs to the
    part. Orphans (in no box) get 0.
    """
    conf = np.zeros(len(points))
    for b in np.unique(labels):
        sel = np.flatnonzero((labels == b) & (status != ORPHAN))
        src = np.flatnonzero((vertex_labels == b) & kept)
        if len(sel) == 0 or len(src) == 0:
            continue
        _, j = cKDTree(vertex_points[src]).query(points[sel])
        conf[sel] = vertex_margin[src[j]]
    return np.clip(conf, 0.0, 1.0)




def match_by_features(
    reference: Reference,
    target: TargetGaussians,
    extractor: FeatureExtractor,
    config: MatchConfig,
    target_vertices: np.ndarray | None,
    target_faces: np.ndarray | None,
    seed: int,
    alignment: AlignResult | None = None,
) -> MatchResult:
    """The paper's part mapping (Sec. 3.3), with alignment first (unless given); see the module docstring."""
    num_parts = reference.num_bones
    ref_labels = reference.part_labels()
    tgt_vertices, index, tgt_faces = target_points(target, config, target_vertices, target_faces, seed)
    if alignment is None:
        alignment = align_shapes(
            tgt_vertices, reference.rest_vertices, method=config.align, icp_iterations=config.icp_iterations, seed=seed
        )
    ref_norm = normalization(reference.rest_vertices)
    frame = alignment.transform.then(ref_norm)
    ref_pts = ref_norm.apply(reference.rest_vertices)
    tgt_pts = frame.apply(tgt_vertices)

    f_ref = np.asarray(extractor.extract(ref_pts, reference.rest_faces), dtype=np.float64)
    f_tgt = np.asarray(extractor.extract(tgt_pts, tgt_faces), dtype=np.float64)
    if f_ref.shape[1] != f_tgt.shape[1]:
        raise InputError(f"match: reference features have {f_ref.shape[1]} dims, target {f_tgt.shape[1]}")
    means, present = part_mean_features(f_ref, ref_labels, num_parts)
    per_part = prototype_count(config.prototypes)
    if per_part == 1:
        similarity = cosine_similarity(f_tgt, means)  # the paper's rule, exactly
    else:
        protos, owner = part_prototype_features(f_ref, ref_labels, num_parts, per_part, seed=seed)
        similarity = prototype_similarity(f_tgt, protos, owner, num_parts)
    vertex_part, margin = assign_by_similarity(similarity, present)
    if config.smooth_neighbours > 1:
        vertex_part = smooth_labels(tgt_pts, vertex_part, similarity, num_parts, config.smooth_neighbours)
    kept = remove_outliers(tgt_pts, vertex_part, num_parts, config.outlier_sigma)
    boxes, rots, valid, centroids = part_boxes(
        tgt_pts, vertex_part, kept, num_parts, frame=config.box_frame, padding=config.box_padding
    )
    g_pts = frame.apply(target.means)
    distances = part_distances(
        g_pts,
        centroids,
        valid,
        **(
            {"vertex_points": tgt_pts[kept], "vertex_labels": vertex_part[kept]}
            if config.tie_break == "nearest_vertex"
            else {}
        ),
    )
    tgt_part, status = assign_to_boxes(g_pts, boxes, rots, valid, centroids, distances=distances)
    confidence = gaussian_confidence(g_pts, tgt_part, status, tgt_pts, vertex_part, margin, kept)
    diagnostics = MatchDiagnostics(
        alignment=alignment,
        frame=frame,
        reference_points=ref_pts,
        target_points=tgt_pts,
        target_index=index,
        vertex_part=vertex_part,
        vertex_margin=margin,
        kept=kept,
        similarity=similarity,
        boxes=boxes,
        box_rotations=rots,
        box_valid=valid,
        centroids=centroids,
        gaussian_status=status,
        reference_labels=ref_labels,
    )
    return finish_match(reference, target, tgt_part, confidence, diagnostics)
