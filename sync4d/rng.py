"""Randomness passed in, never drawn from global state: generators made from the run's one ``seed``."""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager

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


@contextmanager
def deterministic_torch() -> Iterator[None]:
    """Torch's deterministic kernels inside the block, the caller's setting restored after.

    On the CPU some backward kernels (e.g. ``grid_sample``'s) accumulate from several threads in whatever order
    they finish, so repeated fits on two threads differ (docs/results/people_animals.md); with deterministic
    kernels a fit ends at its one-thread result every time, still using both threads. Ops without a
    deterministic kernel warn instead of failing.
    """
    enabled, warn_only = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(enabled, warn_only=warn_only)
