"""What fills the pixels of a test view that no training view sees, and what they do to its PSNR.

    python benchmarks/analysis/unseen_pixels.py outputs/synthetic/3dgs/<timestamp>/config.yml \
                                                outputs/synthetic/uw3dgs/<timestamp>/config.yml
    python benchmarks/analysis/unseen_pixels.py RUN/config.yml --large 2.0 --step 2500   # a kept checkpoint

Scenes with ground-truth ranges only (the synthetic ones). For every test view of each trained run it
prints the share of pixels whose surface no training camera has in its field of view (`covisible_mask`),
the mean coverage (alpha) of the model there, UWI PSNR over those pixels, over the rest and over the
whole image; then the same with the Gaussians whose largest axis exceeds `--large` world units switched
off (opacity 0), which shows how much of a view's score those few large Gaussians carry. On the built-in
forward scene this is how the README traces `3dgs`'s lead on view 0000 to its open-water Gaussians.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from uw3dgs.engine.evaluator import load_trained
from uw3dgs.metrics.image import psnr


def render_without(model, camera, off: torch.Tensor | None) -> dict:
    """The model's outputs for `camera` with the Gaussians in the mask `off` at opacity 0 (none when None)."""
    opacities = model.gaussians.opacities
    saved = opacities.detach().clone()
    if off is not None:
        opacities.data[off] = torch.finfo(saved.dtype).min
    try:
        with torch.no_grad():
            return model.get_outputs(camera)
    finally:
        opacities.data.copy_(saved)


def view_rows(config_path: Path, large: float, step: int | None = None) -> list[str]:
    config, datamanager, model, _ = load_trained(config_path, step=step)
    is_large = model.gaussians.scales.detach().exp().max(dim=-1).values > large
    rows = []
    for batch in datamanager.test_batches():
        if "covisible" not in batch:
            raise SystemExit(f"{config_path}: the dataset has no ground-truth ranges, so no pixel can be called "
                             "unseen; run this on a synthetic scene")
        seen = batch["covisible"]
        any_unseen = bool((~seen).any())
        name = datamanager.scene.image_names[batch["index"]]
        cells = [f"{config.method_name} seed {config.seed}", name, f"{float((~seen).float().mean()):.1%}"]
        for off in (None, is_large):
            out = render_without(model, batch["camera"], off)
            render, gt = out["rgb"].clamp(0, 1), batch["image"]
            unseen = [f"{float(out['alpha'][~seen].mean()):.2f}", f"{float(psnr(render, gt, ~seen)):.2f}"] \
                if any_unseen else ["-", "-"]
            cells += [*unseen, f"{float(psnr(render, gt, seen)):.2f}", f"{float(psnr(render, gt)):.2f}"]
        rows.append("| " + " | ".join(cells) + f" | {int(is_large.sum())} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("configs", nargs="+", type=Path, help="config.yml of trained runs")
    parser.add_argument("--large", type=float, default=2.0,
                        help="largest axis, in the run's world units, of a 'large' Gaussian")
    parser.add_argument("--step", type=int, default=None, help="the checkpoint of this step (default: the latest)")
    args = parser.parse_args()
    print(f"| run | view | unseen share | alpha unseen | PSNR unseen | PSNR seen | PSNR | large off: alpha unseen | "
          f"PSNR unseen | PSNR seen | PSNR | large (> {args.large:g}) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for path in args.configs:
        print("\n".join(view_rows(path, args.large, args.step)))


if __name__ == "__main__":
    main()
