"""`watersplatting`: WaterSplatting (Li et al. 2024), 3DGS with the water integrated between the depth-sorted Gaussians
of each pixel (`uw3dgs.render.medium_rasterize`), the water from an MLP of the ray direction alone
(`fields/direction_medium.py`), and their training recipe as the defaults (docs/methods/watersplatting.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from uw3dgs.cameras import Camera
from uw3dgs.config import Target, target
from uw3dgs.data.datamanager import Batch
from uw3dgs.data.downscale import area_downscale, downscale_camera
from uw3dgs.data.scene import SceneData
from uw3dgs.engine.callbacks import StepSchedule, TrainingCallback
from uw3dgs.engine.config import TrainConfig
from uw3dgs.engine.optimizers import Optimizers, ParamGroupConfig
from uw3dgs.fields.direction_medium import DirectionMedium, DirectionMediumConfig
from uw3dgs.methods.gaussian_splatting import (
    COVERAGE_EPS,
    GaussianSplattingModel,
    GaussianSplattingModelConfig,
    gaussian_optimizers,
)
from uw3dgs.metrics.image import dssim_loss, psnr
from uw3dgs.metrics.medium import medium_eval_summary, restored_image_metrics
from uw3dgs.options import check_number
from uw3dgs.registry import MethodSpec
from uw3dgs.render.medium_rasterize import rasterize_medium
from uw3dgs.render.medium_types import PixelMedium
from uw3dgs.render.types import Splats
from uw3dgs.strategy import DefaultStrategy, DensificationConfig, DensityControl
from uw3dgs.utils.profiling import section
from uw3dgs.utils.visualize import depth_to_image

DIRECTION_MEANING = (
    "WaterSplatting's medium: per viewing direction d (unit, dataset frame, d = (cos lat cos lon, cos lat sin lon, "
    "sin lat)), c_med (RGB in [0, 1]) and sigma_bs, sigma_attn (RGB, per unit of camera-space depth, dataset units): "
    "I = sum_i T_i alpha_i c_i exp(-sigma_attn z_i) + c_med (1 - sum_i T_i alpha_i exp(-sigma_bs z_i)) over the "
    "depth-sorted Gaussians. b_inf, beta_d, beta_b: c_med, sigma_attn and sigma_bs per unit of range, averaged over "
    "the training views' pixels.")
"""What medium.json's values mean for this method."""

MEDIUM_GROUP = "medium_mlp"
"""The parameter group of the direction MLP (its own learning-rate schedule and gradient clipping)."""


@dataclass(frozen=True)
class WaterSplattingModelConfig(GaussianSplattingModelConfig):
    _target: Target = target(lambda: WaterSplattingModel)
    medium: DirectionMediumConfig = field(default_factory=DirectionMediumConfig)
    densification: DensificationConfig = field(default_factory=lambda: DensificationConfig(
        refine_stop=10000, refine_stop_share=0.667, grad_threshold=0.0008, absgrad=True, percent_dense=0.001,
        min_opacity=0.5, late_min_opacity=0.1, reset_opacity_every=500, reset_opacity_value=0.5,
        prune_screen_size=None, prune_world_size=10.0))
    data_loss_eps: float = 1e-3
    """The data terms are divided by stop-gradient(prediction) + this (their reg-L1 and reg-D-SSIM): errors in dark
    pixels count as much as in bright ones."""
    num_downscales: int = 2
    """Training starts at 1 / 2^this of the data's resolution (but see min_train_size) ..."""
    resolution_schedule: int = 3000
    """... and doubles it every this many steps, up to the full resolution. Evaluation renders at full resolution."""
    min_train_size: int = 300
    """... and never below this many pixels on the longer side of the training images: num_downscales is lowered to
    the largest k with that side / 2^k >= this (0: num_downscales as given). Their SeaThru-NeRF images, 1,383 px wide,
    start at 345 px, which this leaves as it is; images of 172 px (IUI3-RedSea at --downscale-factor 8) would start
    at 43x28 pixels, where most initial Gaussians never pass the 0.5 opacity cull (docs/table1.md)."""
    reference_steps: int = 15000
    """resolution_schedule is for a run of this many steps (their 15,000); a run of --max-num-iterations N scales it
    by N / this, so a short run keeps their proportions (full resolution from 40% of the run on; unscaled, a 6,000-step
    run would never train at full resolution); 0 takes it as given."""

    def check_options(self) -> None:
        super().check_options()
        check_number(self, "data_loss_eps", gt=0)
        check_number(self, "num_downscales", ge=0, integer=True)
        check_number(self, "resolution_schedule", ge=1, integer=True)
        check_number(self, "min_train_size", ge=0, integer=True)
        check_number(self, "reference_steps", ge=0, integer=True)

    def downscales_for(self, longer_side: int) -> int:
        """num_downscales for training images whose longer side is `longer_side` pixels (`min_train_size`)."""
        k = self.num_downscales
        while k > 0 and longer_side / 2**k < self.min_train_size:
            k -= 1
        return k

    def resolution_schedule_for_run(self, max_num_iterations: int) -> int:
        """`resolution_schedule` for a run of `max_num_iterations` steps (`reference_steps`), at least 1."""
        if self.reference_steps == 0:
            return self.resolution_schedule
        return max(round(self.resolution_schedule * max_num_iterations / self.reference_steps), 1)


