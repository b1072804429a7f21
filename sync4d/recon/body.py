"""Skeleton geometry: segments, Gaussian bones along them, and a capsule body around them.

Pure NumPy helpers shared by ``recon=mocap`` and by anything that needs a body with a shape around a
skeleton (e.g. two bodies of different proportions from one skeleton, for part matching).

A skeleton is ``joint_positions`` (J, 3) [m] plus ``parents`` (J,) int with ``-1`` for the root. Segment
``j`` runs from ``parents[j]`` to joint ``j``; it is named by its child joint ``j``.
"""

from __future__ import annotations

import numpy as np


def skeleton_segments(joint_positions: np.ndarray, parents: np.ndarray, *, min_length: float = 1e-6) -> np.ndarray:
    """Child-joint indices of the segments of a skeleton that have a length above ``min_length``.

    Args:
        joint_positions: (J, 3) joint positions [m].
        parents: (J,) parent index per joint, -1 for roots.
        min_length: shorter segments (e.g. BVH helper joints with zero offset) are skipped [m].

    Returns:
        (S,) int64 child joint index of each kept segment, in joint order.
    """
    parents = np.asarray(parents)
    keep = [
        j
        for j in range(len(parents))
        if parents[j] >= 0 and np.linalg.norm(joint_positions[j] - joint_positions[parents[j]]) > min_length
    ]
    return np.asarray(keep, dtype=np.int64)


