"""Building and loading the compiled CPU kernels: every `.cpp` of this folder as one Python module.

The sources are built the first time a kernel is used, with `torch.utils.cpp_extension.load` (JIT, ninja + the
system C++ compiler), into a folder per CPU flag set and version of the sources and checkout under
`$UW3DGS_CACHE/torch_extensions` (default `~/.cache/uw3dgs/torch_extensions`; `$TORCH_EXTENSIONS_DIR` overrides
it); later processes reuse the build. If the build fails (no compiler, ...) `load_extension` warns once and
returns None, and every caller takes its PyTorch reference instead.
"""

from __future__ import annotations

import hashlib
import os
import socket
import sys
import threading
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

import torch
from torch import Tensor

from uw3dgs.data.cache import default_cache_dir
from uw3dgs.utils.console import info

EXTENSION_NAME = "uw3dgs_cpu_kernels"
KERNELS_DIR = Path(__file__).parent
SOURCES = sorted(KERNELS_DIR.glob("*.cpp"))
"""Every stage's C++ (this folder's .cpp files, bindings.cpp among them): one module."""
HEADERS = sorted(KERNELS_DIR.glob("*.h"))
"""Headers the sources include: part of the build's version, and of the wheel."""
CFLAGS = ["-O3", "-fopenmp", "-ffp-contract=off", "-fno-math-errno"]
"""-ffp-contract=off: no fused multiply-adds, so results follow the reference's rounding as closely as possible."""


AVX512 = ["avx512f", "avx512dq", "avx512vl", "avx512bw"]


def _simd_flags() -> list[str]:
    """AVX-512 or AVX2 when this CPU has it (x86 Linux): compositing then works on 16 or 8 pixels per instruction.

    The build folder is named after the flag set, so caches built for different CPUs never mix.
    """
    try:
        flags = set(Path("/proc/cpuinfo").read_text().split())
    except OSError:
        return []
    if not {"avx2", "fma"} <= flags:
        return []
    return ["-mavx2", "-mfma"] + ([f"-m{f}" for f in AVX512] if set(AVX512) <= flags else [])


STALE_LOCK_SECONDS = 900.0
"""A build lock of another host older than this is taken as left by a killed build (a build takes one to three
minutes); on this host the lock's process is asked directly."""

_lock = threading.Lock()
_state: dict[str, object] = {}


def build_directory() -> Path:
    """Where the JIT build goes: $TORCH_EXTENSIONS_DIR, else $UW3DGS_CACHE (or ~/.cache/uw3dgs)/torch_extensions;
    one folder per CPU flag set, version of the sources and checkout."""
    if os.environ.get("TORCH_EXTENSIONS_DIR"):
        root = Path(os.environ["TORCH_EXTENSIONS_DIR"])
    else:
        root = default_cache_dir() / "torch_extensions"
    flags = _simd_flags()
    simd = "_avx512" if "-mavx512f" in flags else "_avx2" if flags else ""
    # the sources' hash (headers too): two checkouts of different versions on one machine never rebuild over each
    # other's module. Their paths too: torch's build file names them, so two checkouts of the same version in one
    # folder rebuilt everything (a minute, inside the first training step) whenever the other one had run last.
    digest = hashlib.sha256(b"".join(str(path.resolve()).encode() + path.read_bytes()
                                     for path in [*SOURCES, *HEADERS])).hexdigest()[:10]
    return root / f"{EXTENSION_NAME}{simd}_torch{torch.__version__.split('+')[0]}_{digest}"


def _lock_is_stale(owner: str, age: float, stale_after: float) -> bool:
    """Whether a build lock written as 'host pid' belongs to a build that is gone."""
    host, _, pid = owner.partition(" ")
    if host != socket.gethostname() or not pid.isdigit():
        return age > stale_after
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # alive, another user's
        return False
    return False


