"""Where a training step's time goes, by component, for `3dgs`, `uw3dgs-no-paup` and `uw3dgs` on the same Gaussians.

    MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000 \\
      python benchmarks/speed/step_profile.py RUN/config.yml [--downscales 8 4] [--sizes 1.0 0.3] \\
        [--threads 1 2] [--steps 100] [--methods ...] [--enhanced-every N ...]

(`OMP_WAIT_POLICY` left unset on a machine the benchmark has to itself: with `passive`, two-thread steps are
10-25% slower, docs/performance.md.)

RUN is a trained run on a real scene (any method); the Gaussians of its latest checkpoint are the model, and the
run is not touched. For every downscale of RUN's images, share of its Gaussians (`--sizes`, a random subset) and
thread count, each method is built on the data at that downscale, its Gaussians replaced by the model's (Adam
moments and densification statistics start at zero, PAUP measures its statistics at its first refresh), and
trains `--steps` steps from step 3,101 (SH degree 3, densification on, past the opacity reset at 3,000; a window
of 100 steps holds one PAUP statistics refresh and one densification event, as training has them). The window is
run twice from the same start: timed without the profiler (the step time), then under `torch.profiler`, where
every `uw3dgs/<section>` range (uw3dgs/utils/profiling.py) collects the forward time of the operations it
records and, through autograd's sequence numbers, the backward time of theirs. An operation in nested sections
counts for the outermost (PAUP's masked render is PAUP's, not the rasterizer's). "other" is the profiled step
time that no section claims (autograd's bookkeeping, gradient accumulation, the loss sum, Python). The profiler
slows small operations, so the sections add up to more than the unprofiled step.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import torch
from torch.profiler import ProfilerActivity, profile

from uw3dgs.config import load_config
from uw3dgs.engine.checkpoint import latest_checkpoint, load_checkpoint
from uw3dgs.engine.trainer import Trainer
from uw3dgs.fields.gaussians import PARAM_NAMES
from uw3dgs.registry import METHODS
from uw3dgs.utils.profiling import SECTION_PREFIX

METHOD_NAMES = ("3dgs", "uw3dgs-no-paup", "uw3dgs")
START_STEP = 3100
BACKWARD_PREFIX = "autograd::engine::evaluate_function: "


def method_config(name: str, saved: Any, downscale: int, scratch: Path, enhanced_every: int = 1) -> Any:
    """Method `name`'s default config on RUN's data at `downscale`; a medium starts at its prior (the estimate's
    fit costs setup time and changes nothing in a step). `enhanced_every`: `--model.paup.enhanced-every` of a
    method with PAUP."""
    config = METHODS[name].config
    model = config.model
    if getattr(model, "medium", None) is not None:
        model = dataclasses.replace(model, medium=dataclasses.replace(model.medium, init="prior"))
    if getattr(model, "paup", None) is not None:
        model = dataclasses.replace(model, paup=dataclasses.replace(model.paup, enhanced_every=enhanced_every))
    return dataclasses.replace(config, model=model, data=saved.data, datamanager=saved.datamanager,
                               downscale_factor=downscale, output_dir=scratch, experiment_name="profile",
                               timestamp=f"{name}-x{downscale}-n{enhanced_every}", progress=False, seed=0)


def transplant(trainer: Trainer, values: dict[str, torch.Tensor]) -> None:
    """Give the trainer's model these Gaussians; Adam moments, density statistics and PAUP's statistics restart."""
    model = trainer.model
    for name, (old, new) in model.gaussians.set_params({k: v.clone() for k, v in values.items()}).items():
        trainer.optimizers.replace_param(name, old, new, lambda m, shape=new.shape: m.new_zeros(shape))
    n = model.gaussians.num_gaussians
    for callback in trainer.callbacks:
        if hasattr(callback, "strategy"):
            callback.state = callback.strategy.initialize_state(model.gaussians)
    if getattr(model, "paup", None) is not None:
        model.paup.reindex(torch.full((n,), -1, dtype=torch.long))


def run_window(trainer: Trainer, steps: int) -> float:
    """Train `steps` steps from START_STEP + 1; wall ms per step."""
    trainer.model.train()
    start = time.perf_counter()
    for step in range(START_STEP + 1, START_STEP + 1 + steps):
        trainer.train_step(step)
    return (time.perf_counter() - start) * 1000 / steps


def by_section(events: list[Any]) -> dict[str, list[float]]:
    """Section name -> [forward us, backward us] over a profiler trace: a section's own range gives its forward
    time; each autograd function's evaluation goes to the section that recorded the forward operation of the same
    sequence number."""
    times: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])
    owner: dict[int, str] = {}
    for event in events:
        if event.name.startswith(BACKWARD_PREFIX):
            continue
        outermost, parent = None, event
        while parent is not None:
            if parent.name.startswith(SECTION_PREFIX):
                outermost = parent
            parent = parent.cpu_parent
        if outermost is None:
            continue
        name = outermost.name[len(SECTION_PREFIX):]
        if outermost is event:
            times[name][0] += event.cpu_time_total
        elif event.sequence_nr >= 0:
            owner.setdefault(event.sequence_nr, name)
    for event in events:
        if event.name.startswith(BACKWARD_PREFIX) and event.cpu_parent is None:
            name = owner.get(event.sequence_nr)
            if name is not None:
                times[name][1] += event.cpu_time_total
    return dict(times)


def profile_method(trainer: Trainer, values: dict[str, torch.Tensor], steps: int) -> dict[str, Any]:
    transplant(trainer, values)
    wall = run_window(trainer, steps)
    end_count = trainer.model.gaussians.num_gaussians
    transplant(trainer, values)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        profiled = run_window(trainer, steps)
    sections = {name: [t / 1000 / steps for t in fb] for name, fb in by_section(prof.events()).items()}
    other = profiled - sum(sum(fb) for fb in sections.values())
    return {"wall": wall, "profiled": profiled, "sections": sections, "other": other, "end": end_count}


def print_table(title: str, results: dict[str, dict[str, Any]]) -> None:
    print(f"\n{title}")
    names = list(results)
    print("| component, ms per step (forward + backward) | " + " | ".join(f"`{n}`" for n in names) + " |")
    print("|---|" + "---:|" * len(names))
    sections = sorted({s for r in results.values() for s in r["sections"]},
                      key=lambda s: -max(sum(r["sections"].get(s, (0, 0))) for r in results.values()))
    for section in sections:
        cells = []
        for r in results.values():
            fwd, bwd = r["sections"].get(section, (0.0, 0.0))
            cells.append(f"{fwd + bwd:.1f} ({fwd:.1f} + {bwd:.1f})" if fwd + bwd > 0 else "-")
        print(f"| {section} | " + " | ".join(cells) + " |")
    print("| other | " + " | ".join(f"{r['other']:.1f}" for r in results.values()) + " |")
    print("| **step, profiled** | " + " | ".join(f"{r['profiled']:.1f}" for r in results.values()) + " |")
    base = results[names[0]]["wall"]
    print("| **step, no profiler** | " + " | ".join(f"**{r['wall']:.1f}** ({r['wall'] / base:.2f}x)"
                                                   for r in results.values()) + " |")
    print("| Gaussians at the end | " + " | ".join(f"{r['end']:,}" for r in results.values()) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("config", type=Path, help="config.yml of a trained run (with a checkpoint)")
    parser.add_argument("--downscales", type=int, nargs="+", default=[8, 4])
    parser.add_argument("--sizes", type=float, nargs="+", default=[1.0, 0.3],
                        help="shares of the run's Gaussians (a random subset)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--methods", nargs="+", default=list(METHOD_NAMES))
    parser.add_argument("--enhanced-every", type=int, nargs="+", default=[], metavar="N",
                        help="also `uw3dgs` with PAUP's masked render every N steps (--model.paup.enhanced-every)")
    args = parser.parse_args()
    saved = load_config(args.config)
    checkpoint = latest_checkpoint(args.config.parent)
    if checkpoint is None:
        raise SystemExit(f"{args.config.parent} holds no checkpoint; train it first")
    state = load_checkpoint(checkpoint, "cpu")["model"]
    model = {name: state[f"gaussians.{name}"] for name in PARAM_NAMES}
    total = len(model["means"])
    with tempfile.TemporaryDirectory() as scratch:
        for downscale in args.downscales:
            trainers = {}
            columns = [(name, name, 1) for name in args.methods]
            columns += [(f"uw3dgs, I_UR^Enh every {n}", "uw3dgs", n) for n in args.enhanced_every]
            for column, name, every in columns:
                trainers[column] = Trainer(method_config(name, saved, downscale, Path(scratch), every))
                trainers[column].setup()
            camera = next(iter(trainers.values())).datamanager.scene.cameras[0]
            for size in args.sizes:
                picked = torch.randperm(total, generator=torch.Generator().manual_seed(0))[:round(size * total)]
                values = {name: value[picked.sort().values] for name, value in model.items()}
                for threads in args.threads:
                    torch.set_num_threads(threads)
                    results = {name: profile_method(trainer, values, args.steps) for name, trainer in trainers.items()}
                    print_table(f"downscale {downscale} ({camera.width} x {camera.height} px), {len(picked):,} "
                                f"Gaussians, {threads} thread(s), steps {START_STEP + 1}-{START_STEP + args.steps}",
                                results)
            for trainer in trainers.values():
                trainer.close()


if __name__ == "__main__":
    main()
