"""Delta-velocity fields (paper Sec. 3.4): ``dv = field(x, part)`` added to the reference velocities.

Each field is a ``torch.nn.Module`` registered in the ``velocity`` group and built with
``(config, num_parts=B, bounds=(lo, hi), seed=...)`` where ``bounds`` is the simulation box [m]. ``velocity_scale``
multiplies the initial reference velocities (the paper's alpha in its no-optimisation ablation) and
``trainable`` says whether frame-pair training optimises it; the transfer stage owns the optimiser
(``transfer.lr``, ``transfer.iterations``, ``transfer.patience``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from sync4d.errors import ConfigError
from sync4d.registry import register
from sync4d.rng import init_linear_layers, torch_generator


def total_variation(planes: torch.Tensor) -> torch.Tensor:
    """Paper Eq. (TV): sum over planes of squared differences of neighbouring feature vectors.

    Args:
        planes: (3, C, R, R) feature planes.
    """
    dj = planes[:, :, 1:, :] - planes[:, :, :-1, :]
    dk = planes[:, :, :, 1:] - planes[:, :, :, :-1]
    return (dj**2).sum() + (dk**2).sum()


@register("velocity", "triplane")
class TriplaneField(nn.Module):
    """Three axis-aligned feature planes over the simulation box, decoded by a 3-layer MLP.

    Features sampled bilinearly on the xy, xz and yz planes are concatenated (3C values) and decoded to a
    per-particle delta velocity [m/s]. The last layer starts at zero so training begins exactly from the
    reference velocities.
    """

    @dataclass
    class Config:
        resolution: int = 32       # plane resolution R (R x R texels per plane)
        features: int = 32         # feature channels C per plane
        hidden: int = 64           # MLP hidden width
        init_std: float = 0.1      # std of the initial plane features (non-zero so the MLP gets gradient)
        tv_weight: float = 1e-4    # weight of the total-variation loss on the planes
        velocity_scale: float = 1.0  # multiplies the reference velocities (kept 1 when training)

        def validate(self) -> None:
            if self.resolution < 2 or self.features < 1 or self.hidden < 1:
                raise ConfigError("velocity: resolution >= 2, features >= 1 and hidden >= 1 are required")

    trainable = True

    def __init__(self, config: Config, *, num_parts: int, bounds: tuple[np.ndarray, np.ndarray], seed: int = 0) -> None:
        super().__init__()
        self.config = config
        self.velocity_scale = config.velocity_scale
        lo, hi = (torch.as_tensor(np.asarray(b, dtype=np.float32)) for b in bounds)
        self.register_buffer("lo", lo)
        self.register_buffer("hi", hi)
        generator = torch_generator(seed)
        planes = torch.randn(3, config.features, config.resolution, config.resolution, generator=generator) * config.init_std
        self.planes = nn.Parameter(planes)
        self.mlp = nn.Sequential(
            nn.Linear(3 * config.features, config.hidden), nn.SiLU(),
            nn.Linear(config.hidden, config.hidden), nn.SiLU(),
            nn.Linear(config.hidden, 3),
        )
        init_linear_layers(self.mlp, generator)
        last = self.mlp[-1]
        assert isinstance(last, nn.Linear)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    def forward(self, x: torch.Tensor, part: torch.Tensor) -> torch.Tensor:
        """(P, 3) positions [m], (P,) parts -> (P, 3) delta velocities [m/s]."""
        lo, hi = self.get_buffer("lo"), self.get_buffer("hi")
        u = ((x - lo) / (hi - lo)) * 2.0 - 1.0  # [-1, 1] in the box
        pairs = (u[:, [0, 1]], u[:, [0, 2]], u[:, [1, 2]])
        feats = [
            F.grid_sample(self.planes[i : i + 1], uv.view(1, -1, 1, 2), align_corners=True, padding_mode="border")
            .view(self.config.features, -1)
            .T
            for i, uv in enumerate(pairs)
        ]
        return self.mlp(torch.cat(feats, dim=1))

    def regularizer(self) -> torch.Tensor:
        return self.config.tv_weight * total_variation(self.planes)


@register("velocity", "per_part")
class PerPartField(nn.Module):
    """One learnable delta velocity per part (the cheap alternative to the triplane)."""

    @dataclass
    class Config:
        velocity_scale: float = 1.0  # multiplies the reference velocities (kept 1 when training)

    trainable = True

    def __init__(self, config: Config, *, num_parts: int, bounds: tuple[np.ndarray, np.ndarray], seed: int = 0) -> None:
        super().__init__()
        self.config = config
        self.velocity_scale = config.velocity_scale
        self.delta = nn.Parameter(torch.zeros(num_parts, 3))

    def forward(self, x: torch.Tensor, part: torch.Tensor) -> torch.Tensor:
        return self.delta[part]

    def regularizer(self) -> torch.Tensor:
        return self.delta.new_zeros(())


@register("velocity", "none")
class NoField(nn.Module):
    """The paper's no-optimisation ablation: reference velocities scaled by ``alpha``, no training."""

    @dataclass
    class Config:
        alpha: float = 1.0   # v <- alpha * v0 (the paper scales its unit initial velocities by alpha)

    trainable = False

    def __init__(self, config: Config, *, num_parts: int, bounds: tuple[np.ndarray, np.ndarray], seed: int = 0) -> None:
        super().__init__()
        self.config = config
        self.velocity_scale = config.alpha

    def forward(self, x: torch.Tensor, part: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(x)

    def regularizer(self) -> torch.Tensor:
        return torch.zeros(())
