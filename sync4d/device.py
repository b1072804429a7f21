"""Device names: one config value (``device: cpu`` or ``cuda``/``cuda:N``) mapped to torch and Warp."""

from __future__ import annotations

from sync4d.errors import ConfigError


def torch_device(device: str) -> str:
    """Torch device string for a config ``device`` value."""
    import torch

    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device={device}: CUDA is not available on this machine; use device=cpu")
    return device if device != "cuda" else "cuda:0"


def warp_device(device: str) -> str:
    """Warp device string for a config ``device`` value (Warp is initialised on first use)."""
    import warp as wp

    wp.init()
    name = "cuda:0" if device == "cuda" else device
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise ConfigError(f"device={device}: Warp finds no CUDA device here; use device=cpu")
    return name