@contextmanager
def build_lock(directory: Path, stale_after: float = STALE_LOCK_SECONDS, poll: float = 0.5) -> Iterator[None]:
    """Hold `directory`'s build lock (`build.pid`, 'host pid') while building or loading the extension there; wait
    while a live process holds it. torch's own lock (`lock`) has no owner and a killed build leaves it behind for
    ever; a lock whose process is gone (or, from another host, older than `stale_after`) is removed with torch's,
    with a warning, and the build starts again."""
    path = directory / "build.pid"
    while True:
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                owner, age = path.read_text(), time.time() - path.stat().st_mtime
            except FileNotFoundError:
                continue
            if _lock_is_stale(owner.strip(), age, stale_after):
                warnings.warn(f"uw3dgs: removing {path} ({owner.strip() or 'no owner'}), left by a build of the "
                              "compiled CPU kernels that did not finish (killed?); building again", RuntimeWarning,
                              stacklevel=3)
                path.unlink(missing_ok=True)
                (directory / "lock").unlink(missing_ok=True)
                continue
            time.sleep(poll)
            continue
        with os.fdopen(fd, "w") as handle:
            handle.write(f"{socket.gethostname()} {os.getpid()}")
        break
    try:
        yield
    finally:
        path.unlink(missing_ok=True)


def load_extension(verbose: bool = False) -> ModuleType | None:
    """Build (first use) or load the extension; None, after one warning, if that fails."""
    with _lock:
        if "module" in _state:
            return _state["module"]  # type: ignore[return-value]
        module = None
        start = time.perf_counter()
        try:
            from torch.utils import cpp_extension

            directory = build_directory()
            directory.mkdir(parents=True, exist_ok=True)
            # torch runs `ninja` from PATH; the `ninja` wheel puts it beside this interpreter, which is not on
            # PATH when a venv's console script is called without activating the venv
            bin_dir = str(Path(sys.executable).parent)
            if bin_dir not in os.environ.get("PATH", "").split(os.pathsep):
                os.environ["PATH"] = bin_dir + os.pathsep + os.environ.get("PATH", "")
            with build_lock(directory):
                if not (directory / f"{EXTENSION_NAME}.so").exists():
                    info(f"building the compiled CPU kernels into {directory} (first use, about two minutes on two "
                             "cores)")
                module = cpp_extension.load(
                    name=EXTENSION_NAME,
                    sources=[str(path) for path in SOURCES],
                    extra_cflags=CFLAGS + _simd_flags(),
                    extra_ldflags=["-fopenmp"],
                    build_directory=str(directory),
                    verbose=verbose,
                )
        except Exception as exc:  # noqa: BLE001 - any build failure means: fall back
            _state["error"] = f"{type(exc).__name__}: {exc}"
            # a RuntimeWarning, not console.warn: callers (and tests) filter or catch it with `warnings`
            warnings.warn(
                "uw3dgs: could not build the compiled CPU kernels (rasterizer backend 'cpu' and the others); falling "
                f"back to the pure-PyTorch references, which are much slower. Reason: {str(exc).strip()[-500:]}",
                RuntimeWarning,
                stacklevel=3,
            )
        _state["module"] = module
        _state["load_seconds"] = time.perf_counter() - start
        return module


def is_available() -> bool:
    """Whether the extension builds / loads on this machine (builds it on first call)."""
    return load_extension() is not None


def runs_on(tensor: Tensor) -> bool:
    """Whether the compiled kernels take this tensor: on the CPU, float32 or float64, and the extension built."""
    return tensor.device.type == "cpu" and tensor.dtype in (torch.float32, torch.float64) and is_available()




def extension() -> ModuleType:
    """The loaded module, for the kernels' Python faces once `runs_on` (or `is_available`) said it is there."""
    module = load_extension()
    if module is None:
        raise RuntimeError(f"the compiled CPU kernels are not available: {_state.get('error')}")
    return module


def main() -> None:
    """`python -m uw3dgs.kernels.build`: build (or find) the kernels now instead of at their first use; exit status 1
    when they cannot be built (the reason is printed)."""
    module = load_extension()
    if module is None:
        print(f"uw3dgs: the compiled CPU kernels could not be built: {_state.get('error')}", file=sys.stderr)
        sys.exit(1)
    print(f"uw3dgs: compiled CPU kernels ready in {build_directory()} ({_state['load_seconds']:.0f} s)")


if __name__ == "__main__":
    main()
