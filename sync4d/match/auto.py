"""``match.method=auto``: both methods run, and the map that agrees better with the reference's structure is kept.

Each map is scored by :func:`sync4d.match.consistency.consistency` on the parts it gives the target's
Gaussians: across categories the feature method's map breaks the reference's parts into pieces and puts
parts in contact that never touch in the reference; the structure match keeps both by construction. The
structure match is kept only when its map keeps strictly more of the reference's structure
(``connected x contacts``); otherwise, when the feature method keeps as much (a shape of the same kind:
its map is as clean), the paper's method is kept. No threshold: two measurements of the maps themselves
are compared.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from sync4d.interfaces import FeatureExtractor
from sync4d.match.by_structure import match_by_structure
from sync4d.match.config import MatchConfig
from sync4d.match.consistency import Consistency, consistency
from sync4d.match.features_match import match_by_features
from sync4d.match.result import MatchResult
from sync4d.types import Reference, TargetGaussians

log = logging.getLogger(__name__)


#: Gaussians the consistency is measured on at most (a random subset, the same for both maps)
SCORE_POINTS = 6000


def result_consistency(result: MatchResult, reference: Reference, target: TargetGaussians, index: np.ndarray
                       ) -> Consistency:
    """The agreements of a match's Gaussian parts (those at ``index``) with the reference's rest parts."""
    return consistency(target.means[index], result.part_map.tgt_part[index], reference.rest_vertices,
                       reference.part_labels(), reference.num_bones)


def choose_method(features: Consistency, structure: Consistency) -> str:
    """``structure`` if its map keeps strictly more of the reference's structure (connected x contacts),
    else ``features``."""
    return "structure" if structure.kept > features.kept else "features"


def match_auto(
    reference: Reference,
    target: TargetGaussians,
    extractor: FeatureExtractor,
    config: MatchConfig,
    target_vertices: np.ndarray | None,
    target_faces: np.ndarray | None,
    seed: int,
) -> MatchResult:
    """Run both methods, keep the one :func:`choose_method` prefers (its diagnostics carry both scores)."""
    by_features = match_by_features(reference, target, extractor, config, target_vertices, target_faces, seed)
    by_structure = match_by_structure(reference, target, config, target_vertices, target_faces, seed)
    rng = np.random.default_rng(seed)
    index = np.sort(rng.choice(target.num, min(target.num, SCORE_POINTS), replace=False))
    scores = {"features": result_consistency(by_features, reference, target, index),
              "structure": result_consistency(by_structure, reference, target, index)}
    method = choose_method(scores["features"], scores["structure"])
    log.info("match: method=auto: %s -> %s", ", ".join(
        f"{m}: connected {c.connected:.4f} contacts {c.contacts:.4f}" for m, c in scores.items()
    ), method)
    result = by_features if method == "features" else by_structure
    return replace(result, diagnostics=replace(result.diagnostics, auto_scores=scores,
                                               auto_residual=by_features.diagnostics.alignment.residual))
