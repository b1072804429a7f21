"""Registries: typed configs, clear errors for duplicates, unknown names, bad keys, failing plugins."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from sync4d import plugins, registry
from sync4d.errors import ConfigError, PluginImportError, RegistryError
from sync4d.registry import available, build, register, unregister

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def toy_component():
    @register("velocity", "_test_toy")
    class Toy:
        @dataclass
        class Config:
            gain: float = 1.0
            steps: int = 3

        def __init__(self, cfg, **deps):
            self.cfg, self.deps = cfg, deps

    yield Toy
    unregister("velocity", "_test_toy")


def test_build_merges_yaml_into_typed_config(toy_component):
    obj = build("velocity", {"type": "_test_toy", "gain": 2.5}, num_parts=3)
    assert isinstance(obj, toy_component)
    assert obj.cfg.gain == 2.5 and obj.cfg.steps == 3
    assert obj.deps == {"num_parts": 3}


def test_unknown_key_names_the_key(toy_component):
    with pytest.raises(ConfigError, match=r"velocity\.gian: unknown key.*known keys: gain, steps"):
        build("velocity", {"type": "_test_toy", "gian": 2.5})


def test_wrong_type_names_the_key(toy_component):
    with pytest.raises(ConfigError, match=r"velocity\.steps"):
        build("velocity", {"type": "_test_toy", "steps": "many"})


def test_unknown_name_lists_available():
    with pytest.raises(RegistryError, match=r"unknown sim 'does_not_exist'; available: .*mpm_warp"):
        build("sim", {"type": "does_not_exist"})


def test_duplicate_registration_is_refused(toy_component):
    with pytest.raises(RegistryError, match="registered twice"):
        @register("velocity", "_test_toy")
        class Other:
            @dataclass
            class Config:
                pass


def test_component_without_config_is_refused():
    with pytest.raises(RegistryError, match="needs a nested dataclass `Config`"):
        @register("velocity", "_no_config")
        class Bare:
            pass


def test_every_group_has_components():
    for group in registry.GROUPS:
        assert available(group), f"no component registered in group {group}"


def test_failing_plugin_stops_with_its_name(tmp_path):
    bad = tmp_path / "broken_plugin"
    bad.mkdir()
    (bad / "__init__.py").write_text("import not_a_real_module_xyz\n")
    with pytest.raises(PluginImportError, match=r"plugin 'broken_plugin'.*ModuleNotFoundError.*not_a_real_module_xyz"):
        plugins.load_plugin_dir(tmp_path)


def test_plugin_dir_registers_components_and_their_options(tmp_path):
    """A package in the plugin folder registers its components; its conf/<group>/<name>.yaml is an option, and a
    component without one is selectable as its schema."""
    from hydra import compose, initialize_config_dir

    from sync4d.config_schemas import register_schemas

    good = tmp_path / "good_plugin"
    (good / "conf" / "logger").mkdir(parents=True)
    (good / "__init__.py").write_text(
        "from dataclasses import dataclass\n"
        "from sync4d.registry import register\n"
        "@register('logger', '_from_plugin_dir')\n"
        "class L:\n"
        "    @dataclass\n"
        "    class Config:\n"
        "        level: int = 1\n"
        "        name: str = 'plain'\n"
        "@register('logger', '_without_yaml')\n"
        "class Bare:\n"
        "    @dataclass\n"
        "    class Config:\n"
        "        level: int = 1\n"
    )
    (good / "conf" / "logger" / "_from_plugin_dir.yaml").write_text(
        "defaults:\n  - schema__from_plugin_dir\n  - _self_\ntype: _from_plugin_dir\nlevel: 2\n")
    try:
        assert plugins.load_plugin_dir(tmp_path) == ["good_plugin"]
        assert "_from_plugin_dir" in available("logger")
        register_schemas()
        with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
            logger = compose(config_name="config", overrides=["logger=_from_plugin_dir", "logger.name=x"]).logger
            bare = compose(config_name="config", overrides=["logger=_without_yaml"]).logger  # its schema alone
        assert (logger.type, logger.level, logger.name) == ("_from_plugin_dir", 2, "x")
        assert (bare.type, bare.level) == ("_without_yaml", 1)
    finally:
        unregister("logger", "_from_plugin_dir")
        unregister("logger", "_without_yaml")


def test_optional_capabilities_are_declared_by_the_builtins():
    """The capability Protocols of sync4d/interfaces.py say what each built-in can do."""
    from sync4d.interfaces import BoundedFrames, CheckedTarget, TargetWithSurface, VideoLogger
    from sync4d.registry import lookup

    assert issubclass(lookup("target", "ply"), CheckedTarget) and not issubclass(lookup("target", "ply"), TargetWithSurface)
    assert all(issubclass(lookup("target", name), TargetWithSurface) for name in ("shell", "laptop", "cross", "mesh"))
    assert issubclass(lookup("logger", "tensorboard"), VideoLogger) and not issubclass(lookup("logger", "none"), VideoLogger)
    assert isinstance(lookup("reference", "video").Config(), BoundedFrames)
    assert not isinstance(lookup("reference", "laptop").Config(), BoundedFrames)
