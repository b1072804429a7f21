"""Where a matched limb ends and the trunk begins on the target, and the part of every target point.

A target branch of the curve skeleton starts where the geodesic levels split, which is often below where
the limb leaves the trunk (levels from the trunk's core reach a leg's top only after crossing the belly).
The limb is grown from its branch over the solid while the solid stays as thin as the limb (local
thickness, :func:`local_thickness`) and within a few limb thicknesses (:func:`grow_limbs`): it stops where
the cross-section widens into the trunk. The trunk (the root branch's points no limb took) takes the
reference's trunk parts by relative position (:func:`fit_spread`); the remaining points (target branches no reference limb matched)
take the part of the region they hang from (:func:`label_regions`).
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
    columns: list[np.ndarray] | None = None,
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
        columns: per limb, the column it stands on (:func:`standing_columns`): grown over beyond ``reach``.

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
    if columns is not None:
        take = grow_columns(graph, labels, limbs, columns, take, thickness, trunk)
    out[take >= 0] = take[take >= 0]
    return out


def grow_columns(graph: csr_matrix, labels: np.ndarray, limbs: list[np.ndarray], columns: list[np.ndarray],
                 take: np.ndarray, thickness: np.ndarray, trunk: float) -> np.ndarray:
    """``take`` with each limb's column (:func:`standing_columns`) points that no limb took and that are
    unlabelled, each with the part of the limb point it is reached from over the column."""
    take = take.copy()
    for members, column in zip(limbs, columns):
        t = limb_thickness(thickness, members)
        if len(members) == 0 or len(column) == 0 or t >= trunk:
            continue
        # a column as thick as the trunk's core (the core: deeper than 0.8 of the deepest point) is the body a
        # leg stands under (a penguin's), not the leg
        ok = (labels[column] < 0) & (take[column] < 0) & (thickness[column] < 0.8 * trunk)
        nodes = np.union1d(members, column[ok])
        seeds = np.searchsorted(nodes, members)
        dist, _, source = dijkstra(graph[nodes][:, nodes], directed=False, indices=seeds, return_predecessors=True,
                                   min_only=True)
        grown = np.flatnonzero(np.isfinite(dist) & (labels[nodes] < 0) & (take[nodes] < 0))
        take[nodes[grown]] = labels[nodes[source[grown]]]
    return take


def standing_columns(points: np.ndarray, graph: csr_matrix, limbs: list[np.ndarray], up: int, *,
                     ground: float = 0.05, min_piece: float = 0.01) -> list[np.ndarray]:
    """Per limb, the column of the solid it stands on: the points of the connected piece of the shape below a
    rising height that holds the limb's points on the ground, up to the height where that piece first meets
    another piece (empty for a limb that does not reach the lowest ``ground`` share of the height).

    Two legs that part low, or whose branches part only at the paws, are still two separate pieces below the
    belly: each leg's column runs up to where it meets the other legs or the belly (a koala's belly between
    its legs is a piece of its own, so it stays trunk). Pieces of fewer than ``min_piece`` of the points
    (sampling noise) are absorbed without stopping the rise.
    """
    h = points[:, up]
    low = h <= h.min() + ground * float(np.ptp(h))
    owner = np.full(len(points), -1, dtype=np.int64)
    for i, m in enumerate(limbs):
        owner[m[low[m]]] = i
    order = np.argsort(h, kind="stable")
    parent = np.arange(len(points))
    size = np.ones(len(points), dtype=np.int64)
    piece_owner = owner.copy()
    stop = np.full(len(limbs), np.inf)
    added = np.zeros(len(points), dtype=bool)
    indptr, indices = graph.indptr, graph.indices
    small = min_piece * len(points)

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for p in order:
        added[p] = True
        for q in indices[indptr[p]:indptr[p + 1]]:
            if not added[q]:
                continue
            a, b = find(p), find(int(q))
            if a == b:
                continue
            oa, ob = int(piece_owner[a]), int(piece_owner[b])
            if oa != ob and ((oa >= 0 and ob >= 0) or (size[a] >= small and size[b] >= small)):
                for o in (oa, ob):
                    if o >= 0 and not np.isfinite(stop[o]):
                        stop[o] = h[p]
            parent[b] = a
            size[a] += size[b]
            piece_owner[a] = oa if oa == ob or ob == -1 else ob if oa == -1 else -2
    out = []
    for i, m in enumerate(limbs):
        seeds = m[low[m]]
        if len(seeds) == 0:
            out.append(np.zeros(0, dtype=np.int64))
            continue
        below = np.flatnonzero(h < stop[i])
        sub = graph[below][:, below]
        dist = dijkstra(sub, directed=False, indices=np.searchsorted(below, seeds[h[seeds] < stop[i]]),
                        min_only=True, unweighted=True)
        out.append(below[np.isfinite(dist)])
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
        up: the up axis; given, a limb standing on the ground also grows over its column
            (:func:`standing_columns`).
    """
    out = np.full(len(points), -1, dtype=np.int64)
    for members, parts in limbs:
        out[members] = parts
    if thickness is not None and graph is not None and limbs:
        members = [m for m, _ in limbs]
        columns = None if up is None else standing_columns(points, graph, members, up)
        out = grow_limbs(graph, out, members, thickness, reach=reach, trunk=trunk_thickness, columns=columns)
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
