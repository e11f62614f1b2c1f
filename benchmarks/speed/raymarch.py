"""Rays per second of the ray-marched methods on the CPU: a training step (march, composite, loss, backward, Adam) and
whole-image rendering (no gradient, in chunks), with one and with two threads, in one run.

    python benchmarks/speed/raymarch.py                                   # tensorf on the built-in synthetic scene
    python benchmarks/speed/raymarch.py --method seathru-nerf --data ../shared/data/seathru-nerf/IUI3-RedSea \
        --downscale-factor 8 --voxels 2097152 --repeats 3

The model is a fresh one (random grids at --voxels, no alpha mask yet: every sample in the box is read, as in the
first steps of a run, the slowest part of TensoRF's schedule); --batch rays a step (the method's batch size by
default). Prints rays/s per thread count and the two-thread speed-up. Whole runs: `uw-train` writes train_time.json.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch
from timing import best_ms  # benchmarks/speed/timing.py, next to this script

from uw3dgs.engine.optimizers import Optimizers
from uw3dgs.registry import DATAMANAGERS, METHODS


def build(method: str, data: Path | None, factor: int, voxels: int | None, batch: int | None):
    config = METHODS[method].config
    model_config = dataclasses.replace(config.model, voxels_init=voxels or config.model.voxels_init,
                                       batch_size=batch or config.model.batch_size)
    manager = (DATAMANAGERS["synthetic"].config if data is None else
               config.datamanager.resolve(data)).setup(data=data, downscale_factor=factor)
    torch.manual_seed(0)
    model = model_config.setup(scene=manager.scene, train_indices=manager.train_indices)
    optimizers = Optimizers(config.optimizers, model.param_groups(), model.scene_extent, config.max_num_iterations)
    return manager, model, optimizers


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--method", default="tensorf", choices=["tensorf", "tensorf-cpu", "seathru-nerf"])
    parser.add_argument("--data", type=Path, default=None, help="dataset folder (default: the built-in scene)")
    parser.add_argument("--downscale-factor", type=int, default=1)
    parser.add_argument("--voxels", type=int, default=None,
                        help="grid voxels (default: the method's start, 128^3 for tensorf)")
    parser.add_argument("--batch", type=int, default=None, help="rays per training step (default: the method's)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    manager, model, optimizers = build(args.method, args.data, args.downscale_factor, args.voxels, args.batch)
    batch = manager.next_train_rays(model.config.batch_size)
    camera = manager.cameras[manager.test_indices[0] if manager.test_indices else 0]
    pixels = camera.width * camera.height

    def train_step() -> None:
        model.train()
        outputs = model.get_train_outputs(batch)
        loss = sum(model.get_loss_dict(outputs, batch, 1).values())
        optimizers.zero_grad()
        loss.backward()
        optimizers.step()

    @torch.no_grad()
    def render() -> None:
        model.eval()
        model.get_outputs(camera)

    print(f"{args.method}: grid {model.field.resolution()}, {model.num_samples()} samples a ray, "
          f"{len(batch['image'])} rays a step, renders {camera.width}x{camera.height}")
    rates = {}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        train_ms = best_ms(train_step, args.repeats)
        render_ms = best_ms(render, args.repeats)
        rates[threads] = (len(batch["image"]) / train_ms * 1000, pixels / render_ms * 1000)
        print(f"{threads} thread(s): training {rates[threads][0]:,.0f} rays/s ({train_ms:.0f} ms a step), "
              f"rendering {rates[threads][1]:,.0f} rays/s ({render_ms:.0f} ms an image)")
    print(f"2 threads / 1 thread: training {rates[2][0] / rates[1][0]:.2f}x, rendering "
          f"{rates[2][1] / rates[1][1]:.2f}x")


if __name__ == "__main__":
    main()
