"""What part matching returns: the part map, the diagnostics it was made with, the alignment used."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from sync4d.match.align import AlignResult, Similarity, normalization
from sync4d.match.consistency import Consistency
from sync4d.match.structure import StructureMatch
from sync4d.types import PartMap, Reference, TargetGaussians

log = logging.getLogger(__name__)

#: a Gaussian's status in the part boxes: in one box, in several (nearest part), in none (nearest part)
IN_ONE_BOX, IN_SEVERAL_BOXES, ORPHAN = 0, 1, 2


@dataclass(frozen=True)
class MatchDiagnostics:
    """Everything :func:`sync4d.match.match_parts` computed on the way, for logs, pictures and tests.

    Attributes:
        alignment: the target -> reference alignment.
        frame: similarity taking target coordinates into the common normalised frame (alignment, then
            the reference's normalisation).
        reference_points: (V, 3) reference vertices in the common frame.
        target_points: (M, 3) target surface vertices in the common frame.
        target_index: (M,) indices of the Gaussians used as surface vertices, or None if a mesh was given.
        vertex_part: (M,) part of highest cosine similarity per target vertex (before outlier removal).
        vertex_margin: (M,) cosine margin best minus second-best part per target vertex.
        kept: (M,) bool, False for removed outliers.
        similarity: (M, B) cosine similarities of the target vertices to the part means (None with
            ``method=structure``).
        boxes: (B, 2, 3) per-part box corners (lo, hi) in the box frame (see ``box_rotations``; None with
            ``method=structure``).
        box_rotations: (B, 3, 3) rotation of each box frame (identity for axis-aligned boxes), or None.
        box_valid: (B,) bool, the part kept at least one target vertex.
        centroids: (B, 3) part centroids of the kept target vertices, common frame (NaN if invalid).
        gaussian_status: (N,) 0 in one box, 1 in several (nearest centroid), 2 orphan (nearest centroid);
            all 0 with ``method=structure``.
        structure: the skeleton match with ``method=structure``, else None.
        reference_labels: (V,) part of each of ``reference_points``.
        method: the method that made the map (``features`` or ``structure``; ``auto`` picks one).
        auto_residual: with ``method=auto``, the feature method's alignment residual (for the record), else None.
        auto_scores: with ``method=auto``, each method's agreement with the reference
            (:class:`~sync4d.match.consistency.Consistency`) the choice was made on, else None.
    """

    alignment: AlignResult
    frame: Similarity
    reference_points: np.ndarray
    target_points: np.ndarray
    target_index: np.ndarray | None
    vertex_part: np.ndarray
    vertex_margin: np.ndarray
    kept: np.ndarray
    similarity: np.ndarray | None
    boxes: np.ndarray | None
    box_rotations: np.ndarray | None
    box_valid: np.ndarray
    centroids: np.ndarray
    gaussian_status: np.ndarray
    structure: StructureMatch | None = None
    reference_labels: np.ndarray | None = None
    method: str = "features"
    auto_residual: float | None = None
    auto_scores: dict[str, Consistency] | None = None

    @property
    def vertex_part_final(self) -> np.ndarray:
        """(M,) target vertex parts after outlier removal, -1 for outliers."""
        return np.where(self.kept, self.vertex_part, -1)

    def summary(self) -> dict[str, float]:
        """Scalar numbers worth logging."""
        n = max(len(self.gaussian_status), 1)
        return {
            "align_rotation_deg": self.alignment.transform.rotation_angle_deg,
            "align_scale": self.alignment.transform.scale,
            "align_residual": self.alignment.residual,
            "outlier_fraction": float(1.0 - self.kept.mean()) if len(self.kept) else 0.0,
            "mean_margin": float(self.vertex_margin.mean()) if len(self.vertex_margin) else 0.0,
            "gaussians_in_several_boxes": float((self.gaussian_status == IN_SEVERAL_BOXES).sum() / n),
            "gaussians_orphan": float((self.gaussian_status == ORPHAN).sum() / n),
            "parts_matched": float(self.box_valid.sum()),
            **(
                {
                    "limbs_matched": float(len(self.structure.pairs)),
                    "limbs_left_over": float(len(self.structure.leftover)),
                }
                if self.structure is not None
                else {}
            ),
        }


@dataclass(frozen=True)
class MatchResult:
    """A part map with its diagnostics and the alignment it used.

    Attributes:
        part_map: the parts of the target's Gaussians.
        diagnostics: what was computed on the way.
        alignment: similarity taking the target's coordinates [m] into the reference's [m]; its
            ``rotation.T`` turns reference motion into the target's frame.
        leftover_parts: reference parts that no target Gaussian received.
    """

    part_map: PartMap
    diagnostics: MatchDiagnostics
    alignment: Similarity
    leftover_parts: tuple[int, ...]



def finish_match(
    reference: Reference,
    target: TargetGaussians,
    tgt_part: np.ndarray,
    confidence: np.ndarray,
    diagnostics: MatchDiagnostics,
) -> MatchResult:
    """The MatchResult of a part map: PartMap checked, left-over parts logged, the target -> reference similarity."""
    num_parts = reference.num_bones
    part_map = PartMap(
        ref_part=reference.part_labels(), tgt_part=tgt_part, confidence=confidence, num_parts=num_parts
    ).validate()
    got = np.bincount(tgt_part, minlength=num_parts) > 0
    leftover = tuple(int(b) for b in np.flatnonzero(~got))
    log.info("match: %s", ", ".join(f"{k}={v:.4g}" for k, v in diagnostics.summary().items()))
    if leftover:
        names = reference.bone_names or tuple(str(b) for b in range(num_parts))
        log.info("match: reference parts without a target part: %s", ", ".join(names[b] for b in leftover))
    alignment = diagnostics.frame.then(normalization(reference.rest_vertices).inverse())
    return MatchResult(part_map, diagnostics, alignment, leftover)
