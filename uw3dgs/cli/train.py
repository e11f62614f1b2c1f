"""`uw-train METHOD [options] [--data PATH]`: train a registered method."""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

import tyro
from rich.console import Console

from uw3dgs.cli.errors import exit_with_error
from uw3dgs.config import load_config
from uw3dgs.engine.config import TrainConfig
from uw3dgs.options import check_config, deferred_checks
from uw3dgs.registry import METHODS
from uw3dgs.utils.console import route_warnings
from uw3dgs.utils.io import describe_os_error

USER_ERRORS = (FileNotFoundError, ValueError, RuntimeError)
EXIT_INTERRUPTED = 130
"""Exit status of a run stopped by Ctrl-C (128 + SIGINT); SIGTERM gives 143 (128 + SIGTERM)."""


def _flag_value(argv: list[str], flag: str) -> str | None:
    for i, arg in enumerate(argv):
        if arg == flag and i + 1 < len(argv):
            return argv[i + 1]
        if arg.startswith(flag + "="):
            return arg.split("=", 1)[1]
    return None


def parse_config(argv: list[str]) -> TrainConfig:
    """Method subcommands from the registry; with --load-config the saved run supplies the defaults."""
    defaults = {name: spec.config for name, spec in METHODS.items()}
    descriptions = {name: spec.description for name, spec in METHODS.items()}
    load = _flag_value(argv, "--load-config")
    if load is not None:
        saved: TrainConfig = load_config(Path(load))
        if saved.method_name not in defaults:
            raise ValueError(f"{load} was trained with method '{saved.method_name}', which is not installed")
        # --resume is never inherited from a saved config: only the flag continues a run
        defaults[saved.method_name] = dataclasses.replace(saved, load_config=Path(load), resume=False)
        if not argv or argv[0] not in defaults:
            argv = [saved.method_name, *argv]
    choices = tyro.extras.subcommand_type_from_defaults(defaults, descriptions, prefix_names=False)
    # the configs' own checks run once the whole config is built, so an error names the option in full
    # (--optimizers.means.lr, --datamanager.scene.width), as typed
    with deferred_checks():
        # CascadeSubcommandArgs: options of a default subcommand (a field, the datamanager) select it without its
        # token (`uw-train uw3dgs --model.medium.init prior`), and options may follow later subcommands
        config = tyro.cli(choices, args=argv, prog="uw-train", description="Train a uw3dgs method.",
                          config=(tyro.conf.CascadeSubcommandArgs,))
    check_config(config)
    return config


def entrypoint(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    route_warnings()
    console = Console()
    hint = "(set UW3DGS_DEBUG=1 for the full traceback)"
    try:
        config = parse_config(argv)
        from uw3dgs.engine.signals import TrainingInterrupted  # after parsing, so --help stays fast
        from uw3dgs.engine.trainer import Trainer
    except USER_ERRORS as exc:
        exit_with_error(exc, console, hint=hint)
    except KeyboardInterrupt:
        console.print("Interrupted.")
        sys.exit(EXIT_INTERRUPTED)

    try:
        trainer = Trainer(config)
        trainer.setup()
        console.print(f"[bold]uw-train[/bold] {config.method_name}: {trainer.datamanager.scene_name}, "
                      f"{len(trainer.datamanager.train_indices)} train / {len(trainer.datamanager.test_indices)} "
                      f"test views, device {trainer.device}, run folder {trainer.run_dir}", soft_wrap=True)
        run_dir = trainer.train()
    except TrainingInterrupted as exc:  # the trainer printed the checkpoint and how to resume: no traceback
        if os.environ.get("UW3DGS_DEBUG"):
            raise
        sys.exit(128 + exc.signum)
    except KeyboardInterrupt:  # Ctrl-C twice, or before training started (the trainer said how to resume)
        if os.environ.get("UW3DGS_DEBUG"):
            raise
        console.print("Interrupted.")
        sys.exit(EXIT_INTERRUPTED)
    except USER_ERRORS as exc:  # FileNotFoundError among them: its message names the file and the fix
        exit_with_error(exc, console, hint=hint)
    except OSError as exc:  # an unwritable or file-shaped output path, a full disk: one line naming the path
        exit_with_error(exc, console, hint=hint, message=describe_os_error(exc))
    # soft_wrap: paths stay on one line, so they can be copied
    console.print(f"Done. Evaluate with: uw-eval {run_dir / 'config.yml'}   |   tensorboard --logdir {run_dir}",
                  soft_wrap=True)


if __name__ == "__main__":
    entrypoint()
