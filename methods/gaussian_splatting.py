"""`3dgs`: plain 3D Gaussian Splatting (Kerbl et al. 2023), the baseline every underwater method is compared to."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

import torch
from torch import Tensor, nn

from uw3dgs.cameras import Camera
from uw3dgs.config import InstantiateConfig, Target, target
from uw3dgs.data.datamanager import Batch
from uw3dgs.data.scene import SceneData
from uw3dgs.engine.callbacks import StepSchedule, TrainingCallback
from uw3dgs.engine.config import TrainConfig
from uw3dgs.engine.optimizers import Optimizers, ParamGroupConfig
from uw3dgs.fields.gaussians import GaussianField, GaussianFieldConfig
from uw3dgs.medium.formation import Water
from uw3dgs.metrics.depth import range_abs_rel
from uw3dgs.metrics.floaters import floater_ratios
from uw3dgs.metrics.image import dssim_loss, l1_loss, psnr
from uw3dgs.models.base import Model, ModelConfig
from uw3dgs.models.field_slot import field_slot
from uw3dgs.options import check_number
from uw3dgs.registry import MethodSpec
from uw3dgs.render import RasterOutput, RasterSettings, Splats, rasterize
from uw3dgs.strategy import DefaultStrategy, DensificationConfig, DensityControl
from uw3dgs.utils.profiling import section
from uw3dgs.utils.visualize import depth_to_image

COVERAGE_EPS = 1e-4
"""Pixels whose alpha is at most this show no surface: their range is the scene's far bound (open water)."""


@dataclass(frozen=True)
class GaussianSplattingModelConfig(ModelConfig):
    _target: Target = target(lambda: GaussianSplattingModel)
    gaussians: Annotated[InstantiateConfig, field_slot("gaussians")] = field(default_factory=GaussianFieldConfig)
    """The Gaussian field: a registered field of kind 'gaussians', chosen by its subcommand (default 'gaussians');
    its knobs are --model.gaussians.*."""
    densification: DensificationConfig = field(default_factory=DensificationConfig)
    raster: RasterSettings = field(default_factory=RasterSettings)
    ssim_lambda: float = 0.2
    """Image loss = (1 - ssim_lambda) L1 + ssim_lambda D-SSIM."""
    background: Literal["black", "white", "random"] = "black"
    """Colour behind the Gaussians; 'random' draws one per training step (evaluation uses black)."""

    def check_options(self) -> None:
        super().check_options()
        check_number(self, "ssim_lambda", ge=0, le=1)


