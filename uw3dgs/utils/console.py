"""The one console every command and library part talks to the user through (rich, on stderr).

`info` and `warn` print one line each, never wrapped (paths stay copyable) and never read as rich markup
(brackets in file names are safe). Progress bars share the same console so messages do not tear them.
"""

from __future__ import annotations

import warnings

from rich.console import Console
from rich.markup import escape

CONSOLE = Console(stderr=True)
"""Writes to whatever sys.stderr is at the time (so pytest's capsys and redirections see it)."""


def info(message: str) -> None:
    """`uw3dgs: <message>`: what is happening (a cache written, a medium estimated)."""
    CONSOLE.print(f"uw3dgs: {escape(message)}", soft_wrap=True, highlight=False)


def warn(message: str) -> None:
    """`uw3dgs: warning: <message>`: something the user should act on, training goes on."""
    CONSOLE.print(f"[yellow]uw3dgs: warning:[/yellow] {escape(message)}", soft_wrap=True, highlight=False)


def route_warnings() -> None:
    """Show Python warnings (a backend falling back, a library's deprecation) as `warn` lines on this console
    instead of warnings' own multi-line format; the commands call it once at start. Code and tests still
    raise and catch them as warnings."""

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        warn(f"{message} ({category.__name__})")

    warnings.showwarning = show
