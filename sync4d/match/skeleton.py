"""Curve skeleton of a shape as a Reeb tree of geodesic distance, segmented into branches.

The shape is a point set (surface samples of a mesh, or Gaussian centres) in a normalised frame (unit
RMS radius). Steps, each a small pure function:

1. a k-nearest-neighbour graph over the points, long edges dropped, components joined by their
   closest pair (:func:`neighbour_graph`);
2. geodesic distance ``f`` over that graph from the point nearest the centroid (:func:`geodesic_from`);
3. the Reeb tree of ``f``: points binned by ``f`` into levels of width ``level_width``, each connected
   component of one level is a node, a node's parent is the node its points' shortest paths come from
   (:func:`reeb_tree`);
4. the tree is cut into chains (branches) between junctions; terminal branches shorter than
   ``prune_length`` (fingers, toes, small ears: noise of the level sets) are absorbed into their parent
   and the chains rebuilt (:func:`prune_branches`).

A branch's ``base`` is where it leaves its parent (the ring of its first level), so limb boundaries sit
where the level sets split: at the narrowing between a limb and the trunk. Cost: a few Dijkstra runs on
M points (~0.1 s for M = 3000 here).

On a solid (a depth per point), distances are measured from the trunk's core instead of the centre point:
the deepest blob's (:func:`trunk_core`), or another thick blob's that is nearer the ground, since the
trunk carries the legs (:func:`trunk_on_legs`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from sync4d.errors import InputError


@dataclass
class SkeletonConfig:
    """Options of the curve skeleton (lengths in units of the shape's RMS radius).

    Attributes:
        neighbours: k of the k-nearest-neighbour graph.
        max_edge_factor: edges longer than this many median nearest-neighbour spacings are dropped (they
            would bridge a gap between two limbs).
        level_width: width of one Reeb level in geodesic distance (RMS-radius units); at least
            ``level_spacings`` median point spacings (a thinner band breaks into sampling fragments).
        level_spacings: smallest level width in median nearest-neighbour spacings.
        prune_length: terminal branches shorter than this are absorbed into their parent (RMS units).
        samples: points the skeleton is built on (a random subset of the volume or surface points).
        volume: build it on the solid (voxel centres of the filled surface) rather than on the surface
            of a mesh: geodesic levels through the solid are cross-sections, which split cleanly where
            limbs leave a thick trunk (surface levels from one surface point do not).
        resolution: voxels along the longest side of the bounding box for ``volume``.
        core_depth: with a depth per point (distance to the outside of the solid), geodesic distance is
            measured from the trunk's core: the connected points deeper than this fraction of the
            deepest point's depth, around it. Levels are then offsets of the trunk, so a limb's branch
            starts where it leaves the trunk (from a single centre point the levels are spheres, which
            cut an elongated trunk into halves and the legs low down). 0 measures from the centre point.
        core_reach: the core extends at most this many times the largest depth (geodesically) from
            its seed (:func:`trunk_core`).
    """

    neighbours: int = 10
    max_edge_factor: float = 4.0
    level_width: float = 0.06
    level_spacings: float = 2.0
    prune_length: float = 0.25
    samples: int = 8000
    volume: bool = True
    resolution: int = 64
    core_depth: float = 0.8
    core_reach: float = 2.0


@dataclass(frozen=True)
class Branch:
    """One chain of Reeb nodes between junctions.

    Attributes:
        nodes: Reeb node ids from base to tip.
        parent: index of the parent branch, -1 for the root branch.
        children: indices of the child branches.
        points: (P,) indices of the points in this chain (not its descendants).
        subtree: (Q,) indices of the points in this chain and all its descendants.
        base: (3,) centroid of the chain's first level (where it leaves its parent), normalised units.
        tip: (3,) centroid of the subtree's farthest level.
        base_level: geodesic distance of the base (RMS units).
        length: geodesic extent of the subtree from the base to its farthest point (RMS units).
    """

    nodes: tuple[int, ...]
    parent: int
    children: tuple[int, ...]
    points: np.ndarray
    subtree: np.ndarray
    base: np.ndarray
    tip: np.ndarray
    base_level: float
    length: float


@dataclass(frozen=True)
class CurveSkeleton:
    """A shape's Reeb tree, cut into branches.

    Attributes:
        points: (M, 3) the points it was built on (normalised frame).
        geodesic: (M,) geodesic distance from the centre point (RMS units).
        centre: index of the centre point.
        node: (M,) Reeb node per point (after pruning: the node that absorbed it).
        branch: (M,) branch per point.
        branches: the branches; index 0 is the root branch (holding the centre).
        level_width: width of one Reeb level (RMS units).
        core: (C,) indices of the trunk's core points the geodesic distance is measured from (just the
            centre without a depth).
        graph: (M, M) the neighbour graph the skeleton was built on.
    """

    points: np.ndarray
    geodesic: np.ndarray
    centre: int
    node: np.ndarray
    branch: np.ndarray
    branches: tuple[Branch, ...]
    level_width: float
    core: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    graph: csr_matrix | None = None

    def is_ancestor(self, a: int, b: int) -> bool:
        """True if branch ``a`` is ``b`` or one of its ancestors."""
        while b >= 0:
            if a == b:
                return True
            b = self.branches[b].parent
        return False


def neighbour_graph(points: np.ndarray, neighbours: int, max_edge_factor: float) -> csr_matrix:
    """(M, M) symmetric sparse graph of k-nearest-neighbour edges weighted by length, made connected.

    Edges longer than ``max_edge_factor`` median spacings are dropped; then each component other than
    the largest is joined to the rest by its shortest connecting edge, until one component remains.
    """
    m = len(points)
    k = int(min(max(neighbours, 2), m - 1))
    tree = cKDTree(points)
    dist, idx = tree.query(points, k + 1)
    dist, idx = dist[:, 1:], idx[:, 1:]
    spacing = float(np.median(dist[:, 0]))
    keep = dist <= max_edge_factor * max(spacing, 1e-12)
    rows = np.repeat(np.arange(m), k)[keep.ravel()]
    cols, vals = idx.ravel()[keep.ravel()], np.maximum(dist.ravel()[keep.ravel()], 1e-9)
    graph = coo_matrix((vals, (rows, cols)), shape=(m, m)).tocsr()
    graph = graph.maximum(graph.T)
    for _ in range(64):
        count, comp = connected_components(graph, directed=False)
        if count == 1:
            break
        largest = np.argmax(np.bincount(comp))
        extra_r, extra_c, extra_v = [], [], []
        for c in range(count):
            if c == largest:
                continue
            inside, outside = np.flatnonzero(comp == c), np.flatnonzero(comp != c)
            d, j = cKDTree(points[outside]).query(points[inside])
            i = int(np.argmin(d))
            extra_r.append(inside[i])
            extra_c.append(outside[j[i]])
            extra_v.append(max(float(d[i]), 1e-9))
        add = coo_matrix((extra_v, (extra_r, extra_c)), shape=(m, m)).tocsr()
        graph = graph.maximum(add).maximum(add.T)
    return graph


def geodesic_from(graph: csr_matrix, source: int) -> tuple[np.ndarray, np.ndarray]:
    """Geodesic distance (M,) from ``source`` over the graph and the shortest-path predecessor (M,)."""
    dist, pred = dijkstra(graph, directed=False, indices=int(source), return_predecessors=True)
    return dist, pred


def reeb_tree(
    graph: csr_matrix, geodesic: np.ndarray, predecessor: np.ndarray, level_width: float, centre: int
) -> tuple[np.ndarray, np.ndarray]:
    """Reeb nodes of the geodesic levels and each node's parent.

    Args:
        graph: (M, M) neighbour graph.
        geodesic: (M,) geodesic distance from the centre.
        predecessor: (M,) shortest-path predecessor (-9999 at the centre).
        level_width: width of one level.
        centre: index of the centre point.

    Returns:
        node (M,) node id per point, parent (K,) parent node per node (-1 for the root node).
    """
    level = np.floor(geodesic / max(level_width, 1e-9)).astype(np.int64)
    coo = graph.tocoo()
    # A level's components are taken in the band of that level and the next one: two fragments of one
    # ring (sampling noise splits thin bands) that join just beyond are one node; two limbs never rejoin.
    node = np.full(len(level), -1, dtype=np.int64)
    offset = 0
    lo, hi = np.minimum(level[coo.row], level[coo.col]), np.maximum(level[coo.row], level[coo.col])
    for lev in range(int(level.max()) + 1):
        band = (lo >= lev) & (hi <= lev + 1)
        rows, cols = coo.row[band], coo.col[band]
        sub = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=graph.shape)
        _, comp = connected_components(sub, directed=False)
        here = np.flatnonzero(level == lev)
        if len(here) == 0:
            continue
        _, local = np.unique(comp[here], return_inverse=True)
        node[here] = offset + local
        offset += int(local.max()) + 1
    num = int(node.max()) + 1
    parent = np.full(num, -1, dtype=np.int64)
    has_pred = predecessor >= 0
    src, dst = node[has_pred], node[predecessor[has_pred]]
    cross = src != dst
    votes: dict[int, dict[int, int]] = {}
    for a, b in zip(src[cross], dst[cross]):
        votes.setdefault(int(a), {}).setdefault(int(b), 0)
        votes[int(a)][int(b)] += 1
    node_level = np.zeros(num, dtype=np.int64)
    node_level[node] = level
    for a, cand in votes.items():
        # the parent lies nearer the centre; among those, the one most shortest paths come from
        lower = {b: n for b, n in cand.items() if node_level[b] < node_level[a]}
        if lower:
            parent[a] = max(lower, key=lambda b: lower[b])
    parent[node[centre]] = -1
    return node, parent


def _children(parent: np.ndarray, alive: np.ndarray) -> list[list[int]]:
    kids: list[list[int]] = [[] for _ in range(len(parent))]
    for n in np.flatnonzero(alive):
        if parent[n] >= 0:
            kids[int(parent[n])].append(int(n))
    return kids


def node_chains(parent: np.ndarray, alive: np.ndarray, root: int) -> tuple[list[list[int]], list[int]]:
    """Chains of alive nodes between junctions and each chain's parent chain (-1 for the root chain)."""
    kids = _children(parent, alive)
    chains: list[list[int]] = []
    chain_parent: list[int] = []
    stack = [(root, -1)]
    while stack:
        start, par = stack.pop()
        chain = [start]
        while len(kids[chain[-1]]) == 1:
            chain.append(kids[chain[-1]][0])
        chains.append(chain)
        chain_parent.append(par)
        me = len(chains) - 1
        for k in kids[chain[-1]]:
            stack.append((k, me))
    return chains, chain_parent


