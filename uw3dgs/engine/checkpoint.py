"""Checkpoints: written atomically (temp file + rename), found by step, pruned to the newest few; and the check
that a model's parameters are finite (the Trainer runs it before every checkpoint, uw-eval before evaluating)."""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

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


def save_checkpoint(run_dir: Path, step: int, state: dict[str, Any], keep: int) -> Path:
    """Write `state` for `step`; a run killed mid-write leaves the previous checkpoints intact."""
    path = checkpoint_path(run_dir, step)
    with atomic_file(path, "wb", fsync=True) as f:
        torch.save(state, f)
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


def load_checkpoint(path: Path, device: torch.device | str = "cpu") -> dict[str, Any]:
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:
        raise RuntimeError(f"checkpoint {path} cannot be read ({exc}); delete it to fall back to the "
                           "previous one") from exc
