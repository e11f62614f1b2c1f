"""`uw3dgs`: 3DGS plus the learnable underwater image formation module (UW-3DGS, the paper), and its
ablations as configs of the same model.

Physics-Aware Uncertainty Pruning (PAUP) is not part of this model yet: until it lands, every
Gaussian's uncertainty U_i is 0 and its physics-aware uncertainty score PUS_i is 1, which is exactly
what L_beta and L_z reduce to without the PAUP branch.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from uw3dgs.cameras import Camera
from uw3dgs.config import Target, target
from uw3dgs.data.datamanager import Batch
from uw3dgs.data.scene import SceneData
from uw3dgs.engine.config import TrainConfig
from uw3dgs.engine.optimizers import ParamGroupConfig
from uw3dgs.fields.medium import MediumField, MediumFieldConfig, MediumGridConfig, form_underwater_image
from uw3dgs.fields.medium_estimate import estimate_medium, open_water_color
from uw3dgs.methods.gaussian_splatting import GaussianSplattingModel, GaussianSplattingModelConfig, gaussian_optimizers
from uw3dgs.metrics.image import psnr, ssim
from uw3dgs.options import check_number
from uw3dgs.registry import MethodSpec
from uw3dgs.render.sh import rgb_to_sh
from uw3dgs.strategy import DensificationConfig
from uw3dgs.utils.console import info
from uw3dgs.utils.visualize import depth_to_image


@dataclass(frozen=True)
class UW3DGSModelConfig(GaussianSplattingModelConfig):
    _target: Target = target(lambda: UW3DGSModel)
    medium_field: str = "medium-grid"
    """Registry name of the medium field (entry points `uw3dgs.fields` of kind 'medium'): 'medium-grid' (VM grids,
    the paper) or 'medium-homogeneous' (one value per channel); its knobs are --model.medium.*."""
    medium: MediumFieldConfig = field(default_factory=MediumGridConfig)
    use_medium: bool = True
    """False renders plain 3DGS (the no-medium ablation): the Gaussians must explain the water themselves."""
    beta_loss_weight: float = 0.05
    """Weight of L_beta (pull of beta toward its prior at the Gaussian centres + VM factor norms)."""
    beta_loss_samples: int = 4096
    """Gaussian centres drawn per step to estimate L_beta's mean over all centres."""
    depth_loss_weight: float = 0.05
    """Weight of L_z = mean_i (1 - U_i) |z(p_i) - zhat_i| over visible Gaussians, in units of the median depth."""

    field_slots: ClassVar[dict[str, tuple[str, str]]] = {**GaussianSplattingModelConfig.field_slots,
                                                         "medium_field": ("medium", "medium")}

    def check_options(self) -> None:
        super().check_options()
        check_number(self, "beta_loss_weight", ge=0)
        check_number(self, "beta_loss_samples", ge=1, integer=True)
        check_number(self, "depth_loss_weight", ge=0)