def prune_branches(
    parent: np.ndarray, node_top: np.ndarray, node_bottom: np.ndarray, root: int, prune_length: float
) -> tuple[np.ndarray, np.ndarray]:
    """Absorb short terminal chains into their parent node until every terminal chain is long enough.

    Args:
        parent: (K,) parent node per node.
        node_top: (K,) largest geodesic distance within each node.
        node_bottom: (K,) smallest geodesic distance within each node.
        root: the root node.
        prune_length: shortest terminal chain kept.

    Returns:
        alive (K,) bool, owner (K,) the alive node each node's points now belong to.
    """
    num = len(parent)
    alive = np.zeros(num, dtype=bool)
    # nodes not connected to the root (no parent chain) are absorbed by construction below
    reach = np.zeros(num, dtype=bool)
    reach[root] = True
    order = np.argsort(node_bottom)
    for n in order:
        if parent[n] >= 0 and reach[parent[n]]:
            reach[n] = True
    alive[:] = reach
    owner = np.arange(num)
    for _ in range(num):
        chains, _ = node_chains(parent, alive, root)
        kids = _children(parent, alive)
        best, best_len = None, np.inf
        for chain in chains[1:]:
            if kids[chain[-1]]:
                continue
            subtree_top = max(node_top[n] for n in chain)
            length = subtree_top - node_bottom[chain[0]]
            if length < prune_length and length < best_len:
                best, best_len = chain, length
        if best is None:
            break
        target = int(parent[best[0]])
        for n in best:
            alive[n] = False
            owner[owner == n] = target
    # unreachable nodes go to their nearest reachable ancestor or the root
    for n in np.flatnonzero(~reach):
        a = parent[n]
        while a >= 0 and not reach[a]:
            a = parent[a]
        owner[owner == n] = root if a < 0 else int(owner[a])
    return alive, owner


