"""The drive held through the frame: each part's rigid motion at every substep, as the kernels read it.

Complementary dynamics (Zhang, Bang, Levin, Jacobson 2020) splits the motion into the rig's part and a
complementary part that carries none of the rig's own motion (per part: no mass-weighted translation and no
moment about the part's centroid). Here the rig is the driving motion of the frame pair: part b goes from its
pose at t (``FramePose.start``) to its pose at t+1 (``end``) with its mass centroid on a straight line and a
constant angular velocity. After every G2P the kernels (:func:`kernels.drive_sums`, :func:`kernels.drive_apply`)
remove each part's rigid deviation from that rig, from positions and velocities alike; the elastic solve keeps
everything else (closing the seams between parts, the shape's own deformation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from sync4d.geometry import matrix_to_rotation_vector, nearest_rotation, rotation_vector_to_matrix
from sync4d.types import FramePose


@dataclass(frozen=True)
class PartRig:
    """The parts' rest geometry, fixed for a model: what the drive needs besides the poses.

    Attributes:
        part: (P,) part of each particle (-1: not driven).
        offset: (P, 3) rest position minus the rest mass centroid of the particle's part [m].
        centroid: (B, 3) rest mass centroid of each part [m] (zeros for a part with no particle).
        inertia: (B, 3, 3) rest inertia of each part about its centroid [kg m^2].
        mass: (B,) mass of each part [kg] (0 for a part with no particle).
        count: (B,) particles of each part.
    """

    part: np.ndarray
    offset: np.ndarray
    centroid: np.ndarray
    inertia: np.ndarray
    mass: np.ndarray
    count: np.ndarray


#: A part with fewer particles than this is held in translation only (its rotation is not determined).
MIN_TURNING_PARTICLES = 4
#: Inertia directions weaker than this share of the strongest are not held (a part on a line turns freely about
#: it; inverting a near-zero moment would amplify float32 rounding into huge corrections).
INERTIA_RCOND = 1e-3


def part_rig(rest: np.ndarray, part: np.ndarray, mass: np.ndarray, num_parts: int) -> PartRig:
    """The rest centroids, inertias and masses of ``num_parts`` parts of particles ``rest`` (P, 3) [m]."""
    part = np.asarray(part, dtype=np.int64)
    driven = (part >= 0) & (part < num_parts)
    idx = np.where(driven, part, 0)
    weight = np.where(driven, mass, 0.0)
    total = np.bincount(idx, weights=weight, minlength=num_parts)
    moment = np.stack([np.bincount(idx, weights=weight * rest[:, k], minlength=num_parts) for k in range(3)], 1)
    centroid = moment / np.maximum(total, 1e-300)[:, None]
    offset = np.where(driven[:, None], rest - centroid[idx], 0.0)
    outer = np.einsum("p,pi,pj->pij", weight, offset, offset)
    inertia = np.zeros((num_parts, 3, 3))
    np.add.at(inertia, idx, np.eye(3) * np.trace(outer, axis1=1, axis2=2)[:, None, None] - outer)
    count = np.bincount(idx, weights=driven.astype(float), minlength=num_parts).astype(np.int64)
    return PartRig(np.where(driven, part, -1), offset, centroid, inertia, total, count)


@dataclass(frozen=True)
class SubstepDrive:
    """The rig at the end of every substep of one rollout, (S, B, ...) each, plus its constant velocities.

    Attributes:
        turn: (S, B, 3, 3) each part's rest -> now rotation.
        centre: (S, B, 3) each part's driven mass centroid [m].
        inertia_inv: (S, B, 3, 3) pseudo-inverse of the part's inertia turned with it [1/(kg m^2)].
        linear: (B, 3) centroid velocity [m/s]; angular: (B, 3) angular velocity [rad/s].
    """

    turn: np.ndarray
    centre: np.ndarray
    inertia_inv: np.ndarray
    linear: np.ndarray
    angular: np.ndarray


def substep_drive(rig: PartRig, pose: FramePose, *, substeps: int, frame_time: float) -> SubstepDrive:
    """The rig of a frame pair at the end of each of ``substeps`` substeps spanning ``frame_time`` [s] (the
    pose's parts beyond the rig's, which hold no particle, are left out)."""
    num_parts = len(rig.mass)
    pose = FramePose(pose.start[:num_parts], pose.end[:num_parts])
    start_rot = nearest_rotation(pose.start[:, :3, :3])
    end_rot = nearest_rotation(pose.end[:, :3, :3])
    c_start = np.einsum("bij,bj->bi", pose.start[:, :3, :3], rig.centroid) + pose.start[:, :3, 3]
    c_end = np.einsum("bij,bj->bi", pose.end[:, :3, :3], rig.centroid) + pose.end[:, :3, 3]
    step = matrix_to_rotation_vector(end_rot @ np.transpose(start_rot, (0, 2, 1)))  # (B, 3)
    s = (np.arange(substeps) + 1.0) / substeps
    turn = rotation_vector_to_matrix(s[:, None, None] * step[None]) @ start_rot[None]  # (S, B, 3, 3)
    centre = c_start[None] + s[:, None, None] * (c_end - c_start)[None]
    inertia_pinv = np.linalg.pinv(rig.inertia, rcond=INERTIA_RCOND, hermitian=True)
    inertia_pinv[rig.count < MIN_TURNING_PARTICLES] = 0.0
    inertia_inv = turn @ inertia_pinv[None] @ np.swapaxes(turn, -1, -2)
    return SubstepDrive(turn, centre, inertia_inv, (c_end - c_start) / frame_time, step / frame_time)


@dataclass
class DriveArrays:
    """A :class:`SubstepDrive` and its :class:`PartRig` as Warp arrays, in the rollout's particle order."""

    offset: wp.array
    part: wp.array
    inv_part_mass: wp.array
    turn: wp.array
    centre: wp.array
    inertia_inv: wp.array
    linear: wp.array
    angular: wp.array

    @property
    def num_parts(self) -> int:
        return int(self.linear.shape[0])

    @staticmethod
    def of(rig: PartRig, drive: SubstepDrive, order: np.ndarray | None, device: str) -> DriveArrays:
        f32 = np.float32
        offset, part = (rig.offset, rig.part) if order is None else (rig.offset[order], rig.part[order])
        inv_mass = np.where(rig.mass > 0, 1.0 / np.maximum(rig.mass, 1e-300), 0.0)
        return DriveArrays(
            offset=wp.array(offset.astype(f32), dtype=wp.vec3, device=device),
            part=wp.array(part.astype(np.int32), dtype=wp.int32, device=device),
            inv_part_mass=wp.array(inv_mass.astype(f32), dtype=float, device=device),
            turn=wp.array(drive.turn.astype(f32), dtype=wp.mat33, device=device),
            centre=wp.array(drive.centre.astype(f32), dtype=wp.vec3, device=device),
            inertia_inv=wp.array(drive.inertia_inv.astype(f32), dtype=wp.mat33, device=device),
            linear=wp.array(drive.linear.astype(f32), dtype=wp.vec3, device=device),
            angular=wp.array(drive.angular.astype(f32), dtype=wp.vec3, device=device),
        )
