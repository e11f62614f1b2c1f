"""Stopping on a signal: SIGINT (Ctrl-C) or SIGTERM (what cluster schedulers send) ends a training run after the
current step, with that step's checkpoint, instead of in the middle of one (`StopRequests`); the other long-running
commands (uw-render, uw-viewer) take SIGTERM as Ctrl-C (`sigterm_as_interrupt`): a clean exit, no temporary file."""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any


class TrainingInterrupted(Exception):
    """SIGINT (Ctrl-C) or SIGTERM stopped the run after a complete step, whose checkpoint was written; a command
    exits with 128 + `signum` (130, 143)."""

    def __init__(self, signum: int, step: int, checkpoint: Path, message: str):
        super().__init__(message)
        self.signum, self.step, self.checkpoint = signum, step, checkpoint


class StopRequests:
    """While training: the first SIGINT or SIGTERM asks the loop to stop after the current step (the state after a
    complete step is consistent: it is checkpointed); a second SIGINT stops at once (KeyboardInterrupt: the last
    periodic checkpoint stands). Handlers are installed in the main thread only, and restored on exit."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopRequests:
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)
        self._previous.clear()

    def _handle(self, signum: int, frame: object) -> None:
        if self.signum is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        if self.signum is None:
            self.signum = signum
            try:  # a handler may run inside a write to stderr: never let the notice break the run
                sys.stderr.write(f"\n{signal.Signals(signum).name}: stopping after this step and writing its "
                                 "checkpoint (Ctrl-C again stops at once, without it)\n")
                sys.stderr.flush()
            except (RuntimeError, OSError, ValueError):
                pass


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C's KeyboardInterrupt (so every `with` block and `finally` cleans up: temporary
    files removed, servers stopped); a command exits with 143 (128 + SIGTERM)."""

    exit_code = 128 + signal.SIGTERM


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Inside: SIGTERM raises `Terminated` in the main thread instead of killing the process (whose native handlers,
    e.g. the one pycolmap's logging installs when imported, dump a stack and leave temporary files). Enter it after
    the imports that install such handlers; the previous handler is restored on exit. Does nothing outside the main
    thread, where no handler can be installed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)
