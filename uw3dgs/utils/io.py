"""Writing files and folders atomically: a run killed at any instant leaves the old version or the new
one, never half of either (checkpoints, configs, eval JSON, cached images and scenes, SfM models).

    with atomic_file(path, "w") as f: ...          # a file: temp file in the same folder, then rename
    write_text(path, text) / write_json(path, data)
    with atomic_folder(target) as tmp: ...         # a folder: filled in a temp sibling, then renamed

A process killed between creating a temp file and its rename (kill -9, power cut) leaves the temp file
(`.<name>.<32 hex>.tmp`); `remove_temp_files` removes those of a folder its owner is about to write again.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
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
    created. `fsync=True` flushes the data to disk before the rename (checkpoints: survive a power cut). An OSError
    that names no file (a write to a full disk) is raised again naming `path`.
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
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if exc.filename is None:  # a failed write (a full disk) names no file: name the one being written
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


TEMP_FILE = re.compile(r"^\.(?P<name>.+)\.[0-9a-f]{32}\.tmp$")
"""The name `atomic_file` gives its temporary file: `.<name>.<uuid4 hex>.tmp` beside the target."""


def remove_temp_files(folder: str | os.PathLike, names: set[str] | None = None) -> list[Path]:
    """Remove the temporary files `atomic_file` left in `folder` (of targets in `names`, or all); only for a folder
    no other process is writing to (a run folder whose lock is held). Returns what was removed."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    removed = []
    for path in folder.iterdir():
        m = TEMP_FILE.match(path.name)
        if m and (names is None or m.group("name") in names) and path.is_file():
            path.unlink(missing_ok=True)
            removed.append(path)
    return removed


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


def describe_os_error(exc: OSError) -> str:
    """An OSError from writing outputs as one line: the path, what is wrong and the usual fix."""
    path = exc.filename if exc.filename is not None else "?"
    if exc.filename2 is not None:
        path = f"{path} -> {exc.filename2}"
    if isinstance(exc, (NotADirectoryError, FileExistsError)):
        fix = "a file is in the way of a folder; choose another path or move the file"
    elif isinstance(exc, IsADirectoryError):
        fix = "a folder is in the way of a file; choose another path"
    elif isinstance(exc, PermissionError) or exc.errno == errno.EROFS:
        fix = "not writable; choose a folder you can write to"
    elif exc.errno == errno.ENOSPC:
        fix = "the disk is full; free some space"
    else:
        fix = ""
    return f"{path}: {exc.strerror or exc}" + (f" ({fix})" if fix else "")


def unwritable_reason(path: str | os.PathLike, folder: bool = False) -> str | None:
    """Why the file (or, with `folder`, the folder) `path` could not be written, or None if it looks writable:
    a file where a folder must be, a folder where the file must be, or a folder this user cannot write to.
    Checked before long work (an evaluation, a scene generation) so that it does not end in a traceback."""
    path = Path(path)
    if path.exists() and path.is_dir() != folder:
        what = "a folder" if path.is_dir() else "a file"
        return f"{path} is {what}; give {'a folder' if folder else 'a file name'}"
    parent = path if folder and path.exists() else path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        return f"{parent} is a file, not a folder; choose another path or move the file"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"{parent} is not writable; choose a folder you can write to"
    return None
