"""Where the project's files are: its root (the folder holding ``sync4d/``, ``conf/``, ``data/``, ``models/``,
``plugins/``, ``outputs/``) and the one way a data path in a config is found."""

from __future__ import annotations

from pathlib import Path

from sync4d.errors import DataMissingError

PROJECT_ROOT = Path(__file__).resolve().parent.parent


def resolve_path(path: str, *, what: str) -> Path:
    """An existing path: as given (relative to the working directory; Hydra keeps it) or relative to the project
    root.

    Raises:
        DataMissingError: neither exists; names ``what`` and both places tried.
    """
    p = Path(path).expanduser()
    if p.exists():
        return p
    alt = PROJECT_ROOT / path
    if not p.is_absolute() and alt.exists():
        return alt
    raise DataMissingError(f"{what} not found: {path} (also tried {alt}); check the path or fetch the data")
