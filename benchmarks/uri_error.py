"""Where the water-free render (URI) of a trained `uw3dgs` run differs from the clean ground truth, by range.

    python benchmarks/uri_error.py outputs/synthetic/uw3dgs/<timestamp>/config.yml
    python benchmarks/uri_error.py RUN/config.yml --bands 0 4 6 8 10 14 --skip 0000.png

Scenes with ground truth only (the synthetic ones). Over the test views (less those named in `--skip`),
pixels are grouped by their true range (open water last) and each group gets its share of the pixels,
its PSNR, its mean signed error per channel in 8-bit grey levels (a bias the medium explains: a beta_D
off by d brightens the URI by exp(d z)) and its share of the total squared error per channel.

`--true-medium` replaces the URI by the rendered underwater image pushed back through the formation model
with the true medium (rendered range and coverage kept): (UWI - backscatter) / attenuation. Where that
removes a bias, the bias was the learned medium's, not the Gaussians'. Far bands amplify any error by
exp(beta_D z) there, so only the near bands say something.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from uw3dgs.engine.evaluator import load_trained
from uw3dgs.fields.medium import form_underwater_image


def dehaze_with_truth(outputs: dict, medium: dict, dataset_scale: float) -> torch.Tensor:
    """The clean radiance [H, W, 3] the rendered UWI implies under the true homogeneous `medium`."""
    beta_d, beta_b, b_inf = (torch.tensor(medium[k]) for k in ("beta_D", "beta_B", "B_inf"))  # [3], broadcast
    water = form_underwater_image(torch.zeros_like(outputs["rgb"]), outputs["alpha"], outputs["range"], beta_d,
                                  beta_b, b_inf, dataset_scale)
    return (outputs["rgb"] - water["backscatter"]) / water["attenuation"]


def grey_levels(mean_error: torch.Tensor) -> str:
    return "(" + ", ".join(f"{float(x) * 255:+.1f}" for x in mean_error) + ")"


def pooled_psnr(error: torch.Tensor) -> float:
    """PSNR of the mean squared error over all the pixels of `error` [M, 3] (peak 1)."""
    return float(-10 * torch.log10(error.square().mean()))


def band_table(config_path: Path, edges: list[float], skip: set[str], true_medium: bool) -> list[str]:
    _, datamanager, model, _ = load_trained(config_path)
    names = datamanager.scene.image_names
    errors, ranges = [], []
    for batch in datamanager.test_batches():
        if "clean_image" not in batch:
            raise SystemExit(f"{config_path}: the dataset has no clean ground truth; run this on a synthetic scene")
        if names[batch["index"]] in skip:
            continue
        with torch.no_grad():
            outputs = model.get_outputs(batch["camera"])
        uri = dehaze_with_truth(outputs, datamanager.scene.gt.medium, model.dataset_scale) if true_medium \
            else outputs["uri"]
        uri = uri.clamp(0, 1)
        errors.append((uri - batch["clean_image"]).reshape(-1, 3).double())
        ranges.append(batch["range"].reshape(-1))
    if not errors:
        raise SystemExit("--skip left no test view")
    error, z = torch.cat(errors), torch.cat(ranges)
    total = error.square().sum(0)
    bounds = [*edges, float("inf")]
    labels = [f"{lo:g}-{hi:g}" for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)] + ["open water"]
    groups = [(z >= lo) & (z < hi) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)] + [~torch.isfinite(z)]
    rows = []
    for label, member in zip(labels, groups, strict=True):
        if not bool(member.any()):
            continue
        e = error[member]
        share = ", ".join(f"{float(x):.0%}" for x in e.square().sum(0) / total.sum())
        rows.append(f"| {label} | {float(member.double().mean()):.1%} | {pooled_psnr(e):.1f} | "
                    f"{grey_levels(e.mean(0))} | ({share}) |")
    rows.append(f"| all | 100% | {pooled_psnr(error):.1f} | {grey_levels(error.mean(0))} | |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("config", type=Path, help="config.yml of a trained uw3dgs run")
    parser.add_argument("--bands", type=float, nargs="+", default=[0, 4, 6, 8, 10, 14],
                        help="range band edges in world units (the last band is open-ended)")
    parser.add_argument("--skip", nargs="*", default=[], help="test images to leave out, e.g. 0000.png")
    parser.add_argument("--true-medium", action="store_true",
                        help="de-haze the rendered UWI with the true medium instead of rendering the URI")
    args = parser.parse_args()
    print("| true range | pixels | URI PSNR | mean error R, G, B (grey levels) | share of all squared error R, G, B |")
    print("|---|---:|---:|---|---|")
    print("\n".join(band_table(args.config, args.bands, set(args.skip), args.true_medium)))


if __name__ == "__main__":
    main()
