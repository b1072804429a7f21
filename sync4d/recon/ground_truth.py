"""``recon=ground_truth``: use the exact articulated reference a synthetic source carries (for tests)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from sync4d.errors import InputError
from sync4d.registry import register
from sync4d.types import Reference, ReferenceInput


@register("recon", "ground_truth")
class GroundTruthReconstructor:
    """Return ``source.ground_truth`` unchanged (validated); no fitting."""

    @dataclass
    class Config:
        """``recon=ground_truth`` has no options; ``bones`` is accepted for a uniform command line.

        Attributes:
            bones: ignored (the ground truth fixes B); kept so ``recon.bones=...`` overrides do not fail.
        """

        bones: Optional[int] = None

    def __init__(self, config: Config, *, device: str = "cpu") -> None:
        self.config = config
        self.device = device

    def reconstruct(self, source: ReferenceInput) -> Reference:
        """The source's ground-truth reference.

        Raises:
            InputError: the source carries no ground truth (a real video or file).
        """
        if source.ground_truth is None:
            raise InputError(
                f"recon=ground_truth: reference '{source.name}' carries no ground truth (only synthetic scenes "
                "do); pick a fitting reconstructor, e.g. recon=video, recon=skinning_fit, recon=lab4d or recon=mocap"
            )
        return source.ground_truth.validate()
