"""Timing helpers shared by the benchmark scripts: best-of-N wall time, and whole training steps of a
trained run timed with alternative implementations swapped in."""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import torch
from torch import Tensor


def best_ms(fn: Callable[[], None], repeats: int, clock: Callable[[], float] = time.perf_counter) -> float:
    """Best time of `repeats` calls after one warm-up call, in milliseconds: wall time, or what `clock` measures
    (time.process_time: this process's CPU time, which other processes on a shared machine inflate far less)."""
    fn()
    times = []
    for _ in range(repeats):
        start = clock()
        fn()
        times.append(clock() - start)
    return min(times) * 1000


@dataclasses.dataclass(frozen=True)
class Way:
    """One way of running a training step: `configure` changes the run's config before the trainer is built (e.g.
    `--model.kernels torch`), `install` swaps an alternative implementation in (benchmarks' own variants, which are
    no config option; called again before each of the way's timings, since such swaps may be module-wide)."""

    configure: Callable[[Any], Any] | None = None
    install: Callable[[Any], None] | None = None


def with_kernels(kernels: str) -> Callable[[Any], Any]:
    """A `Way.configure` giving the run's model this `--model.kernels` policy."""
    return lambda config: dataclasses.replace(config, model=dataclasses.replace(config.model, kernels=kernels))


def training_step(config: Path, scratch: Path, way: Way = Way()) -> tuple[Callable[[], None], Any]:
    """One more training step of a trained run per call, resumed from a copy of its latest checkpoint in
    `scratch` (the run itself is not touched), the run's config changed and the trainer changed by `way`; and the
    Trainer that runs them."""
    from uw3dgs.config import load_config
    from uw3dgs.engine.checkpoint import CHECKPOINT_DIR, latest_checkpoint
    from uw3dgs.engine.trainer import Trainer

    saved = load_config(config)
    checkpoint = latest_checkpoint(config.parent)
    if checkpoint is None:
        raise SystemExit(f"{config.parent} holds no checkpoint; train it first")
    if way.configure is not None:
        saved = way.configure(saved)
    copy = scratch / "bench" / saved.method_name / "run" / CHECKPOINT_DIR
    copy.mkdir(parents=True)
    shutil.copy(checkpoint, copy / checkpoint.name)
    trainer = Trainer(dataclasses.replace(saved, resume=True, load_config=None, progress=False, output_dir=scratch,
                                          experiment_name="bench", timestamp="run"))
    trainer.setup()
    step = [trainer.start_step]

    def run() -> None:
        step[0] += 1
        trainer.train_step(step[0])

    print(f"training steps of {config} ({trainer.model.gaussians.num_gaussians} Gaussians):")
    return run, trainer


def time_training_steps(config: Path, ways: dict[str, Way], repeats: int) -> dict[str, float]:
    """Best ms per training step of the run at `config` run each way (one trainer per way, from the same
    checkpoint); the ways alternate, so all see the same drift of the machine."""
    best = dict.fromkeys(ways, float("inf"))
    with tempfile.TemporaryDirectory() as scratch:
        runs = {name: training_step(config, Path(scratch) / str(i), way) for i, (name, way) in enumerate(ways.items())}
        for _ in range(2):
            for name, (step, trainer) in runs.items():
                if ways[name].install is not None:
                    ways[name].install(trainer)
                best[name] = min(best[name], best_ms(step, repeats))
    return best


def mean_training_steps(config: Path, ways: dict[str, Way], steps: int,
                        rounds: int) -> dict[str, float]:
    """Mean ms per training step over `steps` consecutive steps of the run at `config`, each way on a fresh copy
    of its latest checkpoint (so every way trains the same model through the same refreshes and densification
    events); the ways alternate `rounds` times and each keeps its best mean."""
    best = dict.fromkeys(ways, float("inf"))
    for _ in range(rounds):
        for name, way in ways.items():
            with tempfile.TemporaryDirectory() as scratch:
                step, trainer = training_step(config, Path(scratch), way)
                if way.install is not None:
                    way.install(trainer)
                start = time.perf_counter()
                for _ in range(steps):
                    step()
                best[name] = min(best[name], (time.perf_counter() - start) * 1000 / steps)
    return best


def compare_passes(title: str, passes: dict[str, Callable[[], tuple[Callable[[], None], list[Tensor]]]],
                   repeats: int) -> None:
    """Time each way's pass (a factory returning the pass and the list its last call fills with outputs and
    gradients), print them with the ratio of the first (the baseline) to the last, and how closely they agree."""
    results = {}
    for name, make in passes.items():
        run, outputs = make()
        results[name] = (best_ms(run, repeats), [t.clone() for t in outputs])
    (base_ms, base_out), (ours_ms, ours_out) = results[next(iter(results))], results[list(results)[-1]]
    worst = max(float((a - b).abs().max() / b.abs().max().clamp_min(1e-12))
                for a, b in zip(ours_out, base_out, strict=True))
    print(f"{title}:")
    for name, (ms, _) in results.items():
        print(f"  {name:32s} {ms:8.1f} ms")
    print(f"  ratio {base_ms / ours_ms:.2f}x; outputs and gradients agree to {worst:.1e} (relative)")


def compare_cli(doc: str, size_option: str, default_size: int, title: str, ways: dict[str, Any],
                make_pass: Callable[[Any, int], tuple[Callable[[], None], list[Tensor]]]) -> None:
    """The command line of a microbenchmark: `size_option` (N) and --repeats, one thread, then `compare_passes`
    over `make_pass(way, N)` for each way; the last way (the current code) is the one left installed.
    `title` may use {n}."""
    parser = argparse.ArgumentParser(description=doc.split("\n")[0])
    parser.add_argument(size_option, type=int, default=default_size)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    torch.set_num_threads(1)
    n = getattr(args, size_option.lstrip("-").replace("-", "_"))
    compare_passes(title.format(n=n), {name: partial(make_pass, way, n) for name, way in ways.items()},
                   args.repeats)
