"""`seasplat`: SeaSplat (Yang et al. 2024), 3DGS with an image-space underwater formation on the rendered depth,
re-implemented from the official code (GitHub dxyang/seasplat; docs/methods/seasplat.md says what matches it).

The Gaussians render the restored image J (SH degree 0) and a depth map; z, that depth normalised per image to [0, 1],
gives the underwater image I = clamp(J exp(-max(beta_D z, 0)) + B_inf (1 - exp(-max(beta_B z, 0))), 0, 1). Before
the medium starts, a learned background colour fills what the Gaussians leave uncovered instead. Training alternates:
Gaussians alone, then the medium alone, then the Gaussians' colours alone, then the Gaussians with the medium held,
interrupted at a fixed cadence by steps that train the medium alone (`SeaSplatScheduleConfig`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal

import torch
from torch import Tensor, nn

from uw3dgs.cameras import Camera
from uw3dgs.config import Target, target
from uw3dgs.data.datamanager import Batch
from uw3dgs.data.scene import SceneData
from uw3dgs.engine.callbacks import StepSchedule, TrainingCallback
from uw3dgs.engine.config import TrainConfig
from uw3dgs.engine.optimizers import Optimizers, ParamGroupConfig
from uw3dgs.fields.gaussians import GaussianFieldConfig
from uw3dgs.medium.formation import Water
from uw3dgs.methods.gaussian_splatting import GaussianSplattingModel, GaussianSplattingModelConfig, gaussian_optimizers
from uw3dgs.methods.seasplat_losses import (
    ALPHA_BACKGROUND_THRESHOLD,
    alpha_background,
    backscatter_loss,
    depth_weighted_l1,
    edge_aware_depth_smoothness,
    gray_world,
    normalized_depth,
    saturation,
)
from uw3dgs.methods.seasplat_medium import RGB, SeaSplatMedium, seasplat_formation
from uw3dgs.metrics.medium import medium_eval_summary, restored_image_metrics
from uw3dgs.options import CheckedConfig, OptionError, check_number
from uw3dgs.registry import MethodSpec
from uw3dgs.strategy import DefaultStrategy, DensificationConfig, DensityControl
from uw3dgs.utils.profiling import section
from uw3dgs.utils.visualize import depth_to_image

Phase = Literal["warmup", "medium", "colors", "gaussians"]
"""What a step trains: 'warmup' the Gaussians and the background colour (no medium yet); 'medium' beta_D, beta_B and
B_inf alone; 'colors' the Gaussians' colours alone (positions, shapes and opacities frozen); 'gaussians' every
Gaussian parameter, the medium held."""
GEOMETRY_PHASES = ("warmup", "gaussians")
"""The phases in which density control runs (their code's ordinary iterations)."""


@dataclass(frozen=True)
class SeaSplatScheduleConfig(CheckedConfig):
    """SeaSplat's alternating schedule, in steps of this framework (one optimizer pass each).

    Their `train.py` counts iterations and runs the medium-only and colour-only passes without advancing the count;
    here every pass is a step, and `phase(step)` maps a step to its phase and to their iteration number, which
    drives density control and the gray-world start."""

    medium_from: int = 10000
    """Steps of Gaussians + learned background before the medium starts (their README's `--seathru_from_iter
    10000`)."""
    medium_init_steps: int = 1000
    """Medium-only steps when the medium starts (train.py: the first backscatter/attenuation update count)."""
    color_init_steps: int = 2000
    """Then steps that train the Gaussians' colours alone, the rest frozen (train.py: `update_gs_color_counter`)."""
    medium_every: int = 100
    """Afterwards, medium-only steps come before every iteration that is a multiple of this
    (`update_bs_at_interval`)."""
    medium_steps: int = 50
    """... this many at a time (`update_bs_at_count`)."""
    gray_world_from: int = 10000
    """The gray-world prior on J applies after this iteration (`gw_from_iter`)."""
    reference_steps: int = 30000
    """The step counts above (but the cadence) are for a run of this many steps (their 30,000 iterations); a run of
    --max-num-iterations N scales medium_from, medium_init_steps, color_init_steps and gray_world_from by N / this,
    so a short run keeps their proportions (the medium starts a third of the way in); 0 takes them as given."""

    def check_options(self) -> None:
        super().check_options()
        check_number(self, "medium_from", ge=0, integer=True)
        check_number(self, "medium_init_steps", ge=0, integer=True)
        check_number(self, "color_init_steps", ge=0, integer=True)
        check_number(self, "medium_every", ge=1, integer=True)
        check_number(self, "medium_steps", ge=0, integer=True)
        check_number(self, "gray_world_from", ge=0, integer=True)
        check_number(self, "reference_steps", ge=0, integer=True)

    def for_run(self, max_num_iterations: int) -> SeaSplatScheduleConfig:
        """This schedule for a run of `max_num_iterations` steps, its step counts scaled (`reference_steps`)."""
        if self.reference_steps == 0:
            return self
        ratio = max_num_iterations / self.reference_steps
        scaled = {name: round(getattr(self, name) * ratio)
                  for name in ("medium_from", "medium_init_steps", "color_init_steps", "gray_world_from")}
        return dataclasses.replace(self, reference_steps=0, **scaled)

    def phase(self, step: int) -> tuple[Phase, int]:
        """(phase, their iteration) of `step` (1-based). Iterations 1..medium_from are the warm-up; then
        medium_init_steps medium steps and color_init_steps + 1 colour steps (the last one is iteration
        medium_from + 1 itself, whose geometry they still freeze); then ordinary iterations, each multiple of
        medium_every preceded by medium_steps medium steps (numbered with the iteration they precede)."""
        start = self.medium_from
        if step <= start:
            return "warmup", step
        q = step - start
        if q <= self.medium_init_steps:
            return "medium", start + 1
        q -= self.medium_init_steps
        if q <= self.color_init_steps + 1:
            return "colors", start + 1
        q -= self.color_init_steps + 1  # q >= 1 counts the steps after iteration start + 1
        every = self.medium_every
        first = (start + 1) // every * every + every  # the first multiple of medium_every after start + 1
        if q <= first - (start + 2):
            return "gaussians", start + 1 + q
        cycle, offset = divmod(q - (first - (start + 2)) - 1, self.medium_steps + every)
        iteration = first + cycle * every
        if offset < self.medium_steps:
            return "medium", iteration
        return "gaussians", iteration + offset - self.medium_steps


@dataclass(frozen=True)
class SeaSplatModelConfig(GaussianSplattingModelConfig):
    _target: Target = target(lambda: SeaSplatModel)
    gaussians: GaussianFieldConfig = field(default_factory=lambda: GaussianFieldConfig(sh_degree=0))
    """Their default SH degree is 0 (arguments/__init__.py `sh_degree`)."""
    densification: DensificationConfig = field(default_factory=lambda: DensificationConfig(refine_stop=15000))
    """3DGS's (their `densify_until_iter` 15,000), counted in their iterations (`SeaSplatScheduleConfig.phase`)."""
    schedule: SeaSplatScheduleConfig = field(default_factory=SeaSplatScheduleConfig)
    background_init: RGB = (0.05, 0.25, 0.8)
    """Starting learned background colour (train.py: r 0.05, g 0.25, b 0.8), learned as a logit."""
    beta_d_init: RGB = (1.1, 0.95, 0.95)
    """Starting beta_D per unit of normalised depth (`AttenuateNetV3` init_vals)."""
    beta_b_init: RGB | None = None
    """Starting beta_B; None draws it uniformly from [0, 1) per channel, as their `BackscatterNetV2`."""
    b_inf_from_background: bool = True
    """When the medium starts, B_inf := the learned background colour and the background is dropped (`bg_from_bs`)."""
    depth_scale: float = 1.0
    """The depth is divided by this before normalising (`normalize_depth`)."""
    depth_min_max: bool = True
    """Normalise the depth per image to [0, 1] by its minimum and maximum (`norm_depth_max`)."""
    depth_weighted_l1_weight: float = 1.0
    """Weight of mean |z (I - I_gt)| (`dwr_lambda`), z detached; all steps."""
    depth_smoothness_weight: float = 2.0
    """Weight of the edge-aware depth smoothness against the training image (`depth_smooth_lambda`); all steps."""
    alpha_background_weight: float = 0.01
    """Weight of the alpha-background loss (`bg_lambda`): coverage where the image looks like the background (before
    the medium) or B_inf (after); all steps."""
    alpha_background_threshold: float = ALPHA_BACKGROUND_THRESHOLD
    """RGB distance below which a pixel looks like the background (their 0.2 sqrt(3))."""
    gray_world_weight: float = 0.1
    """Weight of the gray-world prior on J (`gw_loss_lambda`)."""
    gray_world_target: float = 0.5
    """Mean each channel of J is pulled to."""
    saturation_weight: float = 2.0
    """Weight of the saturation loss on J once the medium runs (`sat_loss_lambda`)."""
    saturation_high: float = 0.7
    """J's values above this (or below 0) are penalised (`RgbSaturationLoss(saturation_val=0.7)`)."""
    backscatter_weight: float = 1.0
    """Weight of DeepSeeColor's backscatter loss on I_gt - B(z detached) once the medium runs (`dcp_loss_lambda`)."""
    backscatter_cost_ratio: float = 1000.0
    """Its weight of backscatter above the image against below (`DarkChannelPriorLossV3` cost_ratio)."""
    backscatter_smooth_l1_beta: float = 0.2
    """Its SmoothL1 transition point for backscatter above the image."""

    def check_options(self) -> None:
        super().check_options()
        if self.background != "black":
            raise OptionError("background", "must be 'black' for seasplat: it learns its background colour before the "
                                            "medium starts (--model.background-init) and shows none after, as theirs")
        check_number(self, "background_init", gt=0, lt=1, each=True)
        check_number(self, "depth_scale", gt=0)
        for name in ("depth_weighted_l1_weight", "depth_smoothness_weight", "alpha_background_weight",
                     "alpha_background_threshold", "gray_world_weight", "saturation_weight",
                     "saturation_high", "backscatter_weight", "backscatter_cost_ratio"):
            check_number(self, name, ge=0)
        check_number(self, "backscatter_smooth_l1_beta", gt=0)


class SeaSplatModel(GaussianSplattingModel):
    config: SeaSplatModelConfig

    def __init__(self, config: SeaSplatModelConfig, scene: SceneData, train_indices: list[int]):
        super().__init__(config, scene, train_indices)
        self.background_logit = nn.Parameter(torch.logit(torch.tensor(config.background_init)))
        self.medium = SeaSplatMedium(config.beta_d_init, config.beta_b_init)
        # a buffer, so a loaded checkpoint renders with the medium exactly when training had started it
        self.register_buffer("medium_started", torch.tensor(False))
        self.phase: Phase = "warmup"
        self.iteration = 0
        """Their iteration number of the current step (`SeaSplatScheduleConfig.phase`); set by `SeaSplatPhases`."""
        self.schedule = config.schedule
        """The schedule for this run's length (`get_training_callbacks` scales it)."""

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {**super().param_groups(), "background": [self.background_logit], **self.medium.param_groups()}

    def get_training_callbacks(self, optimizers: Optimizers, max_num_iterations: int) -> list[TrainingCallback]:
        strategy = DefaultStrategy(self.config.densification, self.scene_extent, max_num_iterations)
        self.schedule = self.config.schedule.for_run(max_num_iterations)
        return [StepSchedule("sh_degree", self.gaussians), SeaSplatPhases(self),
                PhasedDensityControl(self.schedule, strategy, self.gaussians, optimizers)]

    def set_phase(self, step: int) -> None:
        """Enter `step`'s phase: freeze the Gaussians' geometry in 'colors' (as their `freeze_parameters`), and on
        the first step after the warm-up start the medium (B_inf from the learned background)."""
        self.phase, self.iteration = self.schedule.phase(step)
        for name in ("means", "scales", "quats", "opacities"):
            getattr(self.gaussians, name).requires_grad_(self.phase != "colors")
        if self.phase != "warmup" and not bool(self.medium_started):
            if self.config.b_inf_from_background:
                self.medium.start_from_background(self.background_logit.detach())
            self.medium_started.fill_(True)

    @property
    def medium_on(self) -> bool:
        """Whether this render forms the underwater image (training: after the warm-up; else: once started)."""
        return self.phase != "warmup" if self.training else bool(self.medium_started)

    def get_outputs(self, camera: Camera) -> dict[str, Any]:
        """`render`'s outputs with 'uri' [H, W, 3] the restored image J (before the medium: the Gaussians over the
        learned background), 'rgb' [H, W, 3] the underwater image, 'depth_normalized' [H, W] z; with the medium on
        also 'attenuation', 'backscatter' [H, W, 3]. In a 'medium' step the Gaussians render without gradient; in the
        others the medium is detached."""
        medium_step = self.training and self.phase == "medium"
        with torch.set_grad_enabled(torch.is_grad_enabled() and not medium_step):
            outputs = self.render(camera)
        raster = outputs["raster"]
        c = self.config
        z = normalized_depth(raster.depth, raster.alpha, c.depth_scale, c.depth_min_max)
        outputs["depth_normalized"] = z
        radiance = outputs["radiance"]
        if not self.medium_on:
            background = torch.sigmoid(self.background_logit)
            outputs["rgb"] = outputs["uri"] = radiance + (1.0 - outputs["alpha"][..., None]) * background
            return outputs
        medium = self.medium
        values = (medium.beta_d, medium.beta_b, medium.b_inf)
        if not medium_step:
            values = tuple(v.detach() for v in values)
        with section("medium"):
            formed = seasplat_formation(radiance, z, *values)
        outputs.update(uri=radiance, rgb=formed["uwi"], attenuation=formed["attenuation"],
                       backscatter=formed["backscatter"])
        return outputs

    def render_view(self, camera: Camera, water: Water | None = None) -> dict[str, Tensor]:
        """`Model.render_view`: the evaluation form whatever the mode, with the water control on SeaSplat's own
        formation (beta_D, beta_B times `water.k` >= 0, `water.b_inf` in place of B_inf): 'rgb' the underwater image
        (k = 1 with the learned B_inf: the model's; k = 0: J), 'uri' J, 'attenuation', 'backscatter' [H, W, 3],
        'alpha', 'range' [H, W]. Before the medium has started: J over the learned background, no water."""
        water = water or Water()
        if water.k < 0:
            raise ValueError(f"the water factor k must be >= 0, got {water.k}")
        out = self.render(camera)
        result = {"alpha": out["alpha"], "range": out["range"]}
        if not bool(self.medium_started):
            rgb = out["radiance"] + (1.0 - out["alpha"][..., None]) * torch.sigmoid(self.background_logit)
            return {**result, "rgb": rgb}
        m = self.medium
        if water.k == 0:
            uri = out["radiance"]
            return {**result, "rgb": uri, "uri": uri, "attenuation": torch.ones_like(uri),
                    "backscatter": torch.zeros_like(uri)}
        b_inf = m.b_inf if water.b_inf is None else torch.tensor(water.b_inf).to(m.b_inf)
        raster, c = out["raster"], self.config
        z = normalized_depth(raster.depth, raster.alpha, c.depth_scale, c.depth_min_max)
        formed = seasplat_formation(out["radiance"], z, water.k * m.beta_d, water.k * m.beta_b, b_inf)
        return {**result, "rgb": formed["uwi"], "uri": out["radiance"], "attenuation": formed["attenuation"],
                "backscatter": formed["backscatter"]}

    def veiling_light(self) -> Tensor | None:
        """`Model.veiling_light`: the learned B_inf once the medium has started (the viewer's water control), else
        None."""
        return self.medium.b_inf.detach() if bool(self.medium_started) else None

    def export_medium(self, dataset_center: tuple[float, float, float], dataset_scale: float,
                      samples: int) -> dict | None:
        """`Model.export_medium`: beta_D, beta_B, B_inf with SeaSplat's formation as their meaning; None before the
        medium has started."""
        if not bool(self.medium_started):
            return None
        return self.medium.summary(dataset_center, dataset_scale, samples)

    def get_loss_dict(self, outputs: dict[str, Any], batch: Batch, step: int) -> dict[str, Tensor]:
        """Their total loss: 0.8 L1 + 0.2 D-SSIM and the depth-weighted L1 on the underwater image, the edge-aware
        depth smoothness, the alpha-background loss, the gray-world prior on J after the schedule's `gray_world_from`,
        and once the medium runs the saturation loss on J and DeepSeeColor's backscatter loss."""
        c = self.config
        losses = super().get_loss_dict(outputs, batch, step)
        pred, gt, z, alpha = outputs["rgb"], batch["image"], outputs["depth_normalized"], outputs["alpha"]
        with section("loss: SeaSplat terms"):
            losses["depth_weighted_l1"] = c.depth_weighted_l1_weight * depth_weighted_l1(pred, gt, z.detach())
            losses["depth_smoothness"] = c.depth_smoothness_weight * edge_aware_depth_smoothness(gt, z)
            if self.medium_on:
                looks_like, colour = pred.detach(), self.medium.b_inf.detach()
            else:
                looks_like, colour = outputs["radiance"].detach(), torch.sigmoid(self.background_logit.detach())
            losses["alpha_background"] = c.alpha_background_weight * alpha_background(
                looks_like, colour, alpha, c.alpha_background_threshold)
            if self.iteration > self.schedule.gray_world_from:
                losses["gray_world"] = c.gray_world_weight * gray_world(outputs["uri"], c.gray_world_target)
            if self.medium_on:
                losses["saturation"] = c.saturation_weight * saturation(outputs["uri"], c.saturation_high)
                # the backscatter of the detached depth: in a 'medium' step the render has no gradient anyway,
                # elsewhere the medium is detached, so this term trains the medium alone, as theirs
                backscatter = outputs["backscatter"] if self.phase == "medium" else outputs["backscatter"].detach()
                losses["backscatter"] = c.backscatter_weight * backscatter_loss(
                    gt - backscatter, c.backscatter_cost_ratio, c.backscatter_smooth_l1_beta)
        return losses

    def medium_summary(self) -> dict[str, Tensor]:
        """B_inf, beta_D, beta_B [3] as the formation uses them (betas clamped at 0; per unit of normalised depth)."""
        m = self.medium
        return {"b_inf": m.b_inf.detach(), "beta_d": m.beta_d.detach().clamp_min(0),
                "beta_b": m.beta_b.detach().clamp_min(0)}

    def get_metrics_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float]:
        metrics = super().get_metrics_dict(outputs, batch)
        metrics["seasplat/iteration"] = float(self.iteration)
        for name, value in self.medium_summary().items():
            for channel, v in zip("rgb", value.tolist(), strict=True):
                metrics[f"medium/{name}_{channel}"] = v
        return metrics

    def get_eval_metrics(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float | None]:
        """3DGS's, and the restored image J's PSNR, SSIM, LPIPS against the clean truth where the scene has it."""
        metrics = super().get_eval_metrics(outputs, batch)
        metrics.update(restored_image_metrics(outputs["uri"], batch))
        return metrics

    def get_eval_summary(self, scene: SceneData) -> dict[str, float | None]:
        """3DGS's (the floater ratios), the medium's `beta_d_*`, `beta_b_*`, `b_inf_*` and, where the scene knows its
        medium, their `*_rel_error` against it (the betas per unit of normalised depth against the truth's per dataset
        unit: docs/methods/seasplat.md); none of these before the medium has started (no medium yet)."""
        out = super().get_eval_summary(scene)
        if not bool(self.medium_started):
            return out
        return {**out, **medium_eval_summary(self.medium_summary(), scene)}

    def get_image_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, Tensor]:
        images = {"gt": batch["image"], "uwi": outputs["rgb"].clamp(0, 1), "uri": outputs["uri"].clamp(0, 1),
                  "depth": depth_to_image(outputs["range"], outputs["alpha"])}
        if "attenuation" in outputs:
            images.update(attenuation=outputs["attenuation"], backscatter=outputs["backscatter"].clamp(0, 1))
        if "clean_image" in batch:
            images["gt_clean"] = batch["clean_image"]
        return images


