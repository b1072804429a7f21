"""Structure-aware part matching: the target's curve skeleton matched to the reference's, branch by branch.

Both shapes get a curve skeleton (:mod:`sync4d.match.skeleton`) in their own normalised frame (centroid at 0,
unit RMS radius; both upright along ``up_axis``). Then:

1. the reference's limbs come from its parts: the parts touching each other form a tree (spanning tree
   of the strongest contacts, rooted at the part holding the centre); the trunk is the root and every
   part where three or more parts meet, with the parts between them; each subtree hanging off the trunk
   is a limb (:func:`reference_limbs`). Every non-root branch of the target's skeleton (with its whole
   subtree) is a candidate for one reference limb (:func:`limb_descriptors`);
2. for each turn of the target about the up axis (``yaw_steps`` of them), the reference limbs are
   assigned to target subtrees by the Hungarian method on a cost of where each limb leaves the trunk,
   where it ends, its direction, its length and where its foot points (:func:`limb_cost`); a limb may stay unmatched at cost
   ``miss_cost`` (a target with fewer limbs: a cross, a table), and an assignment that holds a subtree
   and one of its descendants is re-solved with that pair forbidden (:func:`assign_limbs`). The turn of
   lowest assignment cost plus chamfer distance wins (the shapes need not face the same way), unless the best
   turn at least 90 deg from it gives the limbs without a left/right partner (a head, a tail) branches whose
   thickness agrees better with theirs (:func:`sync4d.match.heading.face_by_thickness`);
3. a matched target subtree takes the reference limb's parts by relative geodesic position along it
   (0 where it leaves the trunk, 1 at its tip), so a longer or bent limb keeps its thigh/shin/foot
   proportions (:func:`transfer_along`); everything else (trunk, unmatched target branches) takes the
   part of the nearest reference trunk point in the turned frame.

Left/right: limbs hanging from the same trunk part with as many parts are partners (:func:`limb_partners`);
a partner left over takes the free branch at the mirror image of the other's (:func:`complete_partners`),
and a tail holding that branch hands it over (:func:`mirror_repair`); a partner on a side branch while the
other holds a branch straddling the plane hands the side branch to a left-over pair (:func:`straddle_repair`).
The branches between the root and a matched limb's branch are trunk (:func:`trunk_branches`). Limbs still
unmatched then take the outermost free branches at least cost, whatever the miss cost (:func:`pair_leftovers`),
when that labelling keeps at least as much of the reference's structure (:meth:`TargetLabelling.kept`).
A matched branch's levels that continue a column-shaped root into a thicker part (a lamp's pole under its
shade) are trunk (:func:`sync4d.match.regions.trunk_column`); the legs end at the body's underside
(:func:`sync4d.match.regions.legs_to_underside`). Unmatched reference limbs are reported
(``StructureMatch.leftover``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from sync4d.match.align import axis_rotation, chamfer_distance
from sync4d.match.consistency import consistency
from sync4d.match.heading import face_by_thickness, reference_thickness, target_thickness
from sync4d.match.regions import label_regions, local_thickness, trunk_column
from sync4d.match.skeleton import CurveSkeleton, SkeletonConfig, curve_skeleton, neighbour_graph

UP_AXES = {"x": 0, "y": 1, "z": 2}


@dataclass
class StructureConfig:
    """Options of the branch assignment (distances in RMS-radius units of each shape).

    Attributes:
        skeleton: curve skeleton options.
        yaw_steps: turns of the target about the up axis tried (360 / yaw_steps degrees apart).
        miss_cost: cost of leaving a reference limb unmatched.
        base_weight: weight of the horizontal base offset term of :func:`limb_cost`.
        reference_base_share: a reference limb's base is the centroid of its first this share of its
            length (:func:`limb_descriptors`).

        length_weight: weight of the squared log length ratio in the limb cost.
        direction_weight: weight of the squared difference of unit limb directions.
        tip_weight: weight of the tip-direction term (the base term has weight 1: where a limb leaves the
            trunk does not change with the pose, where it ends does).
        area_weight: weight of the squared log ratio of the limbs' shares of the surface.
        attach_weight: weight of the squared difference of where the limbs leave the trunk along the up
            axis, relative to the trunk's height (:func:`attach_heights`): a pose-free role (legs leave
            at the trunk's bottom, arms at its top, whatever the pose).
        chamfer_weight: weight of the chamfer distance of the turned shapes in the choice of the turn.
        foot_weight: weight of the term of where a limb's foot points (:func:`limb_feet`) in the limb cost: a
            target nearly symmetric front to back (a toy) faces the way its feet point.
        aligned_turn_cost: with ``match.align`` = ``pca``/``pca_icp`` (the target was fitted to the
            reference), the cost of turning it half a turn away from the fitted heading.
        profile_bins: bins of relative position along a limb in the part profile.
        mirror_repair: apply :func:`mirror_repair` to the chosen assignment.
        limb_reach: a matched limb grows over the target's solid within this many limb thicknesses of its
            branch, where the solid is thinner than half-way to the trunk (:func:`sync4d.match.regions.grow_limbs`).
    """

    skeleton: SkeletonConfig = field(default_factory=SkeletonConfig)
    yaw_steps: int = 24
    base_weight: float = 0.5
    reference_base_share: float = 0.4
    miss_cost: float = 3.0
    length_weight: float = 0.1
    direction_weight: float = 0.5
    tip_weight: float = 1.0
    area_weight: float = 0.5
    attach_weight: float = 1.0
    chamfer_weight: float = 2.0
    foot_weight: float = 5.0
    aligned_turn_cost: float = 4.0
    mirror_repair: bool = True
    profile_bins: int = 20
    limb_reach: float = 3.0


@dataclass(frozen=True)
class LimbSet:
    """Descriptors of a set of limbs (point sets) of one skeleton.

    Attributes:
        members: per limb, the (Q,) indices of its points.
        base: (L, 3) where each limb leaves the trunk: centroid of its level nearest the centre.
        tip: (L, 3) centroid of its farthest level.
        base_level: (L,) geodesic distance of the base from the centre.
        length: (L,) geodesic extent from the base to the tip.
        area: (L,) the limb's share of the shape's surface points (for voxels: of the outer layer).
        foot: (L, 3) where each limb's foot points (:func:`limb_feet`), or None.
        thickness: (L,) each limb's thickness over its trunk's (:mod:`sync4d.match.heading`), or None.
    """

    members: tuple[np.ndarray, ...]
    base: np.ndarray
    tip: np.ndarray
    base_level: np.ndarray
    length: np.ndarray
    area: np.ndarray
    foot: np.ndarray | None = None
    thickness: np.ndarray | None = None

    def relative_position(self, geodesic: np.ndarray, limb: int) -> np.ndarray:
        """(Q,) relative geodesic position in [0, 1] of the limb's points (0 at the base, 1 at the tip)."""
        return np.clip((geodesic[self.members[limb]] - self.base_level[limb]) / self.length[limb], 0.0, 1.0)