def _frame_from_axis(axis: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose third column is the unit vector ``axis`` (first two columns arbitrary)."""
    z = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def segment_radii(
    joint_positions: np.ndarray,
    parents: np.ndarray,
    segments: np.ndarray,
    radius_scale: float,
    *,
    radii: np.ndarray | None = None,
    min_radius: float = 0.0,
) -> np.ndarray:
    """(S,) capsule radius of each segment [m]: ``radii[j]`` if given, else ``radius_scale * length``.

    The result is floored at ``min_radius`` [m].
    """
    lengths = np.linalg.norm(joint_positions[segments] - joint_positions[np.asarray(parents)[segments]], axis=1)
    r = np.asarray(radii, dtype=np.float64)[segments] if radii is not None else radius_scale * lengths
    return np.maximum(r, min_radius)


def capsule_mesh(
    start: np.ndarray, end: np.ndarray, radius: float, *, rings: int = 8, sectors: int = 12,
    band_spacing: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """A closed (watertight) triangle mesh of one capsule around the segment start -> end.

    Args:
        start: (3,) first end point [m].
        end: (3,) second end point [m] (distinct from ``start``).
        radius: capsule radius [m] (> 0).
        rings: latitude rings per hemisphere (>= 2).
        sectors: longitude divisions (>= 3).
        band_spacing: largest distance between vertex rings along the cylinder [m]; None = one band
            (vertices only on the end caps, so a long capsule has no vertex along its middle).

    Returns:
        (vertices (N, 3) [m], faces (F, 3) int64, outward-oriented).
    """
    axis = end - start
    length = float(np.linalg.norm(axis))
    rot = _frame_from_axis(axis)
    # Latitudes from the top pole (+z) to the bottom pole; the equator row is doubled so the
    # cylinder part joins the two hemispheres.
    top = np.linspace(0.0, np.pi / 2, rings + 1)[1:]
    bottom = np.linspace(np.pi / 2, np.pi, rings + 1)[:-1]
    phis = np.linspace(0.0, 2 * np.pi, sectors, endpoint=False)
    rows = []
    bands = max(1, int(np.ceil(length / band_spacing))) if band_spacing and band_spacing > 0 else 1
    middle = [(np.pi / 2, length / 2 - length * k / bands) for k in range(1, bands)]
    for lat, shift in [(a, length / 2) for a in top] + middle + [(a, -length / 2) for a in bottom]:
        ring = np.stack(
            [radius * np.sin(lat) * np.cos(phis), radius * np.sin(lat) * np.sin(phis),
             np.full(sectors, radius * np.cos(lat) + shift)],
            axis=1,
        )
        rows.append(ring)
    local = np.concatenate(
        [np.array([[0.0, 0.0, radius + length / 2]]), *rows, np.array([[0.0, 0.0, -radius - length / 2]])]
    )
    n_rows = len(rows)
    faces: list[tuple[int, int, int]] = []
    bottom_pole = 1 + n_rows * sectors
    for s in range(sectors):
        s2 = (s + 1) % sectors
        faces.append((0, 1 + s, 1 + s2))
        last = 1 + (n_rows - 1) * sectors
        faces.append((bottom_pole, last + s2, last + s))
        for r in range(n_rows - 1):
            a, b = 1 + r * sectors + s, 1 + r * sectors + s2
            c, d = a + sectors, b + sectors
            faces.append((a, c, b))
            faces.append((b, c, d))
    verts = local @ rot.T + (start + end) / 2
    return verts, np.asarray(faces, dtype=np.int64)


def capsule_body(
    joint_positions: np.ndarray,
    parents: np.ndarray,
    radius_scale: float = 0.15,
    *,
    radii: np.ndarray | None = None,
    min_radius: float = 0.0,
    min_length: float = 1e-6,
    rings: int = 6,
    sectors: int = 10,
    band_spacing: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A body mesh made of one capsule per skeleton segment, merged into one vertex/face list.

    Each capsule is closed and outward-oriented; capsules overlap at the joints and are not
    boolean-unioned, so the merged mesh is a union of watertight shells (fine for sampling, rendering
    and feature extraction; not a single 2-manifold).

    Different proportions from one skeleton: call twice with different ``radius_scale`` (or ``radii``),
    or with scaled ``joint_positions``.

    Args:
        joint_positions: (J, 3) joint positions [m].
        parents: (J,) parent index per joint, -1 for roots.
        radius_scale: capsule radius as a fraction of its segment's length (used when ``radii`` is None).
        radii: (J,) radius of the segment ending at each joint [m] (root entry ignored), or None.
        min_radius: lower bound of every radius [m] (keeps very short segments visible).
        min_length: segments shorter than this are skipped [m].
        rings: latitude rings per hemisphere of each capsule.
        sectors: longitude divisions of each capsule.
        band_spacing: largest ring spacing along each cylinder [m] (see :func:`capsule_mesh`).

    Returns:
        vertices: (N, 3) [m].
        faces: (F, 3) int64 indices into vertices.
        segment: (N,) int64 child-joint index j of the segment (parents[j] -> j) that made each vertex.

    Raises:
        ValueError: shapes disagree, or no segment is longer than ``min_length``.
    """
    joints = np.asarray(joint_positions, dtype=np.float64)
    parents = np.asarray(parents, dtype=np.int64)
    if joints.ndim != 2 or joints.shape[1] != 3 or parents.shape != (len(joints),):
        raise ValueError(f"capsule_body: need (J, 3) joints and (J,) parents, got {joints.shape}, {parents.shape}")
    segments = skeleton_segments(joints, parents, min_length=min_length)
    if len(segments) == 0:
        raise ValueError("capsule_body: the skeleton has no segment longer than min_length")
    rad = segment_radii(joints, parents, segments, radius_scale, radii=radii, min_radius=min_radius)
    verts, faces, owner = [], [], []
    offset = 0
    for j, r in zip(segments, rad):
        v, f = capsule_mesh(joints[parents[j]], joints[j], float(max(r, 1e-9)), rings=rings, sectors=sectors,
                            band_spacing=band_spacing)
        verts.append(v)
        faces.append(f + offset)
        owner.append(np.full(len(v), j, dtype=np.int64))
        offset += len(v)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(owner)


def segment_gaussians(
    joint_positions: np.ndarray,
    parents: np.ndarray,
    segments: np.ndarray,
    radii: np.ndarray,
    *,
    along_factor: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian bones along skeleton segments.

    Args:
        joint_positions: (J, 3) [m].
        parents: (J,).
        segments: (S,) child-joint index per segment.
        radii: (S,) capsule radius per segment [m]: the std-dev across the segment.
        along_factor: std-dev along the segment as a fraction of its length.

    Returns:
        (centres (S, 3) at the segment midpoints [m], covariances (S, 3, 3) elongated along the segment [m^2]).
    """
    a = joint_positions[np.asarray(parents)[segments]]
    b = joint_positions[segments]
    centers = 0.5 * (a + b)
    covs = np.zeros((len(segments), 3, 3))
    for i in range(len(segments)):
        rot = _frame_from_axis(b[i] - a[i])
        length = float(np.linalg.norm(b[i] - a[i]))
        sig = np.array([radii[i], radii[i], max(along_factor * length, radii[i])])
        covs[i] = (rot * sig**2) @ rot.T
    return centers, covs


def segment_distance_sq(points: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """(N, S) squared Euclidean distance of each point to each line segment start -> end [m^2].

    Args:
        points: (N, 3) [m].
        starts: (S, 3) [m].
        ends: (S, 3) [m].
    """
    axis = ends - starts
    len2 = np.maximum((axis * axis).sum(-1), 1e-18)
    rel = points[:, None, :] - starts[None]
    s = np.clip((rel * axis[None]).sum(-1) / len2, 0.0, 1.0)
    closest = starts[None] + s[..., None] * axis[None]
    return ((points[:, None, :] - closest) ** 2).sum(-1)


def segment_skinning(
    points: np.ndarray,
    joint_positions: np.ndarray,
    parents: np.ndarray,
    segments: np.ndarray,
    radii: np.ndarray,
    groups: np.ndarray | None = None,
    *,
    temperature: float = 0.25,
) -> np.ndarray:
    """Skinning weights by distance to skeleton segments.

    The distance of x to segment s is measured in units of the segment's radius (a Mahalanobis
    distance with an isotropic covariance r_s^2 around the segment's line), so a capsule's own surface
    is at distance 1 whatever its size; ``W = softmax(-d^2 / temperature)`` over bones, where a bone made
    of several segments (``groups``) takes its nearest member. A plain Mahalanobis distance to one
    Gaussian per segment would let large bones take over the ends of small neighbouring ones.

    Args:
        points: (N, 3) [m].
        joint_positions: (J, 3) rest joints [m].
        parents: (J,).
        segments: (S,) child joint per segment.
        radii: (S,) radius per segment [m].
        groups: (S,) bone index per segment, or None (one bone per segment).
        temperature: softness of the blend (smaller = crisper parts), in squared radius units.

    Returns:
        (N, B) weights, rows sum to 1.
    """
    d2 = segment_distance_sq(points, joint_positions[np.asarray(parents)[segments]], joint_positions[segments])
    d2 = d2 / np.maximum(radii, 1e-9)[None] ** 2
    if groups is not None:
        n_bones = int(groups.max()) + 1
        per_bone = np.full((len(points), n_bones), np.inf)
        for s, g in enumerate(groups):
            per_bone[:, g] = np.minimum(per_bone[:, g], d2[:, s])
        d2 = per_bone
    logits = -d2 / temperature
    logits -= logits.max(1, keepdims=True)
    w = np.exp(logits)
    return w / w.sum(1, keepdims=True)
