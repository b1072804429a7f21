"""Evaluation commands: ``python -m sync4d.evaluate <name> [options]``.

Each command is a module ``sync4d_tools.evaluate.<name>`` with ``main(argv: list[str] | None) -> dict``; it
prints one JSON object on the last line of stdout (the measured numbers) and returns it.
"""

from __future__ import annotations

import pkgutil
from pathlib import Path
from typing import Any

from sync4d.errors import InputError


def commands() -> list[str]:
    """Names of the available evaluation commands (modules of this package not starting with ``_``)."""
    return sorted(m.name for m in pkgutil.iter_modules([str(Path(__file__).parent)]) if not m.name.startswith("_"))


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
