"""Camera helpers: look-at cameras, framing a point set, turntable orbits (OpenCV axes).

All cameras are :class:`sync4d.types.Camera` with ``world_to_cam`` in the OpenCV convention: camera x
right, y down, z forward (the viewing direction). World up defaults to +Y, the project's scenes' convention.
The principal point is the image centre
(``cx = width / 2`` with pixel centres at half-integers, as the renderers use).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sync4d.errors import InputError
from sync4d.types import Camera

ArrayLike3 = Sequence[float] | np.ndarray


def focal_from_fov(fov_deg: float, size: int) -> float:
    """Focal length [px] that spans ``fov_deg`` [deg] across ``size`` [px]."""
    return 0.5 * size / math.tan(math.radians(fov_deg) / 2.0)


def intrinsics(fov_deg: float, width: int, height: int) -> np.ndarray:
    """(3, 3) pinhole K with square pixels, vertical field of view ``fov_deg`` [deg], centred."""
    f = focal_from_fov(fov_deg, height)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def look_at(
    eye: ArrayLike3,
    target: ArrayLike3,
    up: ArrayLike3 = (0.0, 1.0, 0.0),
    fov_deg: float = 40.0,
    width: int = 256,
    height: int = 256,
) -> Camera:
    """A camera at ``eye`` looking at ``target`` with ``up`` pointing up in the image.

    Args:
        eye: (3,) camera centre [m].
        target: (3,) point on the optical axis [m].
        up: (3,) world direction that appears up in the image (need not be unit or orthogonal).
        fov_deg: vertical field of view [deg].
        width: image width [px].
        height: image height [px].

    Returns:
        The camera (OpenCV axes: z from eye to target, y down = -up projected).

    Raises:
        InputError: eye == target, or ``up`` is parallel to the viewing direction.
    """
    eye_a = np.asarray(eye, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - eye_a
    norm = np.linalg.norm(fwd)
    if norm < 1e-12:
        raise InputError("look_at: eye and target coincide; move the camera away from the target")
    fwd /= norm
    right = np.cross(fwd, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-9:
        raise InputError(f"look_at: up {list(up)} is parallel to the viewing direction; choose another up")
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)  # z x x = y for a right-handed (x right, y down, z forward) frame
    R = np.stack([right, down, fwd])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye_a
    return Camera(K=intrinsics(fov_deg, width, height), world_to_cam=w2c, width=int(width), height=int(height))


def bounding_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (3,) [m] of the axis-aligned bounding box and the radius [m] of the box's enclosing sphere
    around it (robust enough for framing and cheap)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if pts.size == 0:
        raise InputError("frame_object: no points to frame")
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    center = 0.5 * (lo + hi)
    radius = float(np.linalg.norm(pts - center, axis=1).max())
    return center, max(radius, 1e-6)


def frame_object(
    points: np.ndarray,
    direction: ArrayLike3 = (0.9, 1.1, 1.6),
    *,
    up: ArrayLike3 = (0.0, 1.0, 0.0),
    fov_deg: float = 40.0,
    width: int = 256,
    height: int = 256,
    margin: float = 1.15,
) -> Camera:
    """A camera looking at a point set from a fixed direction, far enough that all of it is in view.

    Pass every frame's points (e.g. ``trajectory.x.reshape(-1, 3)``) to keep the whole motion in view
    from one fixed camera.

    Args:
        points: (..., 3) points to frame [m].
        direction: (3,) direction from the object's centre towards the camera.
        up: (3,) world up.
        fov_deg: vertical field of view [deg].
        width: image width [px].
        height: image height [px].
        margin: the bounding sphere fills 1/margin of the smaller field of view.

    Returns:
        The camera.
    """
    center, radius = bounding_sphere(points)
    d = np.asarray(direction, dtype=np.float64)
    d = d / max(float(np.linalg.norm(d)), 1e-12)
    # Half-angle of the narrower side; a sphere of radius r is inside a cone of half-angle a at distance
    # r / sin(a).
    half_v = math.radians(fov_deg) / 2.0
    half_h = math.atan(math.tan(half_v) * width / height)
    half = min(half_v, half_h)
    dist = margin * radius / math.sin(half)
    return look_at(center + dist * d, center, up, fov_deg, width, height)


def orbit(
    points: np.ndarray,
    num_frames: int,
    *,
    elevation_deg: float = 20.0,
    start_azimuth_deg: float = 0.0,
    up: ArrayLike3 = (0.0, 1.0, 0.0),
    fov_deg: float = 40.0,
    width: int = 256,
    height: int = 256,
    margin: float = 1.15,
) -> list[Camera]:
    """Turntable cameras circling a point set about ``up`` through its centre.

    Args:
        points: (..., 3) points to frame [m].
        num_frames: cameras in one full turn (the last one stops short of the first).
        elevation_deg: angle above the plane orthogonal to ``up`` [deg].
        start_azimuth_deg: azimuth of the first camera [deg], measured from the world axis least
            aligned with ``up`` projected onto that plane.
        up, fov_deg, width, height, margin: as in :func:`frame_object`.

    Returns:
        ``num_frames`` cameras.
    """
    up_a = np.asarray(up, dtype=np.float64)
    up_a = up_a / np.linalg.norm(up_a)
    seed = np.eye(3)[int(np.argmin(np.abs(up_a)))]
    e1 = seed - up_a * (seed @ up_a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up_a, e1)
    elev = math.radians(elevation_deg)
    cams = []
    for i in range(num_frames):
        az = math.radians(start_azimuth_deg) + 2.0 * math.pi * i / max(num_frames, 1)
        d = math.cos(elev) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(elev) * up_a
        cams.append(frame_object(points, d, up=up_a, fov_deg=fov_deg, width=width, height=height, margin=margin))
    return cams


def project_points(points: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of points.

    Args:
        points: (N, 3) world points [m].
        camera: the camera.

    Returns:
        (N, 2) pixel coordinates (u, v) [px] (pixel centres at half-integers) and (N,) camera depths [m].
    """
    pts = np.asarray(points, dtype=np.float64)
    xc = pts @ camera.world_to_cam[:3, :3].T + camera.world_to_cam[:3, 3]
    uvw = xc @ np.asarray(camera.K, dtype=np.float64).T
    return uvw[:, :2] / uvw[:, 2:3], xc[:, 2]


