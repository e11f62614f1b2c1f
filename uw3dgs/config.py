"""Config base class and the YAML form of configs saved in every run folder.

Every knob is a field of a frozen dataclass; `setup()` builds the object the config describes
(the `_target` pattern of nerfstudio). Configs are saved as plain YAML (no Python object tags): each
dataclass becomes a mapping with a `_type` key naming its class, so a run folder's `config.yml`
is readable, diffable and loadable without executing arbitrary code.
"""

from __future__ import annotations

import dataclasses
import importlib
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tyro
import yaml

from uw3dgs.utils.io import write_text

Target = tyro.conf.Suppress[Callable[..., Any]]
"""Annotation of `_target` (a class or a factory taking the config first): not a command-line option."""


def target(factory: Any) -> Any:
    """`_target: Target = target(lambda: MyClass)` (a lambda, so the class may be defined below)."""
    return field(default_factory=factory, repr=False)


@dataclass(frozen=True)
class InstantiateConfig:
    """A config that knows which class it configures: `config.setup(**kwargs)` builds it."""

    _target: Target = target(lambda: object)

    def setup(self, **kwargs: Any) -> Any:
        return self._target(self, **kwargs)


def config_to_dict(value: Any) -> Any:
    """Dataclasses, paths and tuples to plain YAML-safe values (recursively)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        out: dict[str, Any] = {"_type": f"{type(value).__module__}.{type(value).__qualname__}"}
        for f in dataclasses.fields(value):
            if f.name != "_target":
                out[f.name] = config_to_dict(getattr(value, f.name))
        return out
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (list, tuple)):
        return [config_to_dict(v) for v in value]
    if isinstance(value, dict):
        return {k: config_to_dict(v) for k, v in value.items()}
    return value


def _import_config_class(qualname: str) -> type:
    module_name, _, cls_name = qualname.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module_name), cls_name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"config class '{qualname}' cannot be imported ({exc}); is the plugin that "
                         "defines it installed?") from exc
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise ValueError(f"'{qualname}' is not a config dataclass")
    return cls


def _convert(value: Any, hint: Any) -> Any:
    """Turn a YAML value back into the type a field is annotated with."""
    if isinstance(value, dict) and "_type" in value:
        return config_from_dict(value)
    origin = typing.get_origin(hint)
    if origin is typing.Annotated:
        return _convert(value, typing.get_args(hint)[0])
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return value if value is None or len(args) != 1 else _convert(value, args[0])
    if hint is Path and isinstance(value, str):
        return Path(value)
    if origin is tuple and isinstance(value, list):
        args = typing.get_args(hint)
        item = args[0] if args else Any
        return tuple(_convert(v, item) for v in value)
    if origin is dict and isinstance(value, dict):
        args = typing.get_args(hint)
        return {k: _convert(v, args[1] if args else Any) for k, v in value.items()}
    return value


def config_from_dict(data: dict[str, Any]) -> Any:
    """Inverse of `config_to_dict`; unknown keys are an error (a typo must not be ignored)."""
    cls = _import_config_class(data["_type"])
    hints = typing.get_type_hints(cls, include_extras=True)
    names = {f.name for f in dataclasses.fields(cls) if f.init and f.name != "_target"}
    unknown = set(data) - names - {"_type"}
    if unknown:
        raise ValueError(f"{cls.__name__} has no option(s) {sorted(unknown)}")
    kwargs = {k: _convert(v, hints[k]) for k, v in data.items() if k != "_type"}
    return cls(**kwargs)


def save_config(config: Any, path: Path) -> None:
    """Write `config` as YAML, atomically (a killed run never leaves half a config)."""
    write_text(path, yaml.safe_dump(config_to_dict(config), sort_keys=False))


def load_config(path: Path) -> Any:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config file {path} does not exist; pass the config.yml of a run folder "
                                "(outputs/<scene>/<method>/<timestamp>/config.yml)")
    data = yaml.safe_load(path.read_text())
    if not isinstance(data, dict) or "_type" not in data:
        raise ValueError(f"{path} is not a uw3dgs config (no '_type' key at the top)")
    try:
        return config_from_dict(data)
    except ValueError as err:
        raise ValueError(f"{path}: {err}. A typo, or a run written by another uw3dgs version whose options "
                         "have since been renamed or removed: fix or delete those lines (see `uw-train METHOD "
                         "--help` for the current options)") from err
