"""`seathru-nerf`: SeaThru-NeRF's medium and losses (Levy et al. 2023, GitHub deborahLevy130/seathru_NeRF) on a
TensoRF field.

Their object field is a mip-NeRF 360 MLP trained 250,000 steps at 16,384 rays a step, out of reach on a CPU; here
the scene field is the radiance-field plugin (a subcommand, default `tensorf`) with TensoRF's recipe
(methods/tensorf.py), and SeaThru-NeRF adds what makes it underwater:
- a medium head on the encoded ray direction (their `UWMLP` water branch): one dense layer of 128 with softplus,
  then c_med = sigmoid(.), sigma_bs = softplus(. + water_bias), sigma_attn = softplus(. + water_bias), per channel;
- their compositor (uw3dgs/raymarch/compositing.py, `composite_underwater`): the object attenuated by sigma_attn and
  the water's backscatter c_med weighted by the object's transmittance;
- their losses: the reweighted L2 ('rawnerf': squared error of the prediction clipped at 1, divided by
  (1e-3 + the clipped prediction without gradient)^2) and the transmittance accuracy loss on the object's
  transmittance at every sample, weight 1e-4 (`configs/llff_256_uw.gin`).
The restored image (their J = sum_i w_i c_i) is the URI; the medium is reported per dataset unit of distance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor, nn

from uw3dgs.cameras import Camera
from uw3dgs.config import Target, target
from uw3dgs.data.datamanager import Batch
from uw3dgs.data.scene import SceneData
from uw3dgs.engine.config import TrainConfig
from uw3dgs.engine.optimizers import ParamGroupConfig
from uw3dgs.methods.tensorf import TensoRFModel, TensoRFModelConfig, cpu_method, tensorf_optimizers
from uw3dgs.metrics.medium import restored_image_metrics
from uw3dgs.options import check_number
from uw3dgs.raymarch.compositing import composite_underwater
from uw3dgs.raymarch.rays import RayBundle
from uw3dgs.registry import MethodSpec
from uw3dgs.utils.visualize import depth_to_image

MEDIUM_KEYS = (("beta_d", "sigma_attn"), ("beta_b", "sigma_bs"), ("b_inf", "c_med"))
"""Eval-JSON names of the medium (DESIGN's keys) and the head's outputs they report."""


def direction_encoding(d: Tensor, degrees: int) -> Tensor:
    """MultiNeRF's `pos_enc(d, min_deg=0, max_deg=degrees, append_identity=True)`: [d, sin(2^k d), sin(2^k d +
    pi / 2)] for k < degrees, [N, 3 + 6 * degrees]."""
    scales = 2.0 ** torch.arange(degrees, device=d.device, dtype=d.dtype)
    scaled = (d[:, None, :] * scales[:, None]).reshape(len(d), -1)
    return torch.cat([d, torch.sin(torch.cat([scaled, scaled + 0.5 * math.pi], dim=-1))], dim=-1)


class MediumHead(nn.Module):
    """SeaThru-NeRF's water branch: the medium seen along a unit world direction."""

    def __init__(self, degrees: int, hidden: int, water_bias: float):
        super().__init__()
        self.degrees, self.water_bias = degrees, water_bias
        self.hidden = nn.Linear(3 + 6 * degrees, hidden)
        self.outputs = nn.Linear(hidden, 9)  # c_med, sigma_bs, sigma_attn: three dense layers of 3, as one
        for layer in (self.hidden, self.outputs):  # flax's he_uniform kernels and zero biases, as theirs
            nn.init.kaiming_uniform_(layer.weight, nonlinearity="relu")
            nn.init.zeros_(layer.bias)

    def forward(self, directions: Tensor) -> dict[str, Tensor]:
        """'c_med', 'sigma_bs', 'sigma_attn' [N, 3] for unit directions [N, 3] (sigmas per unit of distance the
        caller's ranges are in)."""
        x = nn.functional.softplus(self.hidden(direction_encoding(directions, self.degrees)))
        raw = self.outputs(x)
        return {"c_med": torch.sigmoid(raw[:, 0:3]),
                "sigma_bs": nn.functional.softplus(raw[:, 3:6] + self.water_bias),
                "sigma_attn": nn.functional.softplus(raw[:, 6:9] + self.water_bias)}


