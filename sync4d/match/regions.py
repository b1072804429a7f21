"""Where a matched limb ends and the trunk begins on the target, and the part of every target point.

A target branch of the curve skeleton starts where the geodesic levels split, which is often below where
the limb leaves the trunk (levels from the trunk's core reach a leg's top only after crossing the belly).
The limb is grown from its branch over the solid while the solid stays as thin as the limb (local
thickness, :func:`local_thickness`) and within a few limb thicknesses (:func:`grow_limbs`): it stops where
the cross-section widens into the trunk. The trunk (the root branch's points no limb took) takes the
reference's trunk parts by relative position (:func:`fit_spread`); the remaining points (target branches no reference limb matched)
take the part of the region they hang from (:func:`label_regions`); a matched branch's levels that continue a column-shaped trunk
into a thicker part (a lamp's pole under its shade) are trunk (:func:`trunk_column`). The legs end at the body's underside
(:func:`legs_to_underside`): below it they take their merged tops, above it they give the belly's sides back.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree


def local_thickness(points: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(M,) radius of the largest inscribed ball containing each point of a solid.

    Args:
        points: (M, 3) voxel centres of the solid; depth: (M,) each one's distance to the outside (same unit).

    A point's own depth is small near the surface even inside a thick trunk; the largest ball that holds
    it (centred at any deeper point whose depth reaches it) says how thick the solid is there.
    """
    radius = np.asarray(depth, dtype=np.float64)
    out = radius.copy()
    balls = cKDTree(points).query_ball_point(points, r=radius)
    for i, idx in enumerate(balls):
        np.maximum.at(out, idx, radius[i])
    return out


