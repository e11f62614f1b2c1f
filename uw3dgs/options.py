"""Option checks: every config checks its own numbers where they are declared.

A config's `check_options()` (called from `CheckedConfig.__post_init__`) raises `OptionError` naming the
field; `check_config` runs the checks of a whole config and names the option in full (`--optimizers.means.lr`),
as the command line and config files do. While a whole config is parsed (`deferred_checks`), the per-config
checks wait, so the first error names the option as the user typed it.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import math
from collections.abc import Iterator
from typing import Any


class OptionError(ValueError):
    """An option's value is out of range. `name` is the field of the config that declares it; once the config's
    place in the whole config is known (`check_config`), `path` is the full dotted path, and the message names
    the option as typed on the command line (`--optimizers.means.lr`) or as the key of a config file."""

    def __init__(self, name: str, reason: str, path: tuple[str, ...] | None = None):
        self.name = name
        self.reason = reason
        self.path = path
        super().__init__(name, reason, path)

    @property
    def key(self) -> str:
        """The dotted key in config.yml: `optimizers.means.lr`."""
        return ".".join(self.path or (self.name,))

    @property
    def flag(self) -> str:
        """The command-line option: `--optimizers.means.lr`."""
        return "--" + self.key.replace("_", "-")

    def at(self, prefix: tuple[str, ...]) -> OptionError:
        """This error located under `prefix` (the path of the config that raised it)."""
        return OptionError(self.name, self.reason, (*prefix, *(self.path or (self.name,))))

    def __str__(self) -> str:
        return f"{self.flag if self.path is not None else self.name} {self.reason}"


def _bounds_text(ge: float | None, gt: float | None, le: float | None, lt: float | None) -> str:
    parts = [f"{op} {v:g}" for op, v in ((">=", ge), (">", gt), ("<=", le), ("<", lt)) if v is not None]
    return " and ".join(parts)


def check_number(config: Any, name: str, *, ge: float | None = None, gt: float | None = None,
                 le: float | None = None, lt: float | None = None, integer: bool = False, optional: bool = False,
                 each: bool = False) -> None:
    """Raise `OptionError` unless `config.<name>` is a finite number (a whole number with `integer`) within the
    bounds; None passes with `optional`; `each` checks every element of a tuple."""
    value = getattr(config, name)
    if value is None and optional:
        return
    kind = "a whole number" if integer else "a finite number"
    bounds = _bounds_text(ge, gt, le, lt)
    want = f"{kind} {bounds}".strip() if not each else f"numbers each {bounds or 'finite'}"
    for v in (value if each and isinstance(value, (tuple, list)) else (value,)):
        ok = not isinstance(v, bool) and (isinstance(v, int) if integer else isinstance(v, (int, float)))
        ok = ok and (integer or math.isfinite(v))
        ok = ok and (ge is None or v >= ge) and (gt is None or v > gt) and (le is None or v <= le) and \
            (lt is None or v < lt)
        if not ok:
            raise OptionError(name, f"must be {want}, got {value!r}")


_DEFERRED: contextvars.ContextVar[bool] = contextvars.ContextVar("uw3dgs_deferred_checks", default=False)


@contextlib.contextmanager
def deferred_checks() -> Iterator[None]:
    """Configs built inside skip their own checks; the caller then runs `check_config` on the whole config,
    which knows where each config sits and so names the option in full (used while parsing the command line
    and while reading a config file)."""
    token = _DEFERRED.set(True)
    try:
        yield
    finally:
        _DEFERRED.reset(token)


@dataclasses.dataclass(frozen=True)
class CheckedConfig:
    """Base of every config dataclass: its options are checked as soon as it is built (`check_options`, which
    subclasses extend, calling super), or once the whole config is built while parsing (`deferred_checks`)."""

    def __post_init__(self) -> None:
        if not _DEFERRED.get():  # while a whole config is parsed, its builder checks it afterwards, with full names
            self.check_options()

    def check_options(self) -> None:
        """Raise `OptionError(field, reason)` for an option out of range (`check_number` covers most)."""


def check_config(config: Any, prefix: tuple[str, ...] = ()) -> None:
    """Run `check_options` of `config` and of every config nested in it (dict values too); the first failure
    is raised as an `OptionError` whose path is the option's full path under `prefix`."""
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        check = getattr(config, "check_options", None)
        if check is not None:
            try:
                check()
            except OptionError as err:
                raise err.at(prefix) from None
        for f in dataclasses.fields(config):
            if f.name != "_target":
                check_config(getattr(config, f.name), (*prefix, f.name))
    elif isinstance(config, dict):
        for key, value in config.items():
            check_config(value, (*prefix, str(key)))