@dataclass(frozen=True)
class StructureMatch:
    """Outcome of :func:`match_structure`.

    Attributes:
        reference: the reference's curve skeleton (normalised reference frame).
        target: the target's curve skeleton (normalised target frame).
        rotation: (3, 3) turn about the up axis taking the normalised target into the normalised reference.
        pairs: (P, 2) matched (reference limb index into ``limbs``, target branch).
        limbs: the reference's limbs, each a tuple of its part indices.
        leftover: the reference limbs (tuples of part indices) left unmatched.
        point_part: (M,) reference part of each target skeleton point.
        cost: assignment cost of the chosen turn.
    """

    reference: CurveSkeleton
    target: CurveSkeleton
    rotation: np.ndarray
    pairs: np.ndarray
    limbs: tuple[tuple[int, ...], ...]
    leftover: tuple[tuple[int, ...], ...]
    point_part: np.ndarray
    cost: float


def limb_descriptors(
    skeleton: CurveSkeleton,
    members: list[np.ndarray],
    depth: np.ndarray | None = None,
    base_share: float = 0.0,
) -> LimbSet:
    """Descriptors of limbs given as point index sets of ``skeleton``; ``depth`` (M,) marks a solid's
    points (voxels), whose outer layer then stands for the surface in the limbs' shares.

    The base is the centroid of the limb's first level, or of its first ``base_share`` of its length if
    that is longer (for a reference limb, whose first level is where it touches the trunk: a thigh's
    inner side, near the body's midline, not its hip).
    """
    geo, pts, h = skeleton.geodesic, skeleton.points, skeleton.level_width
    base, tip, base_level, length = [], [], [], []
    for m in members:
        g = geo[m]
        lo, hi = float(g.min()), float(g.max())
        base.append(pts[m[g <= lo + max(h, base_share * (hi - lo))]].mean(axis=0))
        tip.append(pts[m[g >= hi - h]].mean(axis=0))
        base_level.append(lo)
        length.append(max(hi - lo, 1e-9))
    surface = np.ones(len(pts), dtype=bool)
    if depth is not None:
        # the solid's outer layer of voxels stands for its surface: shares and radii then compare with
        # those of a reference given by surface samples
        surface = depth <= 1.5 * float(depth[depth > 0].min() if (depth > 0).any() else 1.0)
    area = np.array([surface[m].sum() / max(surface.sum(), 1) for m in members])
    return LimbSet(
        tuple(members),
        np.array(base).reshape(-1, 3),
        np.array(tip).reshape(-1, 3),
        np.array(base_level),
        np.array(length),
        area,
    )


def limb_feet(points: np.ndarray, members: list[np.ndarray] | tuple[np.ndarray, ...], up: int, sole: float = 0.05,
              shins: float = 0.25) -> np.ndarray:
    """(L, 3) where each limb's foot points: the horizontal offset of the centroid of its points in the lowest
    ``sole`` of the shape's height from the centroid of its points in the band above (up to ``shins``).

    Toes, paws and a toy's feet reach forward of the legs they stand on. A limb that does not reach the
    ground (an arm, a raised tail) has no foot: (0, 0, 0), as has one with no points in the band.
    """
    h = points[:, up]
    rel = (h - h.min()) / max(float(np.ptp(h)), 1e-9)
    out = np.zeros((len(members), 3))
    for i, m in enumerate(members):
        low, band = m[rel[m] <= sole], m[(rel[m] > sole) & (rel[m] <= shins)]
        if len(low) and len(band):
            out[i] = points[low].mean(axis=0) - points[band].mean(axis=0)
    out[:, up] = 0.0
    return out


def with_feet(limbs: LimbSet, points: np.ndarray, up: int) -> LimbSet:
    """``limbs`` with their feet (:func:`limb_feet`) on the skeleton points ``points``."""
    return replace(limbs, foot=limb_feet(points, limbs.members, up))


def attach_heights(skeleton: CurveSkeleton, members: list[np.ndarray] | tuple[np.ndarray, ...], trunk: np.ndarray,
                   up: int, away: np.ndarray | None = None) -> np.ndarray:
    """(L,) where each limb leaves the trunk along the up axis: its height above the trunk's middle over the
    trunk's length (clipped to [-2, 2]).

    A target branch leaves the trunk at its first level (its points within one level of its lowest
    geodesic distance from the core). A reference limb can lie along the trunk (an arm hanging beside
    the chest touches it from shoulder to elbow), so with ``away`` (L, 3) it leaves at the end of its
    points (``members``: the limb's first part) farthest from ``away`` (the centroid of the limb's
    other parts, or its tip), within one level: the shoulder, the hip, the neck's base. The trunk's
    middle is that of the 2-98 % range of ``trunk``'s points (indices) along ``up``, its length the
    2-98 % range along its principal axis (a standing body's height, a lying one's or a table top's
    length: the term stays small where the trunk is flat). Where a limb leaves does not change with the
    pose: a toy's arms hanging down leave its body half-way up, its legs at the bottom, its head at the top.
    """
    h, w = skeleton.points[:, up], skeleton.level_width
    body = skeleton.points[trunk] if len(trunk) >= 3 else skeleton.points
    lo, hi = np.percentile(body[:, up], [2.0, 98.0])
    axis = np.linalg.svd(body - body.mean(axis=0), full_matrices=False)[2][0]
    along = np.percentile(body @ axis, [2.0, 98.0])
    length = max(float(along[1] - along[0]), 1e-9)
    out = []
    for i, m in enumerate(members):
        if away is None:
            g = skeleton.geodesic[m]
            near = g <= g.min() + w
        else:
            d = np.linalg.norm(skeleton.points[m] - away[i], axis=1)
            near = d >= d.max() - w
        out.append(float(h[m[near]].mean()))
    return np.clip((np.array(out) - 0.5 * (lo + hi)) / length, -2.0, 2.0)


