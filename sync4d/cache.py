"""Stage cache: expensive stage outputs stored under ``outputs/cache/<stage>/<hash>/``.

The key hashes the stage's own config, the keys of its inputs and the source of the code that computes
it (:func:`code_hash`: the component's modules and every ``sync4d`` module they import, transitively),
so an E/nu sweep reuses the reconstruction and the part map while an edit to the reconstruction's code
does not reuse a stale one. Values are frozen dataclasses of arrays (``sync4d.types``), stored as
``.npz`` plus a JSON of the non-array fields, written atomically.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import hashlib
import importlib.util
import inspect
import json
import logging
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from sync4d.io.atomic import atomic_save_npz, atomic_write_json

log = logging.getLogger(__name__)
T = TypeVar("T")
PACKAGE = "sync4d"


def stage_key(stage: str, *parts: Any) -> str:
    """A short stable hash of a stage name and JSON-serialisable parts (configs, upstream keys, code hashes)."""
    blob = json.dumps([stage, *parts], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def code_hash(*objects: Any) -> str:
    """Hash of the source of the modules defining ``objects`` (classes, functions or modules) and of every
    ``sync4d`` module they import, directly or not (function-level imports included)."""
    names: set[str] = set()
    for obj in objects:
        module = obj if inspect.ismodule(obj) else inspect.getmodule(obj)
        if module is not None:
            names |= _import_closure(module.__name__)
    digest = hashlib.sha256()
    for name in sorted(names):
        digest.update(name.encode() + b"\0" + _source(name) + b"\0")
    return digest.hexdigest()[:16]


@functools.cache
def _source(module: str) -> bytes:
    spec = importlib.util.find_spec(module)
    return Path(spec.origin).read_bytes() if spec and spec.origin and spec.origin.endswith(".py") else b""


@functools.cache
def _import_closure(module: str) -> frozenset[str]:
    """``module`` and the ``sync4d`` modules it imports, transitively (read from the source, not run)."""
    seen: set[str] = set()
    todo = [module]
    while todo:
        name = todo.pop()
        if name in seen or not (name == PACKAGE or name.startswith(PACKAGE + ".")):
            continue
        source = _source(name)
        if not source and importlib.util.find_spec(name) is None:
            continue
        seen.add(name)
        todo.extend(_imports_of(name, source))
    return frozenset(seen)


def _imports_of(module: str, source: bytes) -> list[str]:
    """Module names a module's source imports (``from a import b`` yields ``a`` and ``a.b``)."""
    out: list[str] = []
    spec = importlib.util.find_spec(module)
    is_package = spec is not None and spec.origin is not None and Path(spec.origin).name == "__init__.py"
    package = module if _source(module) and is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            out.append(base)
            out += [f"{base}.{alias.name}" for alias in node.names]
    return [name for name in out if name.startswith(PACKAGE) and _is_module(name)]


@functools.cache
def _is_module(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def save(folder: Path, value: Any) -> None:
    """Store a dataclass of arrays/scalars/strings/tuples (None allowed) in ``folder``."""
    arrays: dict[str, np.ndarray] = {}
    meta: dict[str, Any] = {"__class__": type(value).__name__}
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
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
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
