"""The target's surface points as matching uses them: a mesh's vertices or the visible Gaussians' means,
surface samples, and the points (voxels of the solid) a curve skeleton is built on."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from sync4d.errors import InputError
from sync4d.match.config import MatchConfig
from sync4d.match.skeleton import SkeletonConfig, cloud_volume_points, volume_points
from sync4d.surface import area_points
from sync4d.types import TargetGaussians


def visible_gaussian_centres(
    target: TargetGaussians, *, max_vertices: int, min_opacity: float, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Surface points of a Gaussian target without a mesh: the means of its visible Gaussians.

    Args:
        target: the Gaussians.
        max_vertices: random subsample size (feature extraction is O(V) to O(V^1.5)).
        min_opacity: Gaussians fainter than this are not surface (floaters, interior fill).

    Returns:
        points (M, 3) [m], index (M,) into the Gaussians.
    """
    index = np.flatnonzero(target.opacities >= min_opacity)
    if len(index) < 8:
        index = np.arange(target.num)
    if len(index) > max_vertices:
        rng = np.random.default_rng(seed)
        index = np.sort(rng.choice(index, size=max_vertices, replace=False))
    return target.means[index].astype(np.float64), index


def target_points(
    target: TargetGaussians,
    config: MatchConfig,
    target_vertices: np.ndarray | None,
    target_faces: np.ndarray | None,
    seed: int,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Target surface vertices (M, 3) [m], their Gaussian index (or None for a mesh) and faces (or None)."""
    if target_vertices is None:
        if target_faces is not None:
            raise InputError("match_parts: target_faces given without target_vertices")
        points, index = visible_gaussian_centres(
            target, max_vertices=config.max_target_vertices, min_opacity=config.min_opacity, seed=seed
        )
        return points, index, None
    faces = None if target_faces is None else np.asarray(target_faces, dtype=np.int64)
    return np.asarray(target_vertices, dtype=np.float64), None, faces




def surface_samples(vertices: np.ndarray, faces: np.ndarray | None, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3) area-uniform samples of a mesh, or a random subset of the points when there are no faces."""
    if faces is None or len(faces) == 0:
        if len(vertices) <= count:
            return vertices
        return vertices[rng.choice(len(vertices), count, replace=False)]
    tri = vertices[faces]
    sampled = area_points(tri, count, rng)
    if sampled is None:
        raise InputError("match: the target mesh has zero area")
    return sampled[0]


def skeleton_points(
    vertices: np.ndarray, faces: np.ndarray | None, config: SkeletonConfig, rng: np.random.Generator
) -> np.ndarray:
    """The points a curve skeleton is built on: voxels of the solid (``config.volume`` and a mesh), else
    surface samples or the given points, subsampled to ``config.samples``."""
    return skeleton_points_depth(vertices, faces, config, rng)[0]


def skeleton_points_depth(
    vertices: np.ndarray, faces: np.ndarray | None, config: SkeletonConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`skeleton_points` and, for voxels of the solid, each one's depth inside it [m] (else None)."""
    depth = None
    if config.volume and faces is not None and len(faces):
        pts, depth = volume_points(vertices, faces, config.resolution, rng, with_depth=True)
    elif config.volume:
        pts, depth = cloud_volume_points(vertices, config.resolution, with_depth=True)
    else:
        pts = surface_samples(vertices, faces, config.samples, rng)
    if len(pts) > config.samples:
        keep = rng.choice(len(pts), config.samples, replace=False)
        pts, depth = pts[keep], None if depth is None else depth[keep]
    return pts, depth


def label_agreement(points: np.ndarray, labels: np.ndarray, neighbours: int = 8) -> np.ndarray:
    """(N,) fraction of each point's nearest ``neighbours`` points that share its label (a confidence)."""
    k = int(min(neighbours, len(points)))
    _, idx = cKDTree(points).query(points, k=k)
    return (labels[idx.reshape(len(points), k)] == labels[:, None]).mean(axis=1)
