"""Camera helpers: look-at axes, framing a point set, turntable orbits."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sync4d.errors import InputError
from sync4d.render.camera import focal_from_fov, frame_object, look_at, orbit, project_points


def test_look_at_puts_target_at_image_centre_and_up_at_top() -> None:
    cam = look_at((3.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 60.0, 64, 48)
    R = cam.world_to_cam[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    uv, depth = project_points(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5], [0.0, -0.5, 0.0]]), cam)
    np.testing.assert_allclose(uv[0], [32.0, 24.0], atol=1e-9)
    assert depth[0] == pytest.approx(3.0)
    assert uv[1, 1] < 24.0  # world up appears above the centre (image y points down)
    # Facing -x with z up, the right hand points to +y, so world -y appears left of the centre.
    assert uv[2, 0] < 32.0
    assert cam.K[1, 1] == pytest.approx(24.0 / math.tan(math.radians(30.0)))


def test_look_at_rejects_degenerate_input() -> None:
    with pytest.raises(InputError, match="parallel"):
        look_at((0, 0, 2), (0, 0, 0), (0, 0, 1))
    with pytest.raises(InputError, match="coincide"):
        look_at((1, 1, 1), (1, 1, 1))


def test_frame_object_keeps_every_point_in_view_with_margin() -> None:
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3)) * [0.3, 0.1, 0.2] + [1.0, 2.0, 0.5]
    cam = frame_object(pts, (1.0, -1.0, 0.5), up=(0.0, 0.0, 1.0), fov_deg=40.0, width=80, height=60, margin=1.2)
    uv, depth = project_points(pts, cam)
    assert np.all(depth > 0)
    assert np.all((uv[:, 0] > 0) & (uv[:, 0] < 80) & (uv[:, 1] > 0) & (uv[:, 1] < 60))
    # The camera sits along the requested direction from the box centre.
    center = 0.5 * (pts.min(0) + pts.max(0))
    eye = -cam.world_to_cam[:3, :3].T @ cam.world_to_cam[:3, 3]
    d = (eye - center) / np.linalg.norm(eye - center)
    np.testing.assert_allclose(d, np.array([1.0, -1.0, 0.5]) / 1.5, atol=1e-9)
    # The bounding sphere just fits the narrower (vertical) field of view, less the margin.
    radius = np.linalg.norm(pts - center, axis=1).max()
    assert np.linalg.norm(eye - center) == pytest.approx(1.2 * radius / math.sin(math.radians(20.0)))


def test_orbit_circles_at_constant_distance_and_elevation() -> None:
    pts = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    cams = orbit(pts, 8, elevation_deg=30.0, up=(0.0, 0.0, 1.0), width=32, height=32)
    eyes = np.array([-c.world_to_cam[:3, :3].T @ c.world_to_cam[:3, 3] for c in cams])
    dist = np.linalg.norm(eyes, axis=1)
    np.testing.assert_allclose(dist, dist[0], rtol=1e-12)
    np.testing.assert_allclose(eyes[:, 2] / dist, math.sin(math.radians(30.0)), atol=1e-12)
    # Consecutive cameras are 45 degrees apart in azimuth.
    az = np.unwrap(np.arctan2(eyes[:, 1], eyes[:, 0]))
    np.testing.assert_allclose(np.diff(az), 2 * math.pi / 8, atol=1e-12)
    assert focal_from_fov(90.0, 100) == pytest.approx(50.0)