class UW3DGSModel(GaussianSplattingModel):
    config: UW3DGSModelConfig

    def __init__(self, config: UW3DGSModelConfig, scene: SceneData, train_indices: list[int]):
        super().__init__(config, scene, train_indices)
        self.dataset_scale = float(scene.dataset_scale)
        self.medium: MediumField | None = None
        if config.use_medium:
            centers = torch.stack([scene.cameras[i].center for i in train_indices]).float()
            self.medium = config.medium.setup(points=scene.points, camera_centers=centers)
            if config.medium.init == "truth" and (scene.gt is None or not scene.gt.medium):
                raise ValueError("--model.medium.init truth needs a scene that knows its medium (gt/medium.json: "
                                 "the synthetic ones); use 'estimate' or 'prior'")

    def initialize_from_data(self, scene: SceneData, train_indices: list[int]) -> None:
        """With init 'estimate' (or 'truth'), start the medium from the point-based estimate (or the true medium),
        the Gaussians' colours de-hazed with it. Here, not in __init__: a resumed run or a model rebuilt for
        uw-eval gets its medium from the checkpoint and must not pay for a fit it throws away."""
        mc = self.config.medium
        if self.medium is None or mc.init == "prior":
            return
        cameras, images = [scene.cameras[i] for i in train_indices], [scene.images[i] for i in train_indices]
        known, water = None, None
        if mc.init == "truth":
            known = scene.gt.medium_tensors()
            info("medium: the true one (gt/medium.json), an oracle for analysis")
        else:
            if mc.open_water_cells > 0:
                water = open_water_color(scene.points.float(), cameras, images, mc.open_water_cells,
                                         mc.open_water_min_share)
            source = "fitted (no open water in view)" if water is None else \
                f"read off open water: ({', '.join(f'{x:.3f}' for x in water.tolist())})"
            info(f"medium estimate: B_inf {source}")
        estimate = estimate_medium(scene.points, scene.point_colors, cameras, images, self.dataset_scale,
                                   b_inf=water, dark_bins=mc.dark_bins, dark_share=mc.dark_share,
                                   sfm_cameras=scene.cameras if mc.dehaze_unseen_with_all_poses else None,
                                   known=known)
        learned = mc.learn_beta
        self.medium.set_homogeneous(estimate.beta_d if learned else None, estimate.beta_b if learned else None,
                                    estimate.b_inf)
        if learned:  # with beta pinned at the prior, the estimate's de-hazed colours would not match it
            # L_beta then keeps the field near what the data says, not near a constant that may be far off
            # (docs/methods/uw3dgs.md: pulled toward beta_prior, red beta_D drifts away from the truth)
            self.medium.set_prior(estimate.beta_d, estimate.beta_b)
            with torch.no_grad():
                self.gaussians.sh0.copy_(rgb_to_sh(estimate.clean_colors.clamp(0, 1))[:, None, :])

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        groups = super().param_groups()
        if self.medium is not None:
            groups.update(self.medium.param_groups())
        return groups

    def get_outputs(self, camera: Camera) -> dict[str, Any]:
        """`render`'s outputs with the water: 'uri' [H, W, 3] the water-free radiance (the rendered one), 'rgb'
        [H, W, 3] the underwater image formed from it; with a medium also 'attenuation', 'backscatter', 'beta_d',
        'beta_b' [H, W, 3] (the betas ray-averaged per pixel, per dataset unit)."""
        outputs = self.render(camera)
        uri = outputs["uri"] = outputs.pop("radiance")
        if self.medium is None:
            outputs["rgb"] = self.over_background(uri, outputs["alpha"])
            return outputs
        beta_d, beta_b = self.ray_betas(camera, outputs["range"])
        formed = form_underwater_image(uri, outputs["alpha"], outputs["range"], beta_d, beta_b, self.medium.b_inf,
                                       self.dataset_scale)
        outputs.update(rgb=formed["uwi"], attenuation=formed["attenuation"], backscatter=formed["backscatter"],
                       beta_d=beta_d, beta_b=beta_b)
        return outputs

    def ray_betas(self, camera: Camera, ranges: Tensor) -> tuple[Tensor, Tensor]:
        """beta_D, beta_B [H, W, 3] averaged along each pixel's ray from the camera to `ranges` [H, W]."""
        dirs = camera.ray_directions().reshape(-1, 3)
        beta_d, beta_b = self.medium.ray_betas(camera.center.to(dirs.dtype), dirs, ranges.reshape(-1))
        shape = (*ranges.shape, 3)
        return beta_d.reshape(shape), beta_b.reshape(shape)

    def depth_consistency(self, outputs: dict[str, Any], camera: Camera) -> Tensor:
        """L_z: |rendered range at the pixel of each visible Gaussian's centre - its distance to the camera|,
        in units of the view's median rendered range (a scalar)."""
        visible = outputs["radii"] > 0
        pix = outputs["means2d"][visible].detach().floor().long()
        inside = (pix[:, 0] >= 0) & (pix[:, 0] < camera.width) & (pix[:, 1] >= 0) & (pix[:, 1] < camera.height)
        if not bool(inside.any()):
            return outputs["range"].sum() * 0.0
        pix = pix[inside]
        rendered = outputs["range"][pix[:, 1], pix[:, 0]]
        own = (self.gaussians.means[visible][inside] - camera.center).norm(dim=-1)
        scale = rendered.detach().median().clamp_min(1e-6)  # unit-free: the weight means the same at any scale
        return ((rendered - own).abs() / scale).mean()

    def get_loss_dict(self, outputs: dict[str, Any], batch: Batch, step: int) -> dict[str, Tensor]:
        losses = super().get_loss_dict(outputs, batch, step)
        c = self.config
        if self.medium is not None and c.beta_loss_weight > 0:
            means = self.gaussians.means.detach()
            if len(means) > c.beta_loss_samples:  # an unbiased estimate of the mean over all centres
                means = means[torch.randint(len(means), (c.beta_loss_samples,), device=means.device)]
            losses["beta_loss"] = c.beta_loss_weight * self.medium.regularizer(means)
        if c.depth_loss_weight > 0:
            losses["depth_loss"] = c.depth_loss_weight * self.depth_consistency(outputs, batch["camera"])
        return losses

    def medium_summary(self) -> dict[str, Tensor]:
        """Learned B_inf and the mean of beta_D, beta_B over the Gaussian centres (per channel)."""
        if self.medium is None:
            return {}
        with torch.no_grad():
            beta_d, beta_b = self.medium.betas(self.gaussians.means)
        return {"b_inf": self.medium.b_inf.detach(), "beta_d": beta_d.mean(0), "beta_b": beta_b.mean(0)}

    def get_metrics_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float]:
        """Adds B_inf and this view's ray-averaged beta_D, beta_B (cheap: already computed for rendering)."""
        metrics = super().get_metrics_dict(outputs, batch)
        if self.medium is None:
            return metrics
        values = {"b_inf": self.medium.b_inf.detach(), "beta_d": outputs["beta_d"].detach().mean((0, 1)),
                  "beta_b": outputs["beta_b"].detach().mean((0, 1))}
        for name, value in values.items():
            for channel, v in zip("rgb", value.tolist(), strict=True):
                metrics[f"medium/{name}_{channel}"] = v
        return metrics

    def get_eval_metrics(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float | None]:
        metrics = super().get_eval_metrics(outputs, batch)
        if "clean_image" in batch and self.medium is not None:
            uri = outputs["uri"].detach().clamp(0, 1)
            metrics["uri_psnr"] = float(psnr(uri, batch["clean_image"]))
            metrics["uri_ssim"] = float(ssim(uri, batch["clean_image"]))
            if "covisible" in batch:
                metrics["uri_psnr_covisible"] = float(psnr(uri, batch["clean_image"], batch["covisible"]))
        return metrics

    def get_eval_summary(self, scene: SceneData) -> dict[str, float]:
        """Error of the learned medium against the ground truth (synthetic scenes), relative, per channel."""
        learned = self.medium_summary()
        out: dict[str, float] = {}
        for name, value in learned.items():
            for channel, v in zip("rgb", value.tolist(), strict=True):
                out[f"{name}_{channel}"] = v
        if scene.gt is None or not learned:
            return out
        truths = dict(zip(("beta_d", "beta_b", "b_inf"), scene.gt.medium_tensors(), strict=True))
        for name in ("b_inf", "beta_d", "beta_b"):
            truth = truths[name]
            rel = ((learned[name].cpu() - truth).abs() / truth.abs().clamp_min(1e-6))
            out[f"{name}_rel_error"] = float(rel.max())
        return out

    def get_image_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, Tensor]:
        images = {"gt": batch["image"], "uwi": outputs["rgb"].clamp(0, 1), "uri": outputs["uri"].clamp(0, 1),
                  "depth": depth_to_image(outputs["range"], outputs["alpha"])}
        if "attenuation" in outputs:
            images["attenuation"] = outputs["attenuation"].clamp(0, 1)
            images["backscatter"] = outputs["backscatter"].clamp(0, 1)
        if "clean_image" in batch:
            images["gt_clean"] = batch["clean_image"]
        return images


