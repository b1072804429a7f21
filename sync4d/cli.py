"""Command-line checks that run before Hydra, so common mistakes get one readable line."""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

from sync4d.registry import GROUPS, available

CONFIG_GROUPS = (*GROUPS, "experiment", "debug")


def group_options(conf_dir: Path, group: str) -> list[str]:
    """Names of the YAML options of a config group folder."""
    folder = conf_dir / group
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


def choices(conf_dir: Path, group: str) -> list[str]:
    """What ``group=<name>`` may select: the group's YAML options and, for a registry group, every registered
    component (a plugin's options come with it: :mod:`sync4d.config_schemas`)."""
    registered = available(group) if group in GROUPS else []
    return sorted({*group_options(conf_dir, group), *registered})


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
        options = choices(conf_dir, group)
        for choice in value.split(","):
            if choice not in options:
                print(f"sync4d: unknown {group} '{choice}'; available: {', '.join(options)}", file=sys.stderr)
                raise SystemExit(2)


def _fail(message: str) -> None:
    """Print one ``sync4d:`` line on stderr and exit with code 2."""
    print("sync4d: " + "; ".join(line.strip() for line in message.splitlines() if line.strip()), file=sys.stderr)
    raise SystemExit(2)


def _is_sweep(argv: list[str]) -> bool:
    """A multirun (``-m``) or an override with sweep syntax: composed per job by Hydra, not checked here."""
    if any(arg in ("-m", "--multirun") for arg in argv):
        return True
    values = [arg.split("=", 1)[1] for arg in argv if "=" in arg]
    functions = ("range(", "choice(", "glob(", "interval(", "tag(")
    return any(("," in v and not v.lstrip().startswith(("[", "{", "'", '"'))) or v.startswith(functions) for v in values)


def check_overrides(argv: list[str], conf_dir: Path) -> None:
    """Compose the config once before Hydra runs; a bad override (unknown key, bad syntax) gives one line.

    Hydra reports these with several lines and exit code 1; here the line names the override and the
    reason, e.g. ``sim.nuu=0.3``. Skipped for flags (``--cfg``, ``--help``), sweeps and ``HYDRA_FULL_ERROR=1``.
    """
    if any(arg.startswith("-") for arg in argv) or _is_sweep(argv) or os.environ.get("HYDRA_FULL_ERROR") == "1":
        return  # HYDRA_FULL_ERROR=1: let Hydra report it with the full detail
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    overrides = [arg for arg in argv if not arg.lstrip("+~").startswith(("hydra.", "hydra/"))]
    from sync4d.config_schemas import register_schemas

    register_schemas()
    try:
        with initialize_config_dir(config_dir=str(conf_dir), version_base="1.3"):
            compose(config_name="config", overrides=overrides)
    except (HydraException, OmegaConfBaseException) as err:
        cause = err.__cause__ or err.__context__
        reason = str(cause).splitlines()[0] if cause is not None and str(cause).strip() else ""
        unknown = re.search(r"Could not override '([\w.]+)'", str(err))
        if unknown and ("not in struct" in reason or " not in '" in reason):
            key = unknown.group(1)
            _fail(f"bad override {key}: no such key (check the spelling; `python train.py --cfg job` prints every "
                  "key; `+key=value` adds a new one)")
        _fail(f"bad override: {str(err).splitlines()[0].rstrip('.')}{'; ' + reason if reason else ''}")


def check_run_dir(argv: list[str]) -> None:
    """Refuse, before Hydra writes anything, an explicit ``hydra.run.dir`` holding another run's outputs.

    The same check runs inside the pipeline for folders Hydra chooses itself (``outputs/<name>/<time>``).
    """
    values = dict(arg.split("=", 1) for arg in argv if "=" in arg and not arg.startswith("-"))
    run_dir = values.get("hydra.run.dir")
    if not run_dir or any(arg in ("-m", "--multirun") for arg in argv):
        return
    from sync4d.errors import Sync4DError
    from sync4d.run.pipeline import claim_run_dir

    resume = values.get("resume")
    try:
        claim_run_dir(Path(run_dir).expanduser(), None if resume in (None, "", "null") else resume)
    except Sync4DError as err:
        _fail(f"{type(err).__name__}: {err}")


def check_command_line(argv: list[str], conf_dir: Path) -> None:
    """All checks that run before Hydra: group choices, overrides, and the run folder."""
    check_group_choices(argv, conf_dir)
    check_overrides(argv, conf_dir)
    check_run_dir(argv)
