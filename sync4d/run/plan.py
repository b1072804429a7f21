"""One typed, immutable plan per run, built once from the composed config before any stage runs.

Every check that needs no data happens here, in milliseconds: mandatory values, top-level options, the
device, every component's typed ``Config`` (unknown keys, wrong types, ranges), the match and transfer
blocks, and ``debug=smoke``'s shrink values. The stages receive the plan's typed blocks and never read the
raw config; the raw config is read here only.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import time
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from omegaconf import DictConfig, OmegaConf

from sync4d.errors import ConfigError
from sync4d.interfaces import BoundedFrames
from sync4d.paths import PROJECT_ROOT
from sync4d.match import MatchConfig
from sync4d.registry import GROUPS, Component, available, component, lookup, plain_dict, typed_config
from sync4d.transfer.config import TransferConfig

log = logging.getLogger("sync4d")
#: Top-level keys that do not change a run's results (excluded from the resume fingerprint).
NOT_RESULTS = ("resume", "name", "cache", "cache_dir", "render", "logger", "hydra", "run_dir")
#: The run's own typed blocks beside the component groups.
BLOCKS: dict[str, type] = {"match": MatchConfig, "transfer": TransferConfig}


@dataclass(frozen=True)
class RunPlan:
    """Everything one run does, typed; built by :func:`build_plan`.

    Attributes:
        name: the run's name (its folder under ``outputs/``); seed: seeds python, numpy, torch and every
            stage's generators; device: ``cpu`` or ``cuda[:N]``.
        frames: output frames T; loop_reference: loop the reference when T exceeds it.
        pivot: ``joint`` (each target part turns about its joint with its parent part, carried by it, the root
            about its own centroid), ``part_centroid`` (each target part turns about its own centroid) or ``bone``.
        budget: ``off`` or ``auto`` (size the simulation from the scene).
        resume: the folder of an interrupted run to continue, or None.
        cache: reuse cached reconstructions and matches; cache_root: where they live.
        self_transfer: the target is the reference's own shape (a pose truth exists).
        render_video: render and export at the end.
        run_dir: the run's folder.
        components: the selected component of every group (``reference``, ``recon``, ``target``,
            ``features``, ``sim``, ``velocity``, ``render``, ``logger``).
        match: the match block; transfer: the transfer block.
        overrides: the command line's overrides (for hparams and reports).
        record: the settings that determine the results (a resume must match them).
    """

    name: str
    seed: int
    device: str
    frames: int
    loop_reference: bool
    pivot: Literal["joint", "part_centroid", "bone"]
    budget: Literal["off", "auto"]
    resume: str | None
    cache: bool
    cache_root: Path
    self_transfer: bool
    render_video: bool
    run_dir: Path
    components: Mapping[str, Component]
    match: MatchConfig
    transfer: TransferConfig
    overrides: Mapping[str, str]
    record: Mapping[str, Any]

    def __getitem__(self, group: str) -> Component:
        return self.components[group]

    def with_component(self, replaced: Component) -> RunPlan:
        """The plan with one group's component replaced (e.g. the simulator sized by ``budget=auto``)."""
        return dataclasses.replace(self, components={**self.components, replaced.group: replaced})


#: Top-level run options whose value must be one of a fixed set.
RUN_CHOICES = {"pivot": ("joint", "part_centroid", "bone"), "budget": ("off", "auto")}


