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
