"""numba (parallel=True) against C++/OpenMP (torch.utils.cpp_extension) on one small 3DGS kernel.

    MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000 OMP_WAIT_POLICY=passive \\
        python benchmarks/speed/numba_vs_cpp.py

Why: the issue asked for the compiled CPU rasterizer to be written either in C++ (cpp_extension + OpenMP)
or in numba (`prange`), choosing after measuring both on a small kernel. This script is that measurement.

What: the forward alpha compositing of 3D Gaussian splatting, written twice with the same algorithm, the
same float32 arithmetic (same operation order, no fast-math, no fused multiply-adds) and the same
parallelisation (one 16x16 tile per parallel iteration). Given N projected, depth-sorted 2D Gaussians
(means2d [N,2], conics [N,3], opacities [N], colours [N,3]), every pixel blends its tile's Gaussians front
to back with alpha = min(0.99, o * exp(-0.5 (a dx^2 + 2 b dx dy + c dy^2))), skips alpha < 1/255 and stops
before T drops below 1e-4; outputs are rgb [H,W,3] and alpha [H,W].
The per-tile Gaussian lists are built once in numpy and shared by both. Each Gaussian is binned by the
axis-aligned box of the ellipse where its alpha can reach 1/255 (an opacity-aware bound, not a fixed
3 sigma: at 3 sigma alpha is still o * 0.011, above 1/255 whenever o > 0.35, and the brute-force check
below would see those contributions).

Measured: the first-call time of each (C++: the `load_inline` build in a fresh folder, so never a cache hit;
numba: the JIT compile on the first call), then the median of --repeats timed calls (after one warm-up)
per scene, thread count and schedule, the two backends alternating so that load changes hit both alike.
Two schedules, the same for both: "static" (the tiles split into one equal block per thread: numba's
default, OpenMP schedule(static)) and "dynamic" (tiles handed out one at a time: numba
`set_parallel_chunksize(1)`, OpenMP schedule(dynamic, 1), what the project's rasterizer uses). Both
allocate their outputs uninitialised: in numba `np.zeros` is itself a parallel loop, and the chunk size
applies to it too, so with chunk size 1 zero-filling costs more than the kernel (docs/rasterizer.md). Outputs
must agree with each other, and on a tiny scene with a float64 numpy brute force (every Gaussian on every
pixel), to 1e-5; the script exits with an error otherwise. It prints Markdown tables.

The C++ build uses the project's own flags (`uw3dgs.kernels.build.CFLAGS` plus the AVX2/AVX-512
flags it adds on this CPU); numba compiles for the host CPU. numba is a benchmark-only dependency:
`pip install -c constraints.txt numba`.
"""

from __future__ import annotations

import argparse
import atexit
import math
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

_t0 = time.perf_counter()
try:
    import numba
except ImportError:
    sys.exit("numba is not installed; this benchmark needs it: pip install -c constraints.txt numba")
NUMBA_IMPORT_S = time.perf_counter() - _t0

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository root
from uw3dgs.data.cache import default_cache_dir  # noqa: E402
from uw3dgs.kernels.build import CFLAGS, _simd_flags  # noqa: E402
from uw3dgs.utils.console import info  # noqa: E402

TILE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
TOLERANCE = 1e-5
CONFIGS = [(2_000, 256), (20_000, 512)]

# float32 constants: numba would otherwise promote float32 arithmetic to float64 on Python float literals
F_ZERO, F_HALF, F_ONE, F_TWO = np.float32(0.0), np.float32(0.5), np.float32(1.0), np.float32(2.0)
F_NEG_HALF = np.float32(-0.5)
F_ALPHA_MIN, F_ALPHA_MAX, F_T_MIN = np.float32(ALPHA_MIN), np.float32(ALPHA_MAX), np.float32(T_MIN)


# ----------------------------------------------------------------------------------------------- scene and tiles


