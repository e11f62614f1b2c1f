"""What the PAUP branch costs a training step: a `uw3dgs` run's steps with PAUP against the same steps without it.

    MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000 OMP_WAIT_POLICY=passive \\
      python benchmarks/speed/paup_cost.py RUN/config.yml [--steps 200] [--rounds 2] [--enhanced-every 2 4]

RUN is a `uw3dgs` run past PAUP's start (its checkpoint holds the statistics). Each way resumes a fresh copy of
the run's latest checkpoint and trains `--steps` more steps, one thread; the mean time per step is what a run
pays, so the window should span statistics refreshes (`--model.paup.every`) and densification events. "with
PAUP" is the method as it trains; "without PAUP" removes the branch from the same model (no masked render, no
second render, no statistics, no L_PAPSL, no pruning by m, plain depth: a `uw3dgs-no-paup` step); "PAUP in
PyTorch" is the method with PAUP's compiled passes switched off (`--model.kernels torch`: phi in PyTorch, the
masked render a frozen render followed by PyTorch's L1); `--enhanced-every N ...` adds, per N, the branch with its
masked render and L_PAPSL every N steps (`--model.paup.enhanced-every`) on the same checkpoint. The ways alternate
`--rounds` times; the best mean of each
is kept.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

import torch
from timing import Way, mean_training_steps, with_kernels  # the sibling benchmark script, next to this one


def without_paup(trainer: Any) -> None:
    """Take the PAUP branch out of a built trainer (what `use_paup=False` builds, on the same Gaussians)."""
    trainer.model.paup = None
    for callback in trainer.callbacks:
        if hasattr(callback, "extra_pruning"):
            callback.extra_pruning = None


PAUP_IN_PYTORCH = Way(configure=with_kernels("torch"))
"""The run with `--model.kernels torch`: phi in PyTorch, the masked render a frozen render followed by PyTorch's L1."""


def enhanced_every(steps: int) -> Way:
    """The run with PAUP's I_UR^Enh every `steps` steps (`--model.paup.enhanced-every`)."""
    def configure(config: Any) -> Any:
        model = config.model
        return dataclasses.replace(config, model=dataclasses.replace(
            model, paup=dataclasses.replace(model.paup, enhanced_every=steps)))
    return Way(configure=configure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("config", type=Path, help="config.yml of a trained uw3dgs run (with a checkpoint)")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--enhanced-every", type=int, nargs="+", default=[], metavar="N",
                        help="also time the branch with I_UR^Enh every N steps, for each N")
    args = parser.parse_args()
    torch.set_num_threads(1)
    ways = {"without PAUP (uw3dgs-no-paup)": Way(install=without_paup), "with PAUP (uw3dgs)": Way(),
            "PAUP in PyTorch": PAUP_IN_PYTORCH,
            **{f"with PAUP, I_UR^Enh every {n} steps": enhanced_every(n) for n in args.enhanced_every}}
    mean = mean_training_steps(args.config, ways, args.steps, args.rounds)
    base = mean["without PAUP (uw3dgs-no-paup)"]
    for name, ms in mean.items():
        print(f"  {name:36s} {ms:8.1f} ms per step (mean of {args.steps})   {ms / base:.2f}x")


if __name__ == "__main__":
    main()
