"""Registries of methods, datamanagers and fields, filled through entry points.

Our own plugins and third-party packages register the same way: an entry point in the group
`uw3dgs.methods`, `uw3dgs.datamanagers` or `uw3dgs.fields` that points at a spec object
(`MethodSpec`, `DataManagerSpec`, `FieldSpec`). Nothing is imported until a registry is first read,
so `uw-train --help` stays fast and a broken plugin names itself instead of breaking everything.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Any, Generic, TypeVar

from uw3dgs.utils.console import warn


@dataclass(frozen=True)
class MethodSpec:
    """A named, described training recipe: the full default config of `uw-train NAME`."""

    name: str
    description: str
    config: Any
    """A `uw3dgs.engine.config.TrainConfig` holding every default of the method."""


@dataclass(frozen=True)
class DataManagerSpec:
    """A data plugin: its config type (whose `setup()` builds it) and how to recognise its layout."""

    name: str
    description: str
    config: Any
    """Default `DataManagerConfig` instance."""


@dataclass(frozen=True)
class FieldSpec:
    """A model part that methods compose, chosen by its registry name as a subcommand (`uw-train uw3dgs NAME`).

    `kind` says which slot of a model it fills: "gaussians" (the scene's Gaussians) or "medium" (the water);
    a model config accepts only fields of the kind its slot asks for. `config` is the field's default config,
    whose `setup()` builds it with the keyword arguments that kind's slot passes (see the method's model)."""

    name: str
    description: str
    config: Any
    kind: str


SpecT = TypeVar("SpecT", MethodSpec, DataManagerSpec, FieldSpec)


class Registry(Generic[SpecT]):
    """Name -> spec, loaded lazily from one entry-point group."""

    def __init__(self, group: str, spec_type: type[SpecT]):
        self.group = group
        self.spec_type = spec_type
        self._specs: dict[str, SpecT] | None = None

    def _load(self) -> dict[str, SpecT]:
        if self._specs is None:
            specs: dict[str, SpecT] = {}
            for ep in sorted(entry_points(group=self.group), key=lambda e: e.name):
                try:
                    spec = ep.load()
                except Exception as exc:  # a broken third-party plugin must not hide the others
                    warn(f"plugin '{ep.name}' ({ep.value}) in {self.group} failed to load: {exc}")
                    continue
                if not isinstance(spec, self.spec_type):
                    warn(f"entry point '{ep.name}' in {self.group} is a {type(spec).__name__}, "
                         f"expected {self.spec_type.__name__}; ignored")
                    continue
                if spec.name in specs:
                    warn(f"'{spec.name}' is registered twice in {self.group}; keeping {specs[spec.name]!r}")
                    continue
                specs[spec.name] = spec
            self._specs = specs
        return self._specs

    def register(self, spec: SpecT) -> None:
        """Add a spec at run time (tests, notebooks); entry points are the way for packages."""
        self._load()[spec.name] = spec

    def __getitem__(self, name: str) -> SpecT:
        specs = self._load()
        if name not in specs:
            kind = self.group.split(".")[-1][:-1]
            raise KeyError(f"unknown {kind} '{name}'; available: {', '.join(specs) or 'none'}")
        return specs[name]

    def __contains__(self, name: str) -> bool:
        return name in self._load()

    def __iter__(self) -> Iterator[str]:
        return iter(self._load())

    def items(self):
        return self._load().items()


METHODS: Registry[MethodSpec] = Registry("uw3dgs.methods", MethodSpec)
DATAMANAGERS: Registry[DataManagerSpec] = Registry("uw3dgs.datamanagers", DataManagerSpec)
FIELDS: Registry[FieldSpec] = Registry("uw3dgs.fields", FieldSpec)


def field_spec(name: str, kind: str) -> FieldSpec:
    """The field registered as `name`, which must be of `kind`; the error lists the fields that are."""
    fitting = [n for n, spec in FIELDS.items() if spec.kind == kind]
    if name not in FIELDS or FIELDS[name].kind != kind:
        raise ValueError(f"unknown {kind} field '{name}'; registered {kind} fields: {', '.join(fitting) or 'none'}")
    return FIELDS[name]
