"""Command-line checks that run before Hydra, so common mistakes get one readable line."""

from __future__ import annotations

import sys
from pathlib import Path

from sync4d.registry import GROUPS

CONFIG_GROUPS = (*GROUPS, "experiment", "debug")


def group_options(conf_dir: Path, group: str) -> list[str]:
    """Names of the YAML options of a config group folder."""
    folder = conf_dir / group
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


def check_group_choices(argv: list[str], conf_dir: Path) -> None:
    """Exit with code 2 and one line when an override selects an option that does not exist.

    Hydra would report the same with a multi-line message; this names the group, the bad value and the
    available options on one line (e.g. ``sim=does_not_exist``). Sweeps (``sim=a,b``) are checked per value.
    """
    for arg in argv:
        if "=" not in arg or arg.startswith(("-", "hydra.", "hydra/")):
            continue
        key, value = arg.split("=", 1)
        group = key.lstrip("+~")
        if group not in CONFIG_GROUPS or value in ("", "null"):
            continue
        options = group_options(conf_dir, group)
        for choice in value.split(","):
            if choice not in options:
                print(f"sync4d: unknown {group} '{choice}'; available: {', '.join(options)}", file=sys.stderr)
                raise SystemExit(2)