@dataclass(frozen=True)
class SeaThruNeRFModelConfig(TensoRFModelConfig):
    """TensoRF's knobs for the field and its schedule, and SeaThru-NeRF's for the medium and the losses (defaults:
    `configs/llff_256_uw.gin`, `internal/configs.py`, `internal/models.py`)."""

    _target: Target = target(lambda: SeaThruNeRFModel)
    direction_degrees: int = 4
    """Frequencies of the direction encoding the medium head reads (`deg_view`)."""
    medium_hidden: int = 128
    """Width of the medium head's hidden layer (`net_width_viewdirs`)."""
    water_bias: float = 0.0
    """Shift inside the sigmas' softplus (`UWMLP.water_bias` in llff_256_uw.gin)."""
    data_loss: Literal["rawnerf", "mse"] = "rawnerf"
    """'rawnerf': their reweighted L2 (`data_loss_type`); 'mse': plain squared error."""
    rawnerf_eps: float = 1e-3
    """The reweighting's floor: weight 1 / (rawnerf_eps + prediction)^2."""
    acc_trans_loss_weight: float = 1e-4
    """Weight of the transmittance accuracy loss (`uw_initial_acc_trans_loss_mult` = `uw_final_...`)."""
    acc_loss_factor: float = 6.0
    """The loss -log(f exp(-|1 - T| / w) + exp(-|T| / w)) favours T = 1 by this factor f (`uw_acc_loss_factor`)."""
    acc_loss_width: float = 0.1
    """Its width w."""

    def check_options(self) -> None:
        super().check_options()
        check_number(self, "direction_degrees", ge=0, integer=True)
        check_number(self, "medium_hidden", ge=1, integer=True)
        check_number(self, "water_bias")
        for name in ("rawnerf_eps", "acc_loss_factor", "acc_loss_width"):
            check_number(self, name, gt=0)
        check_number(self, "acc_trans_loss_weight", ge=0)


