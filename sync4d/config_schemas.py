"""Each registered component's typed ``Config`` as the Hydra schema of its YAML option.

The dataclass is the one source of a component's defaults; ``conf/<group>/<name>.yaml`` names its
schema first in its defaults list (``- schema_<name>``) and then states only deliberate deviations.
Hydra thus knows every key (``sim.E=0`` overrides a key the YAML never mentions; ``--cfg job`` prints
them all) and refuses unknown ones, while the values come from the code.
"""

from __future__ import annotations

import dataclasses

from hydra.core.config_store import ConfigStore

from sync4d.registry import GROUPS, available, lookup, omegaconf_schema

_registered = False


def schema_name(name: str) -> str:
    """The ConfigStore option holding component ``name``'s schema (``schema_mpm_warp``)."""
    return f"schema_{name}"


def register_schemas() -> None:
    """Store every registered component's schema under ``<group>/schema_<name>`` (idempotent).

    Call before Hydra composes (``train.py``, the command-line checks, tests); loads the plugins first.
    """
    global _registered
    if _registered:
        return
    from sync4d.plugins import load_all

    load_all()
    store = ConfigStore.instance()
    for group in GROUPS:
        for name in available(group):
            cls = lookup(group, name)
            schema = omegaconf_schema(cls.Config)  # type: ignore[attr-defined]
            node = dataclasses.make_dataclass(
                f"{schema.__name__}_{group}_{name}", [("type", str, dataclasses.field(default=name))], bases=(schema,)
            )
            store.store(group=group, name=schema_name(name), node=node)
    from sync4d.match import MatchConfig
    from sync4d.transfer import TransferConfig

    store.store(group="match", name="defaults", node=omegaconf_schema(MatchConfig))
    store.store(group="transfer", name="defaults", node=omegaconf_schema(TransferConfig))
    _registered = True
