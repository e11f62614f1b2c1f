"""Whole training steps of a trained run with each CPU speed change of a training step undone, one at a time.

    MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000 OMP_WAIT_POLICY=passive \\
      python benchmarks/speed/training_step.py RUN/config.yml

Resumes a copy of the run's latest checkpoint (the run itself is not touched) and times one more training
step (render, losses, backward, Adam, densification statistics), one thread, best of `--repeats`: as uw3dgs
does it now, with one change undone at a time, with all undone, and with the SH colours also back to one term
per basis function (3DGS's form, the code before `sh_eval.py`). The ways alternate twice, so all see the same
drift of the machine and of the model. The changes and their microbenchmarks: the SH colours by the compiled
kernel, and in PyTorch with their own backward (`sh_eval.py`), the medium's VM fields read by the compiled
kernel, and in PyTorch channel-major
(`medium_field.py`; a run without a medium, `3dgs`, reads no fields, so there those rows show the timing
noise), Adam fused (`adam_fused.py`), L_z and PAUP's phi and masked render + L1 compiled (`paup_cost.py`: PAUP's
share). Where the time of a step goes: `step_profile.py`.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import torch
from medium_field import CHANNEL_MAJOR, forward_row_major  # the sibling benchmark scripts, next to this one
from sh_eval import eval_sh_autograd_product, eval_sh_per_term
from timing import Way, time_training_steps, with_kernels

import uw3dgs.fields.gaussians as gaussians_module
from uw3dgs.fields.medium import VMField
from uw3dgs.render.sh import eval_sh_split


def way(kernels: str = "compiled", sh: Callable = eval_sh_split, medium: Callable = CHANNEL_MAJOR,
        fused: bool = True) -> Way:
    """A training step with `--model.kernels kernels` and these PyTorch variants of the SH colours and the VM read
    (used where the kernels are 'torch') and of Adam (a built Adam reads its flag at every step)."""

    def install(trainer) -> None:
        gaussians_module.eval_sh_split = sh  # GaussianField.colors calls the module-level name
        VMField.forward = medium
        for optimizer in trainer.optimizers.optimizers.values():
            for group in optimizer.param_groups:
                group["fused"] = fused

    return Way(configure=with_kernels(kernels), install=install)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("config", type=Path, help="config.yml of a trained run (with a checkpoint)")
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()
    torch.set_num_threads(1)
    ways = {
        "now": way(),
        "--model.kernels torch": way("torch"),
        "Adam per-operation loop": way(fused=False),
        "kernels torch, SH autograd's backward": way("torch", sh=eval_sh_autograd_product),
        "kernels torch, medium row-major": way("torch", medium=forward_row_major),
        "all undone": way("torch", eval_sh_autograd_product, forward_row_major, fused=False),
        "and SH one term per function": way("torch", eval_sh_per_term, forward_row_major, fused=False),
    }
    best = time_training_steps(args.config, ways, args.repeats)
    gaussians_module.eval_sh_split, VMField.forward = eval_sh_split, CHANNEL_MAJOR
    for name, ms in best.items():
        print(f"  {name:40s} {ms:8.1f} ms per step   {ms / best['now']:.2f}x the time of now")


if __name__ == "__main__":
    main()
