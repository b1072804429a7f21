"""From the reference's bone motion to the target's driving motion (paper Sec. 3.3-3.4).

Coverage ratio. The paper scales reference displacements by s_t / s_o, "the coverage ratio for target
space and reference space". We define the coverage s of a shape as the RMS distance of its surface
from its centroid, measured on area-weighted surface samples (or on its points when it has no faces):

    s = sqrt(mean_i |p_i - mean(p)|^2)

It is invariant to rotation and translation and exactly proportional to a uniform scale, so a scaled
copy of the reference (target = k * reference) gets s_t / s_o = k and exactly k-scaled motion. Sampling
the surface by area (rather than taking mesh vertices) keeps it independent of how finely either mesh is
tessellated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sync4d.geometry import part_centroids
from sync4d.surface import area_points
from sync4d.types import DrivingMotion, Reference


def surface_samples(points: np.ndarray, faces: np.ndarray | None, *, count: int = 20000, seed: int = 0) -> np.ndarray:
    """(count, 3) area-weighted samples of a triangle surface, or ``points`` themselves without faces."""
    points = np.asarray(points, dtype=np.float64)
    if faces is None or len(faces) == 0:
        return points
    tri = points[faces]
    sampled = area_points(tri, count, np.random.default_rng(seed))
    return points if sampled is None else sampled[0]


def coverage(points: np.ndarray, faces: np.ndarray | None = None) -> float:
    """Coverage s of a shape: RMS distance of its (area-sampled) surface from its centroid [m]."""
    samples = surface_samples(points, faces)
    return float(np.sqrt(((samples - samples.mean(axis=0)) ** 2).sum(axis=1).mean()))


def similarity_matrix(scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) x -> scale * R x + t."""
    out = np.eye(4)
    out[:3, :3] = scale * rotation
    out[:3, 3] = translation
    return out


def conjugate(transforms: np.ndarray, similarity: np.ndarray) -> np.ndarray:
    """S T S^-1 for every (..., 4, 4) rigid T: the same rigid motion seen in the target's space.

    With S = [sR | t] the rotation part becomes R Q R^T and translations are scaled by s, so the result
    stays rigid.
    """
    return similarity @ transforms @ np.linalg.inv(similarity)


def driving_motion(
    reference: Reference,
    *,
    target_points: np.ndarray,
    target_faces: np.ndarray | None,
    num_frames: int,
    loop: bool = True,
    rotation: np.ndarray | None = None,
    part_centroids: np.ndarray | None = None,
    joints_of: tuple[np.ndarray, np.ndarray] | None = None,
) -> DrivingMotion:
    """Express the reference's part motion in the target's space.

    Args:
        reference: the reconstructed reference.
        target_points, target_faces: the target's surface (or its Gaussian means and None) [m].
        num_frames: output length T; the reference is looped (``loop``) or truncated/held.
        rotation: (3, 3) rotation taking the reference's frame to the target's (from alignment); None
            for identity (both shapes given in the same upright frame).
        part_centroids: (B, 3) rest centroids of the target's parts [m]. When given, each part turns about
            its own centroid (by its bone's rotation) and its centroid moves by the scaled bone-centre
            displacement, so the part's motion is anchored on the target's own geometry (see
            :func:`recentre_on_parts`); None keeps the bone transforms as mapped into target space.
        joints_of: the target's (N, 3) points [m] and (N,) parts. When given (with ``part_centroids``), the parts
            are hung on a tree (:func:`part_skeleton`, joins chosen where the reference's own bones agree) and every
            part but each tree's root turns about its joint with its parent, carried by the parent
            (:func:`articulate`), so neighbours agree where they meet; the part transforms are then given rest
            -> t (frame 0 the identity) and ``part_parent`` holds the tree.

    Returns:
        A validated :class:`DrivingMotion` whose displacements are (s_t / s_o) R (b_{t+1} - b_t).
    """
    s_ref = coverage(reference.rest_vertices, reference.rest_faces)
    s_tgt = coverage(target_points, target_faces)
    ratio = s_tgt / s_ref
    rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
    ref_center = surface_samples(reference.rest_vertices, reference.rest_faces).mean(axis=0)
    tgt_center = surface_samples(target_points, target_faces).mean(axis=0)
    sim = similarity_matrix(ratio, rot, tgt_center - ratio * rot @ ref_center)

    frame_index = frame_indices(reference.num_frames, num_frames, loop=loop)
    bones = conjugate(reference.bone_transforms[frame_index], sim)
    skeleton = None
    if joints_of is not None:
        skeleton = part_skeleton(joints_of[0], joints_of[1], bones.shape[1],
                                 motion=bones @ np.linalg.inv(bones[0])[None])
    if part_centroids is not None:
        mapped_centers = reference.bone_centers @ (ratio * rot).T + sim[:3, 3]
        bones = recentre_on_parts(bones, mapped_centers, np.asarray(part_centroids, dtype=np.float64))
        if skeleton is not None:
            bones = articulate(bones @ np.linalg.inv(bones[0])[None], skeleton)
    # The global transform moves the whole object; in target space its translation scales like the rest.
    glob = conjugate(reference.global_transforms[frame_index], sim)
    centers_ref = reference.bone_centers_at()[frame_index]  # (T, B, 3)
    if loop and reference.num_frames < num_frames:
        # Displacements across a loop seam would jump back to frame 0; use the motion's own steps instead.
        steps = np.diff(reference.bone_centers_at(), axis=0)
        wrap = reference.bone_centers_at()[0] - reference.bone_centers_at()[-1]
        cyc = np.concatenate([steps, wrap[None]])
        disp_ref = cyc[frame_index[:-1] % reference.num_frames]
    else:
        disp_ref = np.diff(centers_ref, axis=0)
    displacements = ratio * np.einsum("ij,tbj->tbi", rot, disp_ref)
    return DrivingMotion(
        part_transforms=bones,
        part_displacements=displacements,
        global_transforms=glob,
        coverage_ratio=float(ratio),
        fps=reference.fps,
        part_parent=None if skeleton is None else skeleton.parent.copy(),
    ).validate()


