"""What a component of each registry group must provide (structural types; no base class needed).

Every component is built as ``cls(cfg, **deps)`` by :func:`sync4d.registry.build`; the keyword
dependencies each group receives are listed below. ``device`` is always the config's ``device`` value
(``cpu``, ``cuda``); map it with :mod:`sync4d.device`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from sync4d.types import (
    Camera,
    DrivingMotion,
    PartMap,
    Reference,
    ReferenceInput,
    TargetGaussians,
    Trajectory,
)


class ReferenceSource(Protocol):
    """Group ``reference``: built with ``(cfg, device=..., seed=...)``; loads or makes the reference input."""

    def load(self) -> ReferenceInput: ...


class Reconstructor(Protocol):
    """Group ``recon``: built with ``(cfg, device=...)``; turns the input into an articulated reference."""

    def reconstruct(self, source: ReferenceInput) -> Reference: ...


class TargetSource(Protocol):
    """Group ``target``: built with ``(cfg, device=..., seed=...)``; loads or makes the static target."""

    def load(self) -> TargetGaussians: ...


class FeatureExtractor(Protocol):
    """Group ``features``: built with ``(cfg, device=...)``; per-point descriptors of a shape.

    ``points`` (V, 3) [m] are already normalised and aligned by :mod:`sync4d.match` when coordinates
    matter; ``faces`` (F, 3) or None for a point cloud. Returns (V, D) float features.
    """

    def extract(self, points: np.ndarray, faces: np.ndarray | None) -> np.ndarray: ...


class Simulator(Protocol):
    """Group ``sim``: built with ``(cfg, device=...)``; animates the target with the driving motion.

    ``velocity_cfg`` selects the velocity field (ignored by ``sim=lbs``); ``on_frame(t, x, F, stats,
    checkpoint=None, control=None)`` is called after every completed frame with the Gaussians' positions
    (N, 3) [m] and deformation gradients (N, 3, 3), or, with ``control`` (a
    :class:`sync4d.sim.control.ControlPoints`), those of the P control points the Gaussians follow, so the
    pipeline writes outputs as the run goes; ``checkpoint`` is the simulator's state to resume from.
    ``resume`` is that state (plus ``frame``) when resuming.
    """

    def run(
        self,
        target: TargetGaussians,
        part_map: PartMap,
        motion: DrivingMotion,
        *,
        velocity_cfg: Any,
        num_frames: int,
        on_frame: Callable[..., None] | None = None,
        resume: dict[str, Any] | None = None,
    ) -> Trajectory: ...


class Renderer(Protocol):
    """Group ``render``: built with ``(cfg, device=...)``; draws Gaussians from a camera.

    Arrays may be numpy or torch; returns (H, W, 3) float RGB in [0, 1] (torch tensor when inputs are
    tensors, so gradients flow).
    """

    def render(
        self, means: Any, covariances: Any, colors: Any, opacities: Any, camera: Camera
    ) -> Any: ...