def limb_thickness(thickness: np.ndarray, members: np.ndarray) -> float:
    """A limb's thickness: the median of the thinner half of its points' (its base may lie in the trunk's balls)."""
    if len(members) == 0:
        return 0.0
    return float(np.median(np.sort(thickness[members])[: max(len(members) // 2, 1)]))


def grow_limbs(
    graph: csr_matrix,
    labels: np.ndarray,
    limbs: list[np.ndarray],
    thickness: np.ndarray,
    *,
    reach: float,
    trunk: float | None = None,
) -> np.ndarray:
    """(M,) ``labels`` with each limb grown over the unlabelled points thinner than the limb-trunk junction.

    Args:
        graph: (M, M) neighbour graph of the points.
        labels: (M,) part per point, -1 where unlabelled (the limbs' points are labelled).
        limbs: per matched limb, the indices of its points.
        thickness: (M,) local thickness (:func:`local_thickness`).
        reach: a point joins a limb if it lies within ``reach`` x the limb's thickness of it (geodesically)
            (the limb's thickness: the median of its thinner half; its base may lie in the trunk's balls)
            and is thinner than the geometric mean of the limb's thickness and the trunk's (the thickest
            point's, or ``trunk``): the limb ends where the cross-section has widened half-way (in log)
            to the trunk's. A limb at least as thick as the trunk (a big head on a small body) is not
            grown: its branch already starts at its narrowing, and the trunk is no wider than it.
        trunk: the trunk's thickness (the thickness at its core); None: the thickest point's.

    Returns:
        (M,) labels; a grown point takes the part of the limb point it was reached from.
    """
    out = labels.copy()
    free = out < 0
    best = np.full(len(out), np.inf)
    take = np.full(len(out), -1, dtype=np.int64)
    trunk = float(thickness.max()) if trunk is None else trunk
    for members in limbs:
        if len(members) == 0:
            continue
        t = limb_thickness(thickness, members)
        if t >= trunk:
            continue
        allowed = np.flatnonzero(free & (thickness <= np.sqrt(t * trunk)))
        nodes = np.union1d(members, allowed)
        sub = graph[nodes][:, nodes]
        seeds = np.searchsorted(nodes, members)
        dist, _, source = dijkstra(sub, directed=False, indices=seeds, return_predecessors=True, min_only=True,
                                   limit=reach * t)
        grown = np.flatnonzero(np.isfinite(dist) & free[nodes])
        closer = dist[grown] < best[nodes[grown]]
        best[nodes[grown[closer]]] = dist[grown[closer]]
        take[nodes[grown[closer]]] = labels[nodes[source[grown[closer]]]]
    out[take >= 0] = take[take >= 0]
    return out


def fit_spread(points: np.ndarray, onto: np.ndarray) -> np.ndarray:
    """(N, 3) ``points`` moved and stretched per axis to the mean and spread of ``onto`` (K, 3).

    The target's trunk takes the reference trunk's parts by relative position within the trunk: a toy's
    short body under a big head has a chest on top and a pelvis below, as a long human trunk does.
    """
    if len(points) < 2 or len(onto) < 2:
        return points
    scale = onto.std(axis=0) / np.maximum(points.std(axis=0), 1e-9)
    return (points - points.mean(axis=0)) * scale + onto.mean(axis=0)


def label_regions(
    points: np.ndarray,
    graph: csr_matrix | None,
    root_points: np.ndarray,
    limbs: list[tuple[np.ndarray, np.ndarray]],
    trunk_points: np.ndarray,
    trunk_labels: np.ndarray,
    *,
    thickness: np.ndarray | None,
    reach: float,
    trunk_thickness: float | None = None,
    up: int | None = None,
) -> np.ndarray:
    """(M,) reference part of every target point.

    Args:
        points: (M, 3) target points in the reference's (turned, normalised) frame.
        graph: (M, M) their neighbour graph, or None.
        root_points: indices of the points of the skeleton's root branch (the trunk's candidates).
        limbs: per matched limb, (indices of its points, the part of each of them).
        trunk_points: (K, 3) the reference's trunk points, same frame; trunk_labels: (K,) their parts.
        thickness: (M,) local thickness, or None (limbs are then not grown).
        reach, trunk_thickness: see :func:`grow_limbs` (``reach``, ``trunk``).
        up: the up axis; with it, the legs end at the body's underside (:func:`legs_to_underside`).
    """
    out = np.full(len(points), -1, dtype=np.int64)
    for members, parts in limbs:
        out[members] = parts
    if thickness is not None and graph is not None and limbs:
        out = grow_limbs(graph, out, [m for m, _ in limbs], thickness, reach=reach, trunk=trunk_thickness)
        if up is not None:
            out, back = legs_to_underside(points, graph, out, [m for m, _ in limbs], root_points, thickness, up,
                                          cap=float(thickness.max()) if trunk_thickness is None else trunk_thickness)
            root_points = np.union1d(root_points, back)
    tree = cKDTree(trunk_points)
    trunk = root_points[out[root_points] < 0]
    if len(trunk):
        out[trunk] = trunk_labels[tree.query(fit_spread(points[trunk], trunk_points))[1]]
    seeds, rest = np.flatnonzero(out >= 0), np.flatnonzero(out < 0)
    if len(rest) and len(seeds) and graph is not None:
        # unmatched branches hang from what they touch: the part of their geodesically nearest labelled point
        dist, _, source = dijkstra(graph, directed=False, indices=seeds, return_predecessors=True, min_only=True)
        reached = rest[np.isfinite(dist[rest])]
        out[reached] = out[source[reached]]
    rest = np.flatnonzero(out < 0)
    if len(rest):
        out[rest] = trunk_labels[tree.query(points[rest])[1]]
    return out


def column_axis(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The centroid (3,), principal axis (3,) of ``points`` (N, 3), and their spread along it over across it."""
    centre = points.mean(axis=0)
    _, spread, axes = np.linalg.svd(points - centre, full_matrices=False)
    return centre, axes[0], float(spread[0] / max(spread[1], 1e-12))


def off_axis(points: np.ndarray, centre: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(N,) distance of ``points`` from the line through ``centre`` along the unit ``axis``."""
    q = points - centre
    return np.linalg.norm(q - np.outer(q @ axis, axis), axis=1)


def trunk_column(points: np.ndarray, geodesic: np.ndarray, level_width: float, thickness: np.ndarray, root: np.ndarray,
                 branch: np.ndarray, *, band: tuple[float, float] = (0.7, 1.4), bulb: float = 1.5,
                 elongation: float = 1.5, inside: float = 0.8) -> np.ndarray:
    """The points of a matched limb's ``branch`` (indices) that continue the trunk's column: a lamp's pole from
    its middle, where the levels part, up to the arm that carries the shade.

    The root branch (``root``, indices) is a column when its points spread ``elongation`` times more along their
    principal axis than across it. The branch's levels (``level_width`` of ``geodesic``) continue it from its
    base on while ``inside`` of a level's points lie within the column's radius of its axis (refitted to the
    root and the levels taken so far: a short root's axis tilts) and the level is as thick as the column (its
    median local thickness within ``band`` x the root's). They are given back only when the rest of the branch
    ends in a part at least ``bulb`` times thicker than the column (its 90th percentile): a thin column carrying
    a thick bulb (a pole and its shade) rather than a limb leaving the trunk; a head or a tail thinner than the
    trunk never is.
    """
    none = np.zeros(0, dtype=np.int64)
    if len(root) < 10 or len(branch) < 10:
        return none
    centre, axis, ratio = column_axis(points[root])
    if ratio < elongation:
        return none
    t0, radius = float(np.median(thickness[root])), float(off_axis(points[root], centre, axis).max())
    level = np.floor((geodesic[branch] - geodesic[branch].min()) / max(level_width, 1e-9)).astype(np.int64)
    column = [root]
    for k in range(int(level.max()) + 1):
        here = branch[level == k]
        if len(here) == 0:
            continue
        thick = float(np.median(thickness[here])) / max(t0, 1e-12)
        if (off_axis(points[here], centre, axis) <= radius).mean() < inside or not band[0] <= thick <= band[1]:
            break
        column.append(here)
        centre, axis, _ = column_axis(points[np.concatenate(column)])
    taken = np.concatenate(column[1:]) if len(column) > 1 else none
    rest = np.setdiff1d(branch, taken)
    if len(taken) == 0 or len(rest) < 10 or np.percentile(thickness[rest], 90) < bulb * t0:
        return none
    return taken


def undersides(points: np.ndarray, labels: np.ndarray, legs: list[np.ndarray], trunk: np.ndarray,
               thickness: np.ndarray, up: int, *, clear: float = 2.0, low: float = 2.0, least: float = 0.01
               ) -> tuple[np.ndarray, float]:
    """(M,) the height of the body's underside over each point's nearest leg (seen from above; nan where
    unknown) and the thickest leg's thickness.

    The belly around a leg: the free ``trunk`` points lying farther from every leg point, seen from above,
    than ``clear`` x that thickness (not the legs' tops), each given to its nearest leg; the leg's underside is
    the ``low``-th percentile of their heights, when they are at least ``least`` of the free trunk points (a
    few stray points are not a belly), and when above the median height of the leg's points. Per leg, as a
    body may slope.
    """
    flat, h = np.delete(points, up, axis=1), points[:, up]
    radius = max(limb_thickness(thickness, m) for m in legs)
    leg_pts = np.concatenate(legs)
    owner = np.concatenate([np.full(len(m), i) for i, m in enumerate(legs)])
    tree = cKDTree(flat[leg_pts])
    body = trunk[labels[trunk] < 0]
    level = np.full(len(legs), np.nan)
    if len(body):
        dist, near = tree.query(flat[body])
        far = dist > clear * radius
        for i in range(len(legs)):
            mine = body[far & (owner[near] == i)]
            if len(mine) >= max(least * len(body), 1):
                level[i] = np.percentile(h[mine], low)
    # a leg hangs below the belly: at least half of it lies under the underside (not a cat stretching,
    # its chest on the floor between its front paws, its hind legs fused with its body)
    level[level <= np.array([np.median(h[m]) for m in legs])] = np.nan
    return level[owner[tree.query(flat)[1]]], radius


def legs_to_underside(points: np.ndarray, graph: csr_matrix, labels: np.ndarray, limbs: list[np.ndarray],
                      trunk: np.ndarray, thickness: np.ndarray, up: int, *, ground: float = 0.05,
                      column: float = 1.0, cap: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """(M,) ``labels`` with the legs ending at the body's underside (:func:`undersides`), and the indices of
    the points they gave back to the trunk.

    Where the levels part, not where the cross-section widens, decides a leg's branch: legs that part low
    leave their merged tops to the trunk (a cat's front legs meet each other below its chest), legs whose
    levels part high carry the belly's sides (a koala). Below the underside there are only legs, above it
    the body. The legs are the limbs with points in the lowest ``ground`` of the height; their thickness
    limit is the geometric mean of the thickest leg's thickness and the trunk's (``cap``), as in
    :func:`grow_limbs`. Each leg takes the free points below the underside within ``column`` x the thickest
    leg's thickness of its own points seen from above that it reaches through such points (the part of the
    leg point each is reached from), where the solid is thinner than the geometric mean of that limit and the
    trunk's (the limit lifted half-way again: merging legs widen before the belly); and gives back its points
    above the underside thicker than the limit (the belly's sides, not a thin leg rising along the body).
    """
    h = points[:, up]
    legs = [m for m in limbs if len(m) and (h[m] <= h.min() + ground * float(np.ptp(h))).any()]
    none = np.zeros(0, dtype=np.int64)
    if len(legs) < 2:
        return labels, none
    level, radius = undersides(points, labels, legs, trunk, thickness, up)
    known = np.isfinite(level)
    out, free, leg_pts = labels.copy(), labels < 0, np.concatenate(legs)
    limit = np.sqrt(radius * cap)
    flat, thin = np.delete(points, up, axis=1), thickness <= limit
    below = np.flatnonzero(free & known & (h < np.where(known, level, -np.inf)) & (thickness <= np.sqrt(limit * cap)))
    below = below[cKDTree(flat[leg_pts]).query(flat[below])[0] <= column * radius] if len(below) else below
    if len(below):
        nodes = np.union1d(leg_pts, below)
        dist, _, source = dijkstra(graph[nodes][:, nodes], directed=False, indices=np.searchsorted(nodes, leg_pts),
                                   return_predecessors=True, min_only=True)
        grown = np.flatnonzero(np.isfinite(dist) & free[nodes])
        out[nodes[grown]] = labels[nodes[source[grown]]]
    above = np.flatnonzero(np.isin(out, np.unique(labels[leg_pts])) & known & (h > np.where(known, level, np.inf)) & ~thin)
    out[above] = -1
    return out, above