def recentre_on_parts(transforms: np.ndarray, bone_centers: np.ndarray, part_centroids: np.ndarray) -> np.ndarray:
    """Move each part's rotation pivot from its bone centre to the target part's own centroid.

    A bone transform T = [R | t] moves the bone centre c to T c. The returned A = [R | g - R g + (T c - c)]
    turns the part by the same R about its centroid g and translates g by the bone centre's displacement
    T c - c: the paper's centroid target is met exactly, and the bone's rotation is kept. Where the
    target part's centroid coincides with the mapped bone centre (a self-transfer), A = T. Parts with
    no Gaussians (NaN centroid) keep T.

    Args:
        transforms: (T, B, 4, 4) part transforms in target space.
        bone_centers: (B, 3) rest bone centres mapped into target space [m].
        part_centroids: (B, 3) rest centroids of the target's parts [m].
    """
    out = transforms.copy()
    rot = transforms[..., :3, :3]
    moved = np.einsum("tbij,bj->tbi", rot, bone_centers) + transforms[..., :3, 3]
    shift = moved - bone_centers
    g = np.where(np.isfinite(part_centroids), part_centroids, bone_centers)
    out[..., :3, 3] = g - np.einsum("tbij,bj->tbi", rot, g) + shift
    return out


@dataclass(frozen=True)
class PartSkeleton:
    """The target's parts as a forest: which part each hangs from, and where.

    Attributes:
        parent: (B,) the part each part is joined to (-1 for the root of a tree: the heaviest part of each
            group of touching parts, and parts that touch nothing).
        joint: (B, 3) rest position of each part's joint with its parent [m] (the mean of the midpoints of the
            neighbour pairs that join them; the part's centroid for a root).
        order: (B,) the parts, every parent before its children.
    """

    parent: np.ndarray
    joint: np.ndarray
    order: np.ndarray


