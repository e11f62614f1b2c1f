"""Compiled CPU rasterizer ('cpu' backend): C++/OpenMP projection, binning, compositing and backward.

The C++ sources (`csrc/cpu_rasterizer.cpp`; `csrc/vm_field.cpp`, the medium's VM field reads of
`fields/vm_kernel.py`; `csrc/sh_colors.cpp`, the SH colours of `sh_kernel.py`; `csrc/floater_mlp.cpp`, PAUP's phi;
`csrc/ssim.cpp`, the SSIM of the D-SSIM loss; `csrc/depth_consistency.cpp`, UW-3DGS's L_z; `csrc/bindings.cpp`) are
built as one module the first time one of them is used, with
`torch.utils.cpp_extension.load` (JIT, ninja + the system C++ compiler), into a folder per CPU flag set and
version of the sources and checkout under `$UW3DGS_CACHE/torch_extensions` (default `~/.cache/uw3dgs/torch_extensions`;
`$TORCH_EXTENSIONS_DIR` overrides it); later processes reuse the build. The rasterizer mirrors `reference.py`
numerically: same projection, opacity-aware radii, (tile, depth) ordering, alpha_min / alpha_max / early-termination
rules and exp() floor, in float32 or float64. If the build fails (no compiler, ...) the backend warns once and
falls back to the 'torch' reference.

Two autograd functions keep `means2d` an intermediate of the graph (so `retain_grad()` gives the
screen-space gradient): projection (means, quats, scales -> means2d, conics, depths) and compositing
(means2d, conics, opacities, features + depth -> render, depth, alpha). Both backwards are hand-written C++; gradients
are accumulated per (tile, Gaussian) slot and reduced per Gaussian in a fixed order, so results are
bitwise reproducible whatever the thread count. When a gradient is needed, the compositing forward also
records which pixels each Gaussian blended (4 bytes per blended run of 8 or 16 pixels), and the backward
replays exactly those; under `torch.no_grad()` nothing is recorded.
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
from torch.autograd.function import once_differentiable

from uw3dgs.data.cache import default_cache_dir
from uw3dgs.render.reference import rasterize_reference
from uw3dgs.render.types import RasterOutput, RasterSettings, TileLists
from uw3dgs.utils.console import info

EXTENSION_NAME = "uw3dgs_cpu_rasterizer"
SOURCES = [Path(__file__).parent / "csrc" / name
           for name in ("bindings.cpp", "cpu_rasterizer.cpp", "vm_field.cpp", "sh_colors.cpp", "floater_mlp.cpp",
                        "ssim.cpp", "depth_consistency.cpp", "medium_compositing.cpp")]
"""The rasterizer, the medium's VM field read (fields/vm_kernel.py), the SH colours (render/sh_kernel.py), PAUP's
phi (paup/scorer.py), the D-SSIM loss's SSIM (metrics/ssim_kernel.py), UW-3DGS's L_z (metrics/depth_consistency.py),
the medium compositor (render/medium_cpu.py) and their Python bindings: one module."""
HEADERS = sorted((Path(__file__).parent / "csrc").glob("*.h"))
"""Headers the sources include (exp_f32.h, vector_io.h): part of the build's version, and of the wheel."""
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

MAX_TILE = 256
"""Largest tile_size the compiled backend takes (its per-row codes hold 8-bit rows); larger ones use the reference."""

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
                              "compiled CPU rasterizer that did not finish (killed?); building again", RuntimeWarning,
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
                    info(f"building the compiled CPU rasterizer into {directory} (first use, about a minute)")
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
                "uw3dgs: could not build the compiled CPU rasterizer (backend 'cpu'); falling back to the "
                f"pure-PyTorch reference, which is much slower. Reason: {str(exc).strip()[-500:]}",
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


def _rasterizes(tensor: Tensor, settings: RasterSettings) -> bool:
    """Whether the compiled rasterizer takes Gaussians of this tensor's device and dtype with these settings."""
    return settings.tile_size <= MAX_TILE and runs_on(tensor)


