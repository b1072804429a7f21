"""render=gsplat: a clear error without CUDA; agreement with splat_torch where CUDA and gsplat exist."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sync4d.errors import ConfigError
from sync4d.registry import available, build
from sync4d.render.camera import look_at
from sync4d.render.gsplat_backend import gsplat_unavailable_reason


def test_gsplat_is_registered() -> None:
    assert {"gsplat", "splat_torch"} <= set(available("render"))


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA; the no-CUDA error cannot occur")
def test_selecting_gsplat_without_cuda_stops_with_one_clear_line() -> None:
    with pytest.raises(ConfigError) as err:
        build("render", {"type": "gsplat"}, device="cpu")
    message = str(err.value)
    assert "\n" not in message
    assert "CUDA" in message and "render=splat_torch" in message


@pytest.mark.skipif(gsplat_unavailable_reason() is not None, reason=f"{gsplat_unavailable_reason()}")
def test_gsplat_agrees_with_splat_torch() -> None:
    rng = np.random.default_rng(0)
    n = 2000
    cam = look_at((1.6, -1.9, 1.3), (0, 0, 0), (0, 0, 1), 40.0, 128, 96)
    means = rng.uniform(-0.5, 0.5, (n, 3))
    A = rng.normal(size=(n, 3, 3)) * 0.01
    covs = A @ A.transpose(0, 2, 1) + 1e-5 * np.eye(3)
    sh = rng.normal(scale=0.5, size=(n, 4, 3))
    opac = rng.uniform(0.2, 0.9, n)
    ours = build("render", {"type": "splat_torch"}, device="cpu").render_full(means, covs, sh, opac, cam)
    theirs = build("render", {"type": "gsplat"}, device="cuda").render_full(means, covs, sh, opac, cam)
    # Footprint details differ (16x16 tiles with an eigenvalue radius, early stop at T < 1e-4): a few
    # 8-bit levels at most on average, and the same silhouette.
    assert np.abs(ours["rgb"] - theirs["rgb"]).mean() < 2e-3
    assert np.abs(ours["rgb"] - theirs["rgb"]).max() < 5e-2
    assert np.abs(ours["alpha"] - theirs["alpha"]).mean() < 2e-3
