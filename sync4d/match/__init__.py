"""Part matching (paper Sec. 3.3): which reference part drives each target Gaussian.

Modules: :mod:`~sync4d.match.config` (:class:`MatchConfig`, every option), :mod:`~sync4d.match.api`
(:func:`match_parts`), :mod:`~sync4d.match.result` (:class:`MatchResult`, :class:`MatchDiagnostics`),
:mod:`~sync4d.match.features_match` (the paper's cosine rule and part boxes), :mod:`~sync4d.match.by_structure`
and :mod:`~sync4d.match.structure` (curve skeletons matched limb by limb), :mod:`~sync4d.match.skeleton`
(the curve skeleton), :mod:`~sync4d.match.auto` (the choice between the two), :mod:`~sync4d.match.align`
(similarity fits), :mod:`~sync4d.match.surface_points` (target surface and skeleton points),
:mod:`~sync4d.match.pictures` (figures of a part map).
"""

from sync4d.match.api import match_parts
from sync4d.match.config import METHODS, MatchConfig
from sync4d.match.result import MatchDiagnostics, MatchResult

__all__ = ["METHODS", "MatchConfig", "MatchDiagnostics", "MatchResult", "match_parts"]