class SeaThruNeRFModel(TensoRFModel):
    config: SeaThruNeRFModelConfig

    def __init__(self, config: SeaThruNeRFModelConfig, scene: SceneData, train_indices: list[int]):
        super().__init__(config, scene, train_indices)
        self.dataset_scale = float(scene.dataset_scale)
        self.medium = MediumHead(config.direction_degrees, config.medium_hidden, config.water_bias)

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {**super().param_groups(), "medium": list(self.medium.parameters())}

    def render_rays(self, rays: RayBundle) -> dict[str, Tensor]:
        """Per ray: 'rgb' [R, 3] the underwater colour, 'uri' [R, 3] the restored one, 'attenuation' [R, 3] the
        direct term, 'backscatter' [R, 3], 'alpha' [R], 'range' [R] (world units), 'trans' [R, S] the object's
        transmittance at each sample (the accuracy loss; in training mode only), and the ray's medium 'c_med',
        'sigma_bs', 'sigma_attn' [R, 3] (per dataset unit)."""
        marched = self.march(rays)
        medium = self.medium(rays.directions)
        ranges = marched["samples"].ranges.detach()
        water = composite_underwater(marched["weights"], marched["trans"], marched["rgb"], ranges * self.dataset_scale,
                                     medium["sigma_attn"], medium["sigma_bs"], medium["c_med"])
        acc = marched["weights"].sum(-1)
        out = {"rgb": water.rgb, "uri": water.restored, "attenuation": water.direct,
               "backscatter": water.backscatter, "alpha": acc,
               "range": self.expected_range(marched["weights"], ranges, acc.detach()), **medium}
        if self.training:  # per sample: only the training loss reads it
            out["trans"] = marched["trans"]
        return out

    def get_loss_dict(self, outputs: dict[str, Any], batch: Batch, step: int) -> dict[str, Tensor]:
        c = self.config
        pred, gt = outputs["rgb"], batch["image"]
        if c.data_loss == "rawnerf":
            clipped = pred.clamp(max=1.0)
            scale = 1.0 / (c.rawnerf_eps + clipped.detach())
            data = ((clipped - gt) ** 2 * scale ** 2).mean()
        else:
            data = ((pred - gt) ** 2).mean()
        losses = {"rgb_loss": data}
        if c.acc_trans_loss_weight > 0:
            t, w = outputs["trans"], c.acc_loss_width
            acc = -torch.log(c.acc_loss_factor * torch.exp(-(1 - t).abs() / w) + torch.exp(-t.abs() / w))
            losses["acc_trans_loss"] = c.acc_trans_loss_weight * acc.mean()
        losses.update(self.tv_losses(step))
        return losses

    def get_metrics_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float]:
        metrics = super().get_metrics_dict(outputs, batch)
        for name, key in MEDIUM_KEYS:
            for channel, v in zip("rgb", outputs[key].detach().mean(0).tolist(), strict=True):
                metrics[f"medium/{name}_{channel}"] = v
        return metrics

    def get_eval_metrics(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float | None]:
        return {**super().get_eval_metrics(outputs, batch), **restored_image_metrics(outputs["uri"], batch)}

    @torch.no_grad()
    def medium_over_views(self, cameras: list[Camera]) -> dict[str, Tensor]:
        """The head's medium averaged over every pixel of `cameras`, per channel, under the eval-JSON names."""
        device = next(self.medium.parameters()).device
        sums: dict[str, Tensor] = {}
        count = 0
        for camera in cameras:
            dirs = camera.to(device).ray_directions().reshape(-1, 3)
            out = self.medium(dirs)
            for name, key in MEDIUM_KEYS:
                sums[name] = sums.get(name, 0) + out[key].double().sum(0)
            count += len(dirs)
        return {name: (value / count).float() for name, value in sums.items()}

    def get_eval_summary(self, scene: SceneData) -> dict[str, float | None]:
        """The medium (`beta_d_*` = sigma_attn, `beta_b_*` = sigma_bs per dataset unit, `b_inf_*` = c_med) averaged
        over the test views' pixels (the training views' without test views), and, where the scene knows its
        medium, `*_rel_error` (largest relative error over the channels)."""
        test = [i for i in range(len(scene.cameras)) if i not in set(self.train_indices)] or self.train_indices
        learned = self.medium_over_views([scene.cameras[i] for i in test])
        out: dict[str, float | None] = dict(super().get_eval_summary(scene))
        for name, value in learned.items():
            for channel, v in zip("rgb", value.tolist(), strict=True):
                out[f"{name}_{channel}"] = v
        if scene.gt is not None and scene.gt.medium:
            truths = dict(zip(("beta_d", "beta_b", "b_inf"), scene.gt.medium_tensors(), strict=True))
            for name, truth in truths.items():
                rel = (learned[name].cpu() - truth).abs() / truth.abs().clamp_min(1e-6)
                out[f"{name}_rel_error"] = float(rel.max())
        return out

    def get_image_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, Tensor]:
        images = {"gt": batch["image"], "uwi": outputs["rgb"].clamp(0, 1), "uri": outputs["uri"].clamp(0, 1),
                  "depth": depth_to_image(outputs["range"], outputs["alpha"]),
                  "backscatter": outputs["backscatter"].clamp(0, 1)}
        if "clean_image" in batch:
            images["gt_clean"] = batch["clean_image"]
        return images


def seathru_optimizers() -> dict[str, ParamGroupConfig]:
    """TensoRF's groups for the field; the medium head at SeaThru-NeRF's rate, 2e-3 decaying to 2e-5 (`lr_init`,
    `lr_final`), Adam eps 1e-8 (`adam_eps`)."""
    return {**tensorf_optimizers(), "medium": ParamGroupConfig(2e-3, eps=1e-8, lr_final=2e-5)}


method = MethodSpec(
    name="seathru-nerf",
    description="SeaThru-NeRF's medium and losses on a TensoRF field: direction-dependent medium head, underwater "
                "compositing, reweighted L2 and transmittance loss; TensoRF's grid, schedule and rays.",
    config=TrainConfig(method_name="seathru-nerf", model=SeaThruNeRFModelConfig(), optimizers=seathru_optimizers(),
                       max_num_iterations=25000),
)

SEATHRU_CPU_STEPS = 12000
"""`seathru-nerf-cpu`'s run length: four times `tensorf-cpu`'s. On IUI3-RedSea at downscale 8 the medium head's test
PSNR rose 1 dB from 3,000 to 6,000 steps and 0.4-0.5 dB more to 12,000 (0.1 dB over the last 2,000), where TensoRF's
field alone did not move past 3,000 (docs/table1.md, "The volumetric methods")."""

cpu = cpu_method(method, "seathru-nerf on tensorf-cpu's field and schedule (spherical-harmonic shading, 64^3 -> 200^3 "
                         "grid, 1,024 rays), run four times as long: 12,000 steps, where its test PSNR stops rising; "
                         "the medium head, compositor and losses unchanged.", steps=SEATHRU_CPU_STEPS)
