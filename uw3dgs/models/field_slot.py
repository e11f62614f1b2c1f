"""A model config's slot for a registered field (Gaussians, medium, radiance), chosen as a tyro subcommand.

    medium: Annotated[MediumFieldConfig, field_slot("medium")] = field(default_factory=MediumGridConfig)

makes one subcommand per registered field of kind "medium" (entry points included): `uw-train uw3dgs
medium-homogeneous --model.medium.b-inf-init ...`. The slot's default (the method's own) needs no token: an option
of the default field selects it (`uw-train uw3dgs --model.medium.init prior`, tyro's `CascadeSubcommandArgs`), and
`uw-train uw3dgs --help` lists its knobs. A field's boolean knob has one flag, the one that flips its default. The
default must be the config of a registered field, or of a subclass registered under its own name, so tyro can
match it to a subcommand.
"""

from __future__ import annotations

from typing import Annotated, Any

import tyro

from uw3dgs.registry import FIELDS


def field_choices(kind: str) -> type:
    """The union of the registered fields of `kind`, one subcommand each, named by registry name, at their
    registered defaults (a method's default for the slot replaces its own field's)."""
    specs = {name: spec for name, spec in FIELDS.items() if spec.kind == kind}
    if not specs:
        raise ValueError(f"no field of kind '{kind}' is registered (entry points uw3dgs.fields)")
    union = tyro.extras.subcommand_type_from_defaults({name: spec.config for name, spec in specs.items()},
                                                      {name: spec.description for name, spec in specs.items()},
                                                      prefix_names=False)
    # one flag per boolean knob, the one that changes its default (`--model.medium.no-learn-beta`): tyro (1.0.17)
    # selects a default subcommand implicitly by its options' names, which do not include a --no-X form
    return Annotated[union, tyro.conf.FlagCreatePairsOff]


def field_slot(kind: str) -> Any:
    """The `Annotated` marker of a slot holding a field of `kind` (see the module's docstring)."""
    return tyro.conf.arg(constructor_factory=lambda: field_choices(kind))


def registered_field_name(class_path: str) -> str | None:
    """The registry name (the subcommand) of the field whose config class is `class_path` ('module.Class', as a
    config file's `_type`), else None."""
    return next((name for name, spec in FIELDS.items()
                 if f"{type(spec.config).__module__}.{type(spec.config).__qualname__}" == class_path), None)
