"""Spherical-harmonics colours: one product over the basis (uw3dgs) against one term per basis function.

    MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000 python benchmarks/sh_eval.py
    python benchmarks/sh_eval.py --gaussians 90000 --run outputs/synthetic/uw3dgs/<timestamp>/config.yml

Times forward + backward of the view-dependent colours of N Gaussians (degree 3, one thread, best of
`--repeats`) both ways and checks they agree. The per-term sum, sh[:, 0] * Y_0 + sh[:, 1] * Y_1 + ...,
is how 3DGS writes it and how uw3dgs did until this benchmark: under autograd every `sh[:, i]` gives a
backward that allocates and accumulates a full [N, 16, 3] gradient, 16 times per step. With `--run`, a
whole training step (render, losses, backward) of that trained run's checkpoint is timed both ways too.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor

import uw3dgs.fields.gaussians as gaussians_module
from uw3dgs.render.sh import _basis, eval_sh


def eval_sh_per_term(degree: int, sh: Tensor, dirs: Tensor) -> Tensor:
    """The per-basis-function sum (3DGS's form), the baseline."""
    result = 0.0
    for i, value in enumerate(_basis(degree, dirs)):
        result = result + value[..., None] * sh[..., i, :]
    return result


def best_ms(fn: Callable[[], None], repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times) * 1000


def colour_pass(evaluate, n: int, seed: int = 0) -> tuple[Callable[[], None], Callable[[], list[Tensor]]]:
    """Forward + backward of max(eval + 0.5, 0) for n random Gaussians, as GaussianField.colors computes it."""
    g = torch.Generator().manual_seed(seed)
    sh0 = torch.randn(n, 1, 3, generator=g).requires_grad_()
    sh_rest = (0.1 * torch.randn(n, 15, 3, generator=g)).requires_grad_()
    means = torch.randn(n, 3, generator=g).requires_grad_()
    weights = torch.rand(n, 3, generator=g)
    last: list[Tensor] = []

    def run() -> None:
        for t in (sh0, sh_rest, means):
            t.grad = None
        dirs = torch.nn.functional.normalize(means - torch.tensor([0.0, 0.0, -5.0]), dim=-1)
        colours = (evaluate(3, torch.cat([sh0, sh_rest], dim=1), dirs) + 0.5).clamp_min(0.0)
        (colours * weights).sum().backward()
        last[:] = [colours.detach(), sh0.grad, sh_rest.grad, means.grad]

    return run, lambda: last


def training_step(config: Path) -> Callable[[], None]:
    from uw3dgs.engine.evaluator import load_trained

    _, datamanager, model, _ = load_trained(config)
    model.train()
    batch = datamanager.next_train()

    def run() -> None:
        outputs = model.get_outputs(batch["camera"])
        sum(model.get_loss_dict(outputs, batch, 10_000).values()).backward()
        for p in model.parameters():
            p.grad = None

    print(f"training step of {config} ({model.gaussians.num_gaussians} Gaussians)")
    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--gaussians", type=int, default=90_000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--run", type=Path, default=None, help="config.yml of a trained run: time whole steps too")
    args = parser.parse_args()
    torch.set_num_threads(1)

    ways = {"per term (3DGS)": eval_sh_per_term, "one product (uw3dgs)": eval_sh}
    results = {}
    for name, evaluate in ways.items():
        run, outputs = colour_pass(evaluate, args.gaussians)
        results[name] = (best_ms(run, args.repeats), [t.clone() for t in outputs()])
    (base_ms, base_out), (ours_ms, ours_out) = results.values()
    worst = max(float((a - b).abs().max() / b.abs().max().clamp_min(1e-12))
                for a, b in zip(ours_out, base_out, strict=True))
    print(f"colours of {args.gaussians} Gaussians, forward + backward, degree 3, 1 thread:")
    for name, (ms, _) in results.items():
        print(f"  {name:22s} {ms:8.1f} ms")
    print(f"  ratio {base_ms / ours_ms:.2f}x; outputs and gradients agree to {worst:.1e} (relative)")
    if args.run is not None:
        step = training_step(args.run)
        for name, evaluate in ways.items():
            gaussians_module.eval_sh = evaluate  # GaussianField.colors calls the module-level name
            print(f"  {name:22s} {best_ms(step, args.repeats):8.1f} ms per step")
        gaussians_module.eval_sh = eval_sh


if __name__ == "__main__":
    main()
