"""The example plugin is discovered, built from its YAML, and makes a box of Gaussians."""

from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from sync4d.registry import available, build


def test_box_plugin_is_discovered_and_builds():
    repo_root = Path(__file__).resolve().parents[2]
    assert "box" in available("target")
    cfg = OmegaConf.load(repo_root / "conf/target/box.yaml")
    gaussians = build("target", cfg, device="cpu", seed=0).load()
    assert gaussians.num == cfg.num_surface + cfg.num_interior
    lo, hi = gaussians.means.min(0), gaussians.means.max(0)
    np.testing.assert_allclose(hi - lo, cfg.size, atol=0.02)
    assert lo[1] > -1e-6  # bottom face on y = 0