def _reused(projection: RasterOutput, dtype: torch.dtype, settings: RasterSettings) -> tuple[Tensor, ...]:
    """An earlier render's screen-space Gaussians (means2d, conics, depths in `dtype`, radii) and its tile lists when
    made with these settings (None: bin again; the same outputs either way, composite_forward)."""
    means2d, conics, depths = (t.detach().to(dtype).contiguous()
                               for t in (projection.means2d, projection.conics, projection.depths))
    lists = projection.tile_lists
    lists = lists.tensors if lists is not None and lists.tile_size == settings.tile_size else None
    return means2d, conics, depths, projection.radii.contiguous(), lists


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K, width, height, settings):
        ext = _state["module"]
        means2d, conics, depths, radii = ext.project_forward(
            means, quats, scales, opacities, viewmat, K, width, height,
            settings.near_plane, settings.far_plane, settings.eps2d, settings.alpha_min,
        )  # fmt: skip
        ctx.save_for_backward(means, quats, scales, viewmat, K)
        ctx.view = (width, height, settings)
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    @once_differentiable
    def backward(ctx, g_means2d, g_conics, g_depths, _g_radii):
        means, quats, scales, viewmat, K = ctx.saved_tensors
        width, height, settings = ctx.view
        n = len(means)
        g_means2d = means.new_zeros(n, 2) if g_means2d is None else g_means2d.contiguous()
        g_conics = means.new_zeros(n, 3) if g_conics is None else g_conics.contiguous()
        g_depths = means.new_zeros(n) if g_depths is None else g_depths.contiguous()
        g_means, g_quats, g_scales = _state["module"].project_backward(
            means, quats, scales, viewmat, K, width, height,
            settings.near_plane, settings.far_plane, settings.eps2d, g_means2d, g_conics, g_depths,
        )  # fmt: skip
        return g_means, g_quats, g_scales, None, None, None, None, None, None


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, depths, radii, width, height, settings, tile_lists):
        ext = _state["module"]
        for_backward = any(ctx.needs_input_grad[:4])  # else no state is recorded for a backward
        render, depth, alpha, weight_sum, pixel_count, *state = ext.composite_forward(
            means2d, conics, opacities, feats, depths, radii, width, height, settings.tile_size,
            settings.alpha_min, settings.alpha_max, settings.transmittance_min, for_backward, list(tile_lists or ()),
        )  # fmt: skip
        ctx.save_for_backward(means2d, conics, opacities, feats, *state)
        ctx.view = (width, height, settings)
        # the state's tile lists (tile starts, sorted Gaussians, their slots, Gaussian starts), for a later render
        lists = state[1:5] if for_backward else []
        ctx.mark_non_differentiable(weight_sum, pixel_count, *lists)
        return render, depth, alpha, weight_sum, pixel_count, *lists

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_render, grad_depth, grad_alpha, _grad_weight_sum, _grad_pixel_count, *_grad_lists):
        means2d, conics, opacities, feats, *state = ctx.saved_tensors
        width, height, settings = ctx.view
        empty = means2d.new_empty(0)  # stands for a zero gradient: unused outputs cost nothing
        # frozen Gaussians (PAUP's masked render) need the opacities' gradient only: about half the work
        geometry = any(ctx.needs_input_grad[i] for i in (0, 1, 3))
        g_means2d, g_conics, g_opacities, g_feats = _state["module"].composite_backward(
            means2d, conics, opacities, feats, width, height, settings.tile_size,
            settings.alpha_max, state,
            *(empty if g is None else g.contiguous() for g in (grad_render, grad_depth, grad_alpha)), geometry,
        )  # fmt: skip
        if not geometry:
            g_means2d = g_conics = g_feats = None
        return g_means2d, g_conics, g_opacities, g_feats, None, None, None, None, None, None


class _MaskedL1(torch.autograd.Function):
    """PAUP's masked render and its L1 to a target in one compiled pass (csrc masked_l1): the forward already has the
    opacities' gradient, so the backward only scales it."""

    @staticmethod
    def forward(ctx, opacities, means2d, conics, features, depths, radii, target, width, height, settings, tile_lists):
        image, l1, grad = _state["module"].masked_l1(
            means2d, conics, opacities, features, depths, radii, width, height, settings.tile_size,
            settings.alpha_min, settings.alpha_max, settings.transmittance_min, list(tile_lists or ()), target,
        )  # fmt: skip
        ctx.save_for_backward(grad)
        ctx.mark_non_differentiable(image)
        return image, l1

    @staticmethod
    @once_differentiable
    def backward(ctx, _grad_image, grad_l1):
        (grad,) = ctx.saved_tensors
        return grad * grad_l1, None, None, None, None, None, None, None, None, None, None


def masked_l1_cpu(projection: RasterOutput, opacities: Tensor, features: Tensor, target: Tensor, width: int,
                  height: int, settings: RasterSettings) -> tuple[Tensor, Tensor] | None:
    """`rasterize.masked_l1` on the compiled backend; None where it does not run (not a CPU float tensor, a tile
    larger than MAX_TILE, no build)."""
    if not _rasterizes(opacities, settings):
        return None
    dtype = opacities.dtype
    means2d, conics, depths, radii, lists = _reused(projection, dtype, settings)
    return _MaskedL1.apply(opacities.contiguous(), means2d, conics, features.detach().to(dtype).contiguous(), depths,
                           radii, target.detach().to(dtype).contiguous(), width, height, settings, lists)


def rasterize_cpu(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    settings: RasterSettings,
    projection: RasterOutput | None = None,
) -> RasterOutput:
    """Same contract and numbers as `rasterize_reference`, compiled ('cpu' backend)."""
    if not _rasterizes(means, settings):
        return rasterize_reference(means, quats, scales, opacities, features, viewmat, K, width, height, settings,
                                   projection)
    dtype = means.dtype
    opacities, features = (t.to(dtype).contiguous() for t in (opacities, features))
    tile_lists = None
    if projection is not None:
        means2d, conics, depths, radii, tile_lists = _reused(projection, dtype, settings)
    else:
        means, quats, scales = (t.to(dtype).contiguous() for t in (means, quats, scales))
        viewmat = viewmat.detach().to(dtype).contiguous()
        K = K.detach().to(dtype).contiguous()
        # the projection reads the opacities for the radii only (no gradient): detached, a render whose Gaussians
        # are frozen but whose opacities carry one (PAUP's masked render) runs no projection backward
        means2d, conics, depths, radii = _Project.apply(means, quats, scales, opacities.detach(), viewmat, K, width,
                                                        height, settings)  # fmt: skip
    feats = torch.cat([features, depths[:, None]], dim=1)  # depth composites like a feature
    # Separate render / depth / alpha outputs: no slicing, so no zero-fill + copy ops in the backward.
    render, depth, alpha, weight_sum, pixel_count, *lists = _Composite.apply(
        means2d, conics, opacities, feats, depths.detach(), radii, width, height, settings, tile_lists
    )
    return RasterOutput(
        render=render,
        alpha=alpha,
        depth=depth,
        means2d=means2d,
        radii=radii,
        depths=depths,
        conics=conics,
        weight_sum=weight_sum,
        pixel_count=pixel_count,
        tile_lists=TileLists(settings.tile_size, tuple(lists)) if lists else None,
    )