def make_scene(n: int, width: int, height: int, seed: int = 0) -> dict[str, np.ndarray]:
    """n random 2D Gaussians: centres over the image, sigmas 1 to 10 px (log-uniform), any orientation.

    Index order is the depth order (front first). Returns float32 arrays.
    """
    rng = np.random.default_rng(seed)
    means2d = rng.uniform([0.0, 0.0], [width, height], size=(n, 2))
    sigma_major = np.exp(rng.uniform(math.log(1.0), math.log(10.0), n))
    sigma_minor = sigma_major / rng.uniform(1.0, 4.0, n)
    theta = rng.uniform(0.0, math.pi, n)
    cos, sin = np.cos(theta), np.sin(theta)
    rot = np.stack([np.stack([cos, -sin], -1), np.stack([sin, cos], -1)], -2)  # [n, 2, 2]
    cov = rot @ (np.stack([sigma_major, sigma_minor], -1)[:, :, None] ** 2 * np.swapaxes(rot, 1, 2))
    inv = np.linalg.inv(cov)
    return {
        "means2d": means2d.astype(np.float32),
        "conics": np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1).astype(np.float32),
        "opacities": rng.uniform(0.05, 1.0, n).astype(np.float32),
        "colors": rng.uniform(0.0, 1.0, (n, 3)).astype(np.float32),
    }


