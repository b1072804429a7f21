"""Stage cache: expensive stage outputs stored under ``outputs/cache/<stage>/<hash>/``.

The key hashes the stage's own config and the keys of its inputs, so an E/nu sweep reuses the
reconstruction and the part map. Values are frozen dataclasses of arrays (``sync4d.types``), stored as
``.npz`` plus a JSON of the non-array fields, written atomically.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from sync4d.io.atomic import atomic_save_npz, atomic_write_json

log = logging.getLogger(__name__)
T = TypeVar("T")
CACHE_VERSION = 2  # bump when a stage's algorithm changes so old entries are not reused


def stage_key(stage: str, *parts: Any) -> str:
    """A short stable hash of a stage name and JSON-serialisable parts (configs, upstream keys)."""
    blob = json.dumps([CACHE_VERSION, stage, *parts], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def save(folder: Path, value: Any) -> None:
    """Store a dataclass of arrays/scalars/strings/tuples (None allowed) in ``folder``."""
    arrays, meta = {}, {"__class__": type(value).__name__}
    for f in dataclasses.fields(value):
        item = getattr(value, f.name)
        if isinstance(item, np.ndarray):
            arrays[f.name] = item
        elif isinstance(item, dict):
            continue
        else:
            meta[f.name] = list(item) if isinstance(item, tuple) else item
    folder.mkdir(parents=True, exist_ok=True)
    atomic_save_npz(folder / "arrays.npz", **arrays)
    atomic_write_json(folder / "meta.json", meta)


def load(folder: Path, cls: type[T]) -> T | None:
    """Load a value stored by :func:`save`, or None when absent or unreadable."""
    try:
        meta = json.loads((folder / "meta.json").read_text())
        with np.load(folder / "arrays.npz") as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, KeyError):
        return None
    if meta.pop("__class__", None) != cls.__name__:
        return None
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        if f.name in arrays:
            kwargs[f.name] = arrays[f.name]
        elif f.name in meta:
            item = meta[f.name]
            kwargs[f.name] = tuple(item) if isinstance(item, list) else item
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:  # type: ignore[misc]
            kwargs[f.name] = None
    return cls(**kwargs)


def cached(root: Path, stage: str, key: str, cls: type[T], compute: Any, *, enabled: bool = True) -> T:
    """Return the cached value for ``stage``/``key`` or compute, store and return it."""
    folder = root / stage / key
    if enabled:
        hit = load(folder, cls)
        if hit is not None:
            log.info("%s: reusing cache %s", stage, folder)
            return hit
    value = compute()
    if enabled:
        save(folder, value)
    return value
