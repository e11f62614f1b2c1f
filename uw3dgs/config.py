"""Config base class and the YAML form of configs saved in every run folder.

Every knob is a field of a frozen dataclass; `setup()` builds the object the config describes
(the `_target` pattern of nerfstudio). Configs are saved as plain YAML (no Python object tags): each
dataclass becomes a mapping with a `_type` key naming its class, so a run folder's `config.yml`
is readable, diffable and loadable without executing arbitrary code.

Every config checks its own numbers where they are declared (`check_options`, see `uw3dgs.options`).
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

from uw3dgs.options import CheckedConfig, OptionError, check_config, deferred_checks
from uw3dgs.utils.io import write_text
from uw3dgs.utils.safe_yaml import load_yaml

Target = tyro.conf.Suppress[Callable[..., Any]]
"""Annotation of `_target` (a class or a factory taking the config first): not a command-line option."""


def target(factory: Any) -> Any:
    """`_target: Target = target(lambda: MyClass)` (a lambda, so the class may be defined below)."""
    return field(default_factory=factory, repr=False)


@dataclass(frozen=True)
class InstantiateConfig(CheckedConfig):
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



# ----------------------------------------------------------------------------------------------------
# Reading configs back: only this project's and registered plugins' classes, values of the annotated types

PLUGIN_GROUPS = ("uw3dgs.methods", "uw3dgs.datamanagers", "uw3dgs.fields")


class ConfigTypeError(ValueError):
    """A value in a config file is not of the type its option is declared with."""


def _registered_modules() -> set[str]:
    """Modules a config file may name classes from, besides `uw3dgs.*`: the top-level packages of the registered
    plugins' entry points (read from package metadata: nothing is imported), and the modules of the config classes
    of specs registered at run time (registries already loaded)."""
    from importlib.metadata import entry_points

    from uw3dgs import registry

    modules = {ep.module.split(".")[0] for group in PLUGIN_GROUPS for ep in entry_points(group=group)}

    def add(value: Any) -> None:
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            modules.add(type(value).__module__)
            for f in dataclasses.fields(value):
                add(getattr(value, f.name, None))
        elif isinstance(value, dict):
            for v in value.values():
                add(v)

    for reg in (registry.METHODS, registry.DATAMANAGERS, registry.FIELDS):
        for spec in (reg._specs or {}).values():
            add(spec.config)
    return modules


def _module_allowed(module_name: str) -> bool:
    if module_name == "uw3dgs" or module_name.startswith("uw3dgs."):
        return True
    return any(module_name == m or module_name.startswith(m + ".") for m in _registered_modules())


def _where(key: str) -> str:
    return f"{key}: " if key else ""


MOVED_CLASSES = {
    "uw3dgs.fields.densification.DensificationConfig": "uw3dgs.strategy.default.DensificationConfig",
}
"""Config classes that moved, old name -> new: run folders saved before the move keep loading (and resuming)."""

REMOVED_OPTIONS = frozenset({"gaussian_field", "medium_field", "radiance_field"})
"""Options that were removed because another key says the same (a field's registry name is its config's `_type`
now that fields are chosen by subcommand): skipped when a config file written before is read."""

EARLIER_DEFAULTS: dict[str, dict[str, Any]] = {
    "uw3dgs.fields.medium.MediumGridConfig": {"flat_start": "zero-basis", "factor_penalty": "norm",
                                              "factor_penalty_weight": 0.001},
}
"""Options whose default changed, per config class: the value a config file written without the option (before it
existed) ran with, which it keeps when read (instead of the new default)."""


def _import_config_class(qualname: Any, key: str = "") -> type:
    if not isinstance(qualname, str) or "." not in qualname:
        raise ConfigTypeError(f"{_where(key)}_type must name a config class as 'module.Class', got {qualname!r}")
    qualname = MOVED_CLASSES.get(qualname, qualname)
    module_name, _, cls_name = qualname.rpartition(".")
    # the module's name is checked before anything is imported: a config file cannot run the import-time code of
    # an arbitrary installed module
    if not _module_allowed(module_name):
        raise ConfigTypeError(f"{_where(key)}_type '{qualname}' is not a config class of uw3dgs or of a registered "
                              "plugin (entry points uw3dgs.methods / uw3dgs.datamanagers / uw3dgs.fields); only "
                              "those can be named in a config file")
    try:
        cls = getattr(importlib.import_module(module_name), cls_name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"{_where(key)}config class '{qualname}' cannot be imported ({exc}); is the plugin that "
                         "defines it installed?") from exc
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise ConfigTypeError(f"{_where(key)}'{qualname}' is not a config dataclass")
    return cls


def _describe(hint: Any) -> str:
    """A type annotation in words, for error messages."""
    origin = typing.get_origin(hint)
    if origin is typing.Annotated:
        return _describe(typing.get_args(hint)[0])
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        words = [_describe(a) for a in args if a is not type(None)]
        return " or ".join(words + (["null"] if type(None) in args else []))
    if origin is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(hint))
    if origin is tuple:
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_describe(args[0])} values"
        return f"a list of {len(args)} values ({', '.join(_describe(a) for a in args)})"
    if origin is dict:
        return "a mapping"
    words = {int: "an integer", float: "a number", bool: "true or false", str: "text", Path: "a path"}
    if hint in words:
        return words[hint]
    if isinstance(hint, type):
        return f"a {hint.__name__} (a mapping with _type)" if dataclasses.is_dataclass(hint) else hint.__name__
    return str(hint)


def _type_error(value: Any, hint: Any, key: str) -> ConfigTypeError:
    return ConfigTypeError(f"{_where(key)}expected {_describe(hint)}, got {value!r} ({type(value).__name__})")


def _float(value: Any) -> float | int | None:
    """A YAML number for a float option (an int as it is, as before); YAML 1.1 reads `1e-3` (no dot) as text, so
    text that is a number counts too."""
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float)):
        return value
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return None
    return None


def _convert(value: Any, hint: Any, key: str = "") -> Any:
    """Turn a YAML value back into the type a field is annotated with; a value of another type is a
    `ConfigTypeError` naming the key and the expected type."""
    origin = typing.get_origin(hint)
    if origin is typing.Annotated:
        return _convert(value, typing.get_args(hint)[0], key)
    if hint is Any or hint is object:
        return config_from_dict(value, key) if isinstance(value, dict) and "_type" in value else value
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if value is None:
            if type(None) in args:
                return None
            raise _type_error(value, hint, key)
        for arg in (a for a in args if a is not type(None)):
            try:
                return _convert(value, arg, key)
            except ConfigTypeError:
                continue
        raise _type_error(value, hint, key)
    if origin is typing.Literal:
        if any(value == a and type(value) is type(a) for a in typing.get_args(hint)):
            return value
        raise _type_error(value, hint, key)
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, (list, tuple)):
            raise _type_error(value, hint, key)
        if len(args) == 2 and args[1] is Ellipsis:
            items = [args[0]] * len(value)
        elif not args:
            items = [Any] * len(value)
        elif len(args) == len(value):
            items = list(args)
        else:
            raise _type_error(value, hint, key)
        return tuple(_convert(v, t, f"{key}[{i}]") for i, (v, t) in enumerate(zip(value, items, strict=True)))
    if origin is list:
        args = typing.get_args(hint)
        if not isinstance(value, list):
            raise _type_error(value, hint, key)
        return [_convert(v, args[0] if args else Any, f"{key}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        args = typing.get_args(hint)
        if not isinstance(value, dict):
            raise _type_error(value, hint, key)
        return {k: _convert(v, args[1] if args else Any, f"{key}.{k}" if key else str(k)) for k, v in value.items()}
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise _type_error(value, hint, key)
    if hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise _type_error(value, hint, key)
    if hint is float:
        number = _float(value)
        if number is None:
            raise _type_error(value, hint, key)
        return number
    if hint is str:
        if isinstance(value, str):
            return value
        raise _type_error(value, hint, key)
    if hint is Path:
        if isinstance(value, str):
            return Path(value)
        raise _type_error(value, hint, key)
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        if not (isinstance(value, dict) and "_type" in value):
            raise _type_error(value, hint, key)
        config = config_from_dict(value, key)
        if not isinstance(config, hint):
            raise ConfigTypeError(f"{_where(key)}expected {_describe(hint)}, got a {type(config).__name__}")
        return config
    if isinstance(value, dict) and "_type" in value:
        return config_from_dict(value, key)
    if isinstance(hint, type) and not isinstance(value, hint):
        raise _type_error(value, hint, key)
    return value


def config_from_dict(data: dict[str, Any], key: str = "") -> Any:
    """Inverse of `config_to_dict`; unknown keys are an error (a typo must not be ignored), and so is a value of
    another type than its option's (naming the dotted `key` of the value, e.g. `optimizers.means.lr`)."""
    cls = _import_config_class(data.get("_type"), key)
    hints = typing.get_type_hints(cls, include_extras=True)
    names = {f.name for f in dataclasses.fields(cls) if f.init and f.name != "_target"}
    data = {k: v for k, v in data.items() if k in names or k not in REMOVED_OPTIONS}
    data = {**EARLIER_DEFAULTS.get(f"{cls.__module__}.{cls.__qualname__}", {}), **data}
    unknown = set(data) - names - {"_type"}
    if unknown:
        raise ValueError(f"{_where(key)}{cls.__name__} has no option(s) {sorted(unknown)}")
    kwargs = {k: _convert(v, hints[k], f"{key}.{k}" if key else k) for k, v in data.items() if k != "_type"}
    try:
        return cls(**kwargs)
    except TypeError as exc:  # a required option missing
        raise ConfigTypeError(f"{_where(key)}{cls.__name__}: {exc}") from exc