class WaterSplattingModel(GaussianSplattingModel):
    config: WaterSplattingModelConfig

    def __init__(self, config: WaterSplattingModelConfig, scene: SceneData, train_indices: list[int]):
        super().__init__(config, scene, train_indices)
        self.direction_medium = DirectionMedium(config.medium, config.kernels)
        self.dataset_scale = float(scene.dataset_scale)
        self.train_cameras = [scene.cameras[i] for i in train_indices]
        self.step = 0
        self.resolution_schedule = config.resolution_schedule
        """Steps between doublings of the training resolution in this run (`get_training_callbacks` scales it)."""
        self.num_downscales = config.downscales_for(max(max(c.width, c.height) for c in self.train_cameras))
        """Downscales of the coarse start for these training images (`min_train_size`)."""

    def set_step(self, step: int) -> None:
        """The training step, for the resolution schedule."""
        self.step = step

    def downscale_factor(self) -> int:
        """1 / the resolution this step trains at (1 outside training)."""
        if not self.training:
            return 1
        return 2 ** max(self.num_downscales - self.step // self.resolution_schedule, 0)

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {**super().param_groups(), MEDIUM_GROUP: list(self.direction_medium.parameters())}

    def get_training_callbacks(self, optimizers: Optimizers, max_num_iterations: int) -> list[TrainingCallback]:
        strategy = DefaultStrategy(self.config.densification, self.scene_extent, max_num_iterations)
        self.resolution_schedule = self.config.resolution_schedule_for_run(max_num_iterations)
        return [StepSchedule("sh_degree", self.gaussians), StepSchedule("resolution", self),
                MediumResettingDensityControl(strategy, self.gaussians, optimizers, (MEDIUM_GROUP,))]

    def get_outputs(self, camera: Camera) -> dict[str, Any]:
        """'rgb' [H, W, 3] the underwater image (object + water), 'uri' the restored one (no water), 'object' and
        'water' its two parts, 'c_med', 'sigma_bs', 'sigma_attn' [H, W, 3] the water per pixel, 'alpha', 'depth'
        (camera-space z of the covered part), 'range' (along the ray; the far bound where uncovered), 'means2d',
        'radii', 'absgrad' [N, 2] (filled by the backward), 'camera' (the one rendered) and 'downscale' (1 / its
        resolution: training starts below the data's, `downscale_factor`)."""
        return self.render_water(camera, self.downscale_factor(), absgrad=self.training)

    def render_water(self, camera: Camera, factor: int = 1, absgrad: bool = False, k: float = 1.0,
                     color: Tensor | None = None) -> dict[str, Any]:
        """`get_outputs`' dict for `camera` at 1 / `factor` of its resolution; `absgrad`: fill 'absgrad' in the
        backward. The water control: `k` >= 0 scales sigma_bs and sigma_attn (1: as learned, 0: no water), `color`
        [3] replaces c_med in every pixel (None: as learned)."""
        if factor > 1:
            camera = downscale_camera(camera, factor)
        with section("medium MLP"):
            medium = self.direction_medium.pixel_medium(camera)
        if k != 1.0 or color is not None:
            if k < 0:
                raise ValueError(f"the water factor k must be >= 0, got {k}")
            medium = PixelMedium(medium.color if color is None else color.to(medium.color).expand_as(medium.color),
                                 k * medium.sigma_bs, k * medium.sigma_attn)
        means, scales, quats, opacities = self.gaussians.activated()
        colors = self.gaussians.colors(camera.center)
        with section("rasterize"):
            out = rasterize_medium(Splats(means, quats, scales, opacities, colors), medium, camera,
                                   self.config.raster, absgrad=absgrad)
        if absgrad and out.means2d.requires_grad:
            out.means2d.retain_grad()
        covered = out.alpha > COVERAGE_EPS
        depth = torch.where(covered, out.depth / out.alpha.clamp_min(COVERAGE_EPS), torch.zeros_like(out.depth))
        ranges = torch.where(covered, depth * camera.ray_norms(), torch.full_like(depth, self.far_range))
        return {"rgb": out.underwater, "uri": out.render, "object": out.object, "water": out.medium,
                "c_med": medium.color, "sigma_bs": medium.sigma_bs, "sigma_attn": medium.sigma_attn,
                "alpha": out.alpha, "depth": depth, "range": ranges, "means2d": out.means2d, "radii": out.radii,
                "absgrad": out.absgrad, "camera": camera, "downscale": factor}

    def render_view(self, camera: Camera, water: Any = None) -> dict[str, Tensor]:
        """The view for uw-viewer and uw-render at full resolution, whatever the mode, changing no state: 'rgb' the
        underwater image, 'uri', 'alpha', 'range', 'backscatter' (the water term) and 'attenuation' (exp(-sigma_attn
        z) at the expected depth z of the covered part). `water` (the control: `k`, `b_inf`) rescales sigma_bs and
        sigma_attn and replaces c_med; None: as learned; k = 0 shows the URI (no water)."""
        k = 1.0 if water is None else water.k
        color = None if water is None or water.b_inf is None else torch.tensor(water.b_inf)
        out = self.render_water(camera, k=k, color=color)
        view = {"rgb": out["rgb"], "uri": out["uri"], "alpha": out["alpha"], "range": out["range"],
                "backscatter": out["water"], "attenuation": torch.exp(-out["sigma_attn"] * out["depth"][..., None])}
        if k == 0:  # no water at all (sigma -> 0 would still leave c_med at infinite range behind the Gaussians)
            view.update(rgb=out["uri"], backscatter=torch.zeros_like(out["uri"]))
        return view

    @torch.no_grad()
    def veiling_light(self) -> Tensor:
        """c_med [3] averaged over the training cameras' optical axes: the water colour the viewer's control starts
        from (the model's own varies with the direction)."""
        axes = torch.stack([c.viewmat[2, :3] for c in self.train_cameras]).to(self.gaussians.means)
        return self.direction_medium(torch.nn.functional.normalize(axes, dim=-1))[0].mean(0)

    @torch.no_grad()
    def export_medium(self, dataset_center: tuple[float, float, float], dataset_scale: float,
                      samples: int) -> dict[str, Any]:
        """The water for medium.json: 'b_inf', 'beta_d', 'beta_b' averaged over the training views' pixels as the
        eval keys are (`medium_summary`), and the MLP on a latitude-longitude grid of world directions in the dataset
        frame (`samples` latitudes x 2 `samples` longitudes): 'c_med', 'sigma_bs', 'sigma_attn' per unit of
        camera-space depth in dataset units."""
        summary = self.medium_summary(self.train_cameras)
        lat = torch.linspace(-torch.pi / 2, torch.pi / 2, samples)
        lon = torch.linspace(-torch.pi, torch.pi, 2 * samples + 1)[:-1]
        la, lo = torch.meshgrid(lat, lon, indexing="ij")
        dirs = torch.stack([la.cos() * lo.cos(), la.cos() * lo.sin(), la.sin()], dim=-1)
        c_med, s_bs, s_attn = self.direction_medium(dirs.to(self.gaussians.means))
        return {"kind": "direction", "meaning": DIRECTION_MEANING,
                **{name: [float(v) for v in value] for name, value in summary.items()},
                "latitudes": lat.tolist(), "longitudes": lon.tolist(), "c_med": c_med.cpu().tolist(),
                "sigma_bs": (s_bs / dataset_scale).cpu().tolist(),
                "sigma_attn": (s_attn / dataset_scale).cpu().tolist()}

    def target_image(self, outputs: dict[str, Any], image: Tensor) -> Tensor:
        """`image` [H, W, 3] at the resolution `outputs` were rendered at (area-averaged)."""
        return area_downscale(image, outputs["downscale"])

    def get_loss_dict(self, outputs: dict[str, Any], batch: Batch, step: int) -> dict[str, Tensor]:
        """(1 - ssim_lambda) reg-L1 + ssim_lambda reg-D-SSIM: prediction and target divided by stop-gradient(prediction)
        + data_loss_eps before the L1 and the SSIM."""
        lam, eps = self.config.ssim_lambda, self.config.data_loss_eps
        pred = outputs["rgb"]
        gt = self.target_image(outputs, batch["image"])
        scale = pred.detach() + eps
        with section("loss: reg-L1 + reg-D-SSIM"):
            l1 = ((gt - pred) / scale).abs().mean()
            return {"rgb_loss": (1 - lam) * l1 + lam * dssim_loss(pred / scale, gt / scale, self.config.kernels)}

    def get_metrics_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float]:
        gt = self.target_image(outputs, batch["image"])
        metrics = {"psnr": float(psnr(outputs["rgb"].detach().clamp(0, 1), gt)),
                   "num_gaussians": float(self.num_gaussians)}
        for name in ("c_med", "sigma_bs", "sigma_attn"):
            for channel, v in zip("rgb", outputs[name].detach().mean((0, 1)).tolist(), strict=True):
                metrics[f"medium/{name}_{channel}"] = v
        return metrics

    def get_eval_metrics(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float | None]:
        """3DGS's (of the underwater image) and the restored image's against the clean truth where there is one."""
        return {**super().get_eval_metrics(outputs, batch), **restored_image_metrics(outputs["uri"], batch)}

    @torch.no_grad()
    def medium_summary(self, cameras: list[Camera]) -> dict[str, Tensor]:
        """The water averaged over every pixel of `cameras`, as the eval keys name a medium: 'b_inf' = c_med;
        'beta_d' = sigma_attn and 'beta_b' = sigma_bs, each divided by the pixel's ray norm |K^-1 (u, v, 1)| (the
        per-range coefficient a camera-z one is: exp(-sigma z) = exp(-sigma / |ray| range)) and by the dataset scale
        (per dataset unit, as the truth)."""
        sums = {name: torch.zeros(3, dtype=torch.float64) for name in ("b_inf", "beta_d", "beta_b")}
        pixels = 0
        for camera in cameras:
            medium = self.direction_medium.pixel_medium(camera.to(self.gaussians.means.device))
            per_range = (camera.ray_norms().to(medium.color)[..., None] * self.dataset_scale)
            for name, value in (("b_inf", medium.color), ("beta_d", medium.sigma_attn / per_range),
                                ("beta_b", medium.sigma_bs / per_range)):
                sums[name] += value.double().sum((0, 1)).cpu()
            pixels += camera.width * camera.height
        return {name: (total / max(pixels, 1)).float() for name, total in sums.items()}

    def get_eval_summary(self, scene: SceneData) -> dict[str, float | None]:
        """3DGS's (the floater ratios) and the water averaged over the test views' pixels (the scene's views that
        are not training views; `medium_summary`), with its error against the true medium on synthetic scenes."""
        train = set(self.train_indices)
        tests = [camera for i, camera in enumerate(scene.cameras) if i not in train]
        return {**super().get_eval_summary(scene), **medium_eval_summary(self.medium_summary(tests), scene)}

    def get_image_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, Tensor]:
        images = {"gt": self.target_image(outputs, batch["image"]), "uwi": outputs["rgb"].clamp(0, 1),
                  "uri": outputs["uri"].clamp(0, 1), "object": outputs["object"].clamp(0, 1),
                  "water": outputs["water"].clamp(0, 1), "depth": depth_to_image(outputs["range"], outputs["alpha"])}
        if "clean_image" in batch:
            images["gt_clean"] = self.target_image(outputs, batch["clean_image"])
        return images


