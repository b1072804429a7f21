"""Each registered component's typed ``Config`` as the Hydra schema of its YAML option.

The dataclass is the one source of a component's defaults; ``conf/<group>/<name>.yaml`` names its
schema first in its defaults list (``- schema_<name>``) and then states only deliberate deviations.
Hydra thus knows every key (``sim.E=0`` overrides a key the YAML never mentions; ``--cfg job`` prints
them all) and refuses unknown ones, while the values come from the code.

A plugin's components (registered outside ``sync4d``) become options too, with no file in the project's
``conf/``: the YAML its package ships as ``conf/<group>/<name>.yaml`` (beside the package's ``__init__.py``),
else an option that is its schema alone. So an installed plugin is selectable as ``target=box``.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from sync4d.registry import GROUPS, available, lookup, omegaconf_schema

#: The classes whose schema (and, for a plugin, option) is in the ConfigStore.
_stored: set[type] = set()


def schema_name(name: str) -> str:
    """The ConfigStore option holding component ``name``'s schema (``schema_mpm_warp``)."""
    return f"schema_{name}"


def register_schemas() -> None:
    """Store every registered component's schema under ``<group>/schema_<name>``, and a plugin component's
    option under ``<group>/<name>`` (idempotent; a component registered since the last call is added).

    Call before Hydra composes (``train.py``, the command-line checks, tests); the registry loads the plugins
    first.
    """
    store = ConfigStore.instance()
    if not _stored:
        from sync4d.match import MatchConfig
        from sync4d.transfer import TransferConfig

        store.store(group="match", name="defaults", node=omegaconf_schema(MatchConfig))
        store.store(group="transfer", name="defaults", node=omegaconf_schema(TransferConfig))
    for group in GROUPS:
        for name in available(group):
            cls = lookup(group, name)
            if cls in _stored:
                continue
            schema = omegaconf_schema(cls.Config)  # type: ignore[attr-defined]
            node = dataclasses.make_dataclass(
                f"{schema.__name__}_{group}_{name}", [("type", str, dataclasses.field(default=name))], bases=(schema,)
            )
            store.store(group=group, name=schema_name(name), node=node)
            if cls.__module__.split(".")[0] != "sync4d":  # a plugin's option; the built-ins' YAML is in conf/
                store.store(group=group, name=name, node=plugin_option(group, name, cls.__module__))
            _stored.add(cls)


def plugin_option(group: str, name: str, module: str) -> DictConfig:
    """The option ``group/name`` of a plugin component defined in ``module``: the YAML its top-level package
    ships as ``conf/<group>/<name>.yaml``, else its schema with nothing changed."""
    yaml: Any = None
    try:
        yaml = importlib.resources.files(module.split(".")[0]).joinpath("conf", group, f"{name}.yaml")
    except (ModuleNotFoundError, TypeError):  # no package (a bare module) or no files to read
        pass
    if yaml is not None and yaml.is_file():
        option = OmegaConf.create(yaml.read_text())
        assert isinstance(option, DictConfig), f"{yaml}: a YAML mapping expected"
        return option
    return OmegaConf.create({"defaults": [schema_name(name), "_self_"]})
