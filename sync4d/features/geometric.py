"""``features=geometric``: heat and wave kernel signatures plus coordinates, no model weights needed.

This stands in for the paper's geometric branch (CorrNet3D features, 128 dims, a trained network):
intrinsic spectral descriptors of the surface, which do not change under rigid motion, uniform scale
or (approximately) remeshing, concatenated with an encoding of the coordinates in the common frame that
:mod:`sync4d.match` puts both shapes into (normalised and aligned), which separates left from right and
front from back where intrinsic descriptors are symmetric.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np

from sync4d.errors import ConfigError
from sync4d.features._common import (
    check_shape,
    fourier_encoding,
    heat_kernel_signature,
    laplacian,
    laplacian_spectrum,
    mesh_components,
    standardize_columns,
    unit_rms,
    wave_kernel_signature,
)
from sync4d.registry import register

log = logging.getLogger(__name__)


@register("features", "geometric")
class GeometricFeatures:
    """HKS || WKS || coordinates, each block normalised and weighted."""

    @dataclass
    class Config:
        n_eigen: int = 64              # Laplacian eigenpairs (shift-invert eigsh)
        hks_times: int = 16            # HKS time samples, log-spaced over [4ln10/l_max, 4ln10/l_1]
        wks_energies: int = 16         # WKS energy samples, log-spaced over the spectrum
        wks_variance: float = 6.0      # WKS filter width in units of the energy spacing
        hks_weight: float = 0.2        # weight of the HKS block (block has mean squared row norm 1)
        wks_weight: float = 0.2        # weight of the WKS block
        xyz_weight: float = 1.0        # weight of the coordinate block
        xyz_encoding: Literal["fourier", "raw"] = "fourier"  # fourier: random Fourier features (cosine ~ Gaussian kernel) | raw
        xyz_bandwidth: float = 0.15    # Fourier kernel width, in units of the shape's RMS radius
        xyz_dims: int = 512            # Fourier feature count per scale (few dims = noisy kernel)
        xyz_scales: int = 1            # Fourier octaves: bandwidths h, h/2, h/4, ... (multi-scale kernel)
        normalize_xyz: bool = False    # re-centre/scale coordinates here (sync4d.match already does it)
        n_neighbors: int = 30          # neighbours of the point-cloud Laplacian (no faces)
        laplacian: Literal["auto", "mesh", "point_cloud"] = "auto"  # auto: mesh if connected, else point cloud | mesh | point_cloud
        seed: int = 0                  # Fourier projection seed (shared by reference and target)

        def validate(self) -> None:
            if self.n_eigen < 4:
                raise ConfigError(f"features.n_eigen={self.n_eigen}: need at least 4 eigenpairs")
            if min(self.hks_weight, self.wks_weight, self.xyz_weight) < 0:
                raise ConfigError("features.*_weight: weights must be >= 0")
            if self.hks_weight + self.wks_weight + self.xyz_weight <= 0:
                raise ConfigError("features: all block weights are 0; set hks_weight, wks_weight or xyz_weight > 0")
            if self.xyz_scales < 1:
                raise ConfigError(f"features.xyz_scales={self.xyz_scales}: must be >= 1")
            if self.xyz_bandwidth <= 0:
                raise ConfigError(f"features.xyz_bandwidth={self.xyz_bandwidth}: must be > 0")

    def __init__(self, config: Config, *, device: str = "cpu") -> None:
        self.config = config
        self.device = device  # the computation is sparse linear algebra on the CPU

    def spectral(self, points: np.ndarray, faces: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Raw (unstandardised) HKS (V, hks_times) and WKS (V, wks_energies) of the shape.

        The shape is scaled to unit RMS radius first, so both are invariant to rigid motion and scale.
        """
        pts, fcs = check_shape(points, faces)
        if fcs is not None and (
            self.config.laplacian == "point_cloud" or (self.config.laplacian == "auto" and mesh_components(len(pts), fcs) > 1)
        ):
            # Intrinsic descriptors of a mesh made of separate shells (e.g. a capsule body) would only
            # see each shell; the point-cloud Laplacian connects nearby shells through space.
            fcs = None
        L, M = laplacian(unit_rms(pts), fcs, n_neighbors=self.config.n_neighbors)
        evals, evecs = laplacian_spectrum(L, M, self.config.n_eigen)
        hks = heat_kernel_signature(evals, evecs, self.config.hks_times)
        wks = wave_kernel_signature(evals, evecs, self.config.wks_energies, variance=self.config.wks_variance)
        return hks, wks

    def coordinates(self, points: np.ndarray) -> np.ndarray:
        """(V, D_xyz) coordinate block (mean squared row norm ~1 for points of unit RMS radius)."""
        pts = unit_rms(points) if self.config.normalize_xyz else np.asarray(points, dtype=np.float64)
        if self.config.xyz_encoding == "raw":
            return pts
        # Several octaves sum several Gaussian kernels: fine scales separate neighbouring parts, coarse
        # scales keep a vertex related to a part it is not right next to (different proportions).
        blocks = [
            fourier_encoding(pts, dims=self.config.xyz_dims, bandwidth=self.config.xyz_bandwidth / 2**k, seed=self.config.seed + k)
            for k in range(self.config.xyz_scales)
        ]
        return np.concatenate(blocks, axis=1) / np.sqrt(self.config.xyz_scales)

    def extract(self, points: np.ndarray, faces: np.ndarray | None) -> np.ndarray:
        """Per-vertex features.

        Args:
            points: (V, 3) vertices in the common normalised, aligned frame.
            faces: (F, 3) triangles or None for a point cloud.

        Returns:
            (V, hks_times + wks_energies + D_xyz) float32: [w_h HKS, w_w WKS, w_x xyz], where the
            spectral blocks are log-transformed and standardised per column.
        """
        pts, fcs = check_shape(points, faces)
        blocks = []
        if self.config.hks_weight > 0 or self.config.wks_weight > 0:
            hks, wks = self.spectral(pts, fcs)
            # HKS spans orders of magnitude across times; the log keeps every time scale in play.
            blocks.append(self.config.hks_weight * standardize_columns(np.log(np.maximum(hks, 1e-30))))
            blocks.append(self.config.wks_weight * standardize_columns(np.log(np.maximum(wks, 1e-30))))
        blocks.append(self.config.xyz_weight * self.coordinates(pts))
        return np.concatenate(blocks, axis=1).astype(np.float32)
