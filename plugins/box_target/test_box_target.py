"""The example plugin is discovered, built from its YAML, and makes a box of Gaussians."""

from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

from sync4d.config_schemas import register_schemas
from sync4d.registry import available, build


def test_box_plugin_is_discovered_and_builds():
    repo_root = Path(__file__).resolve().parents[2]
    assert "box" in available("target")
    register_schemas()  # the Configs are the schemas of the YAML options: Hydra needs them before composing
    with initialize_config_dir(config_dir=str(repo_root / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["target=box"]).target  # the YAML over its Config schema
    gaussians = build("target", cfg, device="cpu", seed=0).load()
    assert gaussians.num == cfg.num_surface + cfg.num_interior
    lo, hi = gaussians.means.min(0), gaussians.means.max(0)
    np.testing.assert_allclose(hi - lo, cfg.size, atol=0.02)
    assert lo[1] > -1e-6  # bottom face on y = 0
