"""A `watersplatting` training step against a `3dgs` step at equal Gaussians, on the CPU.

    OMP_NUM_THREADS=1 python benchmarks/speed/watersplatting_step.py [--repeats 10] [--steps 20]

Both methods start on the built-in synthetic scene from the same initial points, train `--steps` steps without
any density change (so the Gaussians stay the same in number), then one more step is timed for each, best of
`--repeats`, the two alternating twice so both see the same drift of the machine. watersplatting renders at full
resolution here (`--model.num-downscales 0`): equal pixels as well as equal Gaussians. A step is everything the
Trainer does: render (for watersplatting the medium MLP and the medium compositor), losses, backward, Adam.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import torch
from timing import best_ms  # the sibling benchmark script, next to this one

from uw3dgs.engine.trainer import Trainer
from uw3dgs.registry import METHODS


def trainer_of(method: str, steps: int, output: Path) -> tuple[Trainer, list[int]]:
    config = METHODS[method].config
    model = dataclasses.replace(config.model, densification=dataclasses.replace(
        config.model.densification, refine_start=10**9, reset_opacity_every=0))
    if method == "watersplatting":
        model = dataclasses.replace(model, num_downscales=0)
    config = dataclasses.replace(config, model=model, output_dir=output, progress=False, device="cpu",
                                 steps_per_save=10**9, steps_per_eval_image=10**9, steps_per_eval_all_images=10**9,
                                 max_num_iterations=10**6)
    trainer = Trainer(config)
    trainer.setup()
    step = [0]
    for _ in range(steps):
        step[0] += 1
        trainer.train_step(step[0])
    return trainer, step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--steps", type=int, default=20, help="steps trained before timing")
    args = parser.parse_args()
    best: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as scratch:
        runs = {method: trainer_of(method, args.steps, Path(scratch) / method) for method in ("3dgs", "watersplatting")}
        for _ in range(2):
            for method, (trainer, step) in runs.items():
                def one(trainer=trainer, step=step) -> None:
                    step[0] += 1
                    trainer.train_step(step[0])

                best[method] = min(best.get(method, float("inf")), best_ms(one, args.repeats))
        counts = {method: trainer.model.num_gaussians for method, (trainer, _) in runs.items()}
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s); Gaussians: {counts}")
    for method, ms in best.items():
        print(f"{method}: {ms:.1f} ms per step")
    print(f"watersplatting / 3dgs: {best['watersplatting'] / best['3dgs']:.2f}x")


if __name__ == "__main__":
    main()
