"""Writing files and folders atomically: a run killed at any instant leaves the old version or the new
one, never half of either (checkpoints, configs, eval JSON, cached images and scenes, SfM models).

    with atomic_file(path, "w") as f: ...          # a file: temp file in the same folder, then rename
    write_text(path, text) / write_json(path, data)
    with atomic_folder(target) as tmp: ...         # a folder: filled in a temp sibling, then renamed
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike, mode: str = "wb", fsync: bool = False) -> Iterator[IO[Any]]:
    """Open a temporary file beside `path` for writing (`mode` 'w' or 'wb'); on a clean exit it replaces
    `path` in one rename, on an exception it is removed and `path` is untouched. The parent folder is
    created. `fsync=True` flushes the data to disk before the rename (checkpoints: survive a power cut).
    The temp file is opened with plain `open`, so it gets the umask's permissions like any other file."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_file writes whole files: mode 'w' or 'wb', got {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        with open(tmp, mode.replace("w", "x")) as f:
            yield f
            if fsync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write `text` to `path` atomically."""
    with atomic_file(path, "w") as f:
        f.write(text)


def write_json(path: str | os.PathLike, data: Any) -> None:
    """Write `data` as indented JSON to `path` atomically."""
    write_text(path, json.dumps(data, indent=2))


@contextlib.contextmanager
def atomic_folder(target: str | os.PathLike, replace: bool = False) -> Iterator[Path]:
    """Yield an empty temporary folder beside `target`; on a clean exit it becomes `target` in one rename.

    If `target` exists by then (another process finished first), the new folder is dropped and the
    existing one kept, unless `replace=True`, which removes the old `target` first (the remove and the
    rename are two steps: a reader may see no `target` in between, never a partial one). On an
    exception the temporary folder is removed and `target` is untouched."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}-"))
    try:
        yield tmp
        if target.exists() and replace:
            shutil.rmtree(target)
        if target.exists():
            shutil.rmtree(tmp)
        else:
            os.replace(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
