"""Component registries selected by Hydra config groups.

A component is a class with a nested ``Config`` dataclass, registered under a group and a short name::

    @register("sim", "mpm_warp")
    class MPMWarp:
        @dataclass
        class Config:
            E: float = 1e4
        def __init__(self, cfg: Config, *, device: str): ...

``conf/sim/mpm_warp.yaml`` holds ``type: mpm_warp`` plus values; :func:`build` merges those values into
the typed ``Config`` so an unknown key or a wrong type fails at start-up naming the key.
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal, Protocol, TypeVar, runtime_checkable

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException, ValidationError

from sync4d.errors import ConfigError, RegistryError

GROUPS: tuple[str, ...] = ("reference", "recon", "features", "target", "sim", "velocity", "render", "logger")

_REGISTRY: dict[str, dict[str, type]] = {group: {} for group in GROUPS}

T = TypeVar("T", bound=type)


@runtime_checkable
class CheckedConfig(Protocol):
    """Capability of a ``Config`` that checks its values beyond their types (raises ConfigError naming the key)."""

    def validate(self) -> None: ...


def register(group: str, name: str) -> Callable[[T], T]:
    """Class decorator that registers a component under ``group``/``name``.

    Raises:
        RegistryError: the group is unknown, the name is taken, or the class has no dataclass ``Config``.
    """
    if group not in _REGISTRY:
        raise RegistryError(f"unknown registry group '{group}'; groups are: {', '.join(GROUPS)}")

    def decorator(cls: T) -> T:
        config = getattr(cls, "Config", None)
        if config is None or not dataclasses.is_dataclass(config):
            raise RegistryError(f"{group}={name}: {cls.__qualname__} needs a nested dataclass `Config`")
        existing = _REGISTRY[group].get(name)
        same = existing is not None and (existing.__module__, existing.__qualname__) == (cls.__module__, cls.__qualname__)
        if existing is not None and not same:
            raise RegistryError(
                f"{group}={name} is registered twice: by {existing.__module__}.{existing.__qualname__} "
                f"and by {cls.__module__}.{cls.__qualname__}; rename one of them"
            )
        _REGISTRY[group][name] = cls
        cls.registry_name = name  # type: ignore[attr-defined]
        return cls

    return decorator


def unregister(group: str, name: str) -> None:
    """Remove a registration (for tests that register throw-away components)."""
    _REGISTRY[group].pop(name, None)


def available(group: str) -> list[str]:
    """Sorted names registered in ``group``."""
    _ensure_plugins_loaded()
    if group not in _REGISTRY:
        raise RegistryError(f"unknown registry group '{group}'; groups are: {', '.join(GROUPS)}")
    return sorted(_REGISTRY[group])


def lookup(group: str, name: str) -> type:
    """The class registered as ``group``/``name``; an unknown name lists what is available."""
    names = available(group)
    if name not in _REGISTRY[group]:
        raise RegistryError(f"unknown {group} '{name}'; available: {', '.join(names) or '(none)'}")
    return _REGISTRY[group][name]


def make_config(group: str, cfg: Mapping[str, Any] | DictConfig) -> tuple[type, Any]:
    """Merge a YAML/dict config (with a ``type`` key) into the component's typed ``Config``.

    Returns:
        (component class, typed Config instance).

    Raises:
        ConfigError: missing ``type``, an unknown key, or a value of the wrong type; names the key.
    """
    values = plain_dict(cfg)
    name = values.pop("type", None)
    if name is None:
        raise ConfigError(f"{group}: config has no 'type' key; set {group}=<one of {', '.join(available(group))}>")
    cls = lookup(group, str(name))
    typed = typed_config(cls.Config, values, where=f"{group}", label=f"{group}={name}")  # type: ignore[attr-defined]
    if isinstance(typed, CheckedConfig):
        typed.validate()
    return cls, typed


@dataclass(frozen=True)
class Component:
    """A selected component: its group, registered name, class and typed ``Config`` (what a run plan holds).

    Attributes:
        group: the registry group (``sim``); name: the registered name (``mpm_warp``).
        cls: the registered class; config: an instance of its ``Config``.
    """

    group: str
    name: str
    cls: type
    config: Any

    def build(self, **deps: Any) -> Any:
        """The component, built with its typed config and keyword dependencies (``device=...``)."""
        return self.cls(self.config, **deps)

    def values(self) -> dict[str, Any]:
        """The config as plain values with ``type`` (for cache keys and records)."""
        return {"type": self.name, **dataclasses.asdict(self.config)}

    def with_values(self, **changes: Any) -> Component:
        """The same component with some config fields changed (validated again)."""
        return component(self.group, {**self.values(), **changes})


def component(group: str, cfg: Mapping[str, Any] | DictConfig) -> Component:
    """The :class:`Component` a group's config selects (see :func:`make_config`)."""
    cls, typed = make_config(group, cfg)
    return Component(group, str(cls.registry_name), cls, typed)  # type: ignore[attr-defined]


