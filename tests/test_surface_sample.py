"""The matching surface of a splat: bounded, evenly spread, opaque, deterministic."""

from __future__ import annotations

import numpy as np

from sync4d.surface import SURFACE_POINTS, splat_surface, spread_sample


def test_sample_is_bounded_and_covers_thin_parts_a_random_sample_misses():
    rng = np.random.default_rng(0)
    body = rng.normal(size=(200_000, 3)) * 0.05                     # a dense blob
    limb = np.c_[np.linspace(0.2, 0.6, 400), np.zeros(400), np.zeros(400)]  # a thin, sparse limb
    pts = np.concatenate([body, limb])
    idx = spread_sample(pts, np.ones(len(pts)), 2000)
    assert 1500 <= len(idx) <= 2000 and np.all(np.diff(idx) > 0)
    on_limb = (idx >= len(body)).sum()
    assert on_limb >= 15                                            # a random 2000 would hold ~4
    np.testing.assert_array_equal(idx, spread_sample(pts, np.ones(len(pts)), 2000))


def test_splat_surface_prefers_opaque_gaussians_and_keeps_small_splats_whole():
    rng = np.random.default_rng(1)
    pts = rng.random((50_000, 3))
    opacity = np.where(np.arange(50_000) % 2 == 0, 0.9, 0.01)
    surface = splat_surface(pts, opacity)
    assert len(surface) <= SURFACE_POINTS
    faint = {tuple(p) for p in pts[opacity < 0.1]}
    assert not any(tuple(p) in faint for p in surface)
    assert len(splat_surface(pts[:100], np.full(100, 0.5))) == 100
