"""Part mapping with shape correspondence (paper Sec. 3.3).

Steps, each a small pure function:

1. reference labels ``y_ref = argmax_b W(x)`` (:meth:`Reference.part_labels`);
2. the target surface (its mesh, or the Gaussian means) is aligned to the reference
   (:func:`sync4d.align.align_shapes`) and both are put in the reference's normalised frame
   (centroid at 0, unit RMS radius), where the features are computed;
3. mean reference feature per part, ``f_b = mean_{y_ref = b} f_ref`` (:func:`part_mean_features`);
4. each target vertex takes the part of highest cosine similarity (:func:`assign_by_similarity`);
   with ``prototypes`` other than 1 a part is represented by several prototype features (k-means
   within the part) or by all its vertices (nearest-neighbour feature matching), and its similarity
   is that of its most similar prototype (:func:`part_prototype_features`; not in the paper, whose
   single mean loses to a compact neighbouring part at seams: measured in docs/results.md);
5. outliers are dropped: vertices farther from their part's centre than ``outlier_sigma`` robust
   spreads (:func:`remove_outliers`);
6. a box per part around its kept vertices (:func:`part_boxes`), and every Gaussian is given the part
   whose box holds it; several boxes -> the nearest of their part centroids, no box -> the nearest part
   centroid overall (:func:`assign_to_boxes`);
7. confidence per Gaussian: the cosine margin (best minus second-best part) of the nearest kept target
   vertex of its part, clipped to [0, 1]; 0 for orphans (:func:`gaussian_confidence`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from sync4d.align import AlignResult, Similarity, align_shapes, normalization
from sync4d.match_structure import StructureConfig, StructureMatch, match_structure
from sync4d.skeleton import SkeletonConfig, cloud_volume_points, volume_points
from sync4d.surface import area_samples
from sync4d.errors import ConfigError, InputError
from sync4d.interfaces import FeatureExtractor
from sync4d.types import PartMap, Reference, TargetGaussians

log = logging.getLogger(__name__)

IN_ONE_BOX, IN_SEVERAL_BOXES, ORPHAN = 0, 1, 2
BOX_FRAMES: tuple[str, ...] = ("aligned", "pca")
TIE_BREAKS: tuple[str, ...] = ("centroid", "nearest_vertex")
METHODS: tuple[str, ...] = ("auto", "features", "structure")


@dataclass
class MatchConfig:
    """Every option of part matching, with its defaults (the single source of them).

    Attributes:
        method: ``structure`` (curve skeletons matched branch by branch, :mod:`sync4d.match_structure`;
            shapes given upright along ``up_axis``, facing any way), ``features`` (the paper's cosine
            assignment of per-vertex features, then part boxes) or ``auto``: ``features`` when the
            aligned target lies on the reference (alignment residual at most ``auto_residual``: the
            same kind of shape), else ``structure`` (:func:`choose_method`).
        auto_residual: with ``auto``, the largest alignment residual (symmetric chamfer distance after
            ``align``, in RMS radii of the reference) at which the features are used.
        up_axis: the up axis shared by the reference and the (aligned) target.
        align: ``none`` | ``pca`` | ``pca_icp`` | ``upright_icp`` (:func:`sync4d.align.align_shapes`). With
            ``structure``, ``pca``/``pca_icp`` first bring an arbitrarily turned target into the
            reference's frame; ``none``/``upright_icp`` trust that both are upright (the turn about the up
            axis is searched by the structure match itself).
        icp_iterations: ICP iterations of the alignment.
        outlier_sigma: (features) robust spreads beyond which a target vertex is an outlier (<= 0 disables).
        prototypes: (features) ``"1"`` (the paper's part mean), ``"k"`` (k-means prototypes) or ``"all"``.
        smooth_neighbours: (features) k of the label vote after the cosine assignment (0 = off).
        tie_break: (features) ``centroid`` | ``nearest_vertex``: the part of a Gaussian in several boxes.
        box_frame: (features) ``aligned`` | ``pca`` part boxes.
        box_padding: (features) box growth as a fraction of its size per side.
        max_target_vertices: Gaussian means used as the surface when the target has no mesh.
        min_opacity: Gaussians below this opacity are not surface points.
        structure: options of the structure match.
    """

    method: Literal["auto", "features", "structure"] = "auto"
    auto_residual: float = 0.155
    up_axis: Literal["x", "y", "z"] = "y"
    align: Literal["none", "pca", "pca_icp", "upright_icp"] = "upright_icp"
    icp_iterations: int = 100
    outlier_sigma: float = 2.5
    prototypes: str = "all"
    smooth_neighbours: int = 0
    tie_break: Literal["centroid", "nearest_vertex"] = "nearest_vertex"
    box_frame: Literal["aligned", "pca"] = "aligned"
    box_padding: float = 0.02
    max_target_vertices: int = 6000
    min_opacity: float = 0.1
    structure: StructureConfig = field(default_factory=StructureConfig)

    def validate(self) -> MatchConfig:
        """Raise ConfigError naming the first bad option."""
        choices = {
            "method": METHODS,
            "up_axis": ("x", "y", "z"),
            "align": ("none", "pca", "pca_icp", "upright_icp"),
            "tie_break": TIE_BREAKS,
            "box_frame": BOX_FRAMES,
        }
        for key, allowed in choices.items():
            if getattr(self, key) not in allowed:
                raise ConfigError(f"match.{key}={getattr(self, key)!r}: use one of {', '.join(allowed)}")
        prototype_count(self.prototypes)
        if not self.auto_residual >= 0.0:
            raise ConfigError(f"match.auto_residual={self.auto_residual}: use a residual >= 0 (RMS radii)")
        if self.icp_iterations < 1 or self.max_target_vertices < 16 or self.structure.yaw_steps < 1:
            raise ConfigError(
                "match.icp_iterations, match.structure.yaw_steps must be >= 1 and " "match.max_target_vertices >= 16"
            )
        if self.structure.skeleton.samples < 64 or self.structure.skeleton.neighbours < 3:
            raise ConfigError("match.structure.skeleton.samples must be >= 64 and .neighbours >= 3")
        return self


@dataclass(frozen=True)
class MatchDiagnostics:
    """Everything :func:`match_parts_detailed` computed on the way, for logs, pictures and tests.

    Attributes:
        alignment: the target -> reference alignment.
        frame: similarity taking target coordinates into the common normalised frame (alignment, then
            the reference's normalisation).
        reference_points: (V, 3) reference vertices in the common frame.
        target_points: (M, 3) target surface vertices in the common frame.
        target_index: (M,) indices of the Gaussians used as surface vertices, or None if a mesh was given.
        vertex_part: (M,) part of highest cosine similarity per target vertex (before outlier removal).
        vertex_margin: (M,) cosine margin best minus second-best part per target vertex.
        kept: (M,) bool, False for removed outliers.
        similarity: (M, B) cosine similarities of the target vertices to the part means (None with
            ``method=structure``).
        boxes: (B, 2, 3) per-part box corners (lo, hi) in the box frame (see ``box_rotations``; None with
            ``method=structure``).
        box_rotations: (B, 3, 3) rotation of each box frame (identity for axis-aligned boxes), or None.
        box_valid: (B,) bool, the part kept at least one target vertex.
        centroids: (B, 3) part centroids of the kept target vertices, common frame (NaN if invalid).
        gaussian_status: (N,) 0 in one box, 1 in several (nearest centroid), 2 orphan (nearest centroid);
            all 0 with ``method=structure``.
        structure: the skeleton match with ``method=structure``, else None.
        reference_labels: (V,) part of each of ``reference_points``.
        method: the method that made the map (``features`` or ``structure``; ``auto`` picks one).
        auto_residual: with ``method=auto``, the alignment residual the choice was made on, else None.
    """

    alignment: AlignResult
    frame: Similarity
    reference_points: np.ndarray
    target_points: np.ndarray
    target_index: np.ndarray | None
    vertex_part: np.ndarray
    vertex_margin: np.ndarray
    kept: np.ndarray
    similarity: np.ndarray | None
    boxes: np.ndarray | None
    box_rotations: np.ndarray | None
    box_valid: np.ndarray
    centroids: np.ndarray
    gaussian_status: np.ndarray
    structure: StructureMatch | None = None
    reference_labels: np.ndarray | None = None
    method: str = "features"
    auto_residual: float | None = None

    @property
    def vertex_part_final(self) -> np.ndarray:
        """(M,) target vertex parts after outlier removal, -1 for outliers."""
        return np.where(self.kept, self.vertex_part, -1)

    def summary(self) -> dict[str, float]:
        """Scalar numbers worth logging."""
        n = max(len(self.gaussian_status), 1)
        return {
            "align_rotation_deg": self.alignment.transform.rotation_angle_deg,
            "align_scale": self.alignment.transform.scale,
            "align_residual": self.alignment.residual,
            "outlier_fraction": float(1.0 - self.kept.mean()) if len(self.kept) else 0.0,
            "mean_margin": float(self.vertex_margin.mean()) if len(self.vertex_margin) else 0.0,
            "gaussians_in_several_boxes": float((self.gaussian_status == IN_SEVERAL_BOXES).sum() / n),
            "gaussians_orphan": float((self.gaussian_status == ORPHAN).sum() / n),
            "parts_matched": float(self.box_valid.sum()),
            **(
                {
                    "limbs_matched": float(len(self.structure.pairs)),
                    "limbs_left_over": float(len(self.structure.leftover)),
                }
                if self.structure is not None
                else {}
            ),
        }


@dataclass(frozen=True)
class MatchResult:
    """A part map with its diagnostics and the alignment it used.

    Attributes:
        part_map: the parts of the target's Gaussians.
        diagnostics: what was computed on the way.
        alignment: similarity taking the target's coordinates [m] into the reference's [m]; its
            ``rotation.T`` turns reference motion into the target's frame.
        leftover_parts: reference parts that no target Gaussian received.
    """

    part_map: PartMap
    diagnostics: MatchDiagnostics
    alignment: Similarity
    leftover_parts: tuple[int, ...]


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


def prototype_count(spec: int | str) -> int:
    """``match.prototypes`` as a count: ``"all"`` -> 0 (every reference vertex), else an int >= 1."""
    if isinstance(spec, str) and spec.strip().lower() == "all":
        return 0
    try:
        count = int(spec)
    except (TypeError, ValueError):
        count = -1
    if count < 1:
        raise ConfigError(
            f"match.prototypes={spec!r}: use 1 (the paper's part mean), k > 1 (k prototypes per part) or 'all'"
        )
    return count


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


def target_surface(
    target: TargetGaussians, *, max_vertices: int, min_opacity: float, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Surface points of a Gaussian target without a mesh: the means of its visible Gaussians.

    Args:
        target: the Gaussians.
        max_vertices: random subsample size (feature extraction is O(V) to O(V^1.5)).
        min_opacity: Gaussians fainter than this are not surface (floaters, interior fill).

    Returns:
        points (M, 3) [m], index (M,) into the Gaussians.
    """
    index = np.flatnonzero(target.opacities >= min_opacity)
    if len(index) < 8:
        index = np.arange(target.num)
    if len(index) > max_vertices:
        rng = np.random.default_rng(seed)
        index = np.sort(rng.choice(index, size=max_vertices, replace=False))
    return target.means[index].astype(np.float64), index


def _target_points(
    target: TargetGaussians,
    cfg: MatchConfig,
    target_vertices: np.ndarray | None,
    target_faces: np.ndarray | None,
    seed: int,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Target surface vertices (M, 3) [m], their Gaussian index (or None for a mesh) and faces (or None)."""
    if target_vertices is None:
        if target_faces is not None:
            raise InputError("match_parts: target_faces given without target_vertices")
        points, index = target_surface(
            target, max_vertices=cfg.max_target_vertices, min_opacity=cfg.min_opacity, seed=seed
        )
        return points, index, None
    faces = None if target_faces is None else np.asarray(target_faces, dtype=np.int64)
    return np.asarray(target_vertices, dtype=np.float64), None, faces


def match_parts(
    reference: Reference,
    target: TargetGaussians,
    extractor: FeatureExtractor | None,
    config: MatchConfig | None = None,
    *,
    target_vertices: np.ndarray | None = None,
    target_faces: np.ndarray | None = None,
    seed: int = 0,
) -> MatchResult:
    """Part map of the target's Gaussians (paper Sec. 3.3), with the alignment it used.

    Args:
        reference: articulated reference (rest mesh and skinning).
        target: the static Gaussians to label.
        extractor: a built ``features`` component (needed by ``method=features`` only).
        config: options (defaults: ``MatchConfig()``).
        target_vertices: (M, 3) target surface [m] in the Gaussians' frame (e.g. the mesh the Gaussians
            came from); None uses the Gaussian means.
        target_faces: (F, 3) faces of ``target_vertices``, or None.
        seed: subsampling / k-means seed.

    Returns:
        MatchResult: the PartMap (tgt_part per Gaussian), diagnostics, the target -> reference similarity.
    """
    cfg = (config or MatchConfig()).validate()
    if cfg.method == "structure":
        return _match_by_structure(reference, target, cfg, target_vertices, target_faces, seed)
    if extractor is None:
        raise ConfigError(f"match.method={cfg.method} needs a features component (features=geometric, ...)")
    alignment = None
    if cfg.method == "auto":
        tgt_vertices = _target_points(target, cfg, target_vertices, target_faces, seed)[0]
        alignment = align_shapes(
            tgt_vertices, reference.rest_vertices, method=cfg.align, icp_iterations=cfg.icp_iterations, seed=seed
        )
        if choose_method(alignment, cfg.auto_residual) == "structure":
            result = _match_by_structure(reference, target, cfg, target_vertices, target_faces, seed)
        else:
            result = _match_by_features(reference, target, extractor, cfg, target_vertices, target_faces, seed, alignment)
        return replace(result, diagnostics=replace(result.diagnostics, auto_residual=alignment.residual))
    return _match_by_features(reference, target, extractor, cfg, target_vertices, target_faces, seed)


def choose_method(alignment: AlignResult, max_residual: float) -> str:
    """``features`` if the aligned target lies on the reference (residual <= ``max_residual``), else ``structure``.

    The features transfer parts by what lies where once the surfaces overlap (a copy, other proportions
    of one kind: residual 0.03-0.05 RMS radii on the benchmark; the laptop on the clam shell 0.106, the
    laptop reconstructed from its video on it 0.140); across categories no rigid fit puts one shape on
    the other (0.17-0.23), and the skeletons' structure decides. The default 0.155 lies in the middle of
    the gap between the two groups, a thin one (docs/matching.md, "One default: auto").
    """
    method = "features" if alignment.residual <= max_residual else "structure"
    log.info("match: method=auto: alignment residual %.4f %s %.3g -> %s", alignment.residual,
             "<=" if method == "features" else ">", max_residual, method)
    return method


def match_parts_detailed(
    reference: Reference,
    target: TargetGaussians,
    extractor: FeatureExtractor | None,
    config: MatchConfig | None = None,
    **kwargs: object,
) -> MatchResult:
    """Alias of :func:`match_parts` (kept for callers of the earlier name)."""
    return match_parts(reference, target, extractor, config, **kwargs)  # type: ignore[arg-type]


def _finish(
    reference: Reference,
    target: TargetGaussians,
    tgt_part: np.ndarray,
    confidence: np.ndarray,
    diagnostics: MatchDiagnostics,
) -> MatchResult:
    num_parts = reference.num_bones
    part_map = PartMap(
        ref_part=reference.part_labels(), tgt_part=tgt_part, confidence=confidence, num_parts=num_parts
    ).validate()
    got = np.bincount(tgt_part, minlength=num_parts) > 0
    leftover = tuple(int(b) for b in np.flatnonzero(~got))
    log.info("match: %s", ", ".join(f"{k}={v:.4g}" for k, v in diagnostics.summary().items()))
    if leftover:
        names = reference.bone_names or tuple(str(b) for b in range(num_parts))
        log.info("match: reference parts without a target part: %s", ", ".join(names[b] for b in leftover))
    alignment = diagnostics.frame.then(normalization(reference.rest_vertices).inverse())
    return MatchResult(part_map, diagnostics, alignment, leftover)


def surface_samples(vertices: np.ndarray, faces: np.ndarray | None, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3) area-uniform samples of a mesh, or a random subset of the points when there are no faces."""
    if faces is None or len(faces) == 0:
        if len(vertices) <= count:
            return vertices
        return vertices[rng.choice(len(vertices), count, replace=False)]
    tri = vertices[faces]
    sampled = area_samples(tri, count, rng)
    if sampled is None:
        raise InputError("match: the target mesh has zero area")
    face, bary = sampled
    return np.einsum("sk,skd->sd", bary, tri[face])


def skeleton_points(
    vertices: np.ndarray, faces: np.ndarray | None, cfg: SkeletonConfig, rng: np.random.Generator
) -> np.ndarray:
    """The points a curve skeleton is built on: voxels of the solid (``cfg.volume`` and a mesh), else
    surface samples or the given points, subsampled to ``cfg.samples``."""
    return skeleton_points_depth(vertices, faces, cfg, rng)[0]


def skeleton_points_depth(
    vertices: np.ndarray, faces: np.ndarray | None, cfg: SkeletonConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`skeleton_points` and, for voxels of the solid, each one's depth inside it [m] (else None)."""
    depth = None
    if cfg.volume and faces is not None and len(faces):
        pts, depth = volume_points(vertices, faces, cfg.resolution, rng, with_depth=True)
    elif cfg.volume:
        pts, depth = cloud_volume_points(vertices, cfg.resolution, with_depth=True)
    else:
        pts = surface_samples(vertices, faces, cfg.samples, rng)
    if len(pts) > cfg.samples:
        keep = rng.choice(len(pts), cfg.samples, replace=False)
        pts, depth = pts[keep], None if depth is None else depth[keep]
    return pts, depth


def label_agreement(points: np.ndarray, labels: np.ndarray, neighbours: int = 8) -> np.ndarray:
    """(N,) fraction of each point's nearest ``neighbours`` points that share its label (a confidence)."""
    k = int(min(neighbours, len(points)))
    _, idx = cKDTree(points).query(points, k=k)
    return (labels[idx.reshape(len(points), k)] == labels[:, None]).mean(axis=1)


def _match_by_structure(
    reference: Reference,
    target: TargetGaussians,
    cfg: MatchConfig,
    target_vertices: np.ndarray | None,
    target_faces: np.ndarray | None,
    seed: int,
) -> MatchResult:
    """Structure-aware matching (:mod:`sync4d.match_structure`) wrapped into a MatchResult."""
    rng = np.random.default_rng(seed)
    tgt_vertices, index, tgt_faces = _target_points(target, cfg, target_vertices, target_faces, seed)
    if (
        tgt_vertices.ndim != 2
        or tgt_vertices.shape[1] != 3
        or len(tgt_vertices) < 16
        or not np.isfinite(tgt_vertices).all()
    ):
        raise InputError(
            f"match: the target surface must be (M >= 16, 3) finite points, got {tgt_vertices.shape}"
            " (NaN/inf or too few Gaussians above match.min_opacity)"
        )
    if cfg.align in ("pca", "pca_icp"):
        alignment = align_shapes(
            tgt_vertices, reference.rest_vertices, method=cfg.align, icp_iterations=cfg.icp_iterations, seed=seed
        )
    else:
        alignment = AlignResult(Similarity.identity(), float("nan"), np.zeros(0), "none")
    # the reference's surface is enough: its parts give the trunk, and distances are taken from it
    ref_samples = skeleton_points(
        reference.rest_vertices, reference.rest_faces, replace(cfg.structure.skeleton, volume=False), rng
    )
    ref_norm = normalization(reference.rest_vertices)
    _, nearest = cKDTree(reference.rest_vertices).query(ref_samples)
    ref_labels = reference.part_labels()[nearest]
    pre = alignment.transform
    tgt_raw, tgt_depth = skeleton_points_depth(tgt_vertices, tgt_faces, cfg.structure.skeleton, rng)
    tgt_samples = pre.apply(tgt_raw)
    tgt_norm = normalization(tgt_samples)
    # the structure match works on each shape normalised by itself, then turns the target about the up axis
    sm = match_structure(
        ref_norm.apply(ref_samples),
        ref_labels,
        reference.num_bones,
        tgt_norm.apply(tgt_samples),
        cfg.structure,
        up_axis=cfg.up_axis,
        part_parents=reference.bone_parents,
        tgt_depth=None if tgt_depth is None else tgt_depth * pre.scale * tgt_norm.scale,
        turn_cost=cfg.structure.aligned_turn_cost if cfg.align in ("pca", "pca_icp") else 0.0,
    )
    frame = pre.then(tgt_norm).then(Similarity(sm.rotation, 1.0, np.zeros(3)))
    sample_pts = tgt_norm.apply(tgt_samples) @ sm.rotation.T
    g_pts = frame.apply(target.means)
    _, j = cKDTree(sample_pts).query(g_pts)
    tgt_part = sm.point_part[j]
    agreement = label_agreement(sample_pts, sm.point_part)
    confidence = agreement[j]
    valid = np.bincount(sm.point_part, minlength=reference.num_bones) > 0
    centroids = np.full((reference.num_bones, 3), np.nan)
    for b in np.flatnonzero(valid):
        centroids[b] = sample_pts[sm.point_part == b].mean(axis=0)
    diagnostics = MatchDiagnostics(
        alignment=alignment,
        frame=frame,
        reference_points=ref_norm.apply(ref_samples),
        target_points=sample_pts,
        target_index=index,
        vertex_part=sm.point_part,
        vertex_margin=agreement,
        kept=np.ones(len(sample_pts), dtype=bool),
        similarity=None,
        boxes=None,
        box_rotations=None,
        box_valid=valid,
        centroids=centroids,
        gaussian_status=np.zeros(target.num, dtype=np.int8),
        structure=sm,
        reference_labels=ref_labels,
        method="structure",
    )
    return _finish(reference, target, tgt_part, confidence, diagnostics)


def _match_by_features(
    reference: Reference,
    target: TargetGaussians,
    extractor: FeatureExtractor,
    cfg: MatchConfig,
    target_vertices: np.ndarray | None,
    target_faces: np.ndarray | None,
    seed: int,
    alignment: AlignResult | None = None,
) -> MatchResult:
    """The paper's part mapping (Sec. 3.3), with alignment first (unless given); see the module docstring."""
    num_parts = reference.num_bones
    ref_labels = reference.part_labels()
    tgt_vertices, index, tgt_faces = _target_points(target, cfg, target_vertices, target_faces, seed)
    if alignment is None:
        alignment = align_shapes(
            tgt_vertices, reference.rest_vertices, method=cfg.align, icp_iterations=cfg.icp_iterations, seed=seed
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
    per_part = prototype_count(cfg.prototypes)
    if per_part == 1:
        similarity = cosine_similarity(f_tgt, means)  # the paper's rule, exactly
    else:
        protos, owner = part_prototype_features(f_ref, ref_labels, num_parts, per_part, seed=seed)
        similarity = prototype_similarity(f_tgt, protos, owner, num_parts)
    vertex_part, margin = assign_by_similarity(similarity, present)
    if cfg.smooth_neighbours > 1:
        vertex_part = smooth_labels(tgt_pts, vertex_part, similarity, num_parts, cfg.smooth_neighbours)
    kept = remove_outliers(tgt_pts, vertex_part, num_parts, cfg.outlier_sigma)
    boxes, rots, valid, centroids = part_boxes(
        tgt_pts, vertex_part, kept, num_parts, frame=cfg.box_frame, padding=cfg.box_padding
    )
    g_pts = frame.apply(target.means)
    distances = part_distances(
        g_pts,
        centroids,
        valid,
        **(
            {"vertex_points": tgt_pts[kept], "vertex_labels": vertex_part[kept]}
            if cfg.tie_break == "nearest_vertex"
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
    return _finish(reference, target, tgt_part, confidence, diagnostics)
