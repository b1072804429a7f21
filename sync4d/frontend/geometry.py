"""Small rotation and projection helpers of the front end (numpy; OpenCV camera axes x right, y down, z
forward). Kept here until the project has one shared geometry module."""

from __future__ import annotations

import math

import numpy as np


def intrinsics_from_fov(width: int, height: int, fov_deg: float) -> np.ndarray:
    """(3, 3) pinhole K with ``fov_deg`` across the image's long side and the principal point at the centre."""
    focal = 0.5 * max(width, height) / math.tan(math.radians(fov_deg) / 2.0)
    return np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])


def rodrigues(rvec: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 3) rotation vectors [rad]."""
    rvec = np.asarray(rvec, dtype=np.float64)
    theta = np.linalg.norm(rvec, axis=-1, keepdims=True)
    axis = rvec / np.maximum(theta, 1e-12)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = np.zeros_like(x)
    cross = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(*rvec.shape[:-1], 3, 3)
    s, c = np.sin(theta)[..., None], np.cos(theta)[..., None]
    outer = axis[..., :, None] * axis[..., None, :]
    return c * np.eye(3) + s * cross + (1.0 - c) * outer


def rotation_vector(rotation: np.ndarray) -> np.ndarray:
    """(3,) rotation vector [rad] of a (3, 3) rotation matrix."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(nearest_rotation(rotation)).as_rotvec()


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The (3, 3) rotation closest to ``matrix`` in the Frobenius norm (SVD, determinant +1)."""
    u, _, vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def rotation_angle_deg(rotation: np.ndarray) -> np.ndarray:
    """Rotation angle(s) [deg] of (..., 3, 3) rotation matrices."""
    trace = np.trace(np.asarray(rotation), axis1=-2, axis2=-1)
    return np.degrees(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))


def rays(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 3) unit viewing rays (camera axes) of pixels (N, 2) [px]."""
    homo = np.concatenate([uv, np.ones((len(uv), 1))], axis=1) @ np.linalg.inv(K).T
    return homo / np.linalg.norm(homo, axis=1, keepdims=True)


def kabsch_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) rotation R minimising sum |b_i - R a_i|^2 over unit vectors a, b (N, 3) (Wahba's problem)."""
    return nearest_rotation(b.T @ a)


def project(points: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) [px] and depths (N,) [world units] of world points (N, 3)."""
    cam = points @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    z = cam[:, 2]
    uv = (cam @ K.T)[:, :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[:, None]
    return uv, z


def pose_matrix(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) world-to-camera transform from a (3, 3) rotation and (3,) translation."""
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = np.asarray(translation, dtype=np.float64).ravel()
    return out