def uw3dgs_optimizers() -> dict[str, ParamGroupConfig]:
    """The paper's rates: 0.05 opacity, 0.005 scaling, 0.001 rotation, 0.001 medium; 3DGS elsewhere."""
    return {**gaussian_optimizers(opacity_lr=0.05, scaling_lr=0.005, rotation_lr=0.001),
            "medium_beta": ParamGroupConfig(0.001), "medium_b_inf": ParamGroupConfig(0.001)}


def _method(name: str, description: str, **model_overrides: Any) -> MethodSpec:
    # DESIGN's schedule: densify until 15,000 of the 40,000 steps (3DGS's absolute value, not its half)
    base = UW3DGSModelConfig(densification=DensificationConfig(refine_stop=15000))
    model = dataclasses.replace(base, **model_overrides)
    config = TrainConfig(method_name=name, model=model, optimizers=uw3dgs_optimizers(), max_num_iterations=40000)
    return MethodSpec(name, description, config)


method = _method("uw3dgs", "UW-3DGS: 3DGS + learnable underwater image formation (VM-grid beta_D, beta_B, B_inf), "
                 "L_beta and L_z (PAUP pending).")
no_medium = _method("uw3dgs-no-medium", "Ablation: plain 3DGS rendering, no L_beta, no L_z.",
                    use_medium=False, beta_loss_weight=0.0, depth_loss_weight=0.0)
no_lbeta = _method("uw3dgs-no-lbeta", "Ablation: beta fixed at beta_prior (B_inf still learned), no L_beta.",
                   medium=MediumGridConfig(learn_beta=False), beta_loss_weight=0.0)
# with U_i = 0 until PAUP lands, depth is composited without (1 - U) weights in every variant
no_lz = _method("uw3dgs-no-lz", "Ablation: no L_z (and, once PAUP lands, depth without the (1 - U) weight).",
                depth_loss_weight=0.0)
