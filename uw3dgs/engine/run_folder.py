"""A run folder belongs to one run: a lock while training, no silent reuse, and `--resume` only where the
checkpoint's parameters fit the model the options describe.

- `RunLock`: an exclusive `fcntl.flock` on `RUN/.uw-train.lock`, held from setup to the end of training; the
  file names the holder (pid, host, start), so a second process says who has the folder. The OS drops the lock
  when the process dies, however it dies.
- `check_fresh`: a new run never writes into a folder that holds a run (config.yml or a checkpoint).
- `shape_mismatch`: what a resumed model would not take from the checkpoint, and which options changed it.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import torch

from uw3dgs.config import config_to_dict
from uw3dgs.engine.checkpoint import CHECKPOINT_DIR, list_checkpoints
from uw3dgs.models.field_slot import registered_field_name
from uw3dgs.utils.console import warn
from uw3dgs.utils.io import describe_os_error, remove_temp_files
from uw3dgs.utils.safe_yaml import load_yaml

try:
    import fcntl
except ImportError:  # not on POSIX: runs are not locked
    fcntl = None

LOCK_NAME = ".uw-train.lock"
WRITTEN = {"config.yml", "dataparser_transforms.json", "status.json"}
"""Files of the run folder itself the trainer writes (atomically); checkpoints/ holds only the trainer's files."""
NOTES_DIR = "notes"
"""The model's notes on how the run started (`Model.run_notes`, e.g. the medium's identifiability report), one JSON
file each; uw-eval copies them into its results."""


class RunFolderError(RuntimeError):
    """The run folder cannot be used by this run (another process holds it, or it holds another run)."""


def _training_refusal(folder: Path, holder: str) -> str:
    return (f"{folder} is in use by another training ({holder}); wait for it to end or stop it, or train into "
            "another --timestamp")


class RunLock:
    """An exclusive lock on a run folder, for the whole training (one process per run folder); with another `name`
    and `refusal` (the message naming the folder and the holder) the lock of another kind of folder (a grid's)."""

    def __init__(self, run_dir: Path, name: str = LOCK_NAME,
                 refusal: Callable[[Path, str], str] = _training_refusal):
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / name
        self.refusal = refusal
        self._file = None

    def acquire(self) -> None:
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            handle = open(self.path, "a+")  # noqa: SIM115 (held open for the whole run)
        except OSError as exc:
            raise RunFolderError(f"cannot create the run folder {self.run_dir}: {describe_os_error(exc)}; choose "
                                 "another --output-dir") from exc
        if fcntl is None:
            self._file = handle
            return
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "a process that has not written its pid yet"
            handle.close()
            if holder.startswith(f"pid {os.getpid()} on {socket.gethostname()},"):  # a notebook, a test
                holder += ": an earlier Trainer of this process, whose train() has not ended; call its close()"
            raise RunFolderError(self.refusal(self.run_dir, holder)) from None
        except OSError as exc:  # a file system without flock (some network mounts): train unlocked
            warn(f"cannot lock {self.path} ({exc.strerror}); two trainings into this folder would not be stopped")
        handle.seek(0)
        handle.truncate()
        handle.write(f"pid {os.getpid()} on {socket.gethostname()}, since {datetime.now():%Y-%m-%d %H:%M:%S}\n")
        handle.flush()
        self._file = handle

    def release(self) -> None:
        if self._file is not None:
            self._file.close()  # closing the only descriptor of the open file drops its flock
            self._file = None

    @property
    def held(self) -> bool:
        return self._file is not None


def lock_holder(folder: Path, name: str = LOCK_NAME) -> str | None:
    """Who holds the lock `name` of `folder` ('pid N on HOST, since ...'), or None where no process holds it (no lock
    file, or a lock its process left when it ended)."""
    if fcntl is None:
        return None
    try:
        handle = open(Path(folder) / name)  # noqa: SIM115 (closed below, which drops a lock taken here)
    except OSError:
        return None
    with handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return handle.read().strip() or "a process that has not written its pid yet"
        except OSError:  # a file system without flock: nothing can be known
            return None
    return None


def holds_a_run(run_dir: Path) -> bool:
    """A run folder in use: it has a config.yml or a completed checkpoint."""
    return (Path(run_dir) / "config.yml").is_file() or bool(list_checkpoints(run_dir))


def check_fresh(run_dir: Path) -> None:
    """A new run never writes into a folder holding another run: the configs and checkpoints would mix."""
    if holds_a_run(run_dir):
        raise RunFolderError(f"{run_dir} already holds a run (config.yml or checkpoints); continue it with "
                             f"uw-train --load-config {Path(run_dir) / 'config.yml'} --resume, or start a new run "
                             "under another --timestamp")


def remove_stale_temp_files(run_dir: Path) -> list[Path]:
    """Temporary files of atomic writes a killed run left (`.step-NNNNNN.ckpt.<hex>.tmp`, `.config.yml.<hex>.tmp`);
    called with the lock held, so no live writer owns them."""
    return (remove_temp_files(Path(run_dir) / CHECKPOINT_DIR) + remove_temp_files(Path(run_dir) / NOTES_DIR)
            + remove_temp_files(run_dir, WRITTEN))


# ----------------------------------------------------------------------------------------------------
# --resume: the checkpoint's parameters must fit the model the (new) options build


def flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    """A nested config dict as {'model.paup.every': value, ...}."""
    out: dict[str, Any] = {}
    if isinstance(data, dict):
        for key, value in data.items():
            out.update(flatten(value, f"{prefix}.{key}" if prefix else str(key)))
    else:
        out[prefix] = data
    return out


def _changed_model_options(saved: dict[str, Any], new: dict[str, Any]) -> dict[str, tuple[Any, Any]]:
    """Dotted keys under `model` (and the method) whose values differ: key -> (saved, new); a nested config whose
    class changed is one entry (its `_type`), not one per knob."""
    a, b = flatten(saved), flatten(new)
    keys = [k for k in dict.fromkeys([*a, *b]) if (k == "method_name" or k.startswith("model."))
            and a.get(k, "<absent>") != b.get(k, "<absent>")]
    retyped = [k.removesuffix("._type") for k in keys if k.endswith("._type")]
    keys = [k for k in keys if k.endswith("._type") or not any(k.startswith(r + ".") for r in retyped)]
    return {k: (a.get(k, "<absent>"), b.get(k, "<absent>")) for k in keys}


def _option_text(key: str, values: tuple[Any, Any]) -> str:
    old, new = values
    if key.endswith("._type"):
        owner = "--" + key.removesuffix("._type").replace("_", "-")
        names = [registered_field_name(str(v)) for v in values]
        if all(names):  # a field slot: the subcommands that chose the two fields
            return f"{owner} (the subcommand '{names[0]}' in the checkpoint, '{names[1]}' now)"
        return f"{owner} (a {str(old).rpartition('.')[2]} in the checkpoint, a {str(new).rpartition('.')[2]} now)"
    return f"--{key.replace('_', '-')} ({old!r} in the checkpoint, {new!r} now)"


def _shape(t: torch.Tensor, free_first: bool) -> str:
    dims = [str(d) for d in t.shape]
    if free_first and dims:
        dims[0] = "N"
    return "[" + ", ".join(dims) + "]"


def state_problems(model: Any, saved: dict[str, torch.Tensor]) -> tuple[list[str], list[str]]:
    """What `model` would not take from the saved state_dict `saved`: the keys only in one of them and the tensors
    of other shapes (the first dimension of those density control resizes is free), as 'key ...' texts; and the
    top-level parts of the model (e.g. 'gaussians') they belong to."""
    saved, now = {**model.checkpoint_defaults(), **saved}, model.state_dict()
    free = set(model.state_keys_resized_in_training())
    reshaped = set(getattr(model, "state_keys_reshaped_in_training", set)())
    problems, parts = [], []
    for key in dict.fromkeys([*saved, *now]):
        if key not in now or key not in saved:
            problems.append(f"{key} {'only in the checkpoint' if key not in now else 'not in the checkpoint'}")
        else:
            a, b = saved[key], now[key]
            if key in reshaped:
                same = a.dim() == b.dim()
            else:
                same = a.shape[1:] == b.shape[1:] and a.dim() == b.dim() if key in free else a.shape == b.shape
            if same:
                continue
            problems.append(f"{key} {_shape(a, key in free)} in the checkpoint, {_shape(b, key in free)} now")
        parts.append(key.split(".")[0])
    return problems, parts


def shape_mismatch(model: Any, state: dict[str, Any], new_config: Any, checkpoint: Path) -> str | None:
    """Why `model` (built from `new_config`) cannot resume from checkpoint `state`, or None if it can.

    Compared: the state_dict keys and every tensor's shape (the first dimension of the tensors density control
    resizes, `model.state_keys_resized_in_training()`, is free) and the names of the parameter groups (the
    optimizers' states). The message names the options that differ from the checkpoint's config: those under the
    mismatching part of the model (`model.gaussians.*` for `gaussians.shN`; another field in a slot by the subcommands
    that chose each), else every model option that differs."""
    problems, parts = state_problems(model, state["model"])
    groups_saved, groups_now = set(state.get("optimizers", {})), set(model.param_groups())
    if groups_saved != groups_now:
        problems.append(f"parameter groups {sorted(groups_saved)} in the checkpoint, {sorted(groups_now)} now")
    if not problems:
        return None
    saved_config = state.get("config")
    if not isinstance(saved_config, dict):  # a checkpoint without its config: the run folder's config.yml
        try:
            saved_config = load_yaml(checkpoint.parent.parent / "config.yml")
        except (OSError, ValueError):
            saved_config = {}
    changed = _changed_model_options(saved_config if isinstance(saved_config, dict) else {},
                                     config_to_dict(new_config))
    near = {k: v for k, v in changed.items()
            if any(k.startswith(f"model.{p}.") or k == f"model.{p}._type" for p in parts)}
    named = near or changed
    options = ", ".join(_option_text(k, v) for k, v in named.items()) or \
        "no option differs from the checkpoint's config (was it written by another uw3dgs version?)"
    shown = "; ".join(problems[:4]) + (f"; ... ({len(problems)} in all)" if len(problems) > 4 else "")
    return (f"--resume cannot change the shapes of the model's parameters: {options} [{shown}]. Resume "
            f"{checkpoint.parent.parent} without those options, or start a new run with them (another --timestamp)")
