"""``match.method=structure``: the structure match (:mod:`sync4d.match.structure`) on the target's solid,
wrapped into a :class:`~sync4d.match.result.MatchResult`."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from sync4d.errors import InputError
from sync4d.match.align import AlignResult, Similarity, align_shapes, normalization
from sync4d.match.config import MatchConfig
from sync4d.match.result import MatchDiagnostics, MatchResult, finish_match
from sync4d.match.structure import match_structure
from sync4d.match.surface_points import label_agreement, skeleton_points, skeleton_points_depth, target_points
from sync4d.types import Reference, TargetGaussians


def match_by_structure(
    reference: Reference,
    target: TargetGaussians,
    config: MatchConfig,
    target_vertices: np.ndarray | None,
    target_faces: np.ndarray | None,
    seed: int,
) -> MatchResult:
    """Structure-aware matching (:mod:`sync4d.match.structure`) wrapped into a MatchResult."""
    rng = np.random.default_rng(seed)
    tgt_vertices, index, tgt_faces = target_points(target, config, target_vertices, target_faces, seed)
    check_target_surface(tgt_vertices)
    if config.align in ("pca", "pca_icp"):
        alignment = align_shapes(
            tgt_vertices, reference.rest_vertices, method=config.align, icp_iterations=config.icp_iterations, seed=seed
        )
    else:
        alignment = AlignResult(Similarity.identity(), float("nan"), np.zeros(0), "none")
    # the reference's surface is enough: its parts give the trunk, and distances are taken from it
    ref_samples = skeleton_points(
        reference.rest_vertices, reference.rest_faces, replace(config.structure.skeleton, volume=False), rng
    )
    ref_norm = normalization(reference.rest_vertices)
    _, nearest = cKDTree(reference.rest_vertices).query(ref_samples)
    ref_labels = reference.part_labels()[nearest]
    pre = alignment.transform
    tgt_raw, tgt_depth = skeleton_points_depth(tgt_vertices, tgt_faces, config.structure.skeleton, rng)
    tgt_samples = pre.apply(tgt_raw)
    tgt_norm = normalization(tgt_samples)
    # the structure match works on each shape normalised by itself, then turns the target about the up axis
    sm = match_structure(
        ref_norm.apply(ref_samples),
        ref_labels,
        reference.num_bones,
        tgt_norm.apply(tgt_samples),
        config.structure,
        up_axis=config.up_axis,
        part_parents=reference.bone_parents,
        tgt_depth=None if tgt_depth is None else tgt_depth * pre.scale * tgt_norm.scale,
        turn_cost=config.structure.aligned_turn_cost if config.align in ("pca", "pca_icp") else 0.0,
    )
    frame = pre.then(tgt_norm).then(Similarity(sm.rotation, 1.0, np.zeros(3)))
    sample_pts = tgt_norm.apply(tgt_samples) @ sm.rotation.T
    g_pts = frame.apply(target.means)
    _, j = cKDTree(sample_pts).query(g_pts)
    tgt_part = sm.point_part[j]
    agreement = label_agreement(sample_pts, sm.point_part)
    confidence = agreement[j]
    valid = np.bincount(sm.point_part, minlength=reference.num_bones) > 0
    centroids = np.full((reference.num_bones, 3), np.nan)
    for b in np.flatnonzero(valid):
        centroids[b] = sample_pts[sm.point_part == b].mean(axis=0)
    diagnostics = MatchDiagnostics(
        alignment=alignment,
        frame=frame,
        reference_points=ref_norm.apply(ref_samples),
        target_points=sample_pts,
        target_index=index,
        vertex_part=sm.point_part,
        vertex_margin=agreement,
        kept=np.ones(len(sample_pts), dtype=bool),
        similarity=None,
        boxes=None,
        box_rotations=None,
        box_valid=valid,
        centroids=centroids,
        gaussian_status=np.zeros(target.num, dtype=np.int8),
        structure=sm,
        reference_labels=ref_labels,
        method="structure",
    )
    return finish_match(reference, target, tgt_part, confidence, diagnostics)


def check_target_surface(points: np.ndarray) -> None:
    """Raise InputError unless ``points`` are (M >= 16, 3) finite target surface points."""
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 16 or not np.isfinite(points).all():
        raise InputError(
            f"match: the target surface must be (M >= 16, 3) finite points, got {points.shape}"
            " (NaN/inf or too few Gaussians above match.min_opacity)"
        )
