"""Evaluation commands: ``python -m sync4d.evaluate <name> [options]``.

Each command is a module ``sync4d_tools.evaluate.<name>`` with ``main(argv: list[str] | None) -> dict``; it
prints one JSON object on the last line of stdout (the measured numbers) and returns it.
"""

from __future__ import annotations

import pkgutil
from pathlib import Path
from typing import Any

from sync4d.errors import ConfigError, InputError

ROOT = Path(__file__).resolve().parents[2]


def commands() -> list[str]:
    """Names of the available evaluation commands (modules of this package not starting with ``_``)."""
    return sorted(m.name for m in pkgutil.iter_modules([str(Path(__file__).parent)]) if not m.name.startswith("_"))


def mapping(conf: object, what: str) -> dict[str, Any]:
    """Plain values of an OmegaConf mapping (what ``OmegaConf.load`` or ``merge`` returned); a list (a YAML file
    that is no mapping) is a :class:`ConfigError` naming ``what``."""
    from omegaconf import OmegaConf

    values = OmegaConf.to_container(conf, resolve=True) if OmegaConf.is_config(conf) else conf
    if not isinstance(values, dict):
        raise ConfigError(f"{what}: expected a mapping of options, got {type(values).__name__}")
    return {str(k): v for k, v in values.items()}


def component_options(group: str, name: str, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The options of ``conf/<group>/<name>.yaml`` as ``python train.py`` composes them (without the Hydra
    schema entry: the typed Config holds the defaults), ``overrides`` merged in, as plain values."""
    from omegaconf import OmegaConf

    path = ROOT / "conf" / group / f"{name}.yaml"
    conf = mapping(OmegaConf.load(path), str(path))
    conf.pop("defaults", None)
    return mapping(OmegaConf.merge(conf, overrides or {}), f"{path} with overrides")


def dotlist(items: list[str], *, option: str) -> dict[str, Any]:
    """``KEY=VALUE`` command-line overrides (dotted keys, YAML values) as a nested dict; an item without ``=``
    is an :class:`InputError` naming ``option``."""
    from omegaconf import OmegaConf

    bad = [item for item in items if "=" not in item or item.startswith("=")]
    if bad:
        raise InputError(f"{option} {bad[0]!r}: expected KEY=VALUE (a dotted key, a YAML value)")
    values = OmegaConf.to_container(OmegaConf.from_dotlist(items))
    assert isinstance(values, dict)
    return {str(k): v for k, v in values.items()}