@dataclass(frozen=True)
class MotionView:
    """Where a camera stands relative to the plane an object moves in (see :func:`motion_view_direction`).

    Attributes:
        elevation_deg: angle above the horizontal plane [deg]; a little keeps the object reading as solid
            rather than as a flat silhouette. (Turning the camera off the plane's normal was tried, 10 and
            20 deg on the default run: the lid's opening angle reads less clearly; not kept.)
    """

    elevation_deg: float = 15.0


SIDE_ON = MotionView(elevation_deg=0.0)


def motion_view_direction(
    sequence: np.ndarray,
    view: MotionView,
    *,
    up: ArrayLike3,
    prefer: ArrayLike3,
) -> np.ndarray:
    """A viewing direction that keeps ``up`` up and faces the plane in which a point sequence moves most.

    The motion's principal plane is found from the covariance of every point's displacement from its
    own mean position over time; its normal (the direction of least motion), laid horizontal
    (perpendicular to ``up``), is the side from which the motion is best seen. The camera is then raised
    by ``view.elevation_deg``. Of the two sides, the one nearer ``prefer`` is taken, so objects moving alike are seen from alike
    sides. Without motion (or motion along ``up`` only) the horizontal part of ``prefer`` is used.

    Args:
        sequence: (T, N, 3) positions per frame [m].
        view: the elevation.
        up: (3,) world up.
        prefer: (3,) direction that picks the side.

    Returns:
        (3,) unit direction from the object's centre towards the camera.
    """
    seq = np.asarray(sequence, dtype=np.float64)
    if seq.ndim != 3 or seq.shape[-1] != 3 or seq.shape[0] == 0:
        raise InputError(f"motion_view_direction: sequence must be (T, N, 3), got {seq.shape}")
    up_a = np.asarray(up, dtype=np.float64)
    up_a = up_a / np.linalg.norm(up_a)
    pref = np.asarray(prefer, dtype=np.float64)
    pref_h = pref - up_a * (pref @ up_a)
    if np.linalg.norm(pref_h) < 1e-9:
        pref_h = np.eye(3)[int(np.argmin(np.abs(up_a)))] - up_a * up_a[int(np.argmin(np.abs(up_a)))]
    pref_h /= np.linalg.norm(pref_h)
    disp = (seq - seq.mean(axis=0, keepdims=True)).reshape(-1, 3)
    # Horizontal basis (e1, e2); the normal sought minimises the motion variance among horizontal directions.
    e1 = pref_h
    e2 = np.cross(up_a, e1)
    h = disp @ np.stack([e1, e2], axis=1)
    cov = h.T @ h
    lam, vec = np.linalg.eigh(cov)
    if lam[1] <= 1e-12 * max(len(disp), 1) or lam[1] - lam[0] <= 1e-3 * lam[1]:
        normal = e1  # no horizontal motion, or no preferred horizontal direction of it
    else:
        normal = vec[0, 0] * e1 + vec[1, 0] * e2
        normal *= np.sign(normal @ pref_h) or 1.0
    el = math.radians(view.elevation_deg)
    d = math.cos(el) * normal + math.sin(el) * up_a
    return d / np.linalg.norm(d)