def build_plan(cfg: DictConfig, *, explicit: set[str] | None = None) -> RunPlan:
    """The run's plan from its composed config; every user error is a :class:`ConfigError` naming the key.

    Args:
        cfg: the composed Hydra config.
        explicit: the dotted keys the user set on the command line (``debug=smoke``'s shrink never replaces
            them); None reads them from Hydra.
    """
    check_run_config(cfg)
    check_device(str(cfg.device))
    explicit = overridden_keys(cfg) if explicit is None else explicit
    shrink = plain_dict(cfg.shrink) if cfg.get("shrink") else {}
    check_shrink(shrink)
    components = {group: component(group, shrunk(group, plain_dict(cfg[group]), shrink.get(group), explicit))
                  for group in GROUPS if group in cfg}
    if "reference.max_frames" not in explicit:  # reference.max_frames=0 typed by the user means every frame
        components["reference"] = bound_reference_frames(components["reference"], int(cfg.frames))
    blocks = {block: typed_config(schema, shrunk(block, plain_dict(cfg[block]), shrink.get(block), explicit),
                                  where=block, label=block).validate() for block, schema in BLOCKS.items()}
    return RunPlan(
        name=str(cfg.name), seed=int(cfg.seed), device=str(cfg.device), frames=int(cfg.frames),
        loop_reference=bool(cfg.loop_reference), pivot=cfg.pivot, budget=cfg.budget,
        resume=None if cfg.get("resume") is None else str(cfg.resume), cache=bool(cfg.cache),
        cache_root=Path(cfg.cache_dir) if cfg.get("cache_dir") else PROJECT_ROOT / "outputs" / "cache",
        self_transfer=bool(cfg.self_transfer), render_video=bool(cfg.render_video), run_dir=run_dir_of(cfg),
        components=components, match=blocks["match"], transfer=blocks["transfer"], overrides=overrides_of(cfg),
        record=results_record(cfg),
    )  # fmt: skip


def check_run_config(cfg: DictConfig) -> None:
    """Reject missing mandatory values (``???``) and malformed top-level values with one line each."""
    missing = sorted(OmegaConf.missing_keys(cfg))
    if missing:
        key = missing[0]
        raise ConfigError(f"{key}: a value is required (it is ??? in the config); set it, e.g. {key}=<value>"
                          + (f" (also missing: {', '.join(missing[1:])})" if len(missing) > 1 else ""))
    for key, minimum in (("frames", 1), ("seed", 0)):
        value = cfg.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise ConfigError(f"{key}={value!r}: must be an integer >= {minimum}")
    resume = cfg.get("resume")
    if resume is not None and not isinstance(resume, str):
        raise ConfigError(f"resume={resume!r}: must be the folder of an interrupted run")
    for key, allowed in RUN_CHOICES.items():
        if str(cfg.get(key)) not in allowed:
            raise ConfigError(f"{key}={cfg.get(key)!r}: must be one of {', '.join(allowed)}")


def check_device(device: str) -> None:
    """Refuse a ``device`` that is not ``cpu``, ``cuda`` or ``cuda:N``, or a CUDA device this machine lacks."""
    if device == "cpu":
        return
    if not re.fullmatch(r"cuda(:\d+)?", device):
        raise ConfigError(f"device={device}: unknown device; use device=cpu, or device=cuda / cuda:N on a CUDA machine")
    import torch

    index = int(device.partition(":")[2] or 0)
    if not torch.cuda.is_available() or index >= torch.cuda.device_count():
        found = torch.cuda.device_count() if torch.cuda.is_available() else 0
        raise ConfigError(f"device={device}: this machine has {found} CUDA device(s); use device=cpu")


def bound_reference_frames(reference: Component, frames: int) -> Component:
    """A reference that reads frames from a file (``max_frames`` 0 = all) reads, and so reconstructs, only the
    ``frames`` the run uses; a ``max_frames`` the user set wins. The log says which key bounds it."""
    if not isinstance(reference.config, BoundedFrames) or reference.config.max_frames != 0:
        return reference
    log.info("reference=%s: reconstructing the first %d frames, the ones the run uses (frames=%d); set "
             "reference.max_frames to reconstruct more", reference.name, frames, frames)
    return reference.with_values(max_frames=frames)


# ---------------------------------------------------------------------------------------------- shrink