def volume_points(
    vertices: np.ndarray, faces: np.ndarray, resolution: int, rng: np.random.Generator, *, with_depth: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """(P, 3) centres of the voxels of the solid bounded by a mesh (surface voxels and their filled inside).

    The surface is sampled densely (>= 8 samples per surface voxel, so the voxel shell has no holes),
    the occupied voxels are filled with :func:`scipy.ndimage.binary_fill_holes`; no watertightness or
    consistent orientation is needed (a union of overlapping closed shells works).
    """
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    pitch = float((hi - lo).max()) / max(resolution, 4)
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    count = int(min(max(8 * area.sum() / pitch**2, 1000), 400_000))
    face = rng.choice(len(faces), size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    sq = np.sqrt(r1)
    pts = np.einsum("sk,skd->sd", np.stack([1 - sq, sq * (1 - r2), sq * r2], axis=1), tri[face])
    return fill_solid(pts, pitch, with_depth=with_depth)


def fill_solid(
    surface: np.ndarray, pitch: float, *, with_depth: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """(P, 3) centres of the voxels (edge ``pitch``) of the solid whose surface ``surface`` samples densely,
    and with ``with_depth`` also (P,) each voxel's distance to the outside of the solid (same unit)."""
    from scipy import ndimage

    origin = surface.min(axis=0) - pitch
    idx = np.floor((surface - origin) / pitch).astype(np.int64)
    occ = np.zeros(tuple(idx.max(axis=0) + 2), dtype=bool)
    occ[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    # a one-voxel dilation closes seams (a union of capsules with its buried faces removed has small
    # holes where the capsules meet); the erosion after filling gives the limbs back their size
    grown = ndimage.binary_dilation(np.pad(occ, 2))
    solid = ndimage.binary_erosion(ndimage.binary_fill_holes(grown))[2:-2, 2:-2, 2:-2] | occ
    idx = np.argwhere(solid)
    points = origin + (idx + 0.5) * pitch
    if not with_depth:
        return points
    depth = ndimage.distance_transform_edt(np.pad(solid, 1))[1:-1, 1:-1, 1:-1] * pitch
    return points, depth[idx[:, 0], idx[:, 1], idx[:, 2]]


def cloud_volume_points(
    points: np.ndarray, resolution: int, *, with_depth: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Voxels of the solid around a point cloud (Gaussian centres): the pitch is at least 2.5 point
    spacings, so that the surface voxels have no holes."""
    spacing = float(np.median(cKDTree(points).query(points, 2)[0][:, 1]))
    pitch = max(float(np.ptp(points, axis=0).max()) / max(resolution, 4), 2.5 * spacing)
    return fill_solid(points, pitch, with_depth=with_depth)


def trunk_core(graph: csr_matrix, points: np.ndarray, depth: np.ndarray, fraction: float, reach: float) -> np.ndarray:
    """(C,) indices of the trunk's core: the points deeper than ``fraction`` x the largest depth that are
    connected (over ``graph``, through such points) to the seed and within geodesic ``reach`` x the
    largest depth of it. The seed is the deepest point, ties broken towards the centroid (a shape of bars
    of one thickness is equally deep along every bar); the reach keeps a thin shape's core from running
    along all of its bars.

    Args:
        graph: (M, M) neighbour graph; points: (M, 3) normalised points (centroid 0);
        depth: (M,) depth inside the solid in the points' unit; fraction, reach: as above.
    """
    d_max = float(depth.max())
    seed = int(np.argmax(depth / max(d_max, 1e-12) - 0.6 * np.linalg.norm(points, axis=1)))
    return core_around(graph, depth, seed, fraction * d_max, reach * d_max)


def core_around(graph: csr_matrix, depth: np.ndarray, seed: int, min_depth: float, reach: float) -> np.ndarray:
    """(C,) the core around ``seed``: the points deeper than ``min_depth``, connected to it through such
    points and within geodesic distance ``reach`` of it (see :func:`trunk_core`)."""
    deep = np.flatnonzero(depth >= min_depth)
    deep = np.union1d(deep, [seed])
    sub = graph[deep][:, deep]
    local = int(np.searchsorted(deep, seed))
    dist = dijkstra(sub, directed=False, indices=local, limit=reach)
    return deep[np.isfinite(dist)]


#: a separate blob of the solid deeper than one of these fractions of its deepest point is a candidate
#: trunk (a body joined to a bigger head by a neck half as deep as the head parts from it only at 0.6)
BLOB_DEPTHS = (0.5, 0.6)


def blob_seeds(graph: csr_matrix, depth: np.ndarray, fraction: float, *, exclude: np.ndarray,
               min_points: int = 8) -> list[int]:
    """The deepest point of every connected piece of the points deeper than ``fraction`` x the largest
    depth (over ``graph``), except the pieces holding an ``exclude`` point and those of fewer than
    ``min_points`` points."""
    deep = np.flatnonzero(depth >= fraction * float(depth.max()))
    _, comp = connected_components(graph[deep][:, deep], directed=False)
    skip = set(comp[np.isin(deep, exclude)].tolist())
    seeds = []
    for c in np.unique(comp):
        members = deep[comp == c]
        if c not in skip and len(members) >= min_points:
            seeds.append(int(members[np.argmax(depth[members])]))
    return seeds


#: the ground: the points in this lowest share of the shape's height
GROUND_SHARE = 0.05


def trunk_on_legs(graph: csr_matrix, points: np.ndarray, depth: np.ndarray, core: np.ndarray, config: SkeletonConfig,
                  up: int) -> np.ndarray:
    """The trunk's core among the solid's thick blobs: the one nearest the ground (by mean geodesic
    distance to the ground points), of those not on the ground themselves.

    The blobs are taken at each depth of :data:`BLOB_DEPTHS` (the pieces the deep points make at that
    fraction of the largest depth). The trunk carries the legs and the legs reach the ground: of a big
    head and a body (a stuffed toy),
    the body is nearer the feet; a base plate lying on the ground (a lamp's) is no trunk. ``core`` is the
    deepest blob's core (:func:`trunk_core`), kept when no other blob qualifies.
    """
    others = list(dict.fromkeys(q for f in BLOB_DEPTHS for q in blob_seeds(graph, depth, f, exclude=core)))
    if not others:
        return core
    h = points[:, up]
    ground = h <= h.min() + GROUND_SHARE * float(np.ptp(h))
    cores = [core]
    for seed in others:
        d = float(depth[seed])
        other = core_around(graph, depth, seed, config.core_depth * d, config.core_reach * d)
        if not ground[other].any():
            cores.append(other)
    if len(cores) == 1:
        return core
    seeds = [int(c[np.argmax(depth[c])]) for c in cores]
    dist = dijkstra(graph, directed=False, indices=seeds)[:, np.flatnonzero(ground)]
    return cores[int(np.argmin(np.where(np.isfinite(dist), dist, np.inf).mean(axis=1)))]


def curve_skeleton(points: np.ndarray, config: SkeletonConfig, depth: np.ndarray | None = None, *, up: int = 1
                   ) -> CurveSkeleton:
    """The curve skeleton of a normalised point set (see the module docstring).

    Args:
        points: (M, 3) points in a normalised frame (unit RMS radius about their centroid), M >= 16.
        config: skeleton options.
        depth: (M,) distance of each point to the outside of the solid (any unit), or None; with it and
            ``config.core_depth > 0`` geodesic distance is taken from the trunk's core (:func:`trunk_core`).

    Returns:
        CurveSkeleton.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 16 or not np.isfinite(pts).all():
        raise InputError(f"curve_skeleton: need (M >= 16, 3) finite points, got {pts.shape}")
    graph = neighbour_graph(pts, config.neighbours, config.max_edge_factor)
    if depth is not None and config.core_depth > 0 and len(depth) == len(pts):
        depth = np.asarray(depth, dtype=np.float64)
        core = trunk_core(graph, pts, depth, config.core_depth, config.core_reach)
        core = trunk_on_legs(graph, pts, depth, core, config, up)
        sk = _skeleton_from(pts, graph, core, config)
        if len(sk.branches) > 1:
            return sk
        # no branch off the core (a shape of bars of one thickness, whose deepest part is an end):
        # the levels from the centre point still split where its bars meet
    centre = int(np.argmin(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))
    return _skeleton_from(pts, graph, np.array([centre]), config)


def _skeleton_from(pts: np.ndarray, graph: csr_matrix, core: np.ndarray, config: SkeletonConfig) -> CurveSkeleton:
    """The skeleton of levels of geodesic distance from the ``core`` points (a single centre, or a core)."""
    centre = int(core[np.argmin(np.linalg.norm(pts[core] - pts[core].mean(axis=0), axis=1))])
    if len(core) > 1:
        geo, pred, _ = dijkstra(graph, directed=False, indices=core, return_predecessors=True, min_only=True)
    else:
        geo, pred = geodesic_from(graph, centre)
    spacing = float(np.median(cKDTree(pts).query(pts, 2)[0][:, 1]))
    width = max(config.level_width, config.level_spacings * spacing)
    node, parent = reeb_tree(graph, geo, pred, width, centre)
    num = len(parent)
    top = np.full(num, -np.inf)
    bottom = np.full(num, np.inf)
    np.maximum.at(top, node, geo)
    np.minimum.at(bottom, node, geo)
    root = int(node[centre])
    alive, owner = prune_branches(parent, top, bottom, root, config.prune_length)
    node = owner[node]
    chains, chain_parent = node_chains(parent, alive, root)
    return replace(_assemble(pts, geo, centre, node, chains, chain_parent, width), core=core, graph=graph)


def _assemble(
    pts: np.ndarray,
    geo: np.ndarray,
    centre: int,
    node: np.ndarray,
    chains: list[list[int]],
    chain_parent: list[int],
    level_width: float,
) -> CurveSkeleton:
    """Branches from node chains: point sets, subtrees, base/tip centroids, lengths."""
    node_branch = np.full(int(node.max()) + 1, -1, dtype=np.int64)
    for i, chain in enumerate(chains):
        node_branch[chain] = i
    branch = node_branch[node]
    children: list[list[int]] = [[] for _ in chains]
    for i, p in enumerate(chain_parent):
        if p >= 0:
            children[p].append(i)
    # subtree membership: walk each point's branch up to the root
    member = np.zeros((len(chains), len(pts)), dtype=bool)
    for i in range(len(chains)):
        a = i
        sel = branch == i
        while a >= 0:
            member[a] |= sel
            a = chain_parent[a]
    out = []
    for i, chain in enumerate(chains):
        own = np.flatnonzero(branch == i)
        sub = np.flatnonzero(member[i])
        first = np.flatnonzero(node == chain[0]) if i > 0 else np.array([centre])
        first = first if len(first) else own[:1]
        base_level = float(geo[first].min()) if len(first) else 0.0
        far = float(geo[sub].max()) if len(sub) else base_level
        tip_pts = sub[geo[sub] >= far - level_width] if len(sub) else first
        out.append(
            Branch(
                nodes=tuple(int(n) for n in chain),
                parent=int(chain_parent[i]),
                children=tuple(children[i]),
                points=own,
                subtree=sub,
                base=pts[first].mean(axis=0),
                tip=pts[tip_pts].mean(axis=0),
                base_level=base_level,
                length=max(far - base_level, 1e-9),
            )
        )
    return CurveSkeleton(pts, geo, centre, node, branch, tuple(out), level_width)