def plain_dict(cfg: Mapping[str, Any] | DictConfig | ListConfig) -> dict[str, Any]:
    """A config node or mapping as a plain, resolved dict."""
    values = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, (DictConfig, ListConfig)) else dict(cfg)
    assert isinstance(values, dict)
    return {str(k): v for k, v in values.items()}


def typed_config(config: type, values: Mapping[str, Any], *, where: str, label: str) -> Any:
    """Merge plain ``values`` into the dataclass ``config``: unknown keys, wrong types and values outside a
    ``Literal[...]`` option set fail with one line naming ``<where>.<key>``.

    OmegaConf checks the types but knows no ``Literal``; it sees such a field as its values' type and the
    allowed set is checked here.
    """
    schema = OmegaConf.structured(omegaconf_schema(config))
    try:
        merged = OmegaConf.merge(schema, dict(values))
    except ConfigKeyError as err:
        known = ", ".join(f.name for f in dataclasses.fields(config))
        raise ConfigError(f"{where}.{err.full_key or err.key}: unknown key for {label}; known keys: {known}") from None
    except ValidationError as err:
        raise ConfigError(f"{where}.{err.full_key or err.key}: {str(err.msg).splitlines()[0]} (for {label})") from None
    except OmegaConfBaseException as err:
        raise ConfigError(f"{label}: {str(err).splitlines()[0]}") from None
    plain = plain_dict(merged)
    hints = typing.get_type_hints(config)
    for key, value in plain.items():
        if dataclasses.is_dataclass(hints[key]) and isinstance(value, dict):
            plain[key] = typed_config(hints[key], value, where=f"{where}.{key}", label=label)
            continue
        allowed = literal_options(hints[key])
        if allowed is not None and value not in allowed:
            raise ConfigError(f"{where}.{key}={value!r}: must be one of {', '.join(map(str, allowed))} (for {label})")
    return config(**plain)


def literal_options(hint: Any) -> tuple[Any, ...] | None:
    """The allowed values of a ``Literal[...]`` (or ``Literal[...] | None``) hint, else None."""
    if typing.get_origin(hint) is Literal:
        return typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        literals = [a for a in args if typing.get_origin(a) is Literal]
        if literals and type(None) in args:
            return (*typing.get_args(literals[0]), None)
    return None


@functools.cache
def omegaconf_schema(config: type) -> type:
    """``config`` as a dataclass OmegaConf can type-check: each ``Literal`` becomes the type of its values."""
    hints = typing.get_type_hints(config)
    fields = []
    for f in dataclasses.fields(config):
        hint = hints[f.name]
        options = literal_options(hint)
        if dataclasses.is_dataclass(hint):
            hint = omegaconf_schema(hint)  # type: ignore[arg-type]
        elif options is not None:
            kinds = {type(o) for o in options if o is not None}
            base = kinds.pop() if len(kinds) == 1 else Any
            hint = base | None if None in options and base is not Any else base
        if dataclasses.is_dataclass(hints[f.name]):  # a nested block: its own schema's defaults
            fields.append((f.name, hint, dataclasses.field(default_factory=hint)))
            continue
        default: Any = dataclasses.field(default=f.default) if f.default is not dataclasses.MISSING else (
            dataclasses.field(default_factory=f.default_factory)
            if f.default_factory is not dataclasses.MISSING else dataclasses.field())
        fields.append((f.name, hint, default))
    return dataclasses.make_dataclass(f"{config.__qualname__.replace('.', '_')}Schema", fields)


def build(group: str, cfg: Mapping[str, Any] | DictConfig, **deps: Any) -> Any:
    """Build the component selected by the ``type`` key with its typed config and keyword dependencies."""
    return component(group, cfg).build(**deps)


_plugins_loaded = False


def _ensure_plugins_loaded() -> None:
    global _plugins_loaded
    if not _plugins_loaded:
        _plugins_loaded = True
        from sync4d import plugins

        plugins.load_all()
