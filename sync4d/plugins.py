"""Plugin discovery: built-ins, then packages under ``plugins/``, then entry points ``sync4d.plugins``.

Built-in components live in the sub-packages named in :data:`BUILTIN_PACKAGES`; every module in them is
imported so that its ``@register`` decorators run (no central list to keep in sync). A third-party
plugin that fails to import stops the run with its name and the original error.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import logging
import pkgutil
import sys
from pathlib import Path

from sync4d.errors import PluginImportError
from sync4d.paths import PROJECT_ROOT

log = logging.getLogger(__name__)

BUILTIN_PACKAGES: tuple[str, ...] = (
    "sync4d.scenes",
    "sync4d.sources",
    "sync4d.recon",
    "sync4d.features",
    "sync4d.sim",
    "sync4d.velocity",
    "sync4d.render",
    "sync4d.loggers",
)
ENTRY_POINT_GROUP = "sync4d.plugins"
PLUGINS_DIR = PROJECT_ROOT / "plugins"


def _import_package_tree(package_name: str) -> None:
    package = importlib.import_module(package_name)
    for info in pkgutil.walk_packages(package.__path__, prefix=package_name + "."):
        if info.name.rsplit(".", 1)[-1].startswith("_"):
            continue  # private helpers (e.g. _kernels) are imported by their users
        importlib.import_module(info.name)


def load_builtins() -> None:
    """Import every built-in component module (errors here are bugs and propagate)."""
    for name in BUILTIN_PACKAGES:
        _import_package_tree(name)


def load_plugin_dir(plugins_dir: Path = PLUGINS_DIR) -> list[str]:
    """Import every package (folder with ``__init__.py``) under ``plugins_dir``.

    Returns:
        The names of the imported plugin packages.

    Raises:
        PluginImportError: a plugin failed to import; names it and the original error.
    """
    loaded: list[str] = []
    if not plugins_dir.is_dir():
        return loaded
    # Plugins are imported by their folder name with plugins_dir on sys.path, the same name pytest uses
    # when it collects a plugin's own tests, so a plugin is never imported (and registered) twice.
    if str(plugins_dir) not in sys.path:
        sys.path.insert(0, str(plugins_dir))
    for folder in sorted(p for p in plugins_dir.iterdir() if (p / "__init__.py").is_file()):
        try:
            importlib.import_module(folder.name)
        except Exception as err:  # noqa: BLE001 - any failure is reported with the plugin's name
            sys.modules.pop(folder.name, None)
            raise PluginImportError(
                f"plugin '{folder.name}' ({folder}) failed to import: {type(err).__name__}: {err}"
            ) from err
        loaded.append(folder.name)
    return loaded


def load_entry_points() -> list[str]:
    """Load installed plugins advertised under the entry-point group ``sync4d.plugins``."""
    loaded: list[str] = []
    for entry in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            entry.load()
        except Exception as err:  # noqa: BLE001
            raise PluginImportError(
                f"plugin entry point '{entry.name}' ({entry.value}) failed to import: {type(err).__name__}: {err}"
            ) from err
        loaded.append(entry.name)
    return loaded


def load_all() -> None:
    """Discover everything in order: built-ins, ``plugins/`` packages, entry points."""
    load_builtins()
    local = load_plugin_dir()
    external = load_entry_points()
    if local or external:
        log.debug("plugins loaded: %s", ", ".join(local + external))
