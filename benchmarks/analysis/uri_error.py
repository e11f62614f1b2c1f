"""Where the water-free render (URI) of a trained `uw3dgs` run differs from the clean ground truth, by range.

    python benchmarks/analysis/uri_error.py outputs/synthetic/uw3dgs/<timestamp>/config.yml
    python benchmarks/analysis/uri_error.py RUN/config.yml --bands 0 4 6 8 10 14 --skip 0000.png
    python benchmarks/analysis/uri_error.py RUN/config.yml --step 5000  # a checkpoint the run kept (--keep-checkpoints)

Scenes with ground truth only (the synthetic ones). Over the test views (less those named in `--skip`),
pixels are grouped by their true range (open water last) and each group gets its share of the pixels,
its PSNR, its mean signed error per channel in 8-bit grey levels (a bias the medium explains: a beta_D
off by d brightens the URI by exp(d z)), its share of the total squared error per channel, and the mean
signed error of the rendered range over its covered pixels (a range short by dz darkens the URI by about
exp(-beta_D dz) where the backscatter has saturated), and the share of the covered pixels' blending weight
that comes from Gaussians in front of the true surface (`--front-margin`, default 5% of the true range; a
Gaussian over open water counts as in front): floaters, which pull the rendered range short.

`--true-medium` replaces the URI by the rendered underwater image pushed back through the formation model
with the true medium (rendered range and coverage kept): (UWI - backscatter) / attenuation. Where that
removes a bias, the bias was the learned medium's, not the Gaussians'. `--true-range` does the same with
the learned medium (re-read along each ray) at the true range of every pixel with a surface: what is
left is the learned medium's error, what goes away was the rendered range's. Both together give back the
clean image up to the render's own UWI error. Far bands amplify any error by exp(beta_D z) there. Open water
(no true surface) keeps the rendered URI in every variant.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from uw3dgs.engine.evaluator import load_trained
from uw3dgs.medium.formation import form_underwater_image
from uw3dgs.metrics.depth import COVERED
from uw3dgs.render.rasterize import rasterize
from uw3dgs.render.types import Splats


def dehaze(outputs: dict, ranges: torch.Tensor, beta_d: torch.Tensor, beta_b: torch.Tensor, b_inf: torch.Tensor,
           dataset_scale: float) -> torch.Tensor:
    """The clean radiance [H, W, 3] the rendered UWI implies under a medium (betas [3] or [H, W, 3]) at `ranges`."""
    water = form_underwater_image(torch.zeros_like(outputs["rgb"]), outputs["alpha"], ranges, beta_d, beta_b,
                                  b_inf, dataset_scale)
    return (outputs["rgb"] - water["backscatter"]) / water["attenuation"]


def learned_medium_at(model, camera, ranges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The model's (beta_D, beta_B) averaged along each pixel's ray to `ranges` [H, W], and its B_inf."""
    return *model.ray_betas(camera, ranges), model.medium.b_inf.detach()


def in_front_share(model, camera, true_range: torch.Tensor, margin: float) -> torch.Tensor:
    """Share [H, W] of each pixel's blending weight from Gaussians in front of the true surface: the centre nearer
    to the camera than (1 - margin) x the true range at the pixel it projects to (inf on open water; a centre
    beside the image takes the nearest edge pixel's).

    Rendered as an image whose colour is 1 for those Gaussians and 0 for the rest, divided by the coverage."""
    means, scales, quats, opacities = (t.detach() for t in model.gaussians.activated())
    uv, _ = camera.project(means)
    ahead = (means @ camera.viewmat[2, :3].to(means.dtype) + camera.viewmat[2, 3]) > 0
    col = uv[:, 0].nan_to_num().floor().long().clamp(0, camera.width - 1)
    row = uv[:, 1].nan_to_num().floor().long().clamp(0, camera.height - 1)
    distance = (means - camera.center.to(means.dtype)).norm(dim=-1)
    front = ahead & (distance < (1 - margin) * true_range[row, col].to(means.dtype))
    indicator = front.to(means.dtype)[:, None].expand(-1, 3).contiguous()
    out = rasterize(Splats(means, quats, scales, opacities, indicator), camera, model.config.raster)
    return out.render[..., 0] / out.alpha.clamp_min(1e-8)


def grey_levels(mean_error: torch.Tensor) -> str:
    return "(" + ", ".join(f"{float(x) * 255:+.1f}" for x in mean_error) + ")"


def pooled_psnr(error: torch.Tensor) -> float:
    """PSNR of the mean squared error over all the pixels of `error` [M, 3] (peak 1)."""
    return float(-10 * torch.log10(error.square().mean()))


