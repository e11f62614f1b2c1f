"""A `watersplatting` training step against a `3dgs` step at equal Gaussians, on the CPU.

    MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000 OMP_NUM_THREADS=1 \\
      python benchmarks/speed/watersplatting_step.py [--repeats 10] [--steps 20] [--clock wall|cpu] [--parts] \\
      [--points 4000]

Both methods start on the built-in synthetic scene from the same `--points` initial points (4,000, the scene's
default; a 6,000-step run ends with about 41,000 (`3dgs`) or 114,000 (`watersplatting`) there), train `--steps` steps
without any density change (so the Gaussians stay the same in number), then one more step is timed for each, best of
`--repeats`, the two alternating three times so both see the same drift of the machine. watersplatting renders at
full resolution here (`--model.num-downscales 0`): equal pixels as well as equal Gaussians. A step is everything the
Trainer does: render (for watersplatting the medium MLP and the medium compositor), losses, backward, Adam.
`--clock cpu` times this process's CPU time instead of wall time (on a machine shared with other work, the wall
time of a one-thread step mostly measures the others). `--parts` also times, on the watersplatting model's
Gaussians and first training view, what a watersplatting step adds to a 3dgs one: the medium compositor against the
3DGS compositor (forward, and forward + backward of a sum of their images) and the medium MLP (forward + backward,
as the model runs it and as its nn.Sequential with autograd).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch
from timing import best_ms  # the sibling benchmark script, next to this one

from uw3dgs.engine.trainer import Trainer
from uw3dgs.registry import DATAMANAGERS, METHODS

CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}


def trainer_of(method: str, steps: int, points: int, output: Path) -> tuple[Trainer, list[int]]:
    config = METHODS[method].config
    synthetic = DATAMANAGERS["synthetic"].config
    synthetic = dataclasses.replace(synthetic, scene=dataclasses.replace(synthetic.scene, num_points=points))
    model = dataclasses.replace(config.model, densification=dataclasses.replace(
        config.model.densification, refine_start=10**9, reset_opacity_every=0))
    if method == "watersplatting":
        model = dataclasses.replace(model, num_downscales=0)
    config = dataclasses.replace(config, model=model, datamanager=synthetic,
                                 output_dir=output, progress=False, device="cpu",
                                 steps_per_save=10**9, steps_per_eval_image=10**9, steps_per_eval_all_images=10**9,
                                 max_num_iterations=10**6)
    trainer = Trainer(config)
    trainer.setup()
    step = [0]
    for _ in range(steps):
        step[0] += 1
        trainer.train_step(step[0])
    return trainer, step


def parts(model) -> dict[str, Callable[[], None]]:
    """What a watersplatting step adds, as calls on `model`'s Gaussians and first training view."""
    from uw3dgs.render import Splats, rasterize
    from uw3dgs.render.medium_rasterize import rasterize_medium
    from uw3dgs.render.medium_types import PixelMedium
    from uw3dgs.render.sh import sh_basis

    camera, settings = model.train_cameras[0], model.config.raster
    with torch.no_grad():
        means, scales, quats, opacities = model.gaussians.activated()
        colors = model.gaussians.colors(camera.center)
        water = model.direction_medium.pixel_medium(camera)
    gaussians = [t.requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
    water = PixelMedium(*(t.clone().requires_grad_(True) for t in (water.color, water.sigma_bs, water.sigma_attn)))

    def composite_3dgs() -> None:
        rasterize(Splats(*gaussians), camera, settings).render.sum().backward()

    def composite_medium() -> None:
        out = rasterize_medium(Splats(*gaussians), water, camera, settings, absgrad=True)
        (out.underwater.sum() + out.render.sum()).backward()

    def forward_3dgs() -> None:
        with torch.no_grad():
            rasterize(Splats(*gaussians), camera, settings)

    def forward_medium() -> None:
        with torch.no_grad():
            rasterize_medium(Splats(*gaussians), water, camera, settings)

    weights = torch.rand(camera.height, camera.width, 9, generator=torch.Generator().manual_seed(0))

    def medium_mlp() -> None:
        (model.direction_medium.pixel_medium(camera).packed() * weights).sum().backward()

    def medium_mlp_autograd() -> None:  # the same function as its nn.Sequential, activations and packing by autograd
        medium = model.direction_medium
        raw = medium.mlp(sh_basis(medium.config.sh_degree, camera.ray_directions().to(weights)))
        sigmas = torch.nn.functional.softplus(raw[..., 3:] + medium.config.density_bias)
        (torch.cat([torch.sigmoid(raw[..., :3]), sigmas], dim=-1) * weights).sum().backward()

    return {"3DGS compositor forward": forward_3dgs, "medium compositor forward": forward_medium,
            "3DGS compositor forward + backward": composite_3dgs,
            "medium compositor forward + backward": composite_medium, "medium MLP forward + backward": medium_mlp,
            "medium MLP forward + backward, nn.Sequential and autograd": medium_mlp_autograd}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--steps", type=int, default=20, help="steps trained before timing")
    parser.add_argument("--clock", choices=tuple(CLOCKS), default="wall")
    parser.add_argument("--parts", action="store_true", help="also time what a watersplatting step adds")
    parser.add_argument("--points", type=int, default=4000, help="initial points = Gaussians of both methods")
    args = parser.parse_args()
    clock = CLOCKS[args.clock]
    best: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as scratch:
        runs = {method: trainer_of(method, args.steps, args.points, Path(scratch) / method)
                for method in ("3dgs", "watersplatting")}
        calls: dict[str, Callable[[], None]] = {}
        for method, (trainer, step) in runs.items():
            def one(trainer=trainer, step=step) -> None:
                step[0] += 1
                trainer.train_step(step[0])

            calls[method] = one
        if args.parts:
            calls.update(parts(runs["watersplatting"][0].model))
        for _ in range(3):
            for name, call in calls.items():
                best[name] = min(best.get(name, float("inf")), best_ms(call, args.repeats, clock))
        counts = {method: trainer.model.num_gaussians for method, (trainer, _) in runs.items()}
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {args.clock} clock; Gaussians: {counts}")
    for name, ms in best.items():
        print(f"{name}: {ms:.1f} ms" + (" per step" if name in runs else ""))
    print(f"watersplatting / 3dgs: {best['watersplatting'] / best['3dgs']:.2f}x")


if __name__ == "__main__":
    main()
