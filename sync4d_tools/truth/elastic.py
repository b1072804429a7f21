"""The elastic truth: the target as an as-rigid-as-possible solid whose bone cores follow the joint motion.

Not a skinning model and not this project's simulator: the target's Gaussians (surface and interior samples)
are the vertices of a tetrahedral mesh (Delaunay, kept where the tet lies inside the target's own surface);
each bone's *core* is held by that bone's rigid motion, and the rest of the solid settles where libigl's
ARAP energy (``igl.arap_precomputation`` / ``igl.arap_solve``, per-tet ``ARAP_ENERGY_TYPE_ELEMENTS``: the sum
over tets of vol |F - R|^2, a quasi-static co-rotated elastic solid with Poisson's ratio 0) is least. Each frame
starts from the previous frame's solution (a quasi-static path through the motion).

**Bone core** (one definition for every target): the points of bone b's own region (argmax of the target
model's skinning, taken from the nearest rest vertex) whose skinning weight of b is at least
:data:`CORE_WEIGHT` (outside the blended joint zones) and whose distance to the bone's segment is at most
:data:`CORE_RADIUS` times the median distance of the region's points to it. The segment is the line
through the bone centre along the major axis of the bone's Gaussian, clipped to the region's extent along
it. Everything outside the cores (the flesh around them and the joints) is elastic.

Checked on known answers (tests/test_elastic_truth.py): every handle rotated rigidly -> the whole solid
rotates rigidly; a bar pulled by its end faces -> uniform stretch, both to solver tolerance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sync4d.errors import ConfigError

#: smallest skinning weight of its own bone for a point to be in that bone's core
CORE_WEIGHT = 0.9
#: core radius as a fraction of the median distance of the bone region's points to its segment
CORE_RADIUS = 0.5
#: ARAP local-global iterations per frame (each frame starts from the previous one's solution)
ITERATIONS = 60
#: tets whose quality (6 sqrt(2) V / l_rms^3, 1 for a regular tet) is below this are dropped as slivers
MIN_QUALITY = 0.02


@dataclass(frozen=True)
class TetMesh:
    """A tetrahedral mesh on given points.

    Attributes:
        vertices: (N, 3) rest positions [m] (all the points, used or not).
        tets: (M, 4) int64 positively oriented tets over ``vertices``.
        used: (N,) bool: the vertex belongs to a kept tet (the others follow their nearest tet).
    """

    vertices: np.ndarray
    tets: np.ndarray
    used: np.ndarray


def tet_quality(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(M,) signed quality 6 sqrt(2) V / l_rms^3 of each tet (1 regular, 0 flat, < 0 inverted)."""
    p = vertices[tets]
    vol = np.einsum("mi,mi->m", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0
    edges = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    l_rms = np.sqrt(np.mean([((p[:, a] - p[:, b]) ** 2).sum(axis=1) for a, b in edges], axis=0))
    return 6.0 * np.sqrt(2.0) * vol / np.maximum(l_rms, 1e-300) ** 3


def tetrahedralise(points: np.ndarray, surface_vertices: np.ndarray, surface_faces: np.ndarray, *,
                   min_quality: float = MIN_QUALITY) -> TetMesh:
    """Delaunay tets on ``points`` kept where they lie inside the closed surface (winding number >= 0.5).

    Tets are oriented positively; slivers (quality below ``min_quality``) are dropped.

    Args:
        points: (N, 3) [m]; surface_vertices, surface_faces: the body's rest surface (may self-intersect).
    """
    import igl
    from scipy.spatial import Delaunay

    points = np.asarray(points, dtype=np.float64)
    tets = Delaunay(points).simplices.astype(np.int64)
    quality = tet_quality(points, tets)
    flip = quality < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    tets = tets[np.abs(quality) >= min_quality]
    centroids = points[tets].mean(axis=1)
    winding = igl.fast_winding_number(np.asarray(surface_vertices, dtype=np.float64),
                                      np.asarray(surface_faces, dtype=np.int64), centroids)
    tets = tets[winding >= 0.5]
    used = np.zeros(len(points), dtype=bool)
    used[tets.ravel()] = True
    return TetMesh(points, tets, used)


def bone_segment(center: np.ndarray, covariance: np.ndarray, region: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bone's segment (a, b) [m]: the major axis of its Gaussian through its centre, clipped to the
    extent of its region's (n, 3) points along that axis."""
    _, vectors = np.linalg.eigh(covariance)
    axis = vectors[:, -1]
    along = (region - center) @ axis
    return center + along.min() * axis, center + along.max() * axis


def distance_to_segment(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) distance of (n, 3) points to the segment a-b [m]."""
    ab = b - a
    s = np.clip((points - a) @ ab / max(float(ab @ ab), 1e-300), 0.0, 1.0)
    return np.linalg.norm(points - (a + s[:, None] * ab), axis=1)


def bone_cores(points: np.ndarray, weights: np.ndarray, bone_centers: np.ndarray,
               bone_covariances: np.ndarray) -> np.ndarray:
    """(N,) the bone whose core holds each point, or -1 (see the module's definition).

    Args:
        points: (N, 3) rest positions [m]; weights: (N, B) skinning weights of the target's own model.
        bone_centers: (B, 3) [m]; bone_covariances: (B, 3, 3) [m^2] (the model's Gaussian bones).
    """
    labels = weights.argmax(axis=1)
    core = np.full(len(points), -1, dtype=np.int64)
    for bone in range(weights.shape[1]):
        region = np.flatnonzero(labels == bone)
        if len(region) < 4:
            continue
        a, b = bone_segment(bone_centers[bone], bone_covariances[bone], points[region])
        dist = distance_to_segment(points[region], a, b)
        inside = (dist <= CORE_RADIUS * np.median(dist)) & (weights[region, bone] >= CORE_WEIGHT)
        core[region[inside]] = bone
    return core


def held_components(mesh: TetMesh, held: np.ndarray) -> TetMesh:
    """The mesh without the tets of connected pieces that hold fewer than 4 held vertices (their rigid
    motion would be free); their vertices become unused and follow their nearest kept tet."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(mesh.vertices)
    a, b = np.repeat(mesh.tets[:, :1], 3, axis=1).ravel(), mesh.tets[:, 1:].ravel()
    _, comp = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)), directed=False)
    counts = np.bincount(comp[held & mesh.used], minlength=comp.max() + 1)
    tets = mesh.tets[counts[comp[mesh.tets[:, 0]]] >= 4]
    used = np.zeros(n, dtype=bool)
    used[tets.ravel()] = True
    return TetMesh(mesh.vertices, tets, used)


def follow_nearest_tet(mesh: TetMesh, solved: np.ndarray) -> np.ndarray:
    """(N, 3) positions of every vertex: the solved ones as they are, each unused one carried by the affine
    map of the kept tet whose centroid is nearest (barycentric coordinates, extrapolated)."""
    from scipy.spatial import cKDTree

    out = solved.copy()
    loose = np.flatnonzero(~mesh.used)
    if len(loose) == 0:
        return out
    rest = mesh.vertices
    _, nearest = cKDTree(rest[mesh.tets].mean(axis=1)).query(rest[loose])
    tet = mesh.tets[nearest]  # (L, 4)
    edges = (rest[tet[:, 1:]] - rest[tet[:, :1]]).transpose(0, 2, 1)  # (L, 3, 3) columns
    bary = np.linalg.solve(edges, (rest[loose] - rest[tet[:, 0]])[..., None])[..., 0]
    moved = (solved[tet[:, 1:]] - solved[tet[:, :1]]).transpose(0, 2, 1)
    out[loose] = solved[tet[:, 0]] + np.einsum("lij,lj->li", moved, bary)
    return out


def arap_frames(mesh: TetMesh, core: np.ndarray, bone_motion: np.ndarray, *,
                iterations: int = ITERATIONS) -> np.ndarray:
    """(T, N, 3) quasi-static ARAP poses: core vertices moved by their bone's rigid motion, the rest solved.

    Args:
        mesh: the solid; core: (N,) bone holding each vertex or -1.
        bone_motion: (T, B, 4, 4) rest -> frame t rigid transform of each bone (frame 0 = rest).
    """
    import igl

    held = core >= 0
    mesh = held_components(mesh, held)
    index = np.flatnonzero(mesh.used)
    local = np.full(len(mesh.vertices), -1, dtype=np.int64)
    local[index] = np.arange(len(index))
    handles = np.flatnonzero(held[index])
    if len(handles) < 4:
        raise ConfigError(f"elastic truth: only {len(handles)} core vertices in the solid; the bones hold nothing")
    rest = mesh.vertices[index]
    data = igl.ARAPData()
    data.energy = igl.ARAP_ENERGY_TYPE_ELEMENTS
    data.max_iter = int(iterations)
    igl.arap_precomputation(rest, local[mesh.tets], 3, handles.astype(np.int32), data)
    bones = core[index[handles]]
    guess = rest.copy()
    frames = []
    for motion in bone_motion:
        rot, shift = motion[bones, :3, :3], motion[bones, :3, 3]
        bc = np.einsum("hij,hj->hi", rot, rest[handles]) + shift
        guess = igl.arap_solve(bc, data, guess)
        solved = np.zeros_like(mesh.vertices)
        solved[index] = guess
        frames.append(follow_nearest_tet(mesh, solved))
    return np.stack(frames)
