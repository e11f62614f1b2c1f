"""`uw-train METHOD [options] [--data PATH]`: train a registered method."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import tyro
from rich.console import Console

from uw3dgs.cli.errors import exit_with_error
from uw3dgs.config import load_config
from uw3dgs.engine.config import TrainConfig
from uw3dgs.registry import METHODS
from uw3dgs.utils.console import route_warnings

USER_ERRORS = (FileNotFoundError, ValueError, RuntimeError)


def _flag_value(argv: list[str], flag: str) -> str | None:
    for i, arg in enumerate(argv):
        if arg == flag and i + 1 < len(argv):
            return argv[i + 1]
        if arg.startswith(flag + "="):
            return arg.split("=", 1)[1]
    return None


def _select_fields(config: TrainConfig, argv: list[str]) -> TrainConfig:
    """Apply `--model.<selector> NAME` (e.g. `--model.medium-field medium-homogeneous`) before parsing: the named
    registered field's config takes its slot, so `--model.medium.*` and `--help` show that field's knobs."""
    model = config.model
    for selector in model.field_slots:
        flags = (f"--model.{selector.replace('_', '-')}", f"--model.{selector}")
        name = next((v for v in (_flag_value(argv, f) for f in flags) if v is not None), None)
        if name is not None and name != getattr(model, selector):
            model = model.with_field(selector, name)
    return config if model is config.model else dataclasses.replace(config, model=model)


def parse_config(argv: list[str]) -> TrainConfig:
    """Method subcommands from the registry; with --load-config the saved run supplies the defaults."""
    defaults = {name: spec.config for name, spec in METHODS.items()}
    descriptions = {name: spec.description for name, spec in METHODS.items()}
    load = _flag_value(argv, "--load-config")
    if load is not None:
        saved: TrainConfig = load_config(Path(load))
        if saved.method_name not in defaults:
            raise ValueError(f"{load} was trained with method '{saved.method_name}', which is not installed")
        defaults[saved.method_name] = dataclasses.replace(saved, load_config=Path(load))
        if not argv or argv[0] not in defaults:
            argv = [saved.method_name, *argv]
    if argv and argv[0] in defaults:
        defaults[argv[0]] = _select_fields(defaults[argv[0]], argv)
    choices = tyro.extras.subcommand_type_from_defaults(defaults, descriptions, prefix_names=False)
    return tyro.cli(choices, args=argv, prog="uw-train", description="Train a uw3dgs method.")


def entrypoint(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    route_warnings()
    console = Console()
    try:
        config = parse_config(argv)
        from uw3dgs.engine.trainer import Trainer  # after parsing, so --help stays fast

        trainer = Trainer(config)
        trainer.setup()
        console.print(f"[bold]uw-train[/bold] {config.method_name}: {trainer.datamanager.scene_name}, "
                      f"{len(trainer.datamanager.train_indices)} train / {len(trainer.datamanager.test_indices)} "
                      f"test views, device {trainer.device}, run folder {trainer.run_dir}", soft_wrap=True)
        run_dir = trainer.train()
    except USER_ERRORS as exc:
        exit_with_error(exc, console, hint="(set UW3DGS_DEBUG=1 for the full traceback)")
    # soft_wrap: paths stay on one line, so they can be copied
    console.print(f"Done. Evaluate with: uw-eval {run_dir / 'config.yml'}   |   tensorboard --logdir {run_dir}",
                  soft_wrap=True)


if __name__ == "__main__":
    entrypoint()
