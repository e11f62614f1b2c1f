"""Rasterizer backends: forward and forward+backward time and peak memory on one shared random scene.

    MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000 python benchmarks/speed/rasterizer.py
    python benchmarks/speed/rasterizer.py --device cuda      # gsplat against the reference on a GPU
    python benchmarks/speed/rasterizer.py --backends cpu,medium-torch,medium-cpu   # with the medium compositor

`medium-cpu` and `medium-torch` are the medium compositor (watersplatting's water between the Gaussians,
`uw3dgs.render.medium_rasterize`) on its compiled and reference backends, with a smoothly varying water per pixel;
their loss weighs the underwater image.

Every (backend, Gaussians, resolution, pass) runs in its own subprocess: the peak memory is the growth
of that process's max RSS (`resource.getrusage`) over its state just before the first render (scene
built, extension loaded), so it counts torch's allocations, which tracemalloc does not see. With the
two malloc variables above glibc keeps freed memory instead of returning it, so RSS is a faithful
high-water mark of the heap. On CUDA the peak is `torch.cuda.max_memory_allocated` over the same span and
every timed run ends with `torch.cuda.synchronize()`. Times are medians of repeated runs after one
warm-up run. Speed-ups are against the 'torch' reference measured in the same invocation.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import time

import torch

CONFIGS = [(20_000, 256), (20_000, 512), (100_000, 256), (100_000, 512)]


def make_scene(n: int, size: int, seed: int = 0):
    """n Gaussians in front of a camera looking down +z, realistic sizes (a few pixels to tens of pixels).

    The world scene depends only on n and seed; the resolution only changes the intrinsics.
    """
    from uw3dgs.cameras import Camera

    gen = torch.Generator().manual_seed(seed)

    def uniform(lo: float, hi: float, *shape: int) -> torch.Tensor:
        return lo + (hi - lo) * torch.rand(*shape, generator=gen)

    z = uniform(2.0, 10.0, n)
    xy = uniform(-0.6, 0.6, n, 2) * z[:, None]
    means = torch.cat([xy, z[:, None]], dim=1)
    scales = torch.exp(uniform(math.log(0.005), math.log(0.08), n, 3))
    quats = torch.randn(n, 4, generator=gen)
    opacities = torch.sigmoid(uniform(-3.0, 4.0, n))
    features = uniform(0.0, 1.0, n, 3)
    f = 0.9 * size
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]])
    return (means, quats, scales, opacities, features), Camera(viewmat=torch.eye(4), K=K, width=size, height=size)


def water(size: int, device: str):
    """A smooth per-pixel water for the medium compositor: c_med, sigma_bs, sigma_attn [size, size, 3]."""
    from uw3dgs.render.medium_types import PixelMedium

    ramp = torch.linspace(0.5, 1.5, size)[None, :, None] * torch.linspace(1.2, 0.8, size)[:, None, None]
    rgb = torch.tensor([0.1, 0.3, 0.4])
    return PixelMedium(color=(rgb * ramp).to(device), sigma_bs=(0.1 * rgb * ramp).to(device),
                       sigma_attn=(0.2 * rgb * ramp.flip(1)).to(device))


def worker(backend: str, n: int, size: int, mode: str, repeats: int, device: str) -> dict:
    from uw3dgs.render import RasterSettings, Splats, rasterize
    from uw3dgs.render.medium_rasterize import rasterize_medium

    medium = None
    if backend.startswith("medium-"):
        backend, medium = backend.removeprefix("medium-"), water(size, device)
    if backend == "cpu":
        from uw3dgs.kernels.build import load_extension

        if load_extension() is None:
            return {"error": "extension did not build"}
    inputs, camera = make_scene(n, size)
    inputs = tuple(t.to(device) for t in inputs)
    camera = camera.to(device)
    settings = RasterSettings(backend=backend)
    weights = torch.rand(size, size, 3, generator=torch.Generator().manual_seed(1)).to(device)
    cuda = device == "cuda"
    sync = torch.cuda.synchronize if cuda else (lambda: None)

    def render(*gaussians):
        if medium is None:
            return rasterize(Splats(*gaussians), camera, settings)
        return rasterize_medium(Splats(*gaussians), medium, camera, settings, absgrad=mode != "fwd")

    def once() -> None:
        if mode == "fwd":
            with torch.no_grad():
                render(*inputs)
            return
        leaves = [t.clone().requires_grad_(True) for t in inputs]
        out = render(*leaves)
        out.means2d.retain_grad()
        image = out.render if medium is None else out.underwater
        ((image * weights).sum() + out.alpha.sum()).backward()

    if cuda:
        sync()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    else:
        base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    times = []
    for i in range(repeats + 1):
        start = time.perf_counter()
        once()
        sync()
        if i:  # the first run is a warm-up (and on CUDA the kernels' first load)
            times.append(time.perf_counter() - start)
    top = torch.cuda.max_memory_allocated() if cuda else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {"seconds": statistics.median(times), "peak_mib": (top - base) / 2**20, "runs": len(times)}


def run_config(backend: str, n: int, size: int, mode: str, repeats: int, device: str) -> dict:
    cmd = [sys.executable, __file__, "--worker", backend, str(n), str(size), mode, str(repeats), device]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"rc {proc.returncode}"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--worker", nargs=6, help=argparse.SUPPRESS)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where the tensors live")
    parser.add_argument("--backends", default=None, help="comma-separated (default: every backend registered for "
                        "--device)")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per config (reference: max(2, this // 2))")
    parser.add_argument(
        "--configs", default=None, help="comma-separated GAUSSIANSxSIZE, e.g. 100000x512 (default: all four)"
    )
    args = parser.parse_args()
    if args.worker:
        backend, n, size, mode, repeats, device = args.worker
        print(json.dumps(worker(backend, int(n), int(size), mode, int(repeats), device)))
        return

    from uw3dgs.render import BACKENDS
    from uw3dgs.utils.console import info

    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: no CUDA device here")
    registered = [b for b, v in BACKENDS.items() if args.device in v.devices]
    backends = args.backends.split(",") if args.backends else registered
    if args.device == "cpu" and "cpu" not in backends and not args.backends:
        backends.append("cpu")  # benchmark it even while it is not registered
    if "torch" in backends:
        backends.remove("torch")
    backends.insert(0, "torch")
    info(f"torch {torch.__version__}, {torch.get_num_threads()} threads, load: {os.getloadavg()}")
    configs = CONFIGS
    if args.configs:
        configs = [tuple(int(v) for v in c.split("x")) for c in args.configs.split(",")]
    rows = []
    for n, size in configs:
        ref = {}
        for backend in backends:
            repeats = max(2, args.repeats // 2) if backend == "torch" else args.repeats
            res = {mode: run_config(backend, n, size, mode, repeats, args.device) for mode in ("fwd", "fwd+bwd")}
            if backend == "torch":
                ref = res
            rows.append((backend, n, size, res, ref))
            info(f"{backend} {n} {size} {res}")

    print(
        "| backend | Gaussians | resolution | fwd ms | fwd+bwd ms | speed-up fwd | speed-up fwd+bwd "
        "| peak MiB fwd | peak MiB fwd+bwd |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for backend, n, size, res, ref in rows:
        cells = [backend, f"{n // 1000}k", f"{size}x{size}"]
        for mode in ("fwd", "fwd+bwd"):
            r = res[mode]
            cells.append("error: " + r["error"] if "error" in r else f"{1000 * r['seconds']:.1f}")
        for mode in ("fwd", "fwd+bwd"):
            r, b = res[mode], ref.get(mode, {})
            ok = "seconds" in r and "seconds" in b
            cells.append(f"{b['seconds'] / r['seconds']:.1f}x" if ok else "-")
        for mode in ("fwd", "fwd+bwd"):
            r = res[mode]
            cells.append(f"{r['peak_mib']:.0f}" if "peak_mib" in r else "-")
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