def part_skeleton(points: np.ndarray, parts: np.ndarray, num_parts: int, *, motion: np.ndarray | None = None,
                  neighbours: int = 8) -> PartSkeleton:
    """A spanning forest of the touching parts of rest ``points`` (N, 3) [m] labelled ``parts`` (N,).

    Two parts touch through the pairs of points that are among each other's ``neighbours`` nearest and no
    farther apart than twice the median nearest-neighbour spacing. Of the touching pairs the tree keeps, from each
    group's heaviest part outwards (Prim's algorithm), the joins whose parts' driving ``motion`` (T, B, 4, 4),
    rest -> t, agrees best at a common pivot (:func:`pivot_residuals`: thighs that touch but swing apart are not
    joined), ties broken by the most contact; without a motion, the most contact.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    parts = np.asarray(parts, dtype=np.int64)
    k = min(neighbours + 1, len(points))
    distance, index = cKDTree(points).query(points, k=k)
    reach = 2.0 * float(np.median(distance[:, 1])) if k > 1 else 0.0
    i = np.repeat(np.arange(len(points)), k - 1)
    j, d = index[:, 1:].ravel(), distance[:, 1:].ravel()
    cross = (parts[i] != parts[j]) & (d <= reach) & (parts[i] >= 0) & (parts[j] >= 0)
    a, b = parts[i[cross]], parts[j[cross]]
    contact = np.zeros((num_parts, num_parts))
    np.add.at(contact, (a, b), 1.0)
    midpoint = np.zeros((num_parts, num_parts, 3))
    np.add.at(midpoint, (a, b), 0.5 * (points[i[cross]] + points[j[cross]]))
    contact_sym = contact + contact.T
    joint_sum = midpoint + np.swapaxes(midpoint, 0, 1)
    touching = contact_sym > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        joint_mid = joint_sum / contact_sym[..., None]
    residual = np.zeros((num_parts, num_parts)) if motion is None else pivot_residuals(motion, joint_mid, touching)
    scale = float(np.ptp(points, axis=0).max()) or 1.0
    # lower is better: the pivot mismatch in object sizes, then the share of contact
    cost = residual / scale - 1e-6 * contact_sym / max(float(contact_sym.max()), 1.0)
    size = np.bincount(np.where(parts >= 0, parts, 0), weights=(parts >= 0).astype(float), minlength=num_parts)
    centroid = np.nan_to_num(part_centroids(points, np.where(parts >= 0, parts, 0), num_parts))
    parent = np.full(num_parts, -1)
    joint = centroid.copy()
    placed = np.zeros(num_parts, dtype=bool)
    order: list[int] = []
    for root in np.argsort(-size, kind="stable"):
        if placed[root]:
            continue
        placed[root] = True
        order.append(int(root))
        while True:  # Prim: the best join from the tree to a touching part not yet in it
            open_join = placed[:, None] & ~placed[None, :] & touching
            if not open_join.any():
                break
            p, c = np.unravel_index(int(np.argmin(np.where(open_join, cost, np.inf))), cost.shape)
            parent[c], joint[c] = p, joint_mid[p, c]
            placed[c] = True
            order.append(int(c))
    return PartSkeleton(parent, joint, np.asarray(order))


def pivot_residuals(motion: np.ndarray, near: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(B, B) RMS over frames of how far apart two parts' motions take their best common pivot [m].

    For each pair (p, c) in ``pairs`` (B, B) bool, the point y minimising sum_t |D_p(t) y - D_c(t) y|^2 (plus a
    small pull towards ``near[p, c]``, which fixes y along a hinge's axis) is the joint the two motions share;
    parts joined in the reference agree there at every frame (residual ~0), parts that merely touch do not.
    """
    B = motion.shape[1]
    out = np.full((B, B), np.inf)
    rot, shift = motion[..., :3, :3], motion[..., :3, 3]
    for p, c in zip(*np.nonzero(np.triu(pairs, 1))):
        a, b = rot[:, p] - rot[:, c], shift[:, p] - shift[:, c]  # (T, 3, 3), (T, 3)
        pull = 1e-3 * len(a)
        lhs = np.einsum("tji,tjk->ik", a, a) + pull * np.eye(3)
        y = np.linalg.solve(lhs, pull * near[p, c] - np.einsum("tji,tj->i", a, b))
        out[p, c] = out[c, p] = float(np.sqrt(np.mean(np.sum((np.einsum("tij,j->ti", a, y) + b) ** 2, axis=1))))
    return out


def articulate(relative: np.ndarray, skeleton: PartSkeleton) -> np.ndarray:
    """(T, B, 4, 4) rest -> t part motions in which each child keeps its own rotation but turns about its joint,
    carried where its parent takes that joint: A_c = [R_c | A_p j - R_c j]. Roots keep ``relative``."""
    out = relative.copy()
    for c in skeleton.order:
        p = skeleton.parent[c]
        if p < 0:
            continue
        j = skeleton.joint[c]
        carried = np.einsum("tij,j->ti", out[:, p, :3, :3], j) + out[:, p, :3, 3]
        out[:, c, :3, 3] = carried - np.einsum("tij,j->ti", relative[:, c, :3, :3], j)
    return out


def frame_indices(reference_frames: int, num_frames: int, *, loop: bool) -> np.ndarray:
    """(num_frames,) which reference frame each output frame uses: looped, or held at the last frame."""
    t = np.arange(num_frames)
    return t % reference_frames if loop else np.minimum(t, reference_frames - 1)