class SeaSplatPhases(TrainingCallback):
    """Puts the model in each step's phase before its forward pass (stateless: the phase follows from the step)."""

    name = "seasplat_phases"

    def __init__(self, model: SeaSplatModel):
        self.model = model

    def before_step(self, step: int) -> None:
        self.model.set_phase(step)


class PhasedDensityControl(DensityControl):
    """3DGS density control on their ordinary iterations only: skipped in the medium-only and colour-only steps, and
    told their iteration number, so that its schedule (every 100 from 500 to 15,000, opacity reset every 3,000) is
    theirs."""

    def __init__(self, schedule: SeaSplatScheduleConfig, *args: Any):
        super().__init__(*args)
        self.schedule = schedule

    def after_backward(self, step: int, batch: Batch, outputs: dict[str, Any]) -> None:
        phase, iteration = self.schedule.phase(step)
        if phase in GEOMETRY_PHASES:
            super().after_backward(iteration, batch, outputs)

    def after_step(self, step: int, batch: Batch, outputs: dict[str, Any]) -> None:
        phase, iteration = self.schedule.phase(step)
        if phase in GEOMETRY_PHASES:
            super().after_step(iteration, batch, outputs)


def seasplat_optimizers(medium_lr: float = 1e-2, background_lr: float = 1e-2) -> dict[str, ParamGroupConfig]:
    """3DGS's rates for the Gaussians; their `bs_at_lr` for the medium and `bg_lr` for the background, with torch
    Adam's default epsilon as their separate optimizers use."""
    return {**gaussian_optimizers(), "background": ParamGroupConfig(background_lr, eps=1e-8),
            "medium_beta": ParamGroupConfig(medium_lr, eps=1e-8), "medium_b_inf": ParamGroupConfig(medium_lr, eps=1e-8)}


method = MethodSpec(
    name="seasplat",
    description="SeaSplat: 3DGS (SH 0) + an image-space medium on the per-image normalised depth, learned "
                "background, depth/gray-world/saturation/backscatter priors, alternating medium and Gaussian steps.",
    config=TrainConfig(method_name="seasplat", model=SeaSplatModelConfig(), optimizers=seasplat_optimizers(),
                       max_num_iterations=30000),
)


def with_schedule(config: TrainConfig, **schedule: int) -> TrainConfig:
    """`config` (a seasplat TrainConfig) with these `SeaSplatScheduleConfig` fields replaced (tests, short runs)."""
    model = config.model
    return dataclasses.replace(config, model=dataclasses.replace(
        model, schedule=dataclasses.replace(model.schedule, **schedule)))
