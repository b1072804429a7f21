"""Meshes (.obj/.ply/.stl/.off/.glb via trimesh) and their conversion to 3D Gaussians.

Surface samples get flat, surface-aligned Gaussians (two tangent axes sized to the sample spacing, a
thin normal axis); an optional interior fill adds isotropic Gaussians inside the closed surface so the
simulated body has volume (MPM needs particles inside, not just on the skin).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import trimesh

from sync4d.errors import InputError
from sync4d.types import TargetGaussians
from sync4d.geometry import matrix_to_quat, rgb_to_sh_dc


def load_mesh(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Load a triangle mesh.

    Returns:
        vertices (V, 3) float64 [file units], faces (F, 3) int64, vertex colours (V, 3) in [0, 1] or None.

    Raises:
        InputError: missing file, unreadable, no faces, or non-finite vertices.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: mesh file not found")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # noqa: BLE001 - trimesh raises many types for bad files
        raise InputError(f"{path}: could not read the mesh ({type(err).__name__}: {err})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise InputError(f"{path}: the mesh has no faces; a surface mesh is needed (or give a .ply of Gaussians)")
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    if not np.isfinite(vertices).all():
        raise InputError(f"{path}: the mesh has NaN/inf vertex coordinates")
    faces = np.asarray(loaded.faces, dtype=np.int64)
    if surface_area(vertices, faces) <= 1e-12 * max(float(np.ptp(vertices, axis=0).max()), 1e-30) ** 2:
        raise InputError(f"{path}: the mesh's {len(faces)} face(s) have no area (coincident or collinear "
                         "vertices); give a mesh with a real surface")
    colors = None
    visual = loaded.visual
    if isinstance(visual, trimesh.visual.ColorVisuals) and visual.kind == "vertex":
        rgba = np.asarray(visual.vertex_colors, dtype=np.float64)
        if rgba.shape[0] == len(vertices) and np.ptp(rgba[:, :3]) > 0:
            colors = rgba[:, :3] / 255.0
    return vertices, faces, colors


def surface_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Total area [m^2] of the (F, 3) triangles ``faces`` over (V, 3) ``vertices``."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


def winding_number(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Generalised winding number of each point w.r.t. a triangle mesh (Jacobson et al. 2013), exact (libigl's
    solid-angle sum; docs/results/house.md has its speed against the former NumPy sum).

    About 1 inside a closed surface and 0 outside, and still meaningful for meshes with small holes.

    Args:
        points: (P, 3) query points.
        vertices: (V, 3), faces: (F, 3) the mesh.

    Returns:
        (P,) winding numbers.
    """
    import igl

    return np.asarray(igl.winding_number(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64),
                                         np.asarray(points, dtype=np.float64)), dtype=np.float64)


def _tangent_frames(normals: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices whose third column is the unit normal."""
    n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], axis=2)


def mesh_to_gaussians(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    num_surface: int = 4000,
    num_interior: int = 0,
    vertex_colors: np.ndarray | None = None,
    default_color: tuple[float, float, float] = (0.7, 0.7, 0.7),
    opacity: float = 0.9,
    normal_scale_ratio: float = 0.15,
    seed: int = 0,
    name: str = "mesh",
) -> TargetGaussians:
    """Sample a mesh into 3D Gaussians.

    Args:
        vertices: (V, 3) [m]; faces: (F, 3).
        num_surface: Gaussians sampled uniformly on the surface (flat, surface-aligned).
        num_interior: isotropic Gaussians filling the inside (winding number > 0.5); 0 for none.
        vertex_colors: (V, 3) RGB in [0, 1] interpolated to the samples, or None for ``default_color``.
        opacity: opacity of every Gaussian, in (0, 1).
        normal_scale_ratio: thickness of a surface Gaussian relative to its tangent size.
        seed: sampling seed (same seed, same Gaussians).

    Returns:
        Validated :class:`TargetGaussians` (SH degree 0): surface samples first, then the interior.
    """
    if num_surface < 1:
        raise InputError(f"{name}: num_surface must be >= 1, got {num_surface}")
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    rng = np.random.default_rng(seed)
    # Area-weighted face choice, then uniform barycentric coordinates (the square-root trick).
    areas = mesh.area_faces
    face_idx = rng.choice(len(faces), size=num_surface, p=areas / areas.sum())
    r1, r2 = rng.random(num_surface), rng.random(num_surface)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    tri = vertices[faces[face_idx]]
    points = np.einsum("nk,nki->ni", bary, tri)
    spacing = np.sqrt(areas.sum() / num_surface)
    frames = _tangent_frames(mesh.face_normals[face_idx])
    surface_scales = np.tile([0.5 * spacing, 0.5 * spacing, 0.5 * spacing * normal_scale_ratio], (num_surface, 1))
    if vertex_colors is not None:
        colors = np.einsum("nk,nki->ni", bary, vertex_colors[faces[face_idx]])
    else:
        colors = np.tile(default_color, (num_surface, 1))

    means, rots, scales, cols = [points], [frames], [surface_scales], [colors]
    if num_interior > 0:
        inside = sample_interior(vertices, faces, num_interior, rng)
        volume = abs(mesh.volume) if mesh.is_volume else np.prod(np.ptp(vertices, axis=0)) * 0.5
        radius = 0.5 * (volume / max(len(inside), 1)) ** (1.0 / 3.0)
        means.append(inside)
        rots.append(np.tile(np.eye(3), (len(inside), 1, 1)))
        scales.append(np.full((len(inside), 3), radius))
        if vertex_colors is not None:
            nearest = np.argmin(((inside[:, None, :] - vertices[None, ::max(1, len(vertices) // 2000)]) ** 2).sum(-1), axis=1)
            cols.append(vertex_colors[::max(1, len(vertices) // 2000)][nearest])
        else:
            cols.append(np.tile(default_color, (len(inside), 1)))
    all_means = np.concatenate(means)
    n = len(all_means)
    logit = float(np.log(opacity / (1.0 - opacity)))
    return TargetGaussians(
        means=all_means.astype(np.float32),
        quats=matrix_to_quat(np.concatenate(rots)).astype(np.float32),
        log_scales=np.log(np.concatenate(scales)).astype(np.float32),
        opacity_logits=np.full(n, logit, dtype=np.float32),
        sh=rgb_to_sh_dc(np.concatenate(cols).astype(np.float64)).astype(np.float32),
        name=name,
    ).validate()


def sample_interior(vertices: np.ndarray, faces: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3) points uniformly inside a closed mesh, by rejection with the winding number.

    Raises:
        InputError: the mesh encloses (almost) no volume, so no interior point is found.
    """
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    found: list[np.ndarray] = []
    total, tries = 0, 0
    while total < count and tries < 50:
        candidates = lo + (hi - lo) * rng.random((max(2 * count, 256), 3))
        keep = candidates[winding_number(candidates, vertices, faces) > 0.5]
        found.append(keep)
        total += len(keep)
        tries += 1
    if total == 0:
        raise InputError("mesh encloses no volume (open or flat surface); set num_interior=0 for a surface-only target")
    return np.concatenate(found)[:count]
