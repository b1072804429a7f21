"""The example plugin: its component makes a box of Gaussians, and its own YAML is the option ``target=box``.

``tests/test_plugins.py`` installs the package and runs ``python train.py target=box`` from the command line.
"""

import sys
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

PLUGIN = Path(__file__).resolve().parents[1]
if str(PLUGIN) not in sys.path:  # as installed: the package importable by its name
    sys.path.insert(0, str(PLUGIN))

from sync4d_box_target import BoxTarget  # noqa: E402

from sync4d.config_schemas import register_schemas  # noqa: E402
from sync4d.registry import available, build  # noqa: E402


def test_box_plugin_registers_its_option_and_builds():
    repo_root = PLUGIN.parents[1]
    assert "box" in available("target")
    register_schemas()  # the plugin's YAML (sync4d_box_target/conf/target/box.yaml) becomes the option target/box
    with initialize_config_dir(config_dir=str(repo_root / "conf"), version_base="1.3"):
        config = compose(config_name="config", overrides=["target=box"]).target  # the YAML over its Config schema
    assert config.type == "box" and list(config.size) == BoxTarget.Config().size
    gaussians = build("target", config, device="cpu", seed=0).load()
    assert gaussians.num == config.num_surface + config.num_interior
    lo, hi = gaussians.means.min(0), gaussians.means.max(0)
    np.testing.assert_allclose(hi - lo, config.size, atol=0.02)
    assert lo[1] > -1e-6  # bottom face on y = 0
