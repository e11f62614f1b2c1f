"""Checkpoints: written atomically (temp file + rename), found by step, pruned to the newest few; and the check
that a model's parameters are finite (the Trainer runs it before every checkpoint, uw-eval before evaluating)."""

from __future__ import annotations

import pickle
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import IO, Any

import torch

from uw3dgs.utils.io import atomic_file

CHECKPOINT_DIR = "checkpoints"
_NAME = re.compile(r"^step-(\d+)\.ckpt$")


@torch.no_grad()
def nonfinite(named: Mapping[str, torch.Tensor | Iterable[torch.Tensor]]) -> list[str]:
    """The names (in order) whose tensor(s) hold a NaN or an infinity; integer tensors are skipped.

    One min/max reduction per tensor (NaN propagates through both; an infinity is the min or the max) and one
    device sync for all of them, not a `torch.isfinite(p).all()` and a sync per tensor (docs/training.md, "What is
    guaranteed")."""
    names, extremes = [], []
    for name, tensors in named.items():
        for t in [tensors] if isinstance(tensors, torch.Tensor) else tensors:
            if t.is_floating_point() and t.numel():
                names.append(name)
                lo_hi = torch.stack(torch.aminmax(t.detach())).float()
                extremes.append(lo_hi if not extremes else lo_hi.to(extremes[0].device))
    if not extremes:
        return []
    finite = torch.isfinite(torch.stack(extremes)).all(dim=1).tolist()
    return list(dict.fromkeys(n for n, ok in zip(names, finite, strict=True) if not ok))


def checkpoint_path(run_dir: Path, step: int) -> Path:
    return run_dir / CHECKPOINT_DIR / f"step-{step:06d}.ckpt"


def checkpoint_step(path: Path) -> int:
    """The step of a checkpoint file named as `checkpoint_path` names it (step-NNNNNN.ckpt)."""
    match = _NAME.match(Path(path).name)
    if match is None:
        raise ValueError(f"{path} is not a checkpoint name (step-NNNNNN.ckpt)")
    return int(match.group(1))


class _RecordedWrites:
    """A file for `torch.save` that keeps the OSError of a failed write (a full disk): torch's serialiser turns it
    into an internal message ('[enforce fail at inline_container.cc] unexpected pos'), which says nothing."""

    def __init__(self, file: IO[bytes]):
        self.file = file
        self.error: OSError | None = None

    def write(self, data: bytes) -> int:
        try:
            return self.file.write(data)
        except OSError as exc:
            self.error = exc
            raise

    def flush(self) -> None:
        self.file.flush()


def save_checkpoint(run_dir: Path, step: int, state: dict[str, Any], keep: int) -> Path:
    """Write `state` for `step`; a run killed mid-write leaves the previous checkpoints intact. A failed write is
    the OSError of the file system (e.g. 'No space left on device'), named with the checkpoint's path."""
    path = checkpoint_path(run_dir, step)
    with atomic_file(path, "wb", fsync=True) as f:
        recorded = _RecordedWrites(f)
        try:
            torch.save(state, recorded)
        except RuntimeError:
            if recorded.error is None:
                raise
            raise OSError(recorded.error.errno, recorded.error.strerror, str(path)) from recorded.error
    for old in list_checkpoints(run_dir)[:-keep] if keep > 0 else []:
        old.unlink(missing_ok=True)
    return path


def list_checkpoints(run_dir: Path) -> list[Path]:
    """Completed checkpoints of a run, oldest first (temp files of an interrupted write are ignored)."""
    folder = Path(run_dir) / CHECKPOINT_DIR
    if not folder.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in folder.iterdir() if (m := _NAME.match(p.name))]
    return [p for _, p in sorted(found)]


def latest_checkpoint(run_dir: Path) -> Path | None:
    found = list_checkpoints(run_dir)
    return found[-1] if found else None


MODEL_KEYS = ("model",)
"""What a checkpoint must hold to be evaluated, exported, rendered or viewed."""
RESUME_KEYS = ("step", "model", "optimizers", "callbacks", "datamanager", "rng")
"""What it must hold to be resumed (`Trainer.checkpoint_state`)."""


def _load_failure(exc: BaseException) -> str:
    """Why torch.load failed, in one line, without PyTorch's advice to load the file unsafely."""
    text = str(exc)
    found = re.search(r"Unsupported global: GLOBAL (\S+)", text)
    if found:
        return (f"it holds a Python object ({found.group(1).rstrip('.')}) that the safe loader refuses; uw-train's "
                "checkpoints hold tensors and plain values only, so it was written by another tool or altered")
    if isinstance(exc, pickle.UnpicklingError):
        found = re.search(r"WeightsUnpickler error:\s*([^\n]+)", text)
        return f"the safe loader refuses it ({found.group(1).strip() if found else 'not a tensor file'})"
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return re.sub(r"^\[enforce fail at [^]]*\]\s*\.?\s*", "", lines[0] if lines else type(exc).__name__)


def load_checkpoint(path: Path, device: torch.device | str = "cpu",
                    required: tuple[str, ...] = MODEL_KEYS) -> dict[str, Any]:
    """The checkpoint's state (tensors and plain values only: PyTorch's safe loader), holding at least `required`
    (its `model` a mapping of tensors); RuntimeError in one line, naming the file, for anything else."""
    path = Path(path)
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except OSError as exc:
        raise RuntimeError(f"checkpoint {path} cannot be read ({exc.strerror or exc})") from exc
    except Exception as exc:
        raise RuntimeError(f"checkpoint {path} cannot be read: {_load_failure(exc)}; use another of the run's "
                           "checkpoints (--step), or pass the config.yml of the run that wrote it") from None
    missing = [key for key in required if not isinstance(state, dict) or key not in state]
    model = state.get("model") if isinstance(state, dict) else None
    if missing or ("model" in required and not (isinstance(model, dict) and model
                                                and all(isinstance(v, torch.Tensor) for v in model.values()))):
        what = f"a {type(state).__name__}" if not isinstance(state, dict) else \
            f"keys {sorted(map(str, state))[:6] or 'none'}"
        raise RuntimeError(f"checkpoint {path} is not a uw3dgs checkpoint (it holds {what}; a uw-train checkpoint "
                           f"holds {', '.join(required)}): it was written by another tool; use a checkpoint uw-train "
                           "wrote, or pass the config.yml of the run that wrote it")
    return state