def save_config(config: Any, path: Path) -> None:
    """Write `config` as YAML, atomically (a killed run never leaves half a config)."""
    write_text(path, yaml.safe_dump(config_to_dict(config), sort_keys=False))


def load_config(path: Path) -> Any:
    """Read a config.yml: plain YAML only (no Python tags), classes of uw3dgs and its registered plugins only,
    every value of its option's type and within its option's range; each failure is one line naming the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config file {path} does not exist; pass the config.yml of a run folder "
                                "(outputs/<scene>/<method>/<timestamp>/config.yml)")
    try:
        data = load_yaml(path)
    except OSError as err:
        raise ValueError(f"{path}: cannot be read ({err.strerror or err})") from err
    if not isinstance(data, dict) or "_type" not in data:
        raise ValueError(f"{path} is not a uw3dgs config (no '_type' key at the top)")
    try:
        with deferred_checks():
            config = config_from_dict(data)
        check_config(config)
    except OptionError as err:
        raise ValueError(f"{path}: {err.key} {err.reason} (the option {err.flag}); fix that value in the file") \
            from err
    except ConfigTypeError as err:
        raise ValueError(f"{path}: {err}; fix that value in the file") from err
    except ValueError as err:
        raise ValueError(f"{path}: {err}. A typo, or a run written by another uw3dgs version whose options "
                         "have since been renamed or removed: fix or delete those lines (see `uw-train METHOD "
                         "--help` for the current options)") from err
    return config