def reference_attach(skeleton: CurveSkeleton, labels: np.ndarray, limb_parts: list[list[int]], parent: np.ndarray,
                     limbs: LimbSet, in_trunk: np.ndarray, up: int) -> np.ndarray:
    """(L,) :func:`attach_heights` of the reference's limbs: each leaves the trunk at the end of its first
    part (the one hanging from the trunk) farthest from its other parts (or, for a one-part limb, its tip)."""
    first, away = [], []
    for i, parts in enumerate(limb_parts):
        root = next(q for q in parts if int(parent[q]) not in parts)
        own = np.flatnonzero(labels == root)
        rest = np.flatnonzero(np.isin(labels, [q for q in parts if q != root]))
        first.append(own if len(own) else limbs.members[i])
        away.append(skeleton.points[rest].mean(axis=0) if len(rest) else limbs.tip[i])
    return attach_heights(skeleton, first, np.flatnonzero(in_trunk), up, np.array(away).reshape(-1, 3))


def part_tree(
    points: np.ndarray, labels: np.ndarray, num_parts: int, root: int, *, contact_spacings: float = 5.0
) -> np.ndarray:
    """(B,) parent part of each part in the spanning tree of strongest contacts (-1: root or absent).

    Two parts touch where their points are within ``contact_spacings`` median spacings (capsule bodies
    leave gaps at the joints); the contact strength is the
    number of such point pairs; the tree is the maximum spanning tree of the contact graph.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

    tree = cKDTree(points)
    spacing = float(np.median(tree.query(points, 2)[0][:, 1]))
    pairs = tree.query_pairs(contact_spacings * spacing, output_type="ndarray")
    a, b = labels[pairs[:, 0]], labels[pairs[:, 1]]
    diff = a != b
    contact = np.zeros((num_parts, num_parts))
    np.add.at(contact, (a[diff], b[diff]), 1.0)
    contact = contact + contact.T
    strength = np.where(contact > 0, 1.0 / (1.0 + contact), 0.0)  # strong contact = short edge
    mst = minimum_spanning_tree(coo_matrix(strength)).toarray()
    mst = (mst + mst.T) > 0
    order, pred = breadth_first_order(mst, root, directed=False, return_predecessors=True)
    parent = np.full(num_parts, -1, dtype=np.int64)
    parent[order[1:]] = pred[order[1:]]
    return parent


def _depth(parent: np.ndarray, p: int) -> int:
    d = 0
    while parent[p] >= 0:
        p, d = int(parent[p]), d + 1
    return d


def bone_tree(skeleton: CurveSkeleton, labels: np.ndarray, num_parts: int, parents: np.ndarray | None
              ) -> tuple[np.ndarray, int]:
    """(B,) parent part of each part, one tree (further roots of a forest hang off the main root), and
    its root part: ``parents`` if known, else from the contacts (:func:`part_tree`)."""
    if parents is None:
        root = int(labels[skeleton.centre])
        return part_tree(skeleton.points, labels, num_parts, root), root
    parent = np.asarray(parents, dtype=np.int64)
    roots = np.flatnonzero(parent < 0)
    root = int(labels[skeleton.centre]) if int(labels[skeleton.centre]) in roots else int(roots[0])
    return np.where((parent < 0) & (np.arange(num_parts) != root), root, parent), root


def reference_limbs(
    skeleton: CurveSkeleton,
    labels: np.ndarray,
    num_parts: int,
    parents: np.ndarray | None = None,
    *,
    min_share: float = 0.02,
) -> tuple[list[list[int]], list[int]]:
    """The reference's limbs as lists of parts, and its trunk parts (see the module docstring).

    Args:
        skeleton: the reference's curve skeleton.
        labels: (M,) part per skeleton point.
        num_parts: B.
        parents: (B,) the known bone tree (-1 for roots), e.g. of a mocap skeleton; None derives it from
            the contacts between parts (:func:`part_tree`), which touching limbs can mislead.
        min_share: smallest share of the points a child subtree needs to count at a trunk junction.
    """
    parent, root = bone_tree(skeleton, labels, num_parts, parents)
    present = set(np.unique(labels).tolist()) | {root}
    kids: dict[int, list[int]] = {p: [] for p in present}
    for c in present:
        if parent[c] >= 0:
            kids[int(parent[c])].append(c)
    share = {p: float((labels == p).mean()) for p in present}
    for p in sorted(present, key=lambda q: -_depth(parent, q)):  # children before parents
        if parent[p] >= 0:
            share[int(parent[p])] += share[p]
    # a junction of the trunk is where two or more sizeable subtrees leave (a hand with a thumb and
    # fingers is not one); the trunk is the root, those junctions and the parts between them
    trunk = {root} | {p for p in present if sum(share[c] >= min_share for c in kids[p]) >= 2}
    for p in list(trunk):  # the parts between two trunk parts are trunk too
        a = int(parent[p])
        path = []
        while a >= 0 and a not in trunk:
            path.append(a)
            a = int(parent[a])
        if a >= 0:
            trunk |= set(path)
    limbs = []
    for p in sorted(trunk):
        for c in kids[p]:
            if c in trunk:
                continue
            sub, stack = [], [c]
            while stack:
                q = stack.pop()
                sub.append(q)
                stack += kids[q]
            limbs.append(sorted(sub))
    return limbs, sorted(trunk)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def horizontal_scale(points: np.ndarray, rotation: np.ndarray, up: int) -> np.ndarray:
    """(3,) per-axis spread of ``points @ rotation.T`` with the up axis left at 1 (see :func:`limb_cost`)."""
    spread = np.sqrt(np.maximum(np.diag(rotation @ np.cov(points.T) @ rotation.T), 1e-12))
    spread[up] = 1.0
    return spread


def limb_cost(
    ref: LimbSet,
    tgt: LimbSet,
    rotation: np.ndarray,
    config: StructureConfig,
    *,
    up: int = 1,
    ref_scale: np.ndarray | None = None,
    tgt_scale: np.ndarray | None = None,
    ref_attach: np.ndarray | None = None,
    tgt_attach: np.ndarray | None = None,
) -> np.ndarray:
    """(R, T) cost of giving reference limb r the target subtree t, target turned by ``rotation``.

    Terms: where the limb leaves the trunk seen from above (its base's horizontal offset from the centre,
    each horizontal axis divided by the shape's spread along it, so that a narrow body's left/right
    offset counts as much as a long body's front/back one; the height of a base depends on where the
    target's level sets split and is not compared); ``tip_weight`` x the squared difference of the unit
    directions from the centre to the tips; ``direction_weight`` x that of the unit base -> tip
    directions; ``length_weight`` x the squared log length ratio; ``area_weight`` x the squared log
    ratio of the shares of the points (a leg is not half a body); ``attach_weight`` x the squared
    difference of the relative attachment heights ``ref_attach`` (R,), ``tgt_attach`` (T,) if given;
    ``foot_weight`` x :func:`foot_disagreement`.
    """
    tb, tt = tgt.base @ rotation.T, tgt.tip @ rotation.T
    rs = np.ones(3) if ref_scale is None else ref_scale
    ts = np.ones(3) if tgt_scale is None else tgt_scale
    flat = np.ones(3)
    flat[up] = 0.0
    hb_r, hb_t = ref.base * flat / rs, tb * flat / ts
    d_base = ((hb_r[:, None] - hb_t[None]) ** 2).sum(-1)
    d_tip = ((_unit(ref.tip)[:, None] - _unit(tt)[None]) ** 2).sum(-1)
    d_dir = ((_unit(ref.tip - ref.base)[:, None] - _unit(tt - tb)[None]) ** 2).sum(-1)
    d_len = np.log(np.maximum(ref.length[:, None], 1e-6) / np.maximum(tgt.length[None], 1e-6)) ** 2
    # one-sided: a target branch holding more than the limb is penalised (a leg is not half a body), a
    # smaller one is not (the target's levels split where a limb leaves the trunk's level sets, often
    # below where it leaves the trunk, so a target limb branch is typically a limb's lower part)
    d_area = np.maximum(np.log(np.maximum(tgt.area[None], 1e-6) / np.maximum(ref.area[:, None], 1e-6)), 0.0) ** 2
    d_attach = 0.0 if ref_attach is None or tgt_attach is None else (ref_attach[:, None] - tgt_attach[None]) ** 2
    return (
        config.attach_weight * d_attach
        + config.foot_weight * foot_disagreement(ref, tgt, rotation)
        + config.base_weight * d_base
        + config.tip_weight * d_tip
        + config.direction_weight * d_dir
        + config.length_weight * d_len
        + config.area_weight * d_area
    )


def foot_disagreement(ref: LimbSet, tgt: LimbSet, rotation: np.ndarray) -> np.ndarray:
    """(R, T) how far the turned target limb's foot points away from the reference limb's: the shorter foot
    vector's length times (1 - cos) / 2 of the angle between them; 0 where either limb has no foot."""
    if ref.foot is None or tgt.foot is None:
        return np.zeros((len(ref.members), len(tgt.members)))
    turned = tgt.foot @ rotation.T
    n_r, n_t = np.linalg.norm(ref.foot, axis=1), np.linalg.norm(turned, axis=1)
    cos = (ref.foot @ turned.T) / np.maximum(n_r[:, None] * n_t[None], 1e-12)
    return np.minimum(n_r[:, None], n_t[None]) * (1.0 - cos) / 2.0


def assign_limbs(
    cost: np.ndarray, skeleton: CurveSkeleton, candidates: np.ndarray, miss_cost: float, *, max_rounds: int = 32
) -> tuple[list[tuple[int, int]], float]:
    """Hungarian assignment of reference limbs (rows) to target subtrees (columns) without nesting.

    A row may take a dummy column at ``miss_cost`` (unmatched). When two chosen subtrees are nested
    (one is an ancestor of the other), the pair of higher cost is forbidden and the problem re-solved.

    Returns:
        (row, column) pairs and the total cost (misses included).
    """
    work = cost.copy()
    n_r, n_c = work.shape
    big = 1e6
    pairs: list[tuple[int, int]] = []
    total = float(n_r * miss_cost)
    for _ in range(max_rounds):
        full = np.full((n_r, n_c + n_r), big)
        full[:, :n_c] = np.minimum(work, big)
        full[np.arange(n_r), n_c + np.arange(n_r)] = miss_cost
        rows, cols = linear_sum_assignment(full)
        pairs = [(int(r), int(c)) for r, c in zip(rows, cols) if c < n_c and full[r, c] < big]
        total = float(full[rows, cols].sum())
        clash = None
        for i, (r1, c1) in enumerate(pairs):
            for r2, c2 in pairs[i + 1 :]:
                a, b = int(candidates[c1]), int(candidates[c2])
                if skeleton.is_ancestor(a, b) or skeleton.is_ancestor(b, a):
                    clash = (r1, c1) if work[r1, c1] >= work[r2, c2] else (r2, c2)
                    break
            if clash:
                break
        if clash is None:
            break
        work[clash] = big
    return pairs, total


def transfer_along(
    ref: CurveSkeleton,
    ref_limbs: LimbSet,
    r: int,
    ref_labels: np.ndarray,
    tgt: CurveSkeleton,
    tgt_limbs: LimbSet,
    t: int,
    num_parts: int,
    bins: int,
) -> np.ndarray:
    """(Q,) reference part of each point of target limb ``t`` by its relative position along the limb.

    The reference limb's parts are tabulated per bin of relative position (majority part; an empty bin
    takes the nearest filled one), and each target point takes the part of its bin.
    """
    s_ref = ref_limbs.relative_position(ref.geodesic, r)
    k = np.clip((s_ref * bins).astype(np.int64), 0, bins - 1)
    votes = np.zeros((bins, num_parts))
    np.add.at(votes, (k, ref_labels[ref_limbs.members[r]]), 1.0)
    filled = np.flatnonzero(votes.sum(1) > 0)
    profile = np.argmax(votes, axis=1)
    profile = profile[filled[np.argmin(np.abs(np.arange(bins)[:, None] - filled[None]), axis=1)]]
    s_tgt = tgt_limbs.relative_position(tgt.geodesic, t)
    return profile[np.clip((s_tgt * bins).astype(np.int64), 0, bins - 1)]


def distance_from_trunk(skeleton: CurveSkeleton, trunk: np.ndarray, config: SkeletonConfig) -> CurveSkeleton:
    """The skeleton with its geodesic distance measured from the trunk's points instead of the centre.

    The reference's parts say where its trunk is; along a limb the distance from the trunk is the
    relative position that :func:`transfer_along` maps (0 where the limb leaves the trunk).
    """
    if not trunk.any():
        return skeleton
    graph = neighbour_graph(skeleton.points, config.neighbours, config.max_edge_factor)
    geo = dijkstra(graph, directed=False, indices=np.flatnonzero(trunk), min_only=True)
    return replace(skeleton, geodesic=np.where(np.isfinite(geo), geo, 0.0))


def yaw_rotations(up_axis: str, steps: int) -> list[np.ndarray]:
    """Rotations about the up axis, ``steps`` of them evenly spaced, identity first."""
    axis = UP_AXES[up_axis]
    return [axis_rotation(axis, 2 * np.pi * k / max(steps, 1)) for k in range(max(steps, 1))]


def mirror_plane_pairs(bases: np.ndarray, up: int, scale: np.ndarray) -> tuple[list[tuple[int, int]], np.ndarray]:
    """The reference's left/right limb pairs and the normal of its vertical plane of symmetry.

    The plane (through the centre, vertical) is the one that best maps the set of limb bases onto
    itself (each horizontal axis divided by the shape's spread along it); a pair is two limbs that are
    each other's nearest base after the reflection, nearer than half their distance apart.

    Returns:
        pairs (i, j), the plane's unit normal (3,) in the scaled frame.
    """
    axes = [a for a in range(3) if a != up]
    pts = bases / scale
    best, best_n = np.inf, np.zeros(3)
    for theta in np.linspace(0.0, np.pi, 36, endpoint=False):
        n = np.zeros(3)
        n[axes[0]], n[axes[1]] = np.cos(theta), np.sin(theta)
        refl = pts - 2.0 * (pts @ n)[:, None] * n
        score = np.linalg.norm(refl[:, None] - pts[None], axis=-1).min(axis=1).sum()
        if score < best:
            best, best_n = score, n
    refl = pts - 2.0 * (pts @ best_n)[:, None] * best_n
    d = np.linalg.norm(refl[:, None] - pts[None], axis=-1)
    near = d.argmin(axis=1)
    apart = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    pairs = [
        (i, int(near[i]))
        for i in range(len(pts))
        if int(near[i]) > i and near[int(near[i])] == i and d[i, near[i]] < 0.5 * apart[i, near[i]]
    ]
    return pairs, best_n


def mirror_repair(
    pairs: list[tuple[int, int]],
    ref: LimbSet,
    tgt: LimbSet,
    rotation: np.ndarray,
    up: int,
    ref_scale: np.ndarray,
    tgt_scale: np.ndarray,
    symmetry: tuple[list[tuple[int, int]], np.ndarray] | None = None,
) -> list[tuple[int, int]]:
    """Give a left/right reference limb whose partner is matched the mirror image of its partner's branch
    when a limb without a partner (a tail, a head) holds that branch.

    A hanging tail can fit a hind leg's branch better than the reference's (posed) hind leg does; the
    body's left/right symmetry says the branch opposite the matched partner is the leg. Bases are
    compared with each horizontal axis divided by the shape's spread (``ref_scale``, ``tgt_scale``), the
    target's turned by ``rotation``; ``pairs`` are (reference limb, target candidate). ``symmetry``: the
    left/right limb pairs and the plane's normal (scaled frame), else :func:`mirror_plane_pairs`'s.
    """
    mirror, normal = symmetry if symmetry is not None else mirror_plane_pairs(ref.base, up, ref_scale)
    paired = {i for p in mirror for i in p}
    held = {r: c for r, c in pairs}
    owner = {c: r for r, c in pairs}
    tb = (tgt.base @ rotation.T) / tgt_scale
    n = normal
    partner = {a: b for i, j in mirror for a, b in ((i, j), (j, i))}

    def mirrored(a: int) -> bool:
        """Limb a's partner holds a branch near the mirror image of a's (a left/right pair that fits)."""
        if partner[a] not in held:
            return True
        here = tb[held[a]]
        image = here - 2.0 * (here @ n) * n
        return 4.0 * float(np.linalg.norm(tb[held[partner[a]]] - image)) < float(np.linalg.norm(here - image))

    for i, j in mirror:
        for a, b in ((i, j), (j, i)):
            if a not in held or b in held:
                continue
            m = tb[held[a]] - 2.0 * (tb[held[a]] @ n) * n
            c = int(np.argmin(np.linalg.norm(tb - m, axis=1)))
            q = owner.get(c)
            if c == held[a] or q is None or (q in paired and mirrored(q)):
                continue
            held[b] = c
            owner[c] = b
            del held[q]
    return sorted(held.items())


def limb_partners(limb_parts: list[list[int]], parent: np.ndarray, base: np.ndarray, length: np.ndarray
                  ) -> list[tuple[int, int]]:
    """Left/right limb pairs read off the bone tree: limbs hanging from the same trunk part with as many
    parts and lengths within a factor 1.5 of each other (arms off the chest, legs off the pelvis); of
    more than two such limbs (four legs off one trunk part), the two of nearest bases pair first. The
    pose enters only there: a leg stretched forward is still the partner of the other."""
    groups: dict[tuple[int, int], list[int]] = {}
    for i, parts in enumerate(limb_parts):
        groups.setdefault((int(parent[min(parts)]), len(parts)), []).append(i)
    out = []
    for group in groups.values():
        close = sorted((float(np.linalg.norm(base[a] - base[b])), a, b) for k, a in enumerate(group)
                       for b in group[k + 1:])
        used: set[int] = set()
        for _, a, b in close:
            if a not in used and b not in used and max(length[a], length[b]) <= 1.5 * min(length[a], length[b]):
                out.append((a, b))
                used |= {a, b}
    return out


def partner_plane(base: np.ndarray, partners: list[tuple[int, int]], up: int, scale: np.ndarray) -> np.ndarray:
    """(3,) unit normal of the vertical plane between left/right partners: the mean direction from one
    base to the other (each horizontal axis divided by the shape's spread ``scale``)."""
    flat = np.ones(3)
    flat[up] = 0.0
    across = np.array([base[a] - base[b] for a, b in partners]).reshape(-1, 3) * flat / scale
    across = across * np.where(across @ across[0] < 0, -1.0, 1.0)[:, None]
    normal = across.mean(axis=0)
    return normal / max(float(np.linalg.norm(normal)), 1e-9)


def complete_partners(
    pairs: list[tuple[int, int]],
    partners: list[tuple[int, int]],
    tgt: LimbSet,
    skeleton: CurveSkeleton,
    cand: np.ndarray,
    rotation: np.ndarray,
    normal: np.ndarray,
    tgt_scale: np.ndarray,
) -> list[tuple[int, int]]:
    """Give an unmatched limb whose partner is matched the free target branch at the mirror image of its
    partner's branch, if there is one.

    The plane of symmetry is vertical through the target's centre with the unit ``normal``
    (:func:`partner_plane`, each horizontal axis divided by the shape's spread ``tgt_scale``). A branch
    qualifies when its base lies nearer that mirror image than the partner's own branch does (by a
    factor 2), and it is not nested with a matched branch: a cow's front leg whose pose puts it far from
    the dog's reaching one.
    """
    tb = (tgt.base @ rotation.T) / tgt_scale
    held = dict(pairs)
    for a, b in partners:
        for x, y in ((a, b), (b, a)):
            if x not in held or y in held:
                continue
            here = tb[held[x]]
            image = here - 2.0 * (here @ normal) * normal
            dist = np.linalg.norm(tb - image, axis=1)
            taken = [int(cand[c]) for c in held.values()]
            free = [c for c in np.argsort(dist) if c not in held.values() and not any(
                skeleton.is_ancestor(int(cand[c]), t) or skeleton.is_ancestor(t, int(cand[c])) for t in taken)]
            if free and 2.0 * dist[free[0]] < float(np.linalg.norm(here - image)):
                held[y] = int(free[0])
    return sorted(held.items())


def straddle_repair(
    pairs: list[tuple[int, int]],
    partners: list[tuple[int, int]],
    cost: np.ndarray,
    side: np.ndarray,
    tgt: LimbSet,
) -> list[tuple[int, int]]:
    """A partner on a side branch while the other partner holds a branch straddling the plane of symmetry
    (two legs in one branch, one leg also on an arm stub): the side branch goes to the left-over partner
    pair (both limbs unmatched) that fits it best by ``cost`` (R, T), and the displaced limb shares the
    straddling branch (:func:`split_partners`); :func:`complete_partners` then gives the taker's partner
    the mirror image. Nothing changes without a left-over pair to take the branch.

    ``side`` (M,) is the signed distance of each target skeleton point from the plane of symmetry; a
    branch straddles it when each side holds at least a quarter of its points (``tgt.members``).
    """
    held = dict(pairs)

    def straddles(c: int) -> bool:
        return 0.25 <= float((side[tgt.members[c]] > 0).mean()) <= 0.75

    for a, b in partners:
        for x, y in ((a, b), (b, a)):
            if x not in held or y not in held or straddles(held[x]) or not straddles(held[y]):
                continue
            free = [(float(cost[t, held[x]]), t) for i, j in partners for t in (i, j) if i not in held and j not in held]
            if free:
                held[min(free)[1]] = held.pop(x)
    return sorted(held.items())


def split_partners(
    pairs: list[tuple[int, int]],
    partners: list[tuple[int, int]],
    ref_base: np.ndarray,
    normal: np.ndarray,
    tgt_points: np.ndarray,
    tgt: LimbSet,
) -> list[tuple[int, int, np.ndarray]]:
    """Two partner limbs in one target branch (two legs whose levels part too low to be two branches):
    when a limb is matched, its partner is not, and the branch straddles the plane of symmetry (each side
    holds at least a quarter of its points), the partner takes the branch's half on its own side.

    Args:
        pairs: (reference limb, candidate) pairs; partners: left/right limb pairs (:func:`limb_partners`).
        ref_base: (R, 3) reference limb bases, each horizontal axis divided by the shape's spread.
        normal: (3,) unit normal of the vertical plane of symmetry in that frame (:func:`partner_plane`).
        tgt_points: (M, 3) target skeleton points, turned into the reference's frame and divided by the
            target's spread per axis; tgt: the candidates' limb sets.

    Returns:
        (partner limb, candidate, mask over the candidate's members of the partner's half) per split.
    """
    held = dict(pairs)
    out = []
    for a, b in partners:
        for x, y in ((a, b), (b, a)):
            if x not in held or y in held:
                continue
            side = (tgt_points[tgt.members[held[x]]] @ normal) * np.sign(float((ref_base[y] - ref_base[x]) @ normal))
            if 0.25 <= float((side > 0).mean()) <= 0.75:
                out.append((y, held[x], side > 0))
                held[y] = held[x]
    return out


def trunk_branches(skeleton: CurveSkeleton, matched: list[int]) -> list[int]:
    """The branches that are trunk: the root branch and every branch between it and a matched limb's
    branch (where the levels had not yet parted the limbs that leave there: a cross's centre above its
    arms, a body between two legs that part low)."""
    out = {0}
    for b in matched:
        a = skeleton.branches[b].parent
        while a > 0:
            out.add(a)
            a = skeleton.branches[a].parent
    return sorted(out)


def point_samples(points: np.ndarray, rng: np.random.Generator, count: int = 800) -> np.ndarray:
    """At most ``count`` of ``points`` (N, 3), drawn without replacement by ``rng``."""
    return points[rng.choice(len(points), min(count, len(points)), replace=False)]


def own_chain_tips(tgt_sk: Any, cand: np.ndarray, tgt_limbs: Any) -> Any:
    """``tgt_limbs`` with each candidate branch's tip measured at the end of its own chain (a head's crown, not an
    ear's tip) where the branch has sub-branches."""
    own_tip = []
    for k, i in enumerate(cand):
        own = tgt_sk.branches[i].points
        if len(own) == 0 or not tgt_sk.branches[i].children:
            own_tip.append(tgt_limbs.tip[k])
            continue
        g = tgt_sk.geodesic[own]
        own_tip.append(tgt_sk.points[own[g >= g.max() - tgt_sk.level_width]].mean(axis=0))
    return replace(tgt_limbs, tip=np.array(own_tip).reshape(-1, 3))


def split_limb(limbs: list[Any], pairs: list[tuple[int, int]], ref_limb: int, branch: int, half: np.ndarray,
               parts: np.ndarray) -> tuple[list[Any], list[tuple[int, int]]]:
    """The branch shared by two partner limbs split: its ``half`` (bool over its members) goes to ``ref_limb`` with
    the labels ``parts``, the rest stays with the limb that held it."""
    held = next(j for j, (_, c) in enumerate(pairs) if c == branch)
    members, own = limbs[held]
    limbs = list(limbs)
    limbs[held] = (members[~half], own[~half])
    limbs.append((members[half], parts[half]))
    return limbs, [*pairs, (ref_limb, branch)]


def repair_pairs(pairs: list[tuple[int, int]], ref_limbs: LimbSet, tgt_limbs: LimbSet, tgt_sk: CurveSkeleton,
                 cand: np.ndarray, rot: np.ndarray, symmetry: tuple[list[tuple[int, int]], np.ndarray] | None,
                 attach: tuple[np.ndarray, np.ndarray], config: StructureConfig, up: int, ref_scale: np.ndarray,
                 tgt_scale: np.ndarray) -> tuple[list[tuple[int, int]], np.ndarray]:
    """The chosen turn's (reference limb, candidate) pairs after :func:`mirror_repair`, :func:`straddle_repair`
    and :func:`complete_partners` (with left/right partners and their plane, ``symmetry``), and the turn's (R, T)
    limb costs; ``tgt_scale``: the target's horizontal spread (:func:`horizontal_scale`)."""
    if config.mirror_repair and len(pairs):
        pairs = mirror_repair(pairs, ref_limbs, tgt_limbs, rot, up, ref_scale, tgt_scale, symmetry)
    cost = limb_cost(ref_limbs, tgt_limbs, rot, config, up=up, ref_scale=ref_scale, ref_attach=attach[0],
                     tgt_scale=horizontal_scale(tgt_sk.points, rot, up), tgt_attach=attach[1])
    if symmetry is not None and len(pairs):
        partners, normal = symmetry
        pairs = straddle_repair(pairs, partners, cost, (tgt_sk.points @ rot.T) / tgt_scale @ normal, tgt_limbs)
        pairs = complete_partners(pairs, partners, tgt_limbs, tgt_sk, cand, rot, normal, tgt_scale)
    return pairs, cost


def free_branches(pairs: list[tuple[int, int]], skeleton: CurveSkeleton, cand: np.ndarray) -> list[int]:
    """Candidate indices of the target branches no matched branch is nested with, the outermost of them only
    (a free branch whose parent branch is free too is part of that parent's limb)."""
    taken = [int(cand[c]) for _, c in pairs]

    # is_ancestor(b, b) holds, so a taken branch counts as nested with itself
    free = [c for c in range(len(cand)) if not any(
        skeleton.is_ancestor(int(cand[c]), t) or skeleton.is_ancestor(t, int(cand[c])) for t in taken)]
    return [c for c in free if not any(skeleton.is_ancestor(int(cand[o]), int(cand[c])) for o in free if o != c)]


def pair_leftovers(pairs: list[tuple[int, int]], cost: np.ndarray, skeleton: CurveSkeleton, cand: np.ndarray
                   ) -> list[tuple[int, int]]:
    """Left-over reference limbs and left-over target branches paired with each other at least cost (R, T),
    whatever the miss cost: a branch the assignment left over hangs off the trunk as a limb does, and as
    trunk it would take the trunk's parts (a lamp's shade as the chest) where any limb is nearer its role."""
    left = [r for r in range(cost.shape[0]) if r not in dict(pairs)]
    free = free_branches(pairs, skeleton, cand)
    if not left or not free:
        return pairs
    rows, cols = linear_sum_assignment(cost[np.ix_(left, free)])
    return sorted(pairs + [(left[i], free[j]) for i, j in zip(rows, cols)])


@dataclass(frozen=True)
class TargetLabelling:
    """What labelling the target's skeleton points from a set of (reference limb, candidate) pairs needs:
    the reference's skeleton, limbs, labels and trunk parts, the target's skeleton and candidate limbs, the
    chosen turn, the left/right ``symmetry`` (partners, plane normal) or None, both shapes' horizontal
    spreads, the target's local thickness (or None), B and the options."""

    ref_sk: CurveSkeleton
    ref_limbs: LimbSet
    ref_labels: np.ndarray
    trunk: list[int]
    tgt_sk: CurveSkeleton
    tgt_limbs: LimbSet
    rotation: np.ndarray
    symmetry: tuple[list[tuple[int, int]], np.ndarray] | None
    ref_scale: np.ndarray
    tgt_scale: np.ndarray
    tgt_thick: np.ndarray | None
    num_parts: int
    config: StructureConfig
    up: int = 1

    def transfer(self, r: int, t: int) -> np.ndarray:
        """The reference limb r's parts carried along the target candidate t (:func:`transfer_along`)."""
        return transfer_along(self.ref_sk, self.ref_limbs, r, self.ref_labels, self.tgt_sk, self.tgt_limbs, t,
                              self.num_parts, self.config.profile_bins)

    def label(self, pairs: list[tuple[int, int]]) -> tuple[list[tuple[int, int]], np.ndarray]:
        """The pairs after :func:`split_partners` and the (M,) reference part of every target skeleton point."""
        limbs = [(self.tgt_limbs.members[t], self.transfer(r, t)) for r, t in pairs]
        sk, rot = self.tgt_sk, self.rotation
        if self.symmetry is not None and len(pairs):
            partners, normal = self.symmetry
            for y, t, half in split_partners(pairs, partners, self.ref_limbs.base / self.ref_scale, normal,
                                             (sk.points @ rot.T) / self.tgt_scale, self.tgt_limbs):
                limbs, pairs = split_limb(limbs, pairs, y, t, half, self.transfer(y, t))
        in_trunk = np.isin(self.ref_labels, self.trunk)
        cand = np.arange(1, len(sk.branches))
        root = np.flatnonzero(np.isin(sk.branch, trunk_branches(sk, [int(cand[c]) for _, c in pairs])))
        thick = self.tgt_thick
        if thick is not None:
            # a lamp's pole above its middle lies in the branch the shade's head was given: it stays trunk
            column = np.unique(np.concatenate([np.zeros(0, dtype=np.int64)] + [
                trunk_column(sk.points, sk.geodesic, sk.level_width, thick, sk.branches[0].points,
                             self.tgt_limbs.members[t]) for _, t in pairs]))
            limbs = [(m[~np.isin(m, column)], q[~np.isin(m, column)]) for m, q in limbs]
            root = np.union1d(root, column)
        return pairs, label_regions(sk.points @ rot.T, sk.graph, root, limbs, self.ref_sk.points[in_trunk],
                                    self.ref_labels[in_trunk], thickness=thick, reach=self.config.limb_reach,
                                    trunk_thickness=None if thick is None else float(thick[sk.core].max()),
                                    up=self.up)

    def kept(self, point_part: np.ndarray) -> float:
        """connected x contacts of a labelling of the target's points against the reference's
        (:func:`sync4d.match.consistency.consistency`): the share of the reference's structure it keeps."""
        return consistency(self.tgt_sk.points, point_part, self.ref_sk.points, self.ref_labels,
                           self.num_parts).kept


def match_structure(
    ref_points: np.ndarray,
    ref_labels: np.ndarray,
    num_parts: int,
    tgt_points: np.ndarray,
    config: StructureConfig,
    *,
    up_axis: str = "y",
    part_parents: np.ndarray | None = None,
    tgt_depth: np.ndarray | None = None,
    turn_cost: float = 0.0,
) -> StructureMatch:
    """Match the target's skeleton branches to the reference's limbs and label the target points.

    Args:
        ref_points: (V, 3) reference surface points, normalised (centroid 0, unit RMS radius).
        ref_labels: (V,) reference part per point in [0, num_parts).
        num_parts: B.
        tgt_points: (M, 3) target points, normalised the same way, upright along ``up_axis``.
        config: options.
        up_axis: the shared up axis of both normalised frames.
        part_parents: (B,) the reference's bone tree if known (see :func:`reference_limbs`).
        tgt_depth: (M,) depth of each target point inside its solid, or None (see :func:`curve_skeleton`).
        turn_cost: added to a turn's score times (1 - cos(turn)) / 2: a prior for the given heading, for
            a target already aligned to the reference (by ICP) rather than merely upright.

    Returns:
        StructureMatch (``point_part`` labels the target points).
    """
    ref_sk = curve_skeleton(ref_points, config.skeleton)
    tgt_sk = curve_skeleton(tgt_points, config.skeleton, tgt_depth, up=UP_AXES[up_axis])
    limb_parts, trunk = reference_limbs(ref_sk, ref_labels, num_parts, part_parents)
    ref_sk = distance_from_trunk(ref_sk, np.isin(ref_labels, trunk), config.skeleton)
    up = UP_AXES[up_axis]
    ref_limbs = with_feet(limb_descriptors(ref_sk, [np.flatnonzero(np.isin(ref_labels, p)) for p in limb_parts],
                                           base_share=config.reference_base_share), ref_sk.points, up)
    tgt_thick = None if tgt_depth is None else local_thickness(tgt_sk.points, tgt_depth)
    cand = np.arange(1, len(tgt_sk.branches))
    tgt_limbs = with_feet(own_chain_tips(tgt_sk, cand, limb_descriptors(
        tgt_sk, [tgt_sk.branches[i].subtree for i in cand], tgt_depth)), tgt_sk.points, up)
    if tgt_thick is not None:
        ref_limbs = replace(ref_limbs, thickness=reference_thickness(ref_sk.points, ref_labels, limb_parts, trunk))
        tgt_limbs = replace(tgt_limbs, thickness=target_thickness(tgt_thick, tgt_limbs.members, tgt_sk.core))
    rng = np.random.default_rng(0)
    ref_sub, tgt_sub = point_samples(ref_points, rng), point_samples(tgt_points, rng)
    ref_scale = horizontal_scale(ref_points, np.eye(3), up)
    parent = bone_tree(ref_sk, ref_labels, num_parts, part_parents)[0]
    attach = (reference_attach(ref_sk, ref_labels, limb_parts, parent, ref_limbs, np.isin(ref_labels, trunk), up),
              attach_heights(tgt_sk, tgt_limbs.members, tgt_sk.branches[0].points, up))
    turns = score_turns(ref_limbs, tgt_limbs, tgt_sk, cand, ref_sub, tgt_sub, config, up_axis, ref_scale, turn_cost,
                        attach)
    partners = limb_partners(limb_parts, parent, ref_limbs.base, ref_limbs.length)
    if tgt_limbs.thickness is not None and ref_limbs.thickness is not None:
        lone = set(range(len(limb_parts))) - {i for pair in partners for i in pair}
        turns = face_by_thickness(turns, ref_limbs.thickness, tgt_limbs.thickness, lone)
    _, rot, pairs, total = turns[0]
    symmetry = (partners, partner_plane(ref_limbs.base, partners, up, ref_scale)) if partners else None
    tgt_scale = horizontal_scale(tgt_points, rot, up)
    pairs, cost = repair_pairs(pairs, ref_limbs, tgt_limbs, tgt_sk, cand, rot, symmetry, attach, config, up,
                               ref_scale, tgt_scale)
    context = TargetLabelling(ref_sk, ref_limbs, ref_labels, trunk, tgt_sk, tgt_limbs, rot, symmetry, ref_scale,
                              tgt_scale, tgt_thick, num_parts, config, up)
    more = pair_leftovers(pairs, cost, tgt_sk, cand)
    found = len(more) > len(pairs)
    pairs, point_part = context.label(pairs)
    if found:
        more, more_part = context.label(more)
        if context.kept(more_part) >= context.kept(point_part):
            pairs, point_part = more, more_part
    matched = {r for r, _ in pairs}
    leftover = tuple(tuple(p) for i, p in enumerate(limb_parts) if i not in matched)
    matched_branches = np.array([(r, int(cand[c])) for r, c in pairs], dtype=np.int64).reshape(-1, 2)
    return StructureMatch(ref_sk, tgt_sk, rot, matched_branches, tuple(tuple(p) for p in limb_parts), leftover,
                          point_part, float(total))


def score_turns(
    ref_limbs: LimbSet,
    tgt_limbs: LimbSet,
    tgt_sk: CurveSkeleton,
    cand: np.ndarray,
    ref_sub: np.ndarray,
    tgt_sub: np.ndarray,
    config: StructureConfig,
    up_axis: str,
    ref_scale: np.ndarray,
    turn_cost: float,
    attach: tuple[np.ndarray, np.ndarray] | None = None,
) -> list[tuple[float, np.ndarray, list[tuple[int, int]], float]]:
    """Every turn of the target about the up axis with its assignment, best first.

    Returns:
        (score, rotation, (reference limb, candidate) pairs, assignment cost) per turn; the score is the
        assignment cost plus ``chamfer_weight`` x chamfer distance plus the heading prior. ``attach``: the
        reference's and the candidates' attachment heights (:func:`attach_heights`), or None.
    """
    up = UP_AXES[up_axis]
    tree = cKDTree(ref_sub)
    tgt_all = tgt_sk.points
    out = []
    for rot in yaw_rotations(up_axis, config.yaw_steps):
        if len(ref_limbs.members) and len(cand):
            cost = limb_cost(
                ref_limbs, tgt_limbs, rot, config, up=up, ref_scale=ref_scale, tgt_scale=horizontal_scale(tgt_all, rot, up),
                ref_attach=None if attach is None else attach[0], tgt_attach=None if attach is None else attach[1],
            )
            pairs, total = assign_limbs(cost, tgt_sk, cand, config.miss_cost)
        else:
            pairs, total = [], config.miss_cost * len(ref_limbs.members)
        score = total + config.chamfer_weight * chamfer_distance(tgt_sub @ rot.T, ref_sub, tree_b=tree)
        cos_turn = (float(np.trace(rot)) - 1.0) / 2.0
        score += turn_cost * (1.0 - cos_turn) / 2.0
        out.append((score, rot, pairs, total))
    return sorted(out, key=lambda t: t[0])