class GaussianSplattingModel(Model):
    config: GaussianSplattingModelConfig

    def __init__(self, config: GaussianSplattingModelConfig, scene: SceneData, train_indices: list[int]):
        super().__init__(config, scene, train_indices)
        self.far_range = float(scene.far)
        self.gaussians: GaussianField = config.gaussians.setup(points=scene.points, colors=scene.point_colors,
                                                                 kernels=config.kernels)

    @property
    def num_gaussians(self) -> int:
        return self.gaussians.num_gaussians

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return self.gaussians.param_groups()

    def state_keys_resized_in_training(self) -> set[str]:
        return {f"gaussians.{name}" for name in self.gaussians.param_names}

    def get_training_callbacks(self, optimizers: Optimizers, max_num_iterations: int) -> list[TrainingCallback]:
        strategy = DefaultStrategy(self.config.densification, self.scene_extent, max_num_iterations)
        return [StepSchedule("sh_degree", self.gaussians), DensityControl(strategy, self.gaussians, optimizers)]

    def background(self, device: torch.device) -> Tensor:
        if self.config.background == "random" and self.training:
            return torch.rand(3, device=device)
        return torch.full((3,), 1.0 if self.config.background == "white" else 0.0, device=device)

    def render(self, camera: Camera, keep: Tensor | None = None, depth_weights: Tensor | None = None,
               frozen: bool = False, colors: Tensor | None = None,
               projection: RasterOutput | None = None) -> dict[str, Any]:
        """Rasterize the Gaussians' view-dependent colours seen from `camera`, no background:
        'radiance' [H, W, 3] = sum_i w_i c_i; 'alpha' [H, W] coverage; 'depth' [H, W] expected camera-space z of
        the covered part (0 where uncovered); 'range' [H, W] the same along the ray from the camera centre
        (world units; the scene's far bound where uncovered: open water); 'means2d' [N, 2] pixel centres
        (their gradient is kept for density control while training); 'radii' [N] pixels, 0 = not visible;
        'weight_sum' [N] each Gaussian's blending weights summed over the image and 'pixel_count' [N] the pixels it
        was blended into (no gradient); 'colors' [N, 3] the view-dependent colours it rendered; 'raster' the
        rasterizer's `RasterOutput`.

        `keep` [N] in [0, 1] scales the opacities (PAUP's relaxed keep mask). `depth_weights` [N] >= 0 weight each
        Gaussian's share of the depth (the paper's (1 - U_i)): depth = sum_i w_i d_i z_i / sum_i w_i d_i, the
        unweighted depth where a covered pixel's weights sum to nothing. `frozen` renders the Gaussians detached:
        gradients reach `keep` and `depth_weights` only. `colors` [N, 3]: the colours seen from `camera` when the
        caller has them (a second render of the same view), else computed. `projection`: the 'raster' of an
        earlier render of this view with opacities at least these, reused by a `frozen` render (`rasterize`)."""
        with torch.set_grad_enabled(torch.is_grad_enabled() and not frozen):
            means, scales, quats, opacities = self.gaussians.activated()
            if colors is None:
                colors = self.gaussians.colors(camera.center)
        if frozen:  # parameters or given: no_grad leaves them attached
            means, quats, colors = means.detach(), quats.detach(), colors.detach()
        rendered = colors
        if keep is not None:
            opacities = opacities * keep
        if depth_weights is not None:  # the weighted depth composites as two more feature channels
            z = means @ camera.viewmat[2, :3] + camera.viewmat[2, 3]
            colors = torch.cat([colors, depth_weights[:, None], (depth_weights * z)[:, None]], dim=-1)
        with section("rasterize"):
            out = rasterize(Splats(means, quats, scales, opacities, colors), camera, self.config.raster, projection)
        if self.training and out.means2d.requires_grad:
            out.means2d.retain_grad()  # density control reads the screen-space gradient
        covered = out.alpha > COVERAGE_EPS
        depth = torch.where(covered, out.depth / out.alpha.clamp_min(COVERAGE_EPS), torch.zeros_like(out.depth))
        radiance = out.render
        if depth_weights is not None:
            radiance, weight, weighted = out.render[..., :3], out.render[..., 3], out.render[..., 4]
            depth = torch.where(weight > COVERAGE_EPS, weighted / weight.clamp_min(COVERAGE_EPS), depth)
        ranges = torch.where(covered, depth * camera.ray_norms(), torch.full_like(depth, self.far_range))
        return {"radiance": radiance, "alpha": out.alpha, "depth": depth, "range": ranges,
                "means2d": out.means2d, "radii": out.radii, "weight_sum": out.weight_sum,
                "pixel_count": out.pixel_count, "colors": rendered, "raster": out}

    def over_background(self, radiance: Tensor, alpha: Tensor) -> Tensor:
        """`radiance` [H, W, 3] composited over the background colour where `alpha` [H, W] leaves it visible."""
        return radiance + (1.0 - alpha[..., None]) * self.background(alpha.device)

    def get_outputs(self, camera: Camera) -> dict[str, Any]:
        """`render`'s outputs with 'rgb' [H, W, 3] = the radiance over the background in place of 'radiance'."""
        outputs = self.render(camera)
        outputs["rgb"] = self.over_background(outputs.pop("radiance"), outputs["alpha"])
        return outputs

    def render_view(self, camera: Camera, water: Water | None = None) -> dict[str, Tensor]:
        """`Model.render_view`: the radiance over the evaluation background (never the random one), alpha, range."""
        out = self.render(camera)
        background = torch.full((3,), 1.0 if self.config.background == "white" else 0.0, device=out["alpha"].device)
        return {"rgb": out["radiance"] + (1.0 - out["alpha"][..., None]) * background, "alpha": out["alpha"],
                "range": out["range"]}

    def get_eval_metrics(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float | None]:
        """Adds `depth_abs_rel` (rendered against true range) where the dataset has true ranges; None (missing)
        where the render covers no pixel with a true surface."""
        metrics: dict[str, float | None] = dict(super().get_eval_metrics(outputs, batch))
        if "range" in batch:
            metrics["depth_abs_rel"] = range_abs_rel(outputs["range"].detach(), outputs["alpha"].detach(),
                                                     batch["range"])
        return metrics

    def get_eval_summary(self, scene: SceneData) -> dict[str, float | None]:
        """`floater_ratio` over the training views (uw3dgs/metrics/floaters.py) against the rendered surface and,
        where the scene knows its true ranges, `floater_ratio_gt` against the true one."""
        was_training = self.training
        self.eval()
        with torch.no_grad():
            means, scales, _, _ = self.gaussians.activated()
            cameras = [scene.cameras[i].to(means.device) for i in self.train_indices]
            truth = None if scene.gt is None else [scene.gt.ranges[i] for i in self.train_indices]
            out = floater_ratios(means, scales.max(dim=-1).values, cameras, self.render, truth)
        self.train(was_training)
        return {**super().get_eval_summary(scene), **out}

    def get_loss_dict(self, outputs: dict[str, Any], batch: Batch, step: int) -> dict[str, Tensor]:
        lam = self.config.ssim_lambda
        pred, gt = outputs["rgb"], batch["image"]
        with section("loss: L1 + D-SSIM"):
            return {"rgb_loss": (1 - lam) * l1_loss(pred, gt) + lam * dssim_loss(pred, gt, self.config.kernels)}

    def get_metrics_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float]:
        return {"psnr": float(psnr(outputs["rgb"].detach().clamp(0, 1), batch["image"])),
                "num_gaussians": float(self.num_gaussians)}

    def get_image_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, Tensor]:
        return {"gt": batch["image"], "render": outputs["rgb"].clamp(0, 1),
                "depth": depth_to_image(outputs["range"], outputs["alpha"])}


def gaussian_optimizers(means_lr: float = 1.6e-4, means_lr_final: float = 1.6e-6, opacity_lr: float = 0.05,
                        scaling_lr: float = 0.005, rotation_lr: float = 0.001,
                        feature_lr: float = 0.0025) -> dict[str, ParamGroupConfig]:
    """3DGS's learning rates; position rates are per unit of scene extent and decay over the run."""
    return {
        "means": ParamGroupConfig(means_lr, scale_by_scene_extent=True, lr_final=means_lr_final),
        "scales": ParamGroupConfig(scaling_lr),
        "quats": ParamGroupConfig(rotation_lr),
        "opacities": ParamGroupConfig(opacity_lr),
        "sh0": ParamGroupConfig(feature_lr),
        "shN": ParamGroupConfig(feature_lr / 20.0),
    }


method = MethodSpec(
    name="3dgs",
    description="3D Gaussian Splatting baseline (no water model): L1 + 0.2 D-SSIM, 3DGS density control.",
    config=TrainConfig(method_name="3dgs", model=GaussianSplattingModelConfig(),
                       optimizers=gaussian_optimizers()),
)
