"""The drive held through the frame: the rig's motion at every substep, as the kernels read it.

Complementary dynamics (Zhang, Bang, Levin, Jacobson 2020) splits the motion into the rig's part and a
complementary part that the rig's handles do not see: the complementary displacement u of every particle is
M-orthogonal to the rig's Jacobian J (J^T M u = 0). Here the rig is linear blend skinning by the parts' driving
motion of the frame pair: part b goes from its pose at t (``FramePose.start``) to its pose at t+1 (``end``) with
its mass centroid on a straight line and a constant angular velocity, and each particle moves with the blend of
its parts' motions by its weights (:func:`blend_weights`: the share of each joined part among its nearest
particles, so a seam follows a blend of the two parts instead of shearing between them; with one part per
particle the rig is part-wise rigid and the projection falls apart into one 6x6 solve per part). After every G2P
the kernels (:func:`kernels.drive_sums`, :func:`kernels.drive_solve`, :func:`kernels.drive_apply`) remove the
particles' deviation from the rig within the rig's 6B degrees of freedom (a translation and a small rotation per
part), from positions and velocities alike; the elastic solve keeps everything else.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from sync4d.geometry import matrix_to_rotation_vector, nearest_rotation, rotation_vector_to_matrix, skew_matrices
from sync4d.types import FramePose

#: Parts a particle's rig blends at most (its strongest weights, renormalised).
BLEND_SLOTS = 4
#: A part with fewer particles than this is held in translation only (its rotation is not determined).
MIN_TURNING_PARTICLES = 4
#: Rig directions weaker than this share of their part's strongest are not held (a part on a line turns freely
#: about it; inverting a near-zero moment would amplify float32 rounding into huge corrections).
INERTIA_RCOND = 1e-3


def blend_weights(points: np.ndarray, part: np.ndarray, num_parts: int, band: float,
                  parent: np.ndarray | None = None) -> np.ndarray:
    """(P, B) rig weights: each particle's own part, blended near a seam with the parts joined to it.

    A particle at distance d [m] from the nearest particle of a joined part c (its parent or a child in the tree
    ``parent`` (B,); any other part when the tree is None) takes w_c = 1/2 (1 - smoothstep(d / h)) of c's motion,
    h = min(``band``, half the radius of gyration of the particle's own part), and keeps the rest (at least 1/2) for
    its own part: on the seam the two parts share the motion equally, ``band`` away it is its own part's alone, and
    a small part (a hand, a paw) is blended over a band in proportion to its size, so it still turns with its own
    drive. A touching part that is not joined (the other thigh) is not blended: the two must be free to separate.
    ``band`` = 0, or a particle of no part (< 0), gives hard labels (a row of zeros for no part)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    part = np.asarray(part, dtype=np.int64)
    driven = part >= 0
    weights = np.zeros((len(part), num_parts))
    weights[np.flatnonzero(driven), part[driven]] = 1.0
    if band <= 0.0 or num_parts < 2:
        return weights
    members = [np.flatnonzero(part == b) for b in range(num_parts)]
    trees = {b: cKDTree(points[idx]) for b, idx in enumerate(members) if len(idx)}
    for b, idx in enumerate(members):
        if not len(idx) or b not in trees:
            continue
        gyration = np.sqrt(((points[idx] - points[idx].mean(0)) ** 2).sum(1).mean())
        h = min(band, 0.5 * gyration)
        if h <= 0.0:
            continue
        if parent is None:
            joined = [c for c in trees if c != b]
        else:
            tree = np.asarray(parent, dtype=np.int64)
            joined = [c for c in trees if c != b and (tree[c] == b or tree[b] == c)]
        for c in joined:
            d, _ = trees[c].query(points[idx], distance_upper_bound=h)
            s = np.clip(np.where(np.isfinite(d), d, h) / h, 0.0, 1.0)
            weights[idx, c] = 0.5 * (1.0 - s * s * (3.0 - 2.0 * s))
        other = weights[idx].sum(1) - 1.0  # the blended shares (own still at 1)
        scale = np.where(other > 0.5, 0.5 / np.maximum(other, 1e-300), 1.0)
        weights[idx] *= scale[:, None]
        weights[idx, b] = 1.0 - other * scale
    return weights


@dataclass(frozen=True)
class PartRig:
    """The rig's rest geometry, fixed for a model: what the drive needs besides the poses.

    Attributes:
        slot_part: (P, K) the parts each particle's rig blends (-1: an empty slot; all empty: not driven).
        slot_weight: (P, K) their weights (summing to 1 over a driven particle's filled slots).
        slot_offset: (P, K, 3) rest position minus the rest mass centroid of the slot's part [m].
        centroid: (B, 3) rest mass centroid of each part (by the particles labelled with it) [m].
        mass: (B,) mass of each part [kg] (0 for a part with no particle); count: (B,) particles of each part.
        pair_mass: (B, B) sum of m w_b w_c over particles [kg]: the rig's normal matrix, translation block.
        pair_moment: (B, B, 3) sum of m w_b w_c r_b [kg m] (r_b: the rest offset from part b's centroid).
        pair_second: (B, B, 3, 3) sum of m w_b w_c r_c r_b^T [kg m^2].
    """

    slot_part: np.ndarray
    slot_weight: np.ndarray
    slot_offset: np.ndarray
    centroid: np.ndarray
    mass: np.ndarray
    count: np.ndarray
    pair_mass: np.ndarray
    pair_moment: np.ndarray
    pair_second: np.ndarray

    @property
    def num_parts(self) -> int:
        return len(self.mass)


def part_rig(rest: np.ndarray, part: np.ndarray, mass: np.ndarray, num_parts: int,
             weights: np.ndarray | None = None) -> PartRig:
    """The rig of particles ``rest`` (P, 3) [m] of ``mass`` (P,) [kg] labelled ``part`` (P,) among ``num_parts``,
    blended by ``weights`` (P, B) (None: hard labels, :func:`blend_weights` with one neighbour)."""
    rest = np.asarray(rest, dtype=np.float64)
    part = np.asarray(part, dtype=np.int64)
    mass = np.asarray(mass, dtype=np.float64)
    driven = (part >= 0) & (part < num_parts)
    idx = np.where(driven, part, 0)
    own = np.where(driven, mass, 0.0)
    total = np.bincount(idx, weights=own, minlength=num_parts)
    moment = np.stack([np.bincount(idx, weights=own * rest[:, k], minlength=num_parts) for k in range(3)], 1)
    centroid = moment / np.maximum(total, 1e-300)[:, None]
    count = np.bincount(idx, weights=driven.astype(float), minlength=num_parts).astype(np.int64)
    if weights is None:
        weights = blend_weights(rest, np.where(driven, part, -1), num_parts, 0.0)
    weights = np.where(driven[:, None], np.asarray(weights, dtype=np.float64)[:, :num_parts], 0.0)
    k = min(BLEND_SLOTS, num_parts) if num_parts else 1
    order = np.argsort(-weights, axis=1, kind="stable")[:, :k]
    slot_weight = np.take_along_axis(weights, order, axis=1)
    slot_weight = slot_weight / np.maximum(slot_weight.sum(1, keepdims=True), 1e-300)
    filled = slot_weight > 0
    slot_part = np.where(filled, order, -1)
    if k < BLEND_SLOTS:  # pad to the kernels' fixed slot count
        pad = BLEND_SLOTS - k
        slot_part = np.pad(slot_part, ((0, 0), (0, pad)), constant_values=-1)
        slot_weight = np.pad(slot_weight, ((0, 0), (0, pad)))
    slot_offset = np.where(slot_part[..., None] >= 0, rest[:, None, :] - centroid[np.clip(slot_part, 0, None)], 0.0)
    # the normal matrix's rest moments, over every pair of a particle's slots
    pair_mass = np.zeros((num_parts, num_parts))
    pair_moment = np.zeros((num_parts, num_parts, 3))
    pair_second = np.zeros((num_parts, num_parts, 3, 3))
    for a in range(BLEND_SLOTS):
        for c in range(BLEND_SLOTS):
            both = (slot_part[:, a] >= 0) & (slot_part[:, c] >= 0)
            if not both.any():
                continue
            b_, c_ = slot_part[both, a], slot_part[both, c]
            mw = mass[both] * slot_weight[both, a] * slot_weight[both, c]
            ra, rc = slot_offset[both, a], slot_offset[both, c]
            np.add.at(pair_mass, (b_, c_), mw)
            np.add.at(pair_moment, (b_, c_), mw[:, None] * ra)
            np.add.at(pair_second, (b_, c_), mw[:, None, None] * rc[:, :, None] * ra[:, None, :])
    return PartRig(slot_part, slot_weight, slot_offset, centroid, total, count, pair_mass, pair_moment, pair_second)


@dataclass(frozen=True)
class SubstepDrive:
    """The rig at the end of every substep of one rollout, (S, B, ...) each, plus its constant velocities.

    Attributes:
        turn: (S, B, 3, 3) each part's rest -> now rotation.
        centre: (S, B, 3) each part's driven mass centroid [m].
        solve: (6B, 6B) damped inverse of the rig's normal matrix J^T M J (:func:`normal_matrix`, :func:`rig_solve`)
            at the frame's middle substep, unknowns ordered (translation [m], rotation vector in the part's turned
            frame [rad]) per part: exact for part-wise rigid rigs, whose matrix does not change as the parts turn;
            with blends only the couplings of parts that share particles turn within the frame.
        linear: (B, 3) centroid velocity [m/s]; angular: (B, 3) angular velocity [rad/s].
    """

    turn: np.ndarray
    centre: np.ndarray
    solve: np.ndarray
    linear: np.ndarray
    angular: np.ndarray


def normal_matrix(rig: PartRig, turn: np.ndarray) -> np.ndarray:
    """(6B, 6B) J^T M J of the rig turned by ``turn`` (B, 3, 3), with each part's rotation unknown in its own turned
    frame (w_b = turn_b w'_b). A particle's rig displacement is sum_b w_b (t_b - turn_b [r_b]x w'_b), r_b its rest
    offset from part b's centroid; the blocks of parts b, c are [[sum m w w I, -turn_c [a_c]x], [[a_b]x turn_b^T,
    (tr(Q P) I - Q P) Q]] with a_b = sum m w_b w_c r_b, P = sum m w_b w_c r_c r_b^T and Q = turn_b^T turn_c. With
    one part per particle the matrix is block-diagonal, [[M_b I, 0], [0, I_b]] with the rest inertia: constant."""
    B = turn.shape[0]
    eye = np.eye(3)
    a_b = rig.pair_moment  # (B, B, 3): sum m w_b w_c r_b
    a_c = np.swapaxes(rig.pair_moment, 0, 1)  # sum m w_b w_c r_c
    Q = np.einsum("bji,cjk->bcik", turn, turn)
    QP = Q @ rig.pair_second
    blocks = np.zeros((B, B, 6, 6))
    blocks[..., :3, :3] = rig.pair_mass[:, :, None, None] * eye
    blocks[..., :3, 3:] = -turn[None] @ skew_matrices(a_c)
    blocks[..., 3:, :3] = skew_matrices(a_b) @ np.swapaxes(turn, -1, -2)[:, None]
    blocks[..., 3:, 3:] = (np.trace(QP, axis1=-2, axis2=-1)[..., None, None] * eye - QP) @ Q
    return blocks.transpose(0, 2, 1, 3).reshape(6 * B, 6 * B)


def rig_solve(rig: PartRig, normal: np.ndarray) -> np.ndarray:
    """(6B, 6B) damped inverse of ``normal`` (6B, 6B). Each part's unknowns are scaled by its own mass and
    inertia first (unit diagonal for a well-posed part), then :data:`INERTIA_RCOND` is added to the diagonal: a
    direction weak within its part (a part on a line turning about it) is fitted only in proportion to its
    strength instead of amplifying float32 rounding, while the others are fitted to within that share. A part of
    fewer than :data:`MIN_TURNING_PARTICLES` particles is held in translation only."""
    B = rig.num_parts
    inertia_scale = np.einsum("bbii->b", rig.pair_second)  # trace of the rest second moment [kg m^2]
    scale = np.zeros((B, 6))
    scale[:, :3] = np.where(rig.mass > 0, 1.0 / np.sqrt(np.maximum(rig.mass, 1e-300)), 0.0)[:, None]
    turning = (rig.count >= MIN_TURNING_PARTICLES) & (inertia_scale > 0)
    scale[:, 3:] = np.where(turning, 1.0 / np.sqrt(np.maximum(inertia_scale, 1e-300)), 0.0)[:, None]
    d = scale.reshape(-1)
    held = d > 0
    scaled = d[:, None] * normal * d[None, :] + np.diag(np.where(held, INERTIA_RCOND, 1.0))
    solve = d[:, None] * np.linalg.inv(scaled) * d[None, :]
    return 0.5 * (solve + solve.T)  # symmetric exactly: the solve is its own adjoint


def substep_drive(rig: PartRig, pose: FramePose, *, substeps: int, frame_time: float) -> SubstepDrive:
    """The rig of a frame pair at the end of each of ``substeps`` substeps spanning ``frame_time`` [s] (the
    pose's parts beyond the rig's, which hold no particle, are left out)."""
    num_parts = rig.num_parts
    pose = FramePose(pose.start[:num_parts], pose.end[:num_parts])
    start_rot = nearest_rotation(pose.start[:, :3, :3])
    end_rot = nearest_rotation(pose.end[:, :3, :3])
    c_start = np.einsum("bij,bj->bi", pose.start[:, :3, :3], rig.centroid) + pose.start[:, :3, 3]
    c_end = np.einsum("bij,bj->bi", pose.end[:, :3, :3], rig.centroid) + pose.end[:, :3, 3]
    step = matrix_to_rotation_vector(end_rot @ np.transpose(start_rot, (0, 2, 1)))  # (B, 3)
    s = (np.arange(substeps) + 1.0) / substeps
    turn = rotation_vector_to_matrix(s[:, None, None] * step[None]) @ start_rot[None]  # (S, B, 3, 3)
    centre = c_start[None] + s[:, None, None] * (c_end - c_start)[None]
    solve = rig_solve(rig, normal_matrix(rig, turn[substeps // 2]))
    return SubstepDrive(turn, centre, solve, (c_end - c_start) / frame_time, step / frame_time)


@dataclass
class DriveArrays:
    """A :class:`SubstepDrive` and its :class:`PartRig` as Warp arrays, in the rollout's particle order."""

    slot_part: wp.array
    slot_weight: wp.array
    slot_offset: wp.array
    turn: wp.array
    centre: wp.array
    solve: wp.array
    linear: wp.array
    angular: wp.array

    @property
    def num_parts(self) -> int:
        return int(self.linear.shape[0])

    @staticmethod
    def of(rig: PartRig, drive: SubstepDrive, order: np.ndarray | None, device: str) -> DriveArrays:
        f32 = np.float32
        part, weight, offset = rig.slot_part, rig.slot_weight, rig.slot_offset
        if order is not None:
            part, weight, offset = part[order], weight[order], offset[order]
        return DriveArrays(
            slot_part=wp.array(part.astype(np.int32), dtype=wp.int32, device=device),
            slot_weight=wp.array(weight.astype(f32), dtype=float, device=device),
            slot_offset=wp.array(offset.astype(f32), dtype=wp.vec3, device=device),
            turn=wp.array(drive.turn.astype(f32), dtype=wp.mat33, device=device),
            centre=wp.array(drive.centre.astype(f32), dtype=wp.vec3, device=device),
            solve=wp.array(drive.solve.astype(f32), dtype=float, device=device),
            linear=wp.array(drive.linear.astype(f32), dtype=wp.vec3, device=device),
            angular=wp.array(drive.angular.astype(f32), dtype=wp.vec3, device=device),
        )
