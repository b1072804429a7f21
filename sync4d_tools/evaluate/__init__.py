"""Evaluation commands: ``python -m sync4d.evaluate <name> [options]``.

Each command is a module ``sync4d_tools.evaluate.<name>`` with ``main(argv: list[str] | None) -> dict``; it
prints one JSON object on the last line of stdout (the measured numbers) and returns it.
"""

from __future__ import annotations

import pkgutil
from pathlib import Path


def commands() -> list[str]:
    """Names of the available evaluation commands (modules of this package not starting with ``_``)."""
    return sorted(m.name for m in pkgutil.iter_modules([str(Path(__file__).parent)]) if not m.name.startswith("_"))
