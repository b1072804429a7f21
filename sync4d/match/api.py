"""``match_parts``: the part map of a target's Gaussians by the configured method."""

from __future__ import annotations

import numpy as np

from sync4d.errors import ConfigError
from sync4d.interfaces import FeatureExtractor
from sync4d.match.auto import match_auto
from sync4d.match.by_structure import match_by_structure
from sync4d.match.config import MatchConfig
from sync4d.match.features_match import match_by_features
from sync4d.match.result import MatchResult
from sync4d.types import Reference, TargetGaussians


def match_parts(
    reference: Reference,
    target: TargetGaussians,
    extractor: FeatureExtractor | None,
    config: MatchConfig | None = None,
    *,
    target_vertices: np.ndarray | None = None,
    target_faces: np.ndarray | None = None,
    seed: int = 0,
) -> MatchResult:
    """Part map of the target's Gaussians (paper Sec. 3.3), with the alignment it used.

    Args:
        reference: articulated reference (rest mesh and skinning).
        target: the static Gaussians to label.
        extractor: a built ``features`` component (needed by ``method=features`` only).
        config: options (defaults: ``MatchConfig()``).
        target_vertices: (M, 3) target surface [m] in the Gaussians' frame (e.g. the mesh the Gaussians
            came from); None uses the Gaussian means.
        target_faces: (F, 3) faces of ``target_vertices``, or None.
        seed: subsampling / k-means seed.

    Returns:
        MatchResult: the PartMap (tgt_part per Gaussian), diagnostics, the target -> reference similarity.
    """
    config = (config or MatchConfig()).validate()
    if config.method == "structure":
        return match_by_structure(reference, target, config, target_vertices, target_faces, seed)
    if extractor is None:
        raise ConfigError(f"match.method={config.method} needs a features component (features=geometric, ...)")
    if config.method == "auto":
        return match_auto(reference, target, extractor, config, target_vertices, target_faces, seed)
    return match_by_features(reference, target, extractor, config, target_vertices, target_faces, seed)
