"""A small orthographic z-buffer splatting renderer for multi-view feature back-projection.

No gradients are needed here (features are computed once), so the renderer is a plain z-buffer:
the surface is represented by dense samples (random points on the triangles, plus the vertices, or the
points themselves for a point cloud), each sample is splatted onto the pixels within ``splat_radius``
of its projection, and ``torch.scatter_reduce(amin)`` keeps the nearest depth per pixel. A vertex is
visible in a view when its depth is within ``depth_tolerance`` of the z-buffer at its pixel.

Camera convention: the rows of a view rotation are (right, up, forward); a point x projects to camera
coordinates ``c = R (x - centre)``, pixel column ``u = (c_x / extent + 1) W / 2`` and row
``v = (1 - c_y / extent) H / 2``; depth is ``c_z`` (smaller is nearer).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from sync4d.errors import InputError
from sync4d.surface import area_points


@dataclass(frozen=True)
class ViewRender:
    """One rendered view.

    Attributes:
        depth: (H, W) camera depth of the nearest surface, +inf on the background [normalised units].
        normal: (H, W, 3) unit normals in camera coordinates (facing the camera, n_z <= 0), 0 on the
            background.
        mask: (H, W) bool, True where the surface covers the pixel.
        shading: (H, W) Lambertian shading for a light at the camera, in [0, 1], 0 on the background.
        vertex_pixel: (V, 2) float pixel coordinates (column u, row v) of every vertex.
        vertex_visible: (V,) bool, the vertex is the visible surface at its pixel.
    """

    depth: np.ndarray
    normal: np.ndarray
    mask: np.ndarray
    shading: np.ndarray
    vertex_pixel: np.ndarray
    vertex_visible: np.ndarray


def look_at_rotation(direction: np.ndarray) -> np.ndarray:
    """(3, 3) view rotation for a camera at ``direction`` (from the centre) looking at the centre.

    Rows are (right, up, forward); ``up`` follows world +y unless the view is (nearly) vertical.
    """
    eye = np.asarray(direction, dtype=np.float64)
    forward = -eye / np.linalg.norm(eye)
    world_up = np.array([0.0, 1.0, 0.0]) if abs(forward[1]) < 0.99 else np.array([0.0, 0.0, 1.0])
    right = np.cross(world_up, forward)
    right /= np.linalg.norm(right)
    up = np.cross(forward, right)
    return np.stack([right, up, forward])


def view_directions(n_views: int, elevation_deg: float) -> np.ndarray:
    """(K, 3) unit camera directions: alternating rings above and below the equator, azimuths spread.

    Views alternate between elevations +e and -e, each ring offset by half a step, so that K views
    cover the shape from above and below (a stand-in for Diff3F's views around the object).
    """
    k = np.arange(n_views)
    azim = 2 * np.pi * k / n_views
    elev = np.deg2rad(np.where(k % 2 == 0, elevation_deg, -elevation_deg))
    return np.stack([np.cos(elev) * np.sin(azim), np.sin(elev), np.cos(elev) * np.cos(azim)], axis=1)


def vertex_normals(points: np.ndarray, faces: np.ndarray | None, *, k: int = 12) -> np.ndarray:
    """(V, 3) unit normals: area-weighted face normals for a mesh, local PCA for a point cloud.

    Point-cloud normals have an arbitrary sign; the renderer turns every normal towards the camera.
    """
    if faces is not None:
        tri = points[faces]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 x area
        vn = np.zeros_like(points)
        for i in range(3):
            np.add.at(vn, faces[:, i], fn)
    else:
        _, idx = cKDTree(points).query(points, k=min(k, len(points)))
        nb = points[idx] - points[idx].mean(axis=1, keepdims=True)
        cov = np.einsum("vki,vkj->vij", nb, nb)
        _, vecs = np.linalg.eigh(cov)
        vn = vecs[:, :, 0]
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.where(norm > 1e-12, vn / np.maximum(norm, 1e-12), np.array([0.0, 0.0, 1.0]))


def surface_samples(
    points: np.ndarray, faces: np.ndarray | None, n_samples: int, *, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Dense surface samples with normals: area-weighted random points on the faces plus the vertices.

    Returns:
        samples (S, 3), normals (S, 3). For a point cloud, the points and their PCA normals.
    """
    vn = vertex_normals(points, faces)
    if faces is None:
        return points, vn
    tri = points[faces]
    sampled = area_points(tri, n_samples, np.random.default_rng(seed))
    if sampled is None:
        raise InputError("features.diff3f: the mesh has zero area")
    samples, face = sampled
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = fn[face] / np.maximum(np.linalg.norm(fn[face], axis=1, keepdims=True), 1e-12)
    return np.concatenate([samples, points]), np.concatenate([normals, vn])


def render_view(
    vertices: np.ndarray,
    samples: np.ndarray,
    sample_normals: np.ndarray,
    rotation: np.ndarray,
    *,
    resolution: int,
    extent: float,
    splat_radius_px: float,
    depth_tolerance_px: float,
) -> ViewRender:
    """Render one orthographic view of a surface given by samples, and test vertex visibility.

    Args:
        vertices: (V, 3) vertices whose visibility and pixel are wanted, centred at the view centre.
        samples: (S, 3) dense surface samples, same frame.
        sample_normals: (S, 3) unit normals of the samples.
        rotation: (3, 3) view rotation (rows right, up, forward).
        resolution: image size H = W [px].
        extent: half-width of the square view in scene units (the shape must fit in it).
        splat_radius_px: each sample covers the pixels within this radius [px].
        depth_tolerance_px: a vertex is visible if its depth exceeds the z-buffer by at most this many
            pixel sizes (surfaces at grazing angles change depth quickly within one pixel).
    """
    h = w = int(resolution)
    pix = 2.0 * extent / resolution
    cam = torch.from_numpy(samples @ rotation.T)
    nrm = torch.from_numpy(sample_normals @ rotation.T)
    nrm = torch.where(nrm[:, 2:3] > 0, -nrm, nrm)  # face the camera (point-cloud signs, open meshes)
    u = (cam[:, 0] / extent + 1.0) * w / 2.0
    v = (1.0 - cam[:, 1] / extent) * h / 2.0
    r = int(np.ceil(splat_radius_px))
    offsets = [(dx, dy) for dx in range(-r, r + 1) for dy in range(-r, r + 1) if dx * dx + dy * dy <= splat_radius_px**2 + 1e-9]
    off = torch.tensor(offsets, dtype=torch.long)  # (O, 2)
    cu = torch.floor(u).long()[:, None] + off[None, :, 0]
    cv = torch.floor(v).long()[:, None] + off[None, :, 1]
    inside = (cu >= 0) & (cu < w) & (cv >= 0) & (cv < h)
    flat = (cv * w + cu)[inside]
    owner = torch.arange(len(cam))[:, None].expand_as(cu)[inside]
    depth_s = cam[owner, 2]
    zbuf = torch.full((h * w,), float("inf"), dtype=cam.dtype)
    zbuf = zbuf.scatter_reduce(0, flat, depth_s, reduce="amin", include_self=True)
    winner = depth_s <= zbuf[flat]  # the nearest sample(s) of each pixel write the attributes
    normal = torch.zeros((h * w, 3), dtype=cam.dtype)
    normal[flat[winner]] = nrm[owner[winner]]
    mask = torch.isfinite(zbuf)

    vcam = vertices @ rotation.T
    vu = (vcam[:, 0] / extent + 1.0) * w / 2.0
    vv = (1.0 - vcam[:, 1] / extent) * h / 2.0
    iu = np.clip(np.floor(vu).astype(np.int64), 0, w - 1)
    iv = np.clip(np.floor(vv).astype(np.int64), 0, h - 1)
    z_at = zbuf.numpy()[iv * w + iu]
    visible = np.isfinite(z_at) & (vcam[:, 2] <= z_at + depth_tolerance_px * pix)

    normal_img = normal.reshape(h, w, 3).numpy()
    shading = np.clip(-normal_img[..., 2], 0.0, 1.0)  # light at the camera: cos of the view angle
    return ViewRender(
        depth=zbuf.reshape(h, w).numpy(),
        normal=normal_img,
        mask=mask.reshape(h, w).numpy(),
        shading=shading,
        vertex_pixel=np.stack([vu, vv], axis=1),
        vertex_visible=visible,
    )


def point_spacing(points: np.ndarray) -> float:
    """Median distance from a point to its nearest neighbour (scene units)."""
    d, _ = cKDTree(points).query(points, k=2)
    return float(np.median(d[:, 1]))
