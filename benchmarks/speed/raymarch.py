"""Rays per second of the ray-marched methods on the CPU: a training step (march, composite, loss, backward, Adam) and
whole-image rendering (no gradient, in chunks), with one and with two threads, under `--model.kernels torch` and
`compiled` (the VM reads by grid_sample or by the compiled kernel), in one run.

    python benchmarks/speed/raymarch.py                                   # tensorf on the built-in synthetic scene
    python benchmarks/speed/raymarch.py --method seathru-nerf --data ../shared/data/seathru-nerf/IUI3-RedSea \
        --downscale-factor 8 --voxels 2097152 --repeats 3 --clock cpu

The model is a fresh one (random grids at --voxels, no alpha mask yet: every sample in the box is read, as in the
first steps of a run, the slowest part of TensoRF's schedule); --batch rays a step (the method's batch size by
default); one model per --kernels policy, built from the same seed, timed in turns. Prints rays/s per thread count
and policy, the compiled / torch ratios and the two-thread speed-up. `--clock cpu` times this process's CPU time
(a shared machine inflates it far less than wall time): with two threads that is the CPU time of both, so its
two-thread "speed-up" is the parallel efficiency (1.0 = perfect), not a wall-time gain. Whole runs: `uw-train`
writes train_time.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

import torch
from timing import best_ms  # benchmarks/speed/timing.py, next to this script

from uw3dgs.engine.optimizers import Optimizers
from uw3dgs.registry import DATAMANAGERS, METHODS

CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}


def build(method: str, manager, voxels: int | None, batch: int | None, kernels: str):
    config = METHODS[method].config
    model_config = dataclasses.replace(config.model, voxels_init=voxels or config.model.voxels_init,
                                       batch_size=batch or config.model.batch_size, kernels=kernels)
    torch.manual_seed(0)
    model = model_config.setup(scene=manager.scene, train_indices=manager.train_indices)
    optimizers = Optimizers(config.optimizers, model.param_groups(), model.scene_extent, config.max_num_iterations)
    return model, optimizers


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--method", default="tensorf", choices=["tensorf", "tensorf-cpu", "seathru-nerf"])
    parser.add_argument("--data", type=Path, default=None, help="dataset folder (default: the built-in scene)")
    parser.add_argument("--downscale-factor", type=int, default=1)
    parser.add_argument("--voxels", type=int, default=None,
                        help="grid voxels (default: the method's start, 128^3 for tensorf)")
    parser.add_argument("--batch", type=int, default=None, help="rays per training step (default: the method's)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts to time (default: 1 2)")
    parser.add_argument("--kernels", nargs="+", choices=["torch", "compiled"], default=["torch", "compiled"],
                        help="--model.kernels policies to time (default: both)")
    parser.add_argument("--clock", choices=tuple(CLOCKS), default="wall",
                        help="wall time, or this process's CPU time (all threads)")
    args = parser.parse_args()

    config = METHODS[args.method].config
    manager = (DATAMANAGERS["synthetic"].config if args.data is None else
               config.datamanager.resolve(args.data)).setup(data=args.data, downscale_factor=args.downscale_factor)
    models = {kernels: build(args.method, manager, args.voxels, args.batch, kernels) for kernels in args.kernels}
    model = next(iter(models.values()))[0]
    batch = manager.next_train_rays(model.config.batch_size)
    camera = manager.cameras[manager.test_indices[0] if manager.test_indices else 0]
    pixels = camera.width * camera.height

    def train_step(model, optimizers) -> None:
        model.train()
        outputs = model.get_train_outputs(batch)
        loss = sum(model.get_loss_dict(outputs, batch, 1).values())
        optimizers.zero_grad()
        loss.backward()
        optimizers.step()

    @torch.no_grad()
    def render(model) -> None:
        model.eval()
        model.get_outputs(camera)

    clock = CLOCKS[args.clock]
    print(f"{args.method}: grid {model.field.resolution()}, {model.num_samples()} samples a ray, "
          f"{len(batch['image'])} rays a step, renders {camera.width}x{camera.height}; {args.clock} clock; "
          f"load average {os.getloadavg()[0]:.2f} at the start")
    rates = {}
    for threads in args.threads:
        torch.set_num_threads(threads)
        for kernels, (model, optimizers) in models.items():
            train_ms = best_ms(lambda: train_step(model, optimizers), args.repeats, clock)  # noqa: B023
            render_ms = best_ms(lambda: render(model), args.repeats, clock)  # noqa: B023
            rates[threads, kernels] = (len(batch["image"]) / train_ms * 1000, pixels / render_ms * 1000)
            print(f"{threads} thread(s), kernels {kernels:8s}: training {rates[threads, kernels][0]:,.0f} rays/s "
                  f"({train_ms:.0f} ms a step), rendering {rates[threads, kernels][1]:,.0f} rays/s "
                  f"({render_ms:.0f} ms an image)")
        if {"torch", "compiled"} <= set(args.kernels):
            train, render_rate = (rates[threads, "compiled"][i] / rates[threads, "torch"][i] for i in range(2))
            print(f"{threads} thread(s), compiled / torch: training {train:.2f}x, rendering {render_rate:.2f}x")
    if {1, 2} <= set(args.threads):
        for kernels in args.kernels:
            print(f"kernels {kernels}, 2 threads / 1 thread: training "
                  f"{rates[2, kernels][0] / rates[1, kernels][0]:.2f}x, rendering "
                  f"{rates[2, kernels][1] / rates[1, kernels][1]:.2f}x")
    print(f"load average {os.getloadavg()[0]:.2f} at the end")

if __name__ == "__main__":
    main()
