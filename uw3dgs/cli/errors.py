"""How every command reports a user error: one readable line, the full traceback only on request."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from typing import NoReturn, TypeVar

from rich.console import Console
from rich.markup import escape


def exit_with_error(exc: BaseException, console: Console | None = None, hint: str = "",
                    message: str | None = None) -> NoReturn:
    """Print `error: <message>` (by default `str(exc)`) and exit with status 2; with UW3DGS_DEBUG set, re-raise for
    the traceback.

    The message is not wrapped (paths in it stay copyable) and brackets in it are not read as markup. It goes to
    `console` (the command's own, for its results), by default a new one on stdout: the command's last word, where
    its results would have been, not to the shared message console (`uw3dgs.utils.console`, stderr).
    """
    if os.environ.get("UW3DGS_DEBUG"):
        raise exc
    text = f"[bold red]error:[/bold red] {escape(str(exc) if message is None else message)}"
    if hint:
        text += f"\n{escape(hint)}"
    (console or Console()).print(text, soft_wrap=True)
    sys.exit(2)


T = TypeVar("T")
USER_ERRORS = (FileNotFoundError, ValueError, RuntimeError)
"""What a command reports as one line: the message names the file or option and the fix."""


def report_user_errors(work: Callable[[], T]) -> T:
    """`work()`, with a user error (USER_ERRORS, or an OSError such as a full disk or a missing permission, named
    with its path) reported by `exit_with_error`."""
    from uw3dgs.utils.io import describe_os_error

    try:
        return work()
    except USER_ERRORS as exc:
        exit_with_error(exc)
    except OSError as exc:
        exit_with_error(exc, message=describe_os_error(exc))
