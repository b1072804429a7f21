"""The displacement loss of a frame pair (paper Eq. L_x): where each part's anchors should end, and the L1
between that and where the rollout put them."""

from __future__ import annotations

import numpy as np
import torch

from sync4d.geometry import apply_rigid, matrix_to_rotation_vector, nearest_rotation, part_centroids, skew_matrices


def anchor_weights(x: np.ndarray, part: np.ndarray, num_parts: int, mode: str) -> list[np.ndarray | None]:
    """Per part, a (K, P_b) matrix of affine weights (rows sum to 1) defining K anchors of its particles.

    ``particles``: None per part, meaning every particle is its own anchor (identity weights).
    ``centroid``: K = 1, the part's centroid. ``anchors``: K = 7, the centroid and the centroids of the
    particles on either side of each principal axis. Any affine combination of a body's points moves
    with the body, so the anchors follow rotation as well as translation.
    """
    if mode == "particles":
        return [None] * num_parts
    out: list[np.ndarray | None] = []
    for b in range(num_parts):
        idx = np.flatnonzero(part == b)
        n = len(idx)
        rows = [np.full(n, 1.0 / max(n, 1))]
        if mode == "anchors" and n >= 8:
            centred = x[idx] - x[idx].mean(axis=0)
            _, _, axes = np.linalg.svd(centred, full_matrices=False)
            for axis in axes:
                side = centred @ axis
                for mask in (side > 0, side <= 0):
                    if mask.sum() > 0:
                        rows.append(mask / mask.sum())
        out.append(np.stack(rows))
    return out


def anchor_points(weights: np.ndarray | None, points: np.ndarray) -> np.ndarray:
    """(K, 3) anchors of a part's (P_b, 3) points: ``weights @ points``, or the points themselves."""
    return points if weights is None else weights @ points


def anchor_targets(points: np.ndarray, part: np.ndarray, weights: list[np.ndarray | None],
                   transforms: np.ndarray) -> list[np.ndarray]:
    """Per part b, its anchors of ``points`` (P, 3) moved by ``transforms[b]`` (B, 4, 4): (K_b, 3) each."""
    return [apply_rigid(transforms[b], anchor_points(w, points[part == b])) for b, w in enumerate(weights)]


class PartLoss:
    """L1 between each part's anchors at the end of a rollout and their targets (paper Eq. L_x)."""

    def __init__(self, part: np.ndarray, weights: list[np.ndarray | None], targets: list[np.ndarray]) -> None:
        self.index = [torch.as_tensor(np.flatnonzero(part == b)) for b in range(len(weights))]
        self.weights = [None if w is None else torch.as_tensor(w, dtype=torch.float32) for w in weights]
        self.targets = [torch.as_tensor(t, dtype=torch.float32) for t in targets]

    def __call__(self, x_end: torch.Tensor) -> torch.Tensor:
        total = x_end.new_zeros(())
        for idx, w, target in zip(self.index, self.weights, self.targets):
            if len(idx):
                anchors = x_end[idx] if w is None else w @ x_end[idx]
                total = total + (anchors - target).abs().sum() / len(anchors)
        return total


def initial_velocity(
    x: np.ndarray, part: np.ndarray, relative: np.ndarray, displacement: np.ndarray, frame_time: float, mode: str,
    *, rest: np.ndarray | None = None, pose: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Initial particle velocities (P, 3) [m/s] and APIC matrices (P, 3, 3) [1/s] for one frame pair.

    Args:
        x: (P, 3) current positions [m]; part: (P,) parts.
        relative: (B, 4, 4) the reference's rigid step P_{t+1} P_t^{-1} per part (target space).
        displacement: (B, 3) the scaled bone-centre displacement (s_t/s_o)(b_{t+1} - b_t) [m].
        frame_time: N dt [s].
        mode: ``centroid`` (paper: one velocity per part), ``drive`` (the rig's velocity at the frame's start:
            each part's centroid on its straight line, turning at a constant angular velocity, as the simulator
            holds it through the frame), ``rigid`` (the bone's rigid step applied to where the particle is, a
            chord) or ``pose`` (towards where the part's pose at t+1 puts the particle's rest
            position: the same field plus the particle's offset from its pose, closed in one frame).
        rest: (P, 3) rest positions [m] and pose: (B, 4, 4) rest -> t+1 part transforms (``pose`` only).
    """
    if mode == "centroid":
        return displacement[part] / frame_time, np.zeros((len(x), 3, 3))
    if mode == "drive":
        return drive_velocity(x, part, relative, frame_time)
    rot = relative[part, :3, :3]
    if mode == "pose":
        assert rest is not None and pose is not None
        aimed = np.einsum("pij,pj->pi", pose[part, :3, :3], rest) + pose[part, :3, 3]
        return (aimed - x) / frame_time, (rot - np.eye(3)) / frame_time
    moved = np.einsum("pij,pj->pi", rot, x) + relative[part, :3, 3]
    return (moved - x) / frame_time, (rot - np.eye(3)) / frame_time


def drive_velocity(x: np.ndarray, part: np.ndarray, relative: np.ndarray, frame_time: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Velocities (P, 3) [m/s] and APIC matrices (P, 3, 3) [1/s] of each part's rigid step as a screw: the part's
    centroid c moves to ``relative[b]`` c in a straight line and the part turns at the constant angular velocity
    w = log(R_b) / frame_time about it: v = (T c - c) / frame_time + w x (x - c), C = [w]x (no chord shrinkage)."""
    num_parts = relative.shape[0]
    centre = part_centroids(x, part, num_parts)
    centre = np.where(np.isfinite(centre), centre, 0.0)
    moved = np.einsum("bij,bj->bi", relative[:, :3, :3], centre) + relative[:, :3, 3]
    spin = matrix_to_rotation_vector(nearest_rotation(relative[:, :3, :3])) / frame_time  # (B, 3)
    velocity = (moved - centre)[part] / frame_time + np.cross(spin[part], x - centre[part])
    return velocity, skew_matrices(spin)[part]