class MediumResettingDensityControl(DensityControl):
    """Density control that also zeroes the Adam moments of the medium's parameter groups whenever the strategy may
    have removed Gaussians (WaterSplatting: the medium's optimizer state is reset after each cull)."""

    name = "densification"

    def __init__(self, strategy: DefaultStrategy, gaussians, optimizers: Optimizers, medium_groups: tuple[str, ...]):
        super().__init__(strategy, gaussians, optimizers)
        self.medium_groups = medium_groups

    def after_step(self, step: int, batch: Batch, outputs: dict[str, Any]) -> None:
        super().after_step(step, batch, outputs)
        if not self.strategy.prunes_at(step):
            return
        for name in self.medium_groups:
            optimizer = self.optimizers.optimizers[name]
            for state in optimizer.state.values():
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in state:
                        state[key].zero_()


def watersplatting_optimizers() -> dict[str, ParamGroupConfig]:
    """Their rates (water_splatting_config.py): 3DGS's, the positions decaying to 5e-5 (not 1.6e-6); the medium MLP
    at 1e-3 decaying to 1.5e-4 over the run, its gradient clipped to norm 1e-3."""
    return {**gaussian_optimizers(means_lr_final=5e-5),
            MEDIUM_GROUP: ParamGroupConfig(1e-3, lr_final=1.5e-4, max_grad_norm=1e-3)}


method = MethodSpec(
    name="watersplatting",
    description="WaterSplatting (Li et al. 2024): 3DGS with the water composited between the depth-sorted Gaussians, "
                "from an MLP of the ray direction; reg-L1 + reg-D-SSIM, absolute-gradient densification.",
    config=TrainConfig(method_name="watersplatting", model=WaterSplattingModelConfig(),
                       optimizers=watersplatting_optimizers(), max_num_iterations=15000),
)
"""The recipe of their `water-splatting` method (water_splatting_config.py); dataclasses.replace makes variants."""
