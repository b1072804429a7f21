"""Pinhole camera helpers of the front end (numpy; OpenCV camera axes x right, y down, z forward); its
rotations are :mod:`sync4d.geometry`'s."""

from __future__ import annotations

import math

import numpy as np

from sync4d.geometry import apply_rigid


def intrinsics_from_fov(width: int, height: int, fov_deg: float) -> np.ndarray:
    """(3, 3) pinhole K with ``fov_deg`` across the image's long side and the principal point at the centre."""
    focal = 0.5 * max(width, height) / math.tan(math.radians(fov_deg) / 2.0)
    return np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])


def rays(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 3) unit viewing rays (camera axes) of pixels (N, 2) [px]."""
    homo = np.concatenate([uv, np.ones((len(uv), 1))], axis=1) @ np.linalg.inv(K).T
    return homo / np.linalg.norm(homo, axis=1, keepdims=True)


def project(points: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) [px] and depths (N,) [world units] of world points (N, 3)."""
    cam = apply_rigid(world_to_cam, points)
    z = cam[:, 2]
    uv = (cam @ K.T)[:, :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[:, None]
    return uv, z


def pose_matrix(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) world-to-camera transform from a (3, 3) rotation and (3,) translation."""
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = np.asarray(translation, dtype=np.float64).ravel()
    return out


def ground_up(points: np.ndarray, up: np.ndarray, *, max_tilt_deg: float = 45.0, tol: float = 0.05,
              trials: int = 300, seed: int = 0) -> np.ndarray | None:
    """(3,) the unit normal of the ground under a moving camera, from its triangulated background points
    (M, 3) [world units]: of the planes RANSAC finds (inliers within ``tol`` x the points' median distance from
    their centroid), the best-supported one whose normal is within ``max_tilt_deg`` of ``up`` (3,) (the
    camera's up: a phone held roughly upright sees the floor or a table below), oriented like ``up``; None
    with fewer than 30 points or no such plane holding a fifth of them. (``tol``: on the default scene's
    hand-held films 0.01 missed the floor at one of three seeds; 0.02 and 0.05 found it at all three, within
    1.1-4.3 deg of the true up.)"""
    pts = np.asarray(points, np.float64)
    if len(pts) < 30:
        return None
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    scale = float(np.median(np.linalg.norm(pts - np.median(pts, axis=0), axis=1))) + 1e-12
    rng = np.random.default_rng(seed)
    best, best_count = None, int(0.2 * len(pts))
    for _ in range(trials):
        a, b, c = pts[rng.choice(len(pts), 3, replace=False)]
        normal = np.cross(b - a, c - a)
        if np.linalg.norm(normal) < 1e-12:
            continue
        normal /= np.linalg.norm(normal)
        if abs(normal @ up) < math.cos(math.radians(max_tilt_deg)):
            continue
        inliers = np.abs((pts - a) @ normal) < tol * scale
        if inliers.sum() > best_count:
            best_count = int(inliers.sum())
            sel = pts[inliers]
            best = np.linalg.svd(sel - sel.mean(0), full_matrices=False)[2][2]
    if best is None:
        return None
    return best if best @ up > 0 else -best