def flatten(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dicts as one dict of dotted keys (``{"a": {"b": 1}}`` -> ``{"a.b": 1}``)."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        dotted = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, Mapping):
            out.update(flatten(value, dotted))
        else:
            out[dotted] = value
    return out


def field_path(config: type, dotted: str) -> bool:
    """Whether a dataclass ``config`` has the (possibly nested) field ``dotted``."""
    head, _, rest = dotted.partition(".")
    fields = {f.name for f in dataclasses.fields(config)}
    if head not in fields:
        return False
    if not rest:
        return True
    hint = typing.get_type_hints(config)[head]
    return dataclasses.is_dataclass(hint) and field_path(hint, rest)  # type: ignore[arg-type]


def schemas_of(group: str) -> list[type]:
    """The Config dataclasses a group or block can hold (every registered component's, or the block's)."""
    if group in BLOCKS:
        return [BLOCKS[group]]
    return [lookup(group, name).Config for name in available(group)]  # type: ignore[attr-defined]


def check_shrink(shrink: Mapping[str, Any]) -> None:
    """Every ``shrink.<group>.<key>`` must name a field of some component of that group (or of a block)."""
    for group, values in shrink.items():
        if group not in GROUPS and group not in BLOCKS:
            raise ConfigError(f"shrink.{group}: no such group or block; use one of {', '.join([*GROUPS, *BLOCKS])}")
        for key in flatten(values or {}):
            if not any(field_path(schema, key) for schema in schemas_of(group)):
                raise ConfigError(f"shrink.{group}.{key}: no {group} component has that field; fix debug/*.yaml")


def shrunk(group: str, values: dict[str, Any], shrink: Mapping[str, Any] | None, explicit: set[str]) -> dict[str, Any]:
    """``values`` with the shrink values the selected component has a field for, except keys the user set.

    A scalar shrink value for a list field is applied to every element (``iterations: 30`` against a
    per-level ``[250, 150]`` gives ``[30, 30]``).
    """
    if not shrink:
        return values
    schema = lookup(group, str(values["type"])).Config if group not in BLOCKS else BLOCKS[group]  # type: ignore[attr-defined]
    out = OmegaConf.create(values)
    for key, value in flatten(shrink).items():
        if f"{group}.{key}" in explicit or not field_path(schema, key):
            continue
        current = OmegaConf.select(out, key)
        if current is None:
            current = default_of(schema, key)
        if isinstance(current, (list, tuple)) or OmegaConf.is_list(current):
            value = value if isinstance(value, (list, tuple)) else [value] * len(current)
        OmegaConf.update(out, key, value, force_add=True)
    return plain_dict(out)


def default_of(schema: type, dotted: str) -> Any:
    """The default of a (possibly nested) field of a dataclass, or None when it has none."""
    head, _, rest = dotted.partition(".")
    f = next(f for f in dataclasses.fields(schema) if f.name == head)
    if f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
    else:
        return None
    return default_of(type(value), rest) if rest and dataclasses.is_dataclass(value) else value


# ---------------------------------------------------------------------------------------------- the run


def overridden_keys(cfg: DictConfig) -> set[str]:
    """The keys the command line set (``sim.E=5e4`` -> ``sim.E``): from Hydra, or from a config composed with
    ``return_hydra_config=True``."""
    return {key.lstrip("+~") for key in overrides_of(cfg)}


def command_line_overrides(cfg: DictConfig) -> list[str]:
    """The command line's overrides as Hydra recorded them."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return list(HydraConfig.get().overrides.task)
    task = OmegaConf.select(cfg, "hydra.overrides.task")
    return [] if task is None else [str(item) for item in task]


def overrides_of(cfg: DictConfig) -> dict[str, str]:
    """The command-line overrides of this run as a dict (for hparams and reports)."""
    out = {}
    for item in command_line_overrides(cfg):
        key, _, value = item.partition("=")
        out[key.lstrip("+~")] = value
    return out


def run_dir_of(cfg: DictConfig) -> Path:
    """The run folder: Hydra's output dir when under Hydra, else ``cfg.run_dir`` or a new timestamped one."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    return Path(cfg.get("run_dir") or PROJECT_ROOT / "outputs" / cfg.name / time.strftime("%Y-%m-%d_%H-%M-%S"))


def results_record(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config minus keys that do not change results: what a resume must match."""
    return {str(k): plain_value(cfg[k]) for k in cfg if str(k) not in NOT_RESULTS}


def plain_value(node: Any) -> Any:
    """A config node as plain, resolved Python values."""
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