def band_table(config_path: Path, edges: list[float], skip: set[str], use_true_medium: bool = False,
               use_true_range: bool = False, front_margin: float = 0.05, step: int | None = None) -> list[str]:
    _, datamanager, model, _ = load_trained(config_path, step=step)
    names = datamanager.scene.image_names
    errors, true_ranges, range_errors, front_shares = [], [], [], []
    for batch in datamanager.test_batches():
        if "clean_image" not in batch:
            raise SystemExit(f"{config_path}: the dataset has no clean ground truth; run this on a synthetic scene")
        if names[batch["index"]] in skip:
            continue
        with torch.no_grad():
            outputs = model.get_outputs(batch["camera"])
            if "uri" not in outputs:
                raise SystemExit(f"{config_path}: this run renders no water-free image (URI); pass a uw3dgs run "
                                 "(uw3dgs, uw3dgs-no-lz, uw3dgs-no-lbeta), not 3dgs or uw3dgs-no-medium")
            uri = outputs["uri"]
            if use_true_medium or use_true_range:
                at = torch.where(batch["range"].isfinite(), batch["range"], outputs["range"]) \
                    if use_true_range else outputs["range"]
                medium = datamanager.scene.gt.medium_tensors() if use_true_medium \
                    else learned_medium_at(model, batch["camera"], at)
                surface = batch["range"].isfinite()[..., None]  # open water has nothing to de-haze: URI as rendered
                uri = torch.where(surface, dehaze(outputs, at, *medium, model.dataset_scale), uri)
        uri = uri.clamp(0, 1)
        errors.append((uri - batch["clean_image"]).reshape(-1, 3).double())
        true_ranges.append(batch["range"].reshape(-1))
        covered = outputs["alpha"] > COVERED
        hit = covered & batch["range"].isfinite()  # covered, with a true surface
        range_errors.append(torch.where(hit, outputs["range"] - batch["range"], torch.nan).reshape(-1).double())
        with torch.no_grad():
            share = in_front_share(model, batch["camera"], batch["range"], front_margin)
        front_shares.append(torch.where(covered, share, torch.nan).reshape(-1).double())
    if not errors:
        raise SystemExit("--skip left no test view")
    error, z, range_error, front = torch.cat(errors), torch.cat(true_ranges), torch.cat(range_errors), \
        torch.cat(front_shares)
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
        dz = range_error[member]  # NaN where uncovered, and everywhere on open water (no true range)
        bias = f"{float(dz.nanmean()):+.2f}" if bool(dz.isfinite().any()) else "-"
        in_front = front[member]
        in_front = f"{float(in_front.nanmean()):.1%}" if bool(in_front.isfinite().any()) else "-"
        rows.append(f"| {label} | {float(member.double().mean()):.1%} | {pooled_psnr(e):.1f} | "
                    f"{grey_levels(e.mean(0))} | ({share}) | {bias} | {in_front} |")
    rows.append(f"| all | 100% | {pooled_psnr(error):.1f} | {grey_levels(error.mean(0))} | | "
                f"{float(range_error.nanmean()):+.2f} | {float(front.nanmean()):.1%} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("config", type=Path, help="config.yml of a trained uw3dgs run")
    parser.add_argument("--bands", type=float, nargs="+", default=[0, 4, 6, 8, 10, 14],
                        help="range band edges in world units (the last band is open-ended)")
    parser.add_argument("--skip", nargs="*", default=[], help="test images to leave out, e.g. 0000.png")
    parser.add_argument("--true-medium", action="store_true",
                        help="de-haze the rendered UWI with the true medium instead of rendering the URI")
    parser.add_argument("--true-range", action="store_true",
                        help="de-haze the rendered UWI at the true ranges (with the learned medium, or the true one)")
    parser.add_argument("--front-margin", type=float, default=0.05,
                        help="a Gaussian nearer than (1 - this) x the true range at its centre's pixel is in front")
    parser.add_argument("--step", type=int, default=None, help="the checkpoint of this step (default: the latest)")
    args = parser.parse_args()
    rows = band_table(args.config, args.bands, set(args.skip), args.true_medium, args.true_range, args.front_margin,
                      args.step)
    print("| true range | pixels | URI PSNR | mean error R, G, B (grey levels) | share of all squared error R, G, B "
          "| rendered range - true (covered pixels) | weight in front of the true surface (covered pixels) |")
    print("|---|---:|---:|---|---|---:|---:|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
