"""Randomness passed in, never drawn from global state: generators made from the run's one ``seed``."""

from __future__ import annotations

import math

import torch


def torch_generator(seed: int) -> torch.Generator:
    """A CPU ``torch.Generator`` seeded with ``seed`` (parameters are initialised on the CPU, then moved)."""
    return torch.Generator().manual_seed(int(seed))


def init_linear_layers(module: torch.nn.Module, generator: torch.Generator) -> None:
    """Re-draw every ``nn.Linear`` of ``module`` as PyTorch's default does, from ``generator``.

    The default initialisation (Kaiming-uniform weights with a = sqrt(5), biases uniform in
    +-1/sqrt(fan_in)) draws from the global generator; this keeps the same distribution while a stage's
    result depends only on the seed it was given, not on what ran before it.
    """
    with torch.no_grad():
        for layer in module.modules():
            if isinstance(layer, torch.nn.Linear):
                torch.nn.init.kaiming_uniform_(layer.weight, a=math.sqrt(5), generator=generator)
                if layer.bias is not None:
                    bound = 1.0 / math.sqrt(layer.in_features) if layer.in_features > 0 else 0.0
                    torch.nn.init.uniform_(layer.bias, -bound, bound, generator=generator)