def bin_tiles(scene: dict[str, np.ndarray], width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-tile Gaussian lists in CSR form: tile t holds ids[offsets[t]:offsets[t+1]], in depth order.

    A Gaussian goes to every tile overlapped by the bounding box of {alpha >= 1/255}: the ellipse
    d^T C d <= 2 ln(255 o), whose half-extents are sqrt(q_max * cov_xx) and sqrt(q_max * cov_yy), plus a
    one-pixel margin for float32 rounding.
    """
    a, b, c = (scene["conics"][:, k].astype(np.float64) for k in range(3))
    det = a * c - b * b
    q_max = 2.0 * np.log(np.maximum(255.0 * scene["opacities"].astype(np.float64), 1.0))
    half_x = np.sqrt(q_max * c / det) + 1.0
    half_y = np.sqrt(q_max * a / det) + 1.0
    mx, my = (scene["means2d"][:, k].astype(np.float64) - 0.5 for k in range(2))  # pixel x has its centre at x+0.5
    ntx, nty = -(-width // TILE), -(-height // TILE)
    tx0 = np.clip(np.floor((mx - half_x) / TILE), 0, ntx).astype(np.int64)
    tx1 = np.clip(np.floor((mx + half_x) / TILE) + 1, 0, ntx).astype(np.int64)  # exclusive
    ty0 = np.clip(np.floor((my - half_y) / TILE), 0, nty).astype(np.int64)
    ty1 = np.clip(np.floor((my + half_y) / TILE) + 1, 0, nty).astype(np.int64)
    spans_x, spans_y = tx1 - tx0, ty1 - ty0
    counts = spans_x * spans_y
    gid = np.repeat(np.arange(len(counts)), counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    tiles = (ty0[gid] + local // spans_x[gid]) * ntx + tx0[gid] + local % spans_x[gid]
    order = np.argsort(tiles, kind="stable")  # stable: Gaussians stay in depth order within a tile
    offsets = np.zeros(ntx * nty + 1, np.int64)
    np.cumsum(np.bincount(tiles, minlength=ntx * nty), out=offsets[1:])
    return offsets, gid[order].astype(np.int32)


# ----------------------------------------------------------------------------------------------- the two kernels


@numba.njit(parallel=True, fastmath=False, cache=False)
def composite_numba(means2d, conics, opacities, colors, offsets, ids, width, height):
    """numba version: one prange iteration per tile, a scalar loop per pixel over the tile's list."""
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    rgb = np.empty((height, width, 3), np.float32)  # every pixel is written; np.zeros would be a parfor
    alpha = np.empty((height, width), np.float32)
    for t in numba.prange(ntx * nty):
        ty = t // ntx
        tx = t - ty * ntx
        for y in range(ty * TILE, min(ty * TILE + TILE, height)):
            py = np.float32(y) + F_HALF
            for x in range(tx * TILE, min(tx * TILE + TILE, width)):
                px = np.float32(x) + F_HALF
                trans = F_ONE
                r = F_ZERO
                g = F_ZERO
                b = F_ZERO
                for k in range(offsets[t], offsets[t + 1]):
                    i = ids[k]
                    dx = px - means2d[i, 0]
                    dy = py - means2d[i, 1]
                    power = F_NEG_HALF * (conics[i, 0] * dx * dx + F_TWO * conics[i, 1] * dx * dy
                                          + conics[i, 2] * dy * dy)
                    a = min(F_ALPHA_MAX, opacities[i] * math.exp(power))
                    if a < F_ALPHA_MIN:
                        continue
                    next_trans = trans * (F_ONE - a)
                    if next_trans < F_T_MIN:
                        break
                    weight = a * trans
                    r += weight * colors[i, 0]
                    g += weight * colors[i, 1]
                    b += weight * colors[i, 2]
                    trans = next_trans
                rgb[y, x, 0] = r
                rgb[y, x, 1] = g
                rgb[y, x, 2] = b
                alpha[y, x] = F_ONE - trans
    return rgb, alpha


CPP_SOURCE = r"""
#include <torch/extension.h>
#include <algorithm>
#include <cmath>
#ifdef _OPENMP
#include <omp.h>
#endif

// C++ version: one OpenMP iteration per tile, a scalar loop per pixel over the tile's list.
std::vector<torch::Tensor> composite(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                     torch::Tensor colors, torch::Tensor offsets, torch::Tensor ids,
                                     int64_t width, int64_t height) {
  const int64_t T = TILE;
  auto rgb = torch::empty({height, width, 3}, means2d.options());  // every pixel is written
  auto alpha = torch::empty({height, width}, means2d.options());
  const float* m = means2d.data_ptr<float>();
  const float* con = conics.data_ptr<float>();
  const float* op = opacities.data_ptr<float>();
  const float* col = colors.data_ptr<float>();
  const int64_t* off = offsets.data_ptr<int64_t>();
  const int32_t* id = ids.data_ptr<int32_t>();
  float* out_rgb = rgb.data_ptr<float>();
  float* out_alpha = alpha.data_ptr<float>();
  const int64_t ntx = (width + T - 1) / T, nty = (height + T - 1) / T;
#pragma omp parallel for schedule(runtime)
  for (int64_t t = 0; t < ntx * nty; ++t) {
    const int64_t ty = t / ntx, tx = t - ty * ntx;
    for (int64_t y = ty * T; y < std::min(ty * T + T, height); ++y) {
      const float py = float(y) + 0.5f;
      for (int64_t x = tx * T; x < std::min(tx * T + T, width); ++x) {
        const float px = float(x) + 0.5f;
        float trans = 1.f, r = 0.f, g = 0.f, b = 0.f;
        for (int64_t k = off[t]; k < off[t + 1]; ++k) {
          const int64_t i = id[k];
          const float dx = px - m[2 * i], dy = py - m[2 * i + 1];
          const float power = -0.5f * (con[3 * i] * dx * dx + 2.f * con[3 * i + 1] * dx * dy
                                       + con[3 * i + 2] * dy * dy);
          const float a = std::min(ALPHA_MAX, op[i] * std::exp(power));
          if (a < ALPHA_MIN) continue;
          const float next_trans = trans * (1.f - a);
          if (next_trans < T_MIN) break;
          const float weight = a * trans;
          r += weight * col[3 * i];
          g += weight * col[3 * i + 1];
          b += weight * col[3 * i + 2];
          trans = next_trans;
        }
        float* p = out_rgb + 3 * (y * width + x);
        p[0] = r;
        p[1] = g;
        p[2] = b;
        out_alpha[y * width + x] = 1.f - trans;
      }
    }
  }
  return {rgb, alpha};
}

// chunk 0: static, the iterations split into one equal block per thread; chunk > 0: dynamic with that chunk.
void set_schedule(int64_t chunk) {
#ifdef _OPENMP
  omp_set_schedule(chunk > 0 ? omp_sched_dynamic : omp_sched_static, int(chunk));
#endif
}

int num_threads() {
#ifdef _OPENMP
  return omp_get_max_threads();
#else
  return 1;
#endif
}
"""


def cpp_flags() -> list[str]:
    """The project's flags for its compiled rasterizer, plus the kernel's constants (hex: the same float32 bits)."""
    constants = [f"-DTILE={TILE}"] + [f"-D{name}={float(value).hex()}f" for name, value in
                                      (("ALPHA_MIN", F_ALPHA_MIN), ("ALPHA_MAX", F_ALPHA_MAX), ("T_MIN", F_T_MIN))]
    return CFLAGS + _simd_flags() + constants


def build_cpp(build_root: Path):
    """Build the C++ kernel with load_inline in a fresh folder under build_root; (module, seconds).

    The folder is removed when the process exits (the loaded library stays mapped until then).
    """
    from torch.utils import cpp_extension

    bin_dir = str(Path(sys.executable).parent)  # ninja from the venv, as uw3dgs.kernels.build does
    os.environ["PATH"] = bin_dir + os.pathsep + os.environ.get("PATH", "")
    build_root.mkdir(parents=True, exist_ok=True)
    folder = tempfile.mkdtemp(prefix="numba_vs_cpp_", dir=build_root)
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    start = time.perf_counter()
    module = cpp_extension.load_inline(
        name="numba_vs_cpp_composite",
        cpp_sources=CPP_SOURCE,
        functions=["composite", "set_schedule", "num_threads"],
        extra_cflags=cpp_flags(),
        extra_ldflags=["-fopenmp"],
        build_directory=folder,
    )
    return module, time.perf_counter() - start


def run_cpp(module, scene, offsets, ids, width, height) -> tuple[np.ndarray, np.ndarray]:
    """Call the C++ kernel on numpy inputs (zero-copy through torch.from_numpy)."""
    args = [torch.from_numpy(scene[k]) for k in ("means2d", "conics", "opacities", "colors")]
    rgb, alpha = module.composite(*args, torch.from_numpy(offsets), torch.from_numpy(ids), width, height)
    return rgb.numpy(), alpha.numpy()


def run_numba(scene, offsets, ids, width, height) -> tuple[np.ndarray, np.ndarray]:
    """Call the numba kernel."""
    s = scene
    return composite_numba(s["means2d"], s["conics"], s["opacities"], s["colors"], offsets, ids, width, height)


def composite_bruteforce(scene, width, height) -> tuple[np.ndarray, np.ndarray]:
    """float64 numpy reference: every Gaussian on every pixel, in order, with the same skip and stop rules."""
    xs, ys = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    trans = np.ones((height, width))
    active = np.ones((height, width), bool)
    rgb = np.zeros((height, width, 3))
    for mean, (a, b, c), o, colour in zip(*(scene[k].astype(np.float64) for k in
                                            ("means2d", "conics", "opacities", "colors")), strict=True):
        dx, dy = xs - mean[0], ys - mean[1]
        alpha = np.minimum(ALPHA_MAX, o * np.exp(-0.5 * (a * dx * dx + 2 * b * dx * dy + c * dy * dy)))
        blend = active & (alpha >= ALPHA_MIN)
        next_trans = trans * (1.0 - alpha)
        active &= ~(blend & (next_trans < T_MIN))
        blend &= active
        rgb += np.where(blend, alpha * trans, 0.0)[..., None] * colour
        trans = np.where(blend, next_trans, trans)
    return rgb, 1.0 - trans


# ----------------------------------------------------------------------------------------------- checks and timing


def max_difference(first, second) -> float:
    """Largest absolute difference over rgb and alpha."""
    return max(float(np.abs(np.asarray(x, np.float64) - y).max()) for x, y in zip(first, second, strict=True))


def check(name: str, difference: float) -> str:
    """Exit with a clear message if difference is above TOLERANCE; else a one-line report."""
    if not difference <= TOLERANCE:
        sys.exit(f"FAILED: {name}: max |difference| {difference:.3g} > {TOLERANCE:g}")
    return f"- {name}: max |difference| {difference:.2g} (tolerance {TOLERANCE:g})"


SCHEDULES = {"static": 0, "dynamic": 1}
"""Chunk size per schedule: 0 = one equal block per thread; 1 = one tile at a time, handed out on demand."""


def set_parallelism(threads: int, schedule: str, module) -> None:
    """Same thread count and schedule for both (numba's pool; the OpenMP pool torch and the extension share)."""
    numba.set_num_threads(threads)
    numba.set_parallel_chunksize(SCHEDULES[schedule])
    torch.set_num_threads(threads)
    module.set_schedule(SCHEDULES[schedule])
    if module.num_threads() != threads:
        sys.exit(f"FAILED: the C++ extension sees {module.num_threads()} OpenMP threads, not {threads}")


def time_both(calls: dict, repeats: int) -> dict[str, list[float]]:
    """One warm-up call each, then `repeats` timed calls each, alternating which backend goes first."""
    for call in calls.values():
        call()
    times: dict[str, list[float]] = {name: [] for name in calls}
    names = list(calls)
    for r in range(repeats):
        for name in names if r % 2 == 0 else names[::-1]:
            start = time.perf_counter()
            calls[name]()
            times[name].append(time.perf_counter() - start)
    return times


def load() -> str:
    """The 1, 5 and 15 minute load averages."""
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def cpu_name() -> str:
    """The CPU model from /proc/cpuinfo."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


# ----------------------------------------------------------------------------------------------- main


def first_calls(build_root: Path) -> tuple[object, list[str]]:
    """Build/compile both on a tiny scene, timing the first call; check them against the brute force there."""
    width, height = 72, 40  # not a multiple of the tile size: partial tiles at the edges
    scene = make_scene(300, width, height, seed=1)
    offsets, ids = bin_tiles(scene, width, height)
    start = time.perf_counter()
    out_numba = run_numba(scene, offsets, ids, width, height)
    numba_first = time.perf_counter() - start
    module, cpp_build = build_cpp(build_root)
    start = time.perf_counter()
    out_cpp = run_cpp(module, scene, offsets, ids, width, height)
    cpp_first = time.perf_counter() - start
    reference = composite_bruteforce(scene, width, height)
    lines = [
        "| | first call (s) |",
        "|---|---:|",
        f"| numba: `import numba` | {NUMBA_IMPORT_S:.2f} |",
        f"| numba: JIT compile + first call (300 Gaussians, 72x40) | {numba_first:.2f} |",
        f"| C++: `load_inline` build in a fresh folder (ninja + g++ + import) | {cpp_build:.2f} |",
        f"| C++: first call (300 Gaussians, 72x40) | {cpp_first:.3f} |",
        "",
        check("numba vs float64 brute force, 300 Gaussians, 72x40", max_difference(out_numba, reference)),
        check("C++ vs float64 brute force, 300 Gaussians, 72x40", max_difference(out_cpp, reference)),
        check("numba vs C++, 300 Gaussians, 72x40", max_difference(out_numba, out_cpp)),
    ]
    return module, lines


def timed_runs(module, repeats: int, thread_counts: list[int]) -> tuple[list[str], list[str]]:
    """Median times for every (scene, thread count, schedule); the table and the agreement lines."""
    table = [
        "| Gaussians | image | (tile, Gaussian) pairs | threads | schedule | numba median (ms) | C++ median (ms) "
        "| numba / C++ |",
        "|---:|---|---:|---:|---|---:|---:|---:|",
    ]
    checks = []
    for n, size in CONFIGS:
        scene = make_scene(n, size, size)
        offsets, ids = bin_tiles(scene, size, size)
        calls = {
            "numba": lambda s=scene, o=offsets, i=ids, w=size: run_numba(s, o, i, w, w),
            "cpp": lambda s=scene, o=offsets, i=ids, w=size: run_cpp(module, s, o, i, w, w),
        }
        checks.append(check(f"numba vs C++, {n} Gaussians, {size}x{size}",
                            max_difference(calls["numba"](), calls["cpp"]())))
        for threads in thread_counts:
            for schedule in SCHEDULES:
                set_parallelism(threads, schedule, module)
                times = time_both(calls, repeats)
                med = {name: statistics.median(values) * 1e3 for name, values in times.items()}
                table.append(f"| {n:,} | {size}x{size} | {len(ids):,} | {threads} | {schedule} | {med['numba']:.1f} | "
                             f"{med['cpp']:.1f} | {med['numba'] / med['cpp']:.2f} |")
                info(f"{n} Gaussians {size}x{size}, {threads} thread(s), {schedule}: " + ", ".join(
                    f"{name} {min(v) * 1e3:.1f}-{max(v) * 1e3:.1f} ms" for name, v in times.items()))
    return table, checks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=9, help="timed calls per backend and case (default 9)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts (default 1 2)")
    args = parser.parse_args()

    load_before = load()
    module, first = first_calls(default_cache_dir() / "torch_extensions")
    table, checks = timed_runs(module, args.repeats, args.threads)

    print(f"{cpu_name()}, {os.cpu_count()} logical CPUs; torch {torch.__version__}, numba {numba.__version__} "
          f"(threading layer {numba.threading_layer()}), numpy {np.__version__}")
    print(f"C++ flags: {' '.join(cpp_flags())}; numba: parallel=True, fastmath=False")
    print(f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', '(unset)')}; load average (1/5/15 min) "
          f"before {load_before}, after {load()}\n")
    print("\n".join(first))
    print()
    print("\n".join(table))
    print(f"\nMedians of {args.repeats} calls after one warm-up; numba / C++ > 1 means C++ is faster.")
    print("\n".join(checks))


if __name__ == "__main__":
    main()
