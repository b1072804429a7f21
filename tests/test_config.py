"""Every option of every config group composes and builds its typed Config; CLI checks are one line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from sync4d.cli import group_options
from sync4d.registry import GROUPS, make_config

ROOT = Path(__file__).resolve().parent.parent
CONF = ROOT / "conf"
OPTIONS = [(g, o) for g in (*GROUPS, "experiment", "debug") for o in group_options(CONF, g)]


@pytest.mark.parametrize(("group", "option"), OPTIONS, ids=[f"{g}={o}" for g, o in OPTIONS])
def test_every_option_composes(group, option):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"{group}={option}"])
    OmegaConf.resolve(cfg)
    if group in GROUPS:
        # Building the typed Config catches unknown keys and wrong types in the YAML (paths left as ??? are
        # filled by the user; give them a value here).
        values = OmegaConf.to_container(cfg[group])
        for key, value in list(values.items()):
            if value == "???":
                values[key] = "some/path"
        make_config(group, values)


def test_default_config_selects_the_embedded_scene():
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="config")
    assert cfg.reference.type == "laptop" and cfg.target.type == "shell" and cfg.sim.type == "mpm_warp"
    assert cfg.device == "cpu"


def test_unknown_component_is_one_readable_line():
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), "sim=does_not_exist"], capture_output=True, text=True, timeout=120,
        cwd=ROOT,
    )
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "unknown sim 'does_not_exist'" in lines[0] and "mpm_warp" in lines[0] and "lbs" in lines[0]


def _repeats(values: dict, defaults: object) -> list[str]:
    """Keys of ``values`` whose value equals the default the typed Config already holds."""
    out = []
    for key, value in values.items():
        if key in ("type", "defaults") or not hasattr(defaults, key):
            continue
        default = getattr(defaults, key)
        default = list(default) if isinstance(default, tuple) else default
        if value == default and type(value) is not bool or value is default:
            out.append(key)
    return out


def _yaml(path: Path) -> dict:
    values = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    assert isinstance(values, dict)
    return values


@pytest.mark.parametrize("group", GROUPS)
def test_no_group_yaml_repeats_a_default(group):
    """The typed Config is the one source of defaults: a YAML states only the component and its deviations."""
    from sync4d.registry import lookup

    for path in sorted((CONF / group).glob("*.yaml")):
        values = _yaml(path)
        if "type" not in values:
            continue
        repeated = _repeats(values, lookup(group, values["type"]).Config())
        assert not repeated, f"{path.relative_to(ROOT)} repeats the Config defaults of {repeated}: delete them"


@pytest.mark.parametrize("experiment", group_options(CONF, "experiment"))
def test_no_experiment_repeats_a_default(experiment):
    """An experiment states deviations only: from the selected components' Configs and from config.yaml."""
    from sync4d.registry import lookup

    values = _yaml(CONF / "experiment" / f"{experiment}.yaml")
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"experiment={experiment}"])
    top = _yaml(CONF / "config.yaml")
    repeated = [k for k, v in values.items() if k not in GROUPS and k in top and top[k] == v and k != "name"]
    for group in GROUPS:
        if isinstance(values.get(group), dict):
            defaults = lookup(group, cfg[group].type).Config()
            repeated += [f"{group}.{k}" for k in _repeats(values[group], defaults)]
    assert not repeated, f"experiment={experiment} repeats defaults {repeated}: delete them"


@pytest.mark.parametrize(("group", "option"), [(g, o) for g, o in OPTIONS if g in GROUPS])
def test_every_config_key_is_overridable(group, option):
    """Each option's composed node holds every field of its Config (its schema), so ``group.key=value`` works
    for keys the YAML does not mention."""
    import dataclasses

    from sync4d.registry import lookup

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"{group}={option}"])
    fields = {f.name for f in dataclasses.fields(lookup(group, cfg[group].type).Config)}
    assert fields <= set(cfg[group].keys()), f"{group}={option} lacks {sorted(fields - set(cfg[group].keys()))}"
