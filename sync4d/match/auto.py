"""``match.method=auto``: the feature method or the structure match, chosen per pair."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from sync4d.interfaces import FeatureExtractor
from sync4d.match.align import AlignResult, align_shapes
from sync4d.match.by_structure import match_by_structure
from sync4d.match.config import MatchConfig
from sync4d.match.features_match import match_by_features
from sync4d.match.result import MatchResult
from sync4d.match.surface_points import target_points
from sync4d.types import Reference, TargetGaussians

log = logging.getLogger(__name__)


def match_auto(
    reference: Reference,
    target: TargetGaussians,
    extractor: FeatureExtractor,
    cfg: MatchConfig,
    target_vertices: np.ndarray | None,
    target_faces: np.ndarray | None,
    seed: int,
) -> MatchResult:
    """Align once, choose the method by the alignment (:func:`choose_method`), run it (reusing the alignment)."""
    tgt_vertices = target_points(target, cfg, target_vertices, target_faces, seed)[0]
    alignment = align_shapes(
        tgt_vertices, reference.rest_vertices, method=cfg.align, icp_iterations=cfg.icp_iterations, seed=seed
    )
    if choose_method(alignment, cfg.auto_residual) == "structure":
        result = match_by_structure(reference, target, cfg, target_vertices, target_faces, seed)
    else:
        result = match_by_features(reference, target, extractor, cfg, target_vertices, target_faces, seed, alignment)
    return replace(result, diagnostics=replace(result.diagnostics, auto_residual=alignment.residual))


def choose_method(alignment: AlignResult, max_residual: float) -> str:
    """``features`` if the aligned target lies on the reference (residual <= ``max_residual``), else ``structure``.

    The features transfer parts by what lies where once the surfaces overlap (a copy, other proportions
    of one kind: residual 0.03-0.05 RMS radii on the benchmark; the laptop on the clam shell 0.106, the
    laptop reconstructed from its video on it 0.140); across categories no rigid fit puts one shape on
    the other (0.17-0.23), and the skeletons' structure decides. The default 0.155 lies in the middle of
    the gap between the two groups, a thin one (docs/matching.md, "One default: auto").
    """
    method = "features" if alignment.residual <= max_residual else "structure"
    log.info("match: method=auto: alignment residual %.4f %s %.3g -> %s", alignment.residual,
             "<=" if method == "features" else ">", max_residual, method)
    return method
