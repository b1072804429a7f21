"""What a component of each registry group must provide (structural types; no base class needed).

Every component is built as ``cls(config, **deps)`` by :func:`sync4d.registry.build`; the keyword
dependencies each group receives are listed below. ``device`` is always the config's ``device`` value
(``cpu``, ``cuda``); map it with :mod:`sync4d.device`.

An optional capability is a Protocol of its own, checked with ``isinstance`` where it is used (a target with
a surface mesh, a target that checks what it loads, a logger that takes videos, a reference read from a file
with a frame bound), never by probing for an attribute's name.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from sync4d.types import (
    Camera,
    FloaterReport,
    FramePose,
    Reference,
    ReferenceInput,
    TargetGaussians,
)


class ReferenceSource(Protocol):
    """Group ``reference``: built with ``(config, device=..., seed=...)``; loads or makes the reference input."""

    def load(self) -> ReferenceInput: ...


@runtime_checkable
class BoundedFrames(Protocol):
    """Capability of a ``reference`` Config that reads frames from a file: ``max_frames`` of them (0 = all)."""

    max_frames: int


class Reconstructor(Protocol):
    """Group ``recon``: built with ``(config, device=...)``; turns the input into an articulated reference."""

    def reconstruct(self, source: ReferenceInput) -> Reference: ...


class TargetSource(Protocol):
    """Group ``target``: built with ``(config, device=..., seed=...)``; loads or makes the static target."""

    def load(self) -> TargetGaussians: ...


@runtime_checkable
class TargetWithSurface(Protocol):
    """Capability of a target made from a mesh: matching and motion use the mesh instead of a sample of the
    Gaussians' centres (:func:`sync4d.surface.target_surface`)."""

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """(V, 3) vertices [m] and (F, 3) triangle faces."""
        ...


@runtime_checkable
class CheckedTarget(Protocol):
    """Capability of a target that checks what it loads (a splat's floaters removed) and reports it."""

    def load_checked(self) -> tuple[TargetGaussians, FloaterReport | None]:
        """The Gaussians, and what the check removed (None when the check is off)."""
        ...


class FeatureExtractor(Protocol):
    """Group ``features``: built with ``(config, device=...)``; per-point descriptors of a shape.

    ``points`` (V, 3) [m] are already normalised and aligned by :mod:`sync4d.match` when coordinates
    matter; ``faces`` (F, 3) or None for a point cloud. Returns (V, D) float features.
    """

    def extract(self, points: np.ndarray, faces: np.ndarray | None) -> np.ndarray: ...


class Simulator(Protocol):
    """Group ``sim``: built with ``(config, device=...)``. A simulator only steps: it models a particle set and
    advances a state by one frame; the transfer stage (:mod:`sync4d.transfer`) owns the frame-pair loop.

    ``differentiable``: whether :meth:`rollout` carries gradients to its inputs (velocity training needs it);
    ``dtype``: the float type of the states it steps.
    The model is whatever the simulator needs that a rollout does not change (grid, masses, skinning weights).
    """

    differentiable: bool
    dtype: torch.dtype

    def prepare(self, points: np.ndarray, *, volume: np.ndarray | None = None, part: np.ndarray | None = None,
                parent: np.ndarray | None = None) -> Any:
        """The model of (P, 3) rest particles [m] with (P,) volumes [m^3] and parts, and the (B,) part each part
        is joined to (-1 for a root; None: no joints known)."""
        ...

    def domain(self, model: Any) -> tuple[np.ndarray, np.ndarray]:
        """The box the simulation lives in [m], (3,) low and high corners (a velocity field spans it)."""
        ...

    def frame_time_for(self, fps: float | None) -> float:
        """Simulated time of one frame [s]."""
        ...

    def substeps_for(self, model: Any, v_max: float = 0.0, *, fps: float | None = None) -> tuple[int, float]:
        """Substeps N and dt [s] of one frame for particles up to ``v_max`` [m/s] fast."""
        ...

    def rollout(
        self, model: Any, x: torch.Tensor, v: torch.Tensor, F: torch.Tensor, C: torch.Tensor, *,
        substeps: int, dt: float, frame_index: int = 0, pose: FramePose | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(x, v, F, C) after ``substeps`` substeps of ``dt`` [s] (shapes (P, 3), (P, 3), (P, 3, 3),
        (P, 3, 3)); ``pose`` is the driving motion of the frame pair."""
        ...


@runtime_checkable
class GridSimulatorConfig(Protocol):
    """Capability of a ``sim`` config whose cost and size the transfer's budget can model (``MPMWarp.Config``): a
    background grid, a material [Pa, kg/m^3] and a substep budget."""

    E: float
    nu: float
    density: float
    n_grid: int
    grid_padding: float
    wall_cells: int
    frame_time: float | None
    substeps: int
    cfl_safety: float
    checkpoint_budget_mb: float
    max_substeps: int


@runtime_checkable
class GridModel(Protocol):
    """Capability of a simulator's model that lives on a background grid (``grid.dx``: its cell [m])."""

    grid: Any


@runtime_checkable
class FigureWriter(Protocol):
    """Capability of a reconstructor that draws what it found (pictures under ``folder``)."""

    def write_figures(self, folder: Path) -> None: ...


@runtime_checkable
class FileSourceConfig(Protocol):
    """Capability of a source's config that names the file it reads (for messages)."""

    path: str | None


class VelocityField(Protocol):
    """Group ``velocity``: built with ``(config, num_parts=B, bounds=(lo, hi), seed=...)``; a torch module giving
    the delta velocity [m/s] added to the reference velocities (paper Eq. v <- v0 + dv)."""

    trainable: bool
    velocity_scale: float

    def __call__(self, x: torch.Tensor, part: torch.Tensor) -> torch.Tensor:
        """(P, 3) positions [m], (P,) parts -> (P, 3) delta velocities [m/s]."""
        ...

    def regularizer(self) -> torch.Tensor:
        """The field's own loss term (e.g. the triplane's total variation)."""
        ...

    def parameters(self) -> Iterator[torch.nn.Parameter]: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> Any: ...


class Logger(Protocol):
    """Group ``logger``: built with ``(config, run_dir=...)``; scalars, images and hyper-parameters of a run."""

    def scalar(self, tag: str, value: float, step: int) -> None: ...

    def image(self, tag: str, image: np.ndarray, step: int = 0) -> None: ...

    def hparams(self, params: dict[str, Any], metrics: dict[str, float]) -> None: ...

    def close(self) -> None: ...


@runtime_checkable
class VideoLogger(Protocol):
    """Capability of a logger that shows clips (TensorBoard: the animated GIF as an image)."""

    def video(self, tag: str, frames: np.ndarray, fps: float, step: int = 0, *, gif_path: Path | None = None) -> None:
        """Log (T, H, W, 3) uint8 ``frames`` shown at ``fps`` [1/s]; also write them as a GIF to ``gif_path``."""
        ...


class Renderer(Protocol):
    """Group ``render``: built with ``(config, device=...)``; draws Gaussians from a camera.

    Arrays may be numpy or torch; returns (H, W, 3) float RGB in [0, 1] (torch tensor when inputs are
    tensors, so gradients flow).
    """

    def render(
        self, means: Any, covariances: Any, colors: Any, opacities: Any, camera: Camera
    ) -> Any: ...
