"""`tensorf`: TensoRF (Chen et al. 2022) with the recipe of its official LLFF configuration (`configs/flower.txt` over
`opt.py`'s defaults): a VM-split field (fields/tensorf.py) marched in NDC, its grid growing from 128^3 to 640^3
voxels at log-spaced sizes, an alpha mask that skips empty space (and crops the grid once), TV losses on the planes,
Adam whose rates decay 10x over the run and restart after every upsampling, 4096 rays a step, 25,000 steps.

The official code also composites a white background on half of the training batches; under water that is wrong
and is left out (the background is black: what no sample covers adds nothing).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Annotated, Any, Literal

import torch
from torch import Tensor, nn

from uw3dgs.cameras import Camera
from uw3dgs.config import Target, target
from uw3dgs.data.datamanager import Batch
from uw3dgs.data.scene import SceneData
from uw3dgs.engine.callbacks import TrainingCallback
from uw3dgs.engine.config import TrainConfig
from uw3dgs.engine.optimizers import Optimizers, ParamGroupConfig
from uw3dgs.fields.tensorf import TensoRFFieldConfig, samples_for, voxels_to_resolution
from uw3dgs.metrics.depth import range_abs_rel
from uw3dgs.metrics.image import psnr
from uw3dgs.models.base import Model, ModelConfig
from uw3dgs.models.field_slot import field_slot
from uw3dgs.options import OptionError, check_number
from uw3dgs.raymarch.compositing import composite, volume_weights
from uw3dgs.raymarch.field import RadianceField, RadianceFieldConfig
from uw3dgs.raymarch.occupancy import OccupancyGrid
from uw3dgs.raymarch.rays import RayBundle
from uw3dgs.raymarch.render_image import render_camera
from uw3dgs.raymarch.samplers import BoxSampler, NDCSampler, RaySamples, average_camera
from uw3dgs.registry import MethodSpec
from uw3dgs.utils.profiling import section
from uw3dgs.utils.visualize import depth_to_image

Vec3 = tuple[float, float, float]
COVERAGE_EPS = 1e-4
"""Rays whose accumulated weight is at most this show no surface: their range is the scene's far bound."""


@dataclass(frozen=True)
class TensoRFModelConfig(ModelConfig):
    """TensoRF's knobs; defaults are the official LLFF configuration's (source named per knob in
    docs/methods/tensorf.md)."""

    _target: Target = target(lambda: TensoRFModel)
    radiance: Annotated[RadianceFieldConfig, field_slot("radiance")] = field(default_factory=TensoRFFieldConfig)
    """The scene field: a registered field of kind 'radiance', chosen by its subcommand (default 'tensorf'); its
    knobs are --model.radiance.*."""
    sampler: Literal["ndc", "box"] = "ndc"
    """'ndc': forward-facing scenes, samples uniform in NDC of the mean training camera (LLFF's `ndc_ray`); 'box':
    samples every step in a world box around the initial points (TensoRF's Blender/NSVF path)."""
    ndc_box_min: Vec3 = (-1.5, -1.67, -1.0)
    """The field's box in NDC, lower corner (the LLFF dataset's `scene_bbox`)."""
    ndc_box_max: Vec3 = (1.5, 1.67, 1.0)
    """The field's box in NDC, upper corner."""
    ndc_near_ratio: float = 0.75
    """The NDC near plane at this fraction of the scene's near bound (LLFF scales the nearest depth to 1/0.75 and
    puts the plane at 1)."""
    box_quantile: float = 0.01
    """'box' sampler: the box spans these quantiles (and 1 - it) of the initial points per axis ..."""
    box_margin: float = 0.1
    """... grown by this fraction of its size on every side."""
    batch_size: int = 4096
    """Rays per training step (`batch_size`)."""
    voxels_init: int = 128 ** 3
    """Voxels of the grid at the start (`N_voxel_init`)."""
    voxels_final: int = 640 ** 3
    """Voxels after the last upsampling (`N_voxel_final`); the sizes between are log-spaced."""
    upsample_steps: tuple[int, ...] = (2000, 3000, 4000, 5500)
    """Steps after which the grid grows (`upsamp_list`)."""
    alpha_mask_steps: tuple[int, ...] = (2500,)
    """Steps after which the alpha mask is rebuilt (`update_AlphaMask_list`); the first also crops the grid to it."""
    alpha_mask_threshold: float = 1e-4
    """A mask vertex is occupied where its dilated alpha is at least this (`alpha_mask_thre`)."""
    alpha_mask_max_voxels: int = 256 ** 3
    """The mask takes the grid's resolution while the grid has fewer voxels than this, else keeps its last one."""
    weight_threshold: float = 1e-4
    """Colours are computed only at samples whose weight exceeds this (`rm_weight_mask_thre`)."""
    distance_scale: float = 25.0
    """Intervals are scaled by this before the density integrates over them (`distance_scale`)."""
    step_ratio: float = 0.5
    """Sampling step in grid voxels (`step_ratio`): samples per ray = |resolution| / step_ratio."""
    max_samples: int = 1_000_000
    """Cap on the samples per ray (`nSamples`)."""
    tv_weight_density: float = 1.0
    """Weight of the density planes' total variation (`TV_weight_density`), decayed like the learning rates."""
    tv_weight_appearance: float = 1.0
    """Weight of the appearance planes' total variation (`TV_weight_app`), decayed like the learning rates."""
    tv_scale: float = 0.01
    """Factor inside TensoRF's `TV_loss_density` / `TV_loss_app` on each plane's TV."""
    tv_decay_ratio: float = 0.1
    """The TV weights fall to this fraction over --max-num-iterations (`lr_decay_target_ratio`, applied per step)."""
    lr_upsample_reset: bool = True
    """After every upsampling the field's learning rates start again from their initial values (`lr_upsample_reset`);
    False: they continue their decay. Adam's moments restart either way (a new optimizer, as the official code)."""
    render_chunk: int = 4096
    """Rays per chunk when rendering a whole image (evaluation, uw-render)."""

    def check_options(self) -> None:
        super().check_options()
        for name in ("batch_size", "voxels_init", "voxels_final", "alpha_mask_max_voxels", "max_samples",
                     "render_chunk"):
            check_number(self, name, ge=1, integer=True)
        for name in ("upsample_steps", "alpha_mask_steps"):
            check_number(self, name, ge=1, integer=True, each=True)
        for name in ("alpha_mask_threshold", "weight_threshold", "tv_weight_density", "tv_weight_appearance",
                     "tv_scale"):
            check_number(self, name, ge=0)
        for name in ("distance_scale", "step_ratio", "ndc_near_ratio", "tv_decay_ratio"):
            check_number(self, name, gt=0)
        check_number(self, "box_quantile", ge=0, lt=0.5)
        check_number(self, "box_margin", ge=0)
        if any(lo >= hi for lo, hi in zip(self.ndc_box_min, self.ndc_box_max, strict=True)):
            raise OptionError("ndc_box_min", f"must be below --model.ndc-box-max on every axis, got {self.ndc_box_min} "
                                             f"and {self.ndc_box_max}")


class TensoRFModel(Model):
    """A radiance field rendered by ray marching; trained on random rays, evaluated on whole images in chunks."""

    config: TensoRFModelConfig

    def __init__(self, config: TensoRFModelConfig, scene: SceneData, train_indices: list[int]):
        super().__init__(config, scene, train_indices)
        self.far_range = float(scene.far)
        cameras = [scene.cameras[i] for i in train_indices]
        if config.sampler == "ndc":
            R, center = average_camera(cameras)
            first = cameras[0]
            lo, hi = torch.tensor(config.ndc_box_min), torch.tensor(config.ndc_box_max)
            self.sampler = NDCSampler(R, center, float(first.K[0, 0]), float(first.K[1, 1]), first.width,
                                      first.height, config.ndc_near_ratio * float(scene.near), lo, hi)
        else:
            lo, hi = scene_box(scene.points, config.box_quantile, config.box_margin)
            self.sampler = BoxSampler(lo, hi, float(scene.near), float(scene.far))
        resolution = voxels_to_resolution(config.voxels_init, lo, hi)
        self.field: RadianceField = config.radiance.setup(lo=lo, hi=hi, resolution=resolution, kernels=config.kernels)
        self.occupancy = OccupancyGrid(lo, hi)
        self.max_num_iterations = 1
        """The run's length (set with the training callbacks): the TV weights decay over it."""

    # -- the Trainer's interface --

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return self.field.param_groups()

    def rays_per_batch(self) -> int | None:
        return self.config.batch_size

    def state_keys_reshaped_in_training(self) -> set[str]:
        grids = {name for name, _ in self.field.named_parameters() if "planes" in name or "lines" in name}
        return {f"field.{name}" for name in grids} | {"occupancy.volume"}

    def load_checkpoint_state(self, state: dict[str, Tensor]) -> None:
        """Take the grids' and the mask's saved shapes (they grow in training), then load."""
        with torch.no_grad():
            for key in self.state_keys_reshaped_in_training():
                module_name, _, name = key.rpartition(".")
                module = self.get_submodule(module_name)
                if name in module._parameters:
                    module._parameters[name] = nn.Parameter(torch.empty_like(state[key]))
                else:
                    module._buffers[name] = torch.empty_like(state[key])
        self.load_state_dict(state)

    def get_training_callbacks(self, optimizers: Optimizers, max_num_iterations: int) -> list[TrainingCallback]:
        self.max_num_iterations = max_num_iterations
        return [GridSchedule(self, optimizers)]

    # -- rendering --

    def num_samples(self) -> int:
        resolution = self.field.resolution() or (128, 128, 128)
        return min(self.config.max_samples, samples_for(resolution, self.config.step_ratio))

    def step_size(self) -> float:
        """TensoRF's `stepSize`: the mean voxel size of the grid times `step_ratio` (in the sampler's space)."""
        res = torch.tensor(self.field.resolution() or (128, 128, 128), dtype=torch.float32)
        return float(((self.field.hi - self.field.lo).cpu() / (res - 1)).mean()) * self.config.step_ratio

    def sample(self, rays: RayBundle) -> RaySamples:
        if isinstance(self.sampler, NDCSampler):
            return self.sampler(rays, self.num_samples(), jitter=self.training)
        return self.sampler(rays, self.num_samples(), self.step_size(), jitter=self.training)

    def march(self, rays: RayBundle) -> dict[str, Tensor]:
        """The samples of `rays`, their densities and weights: 'samples', 'sigma' [R, S], 'weights' [R, S], 'trans'
        [R, S], 'rgb' [R, S, 3] (colours where the weight exceeds --model.weight-threshold, else 0)."""
        samples = self.sample(rays)
        valid = samples.valid & inside_box(samples.points, self.field.lo, self.field.hi)
        with section("occupancy"):
            if self.occupancy.built and bool(valid.any()):
                kept = valid.clone()
                kept[valid] = self.occupancy.occupied(samples.points[valid])
                valid = kept
        sigma = torch.zeros_like(samples.deltas)
        with section("density"):
            if bool(valid.any()):
                sigma = sigma.masked_scatter(valid, self.field.density(samples.points[valid]))
        weights, trans = volume_weights(sigma, samples.deltas * self.config.distance_scale)
        rgb = torch.zeros(*weights.shape, 3, dtype=weights.dtype, device=weights.device)
        shade = weights > self.config.weight_threshold
        with section("colour"):
            if bool(shade.any()):
                dirs = samples.viewdirs[:, None].expand(-1, weights.shape[1], -1)
                colors = self.field.color(samples.points[shade], dirs[shade])
                rgb = rgb.masked_scatter(shade[..., None], colors)
        return {"samples": samples, "sigma": sigma, "weights": weights, "trans": trans, "rgb": rgb}

    def expected_range(self, weights: Tensor, ranges: Tensor, acc: Tensor) -> Tensor:
        """Per ray, the weight-averaged world distance of its samples; the far bound where nothing is hit."""
        finite = torch.where(torch.isinf(ranges), torch.zeros_like(ranges), ranges)
        mean = (weights * finite).sum(-1) / acc.clamp_min(COVERAGE_EPS)
        return torch.where(acc > COVERAGE_EPS, mean, torch.full_like(mean, self.far_range))

    def render_rays(self, rays: RayBundle) -> dict[str, Tensor]:
        """Per ray: 'rgb' [R, 3] (clamped to [0, 1] as TensoRF does), 'alpha' [R] the accumulated weight, 'range' [R]
        (world units; the far bound where nothing is hit)."""
        marched = self.march(rays)
        rgb, acc = composite(marched["weights"], marched["rgb"])
        ranges = self.expected_range(marched["weights"], marched["samples"].ranges.detach(), acc.detach())
        return {"rgb": rgb.clamp(0, 1), "alpha": acc, "range": ranges}

    def get_train_outputs(self, batch: Batch) -> dict[str, Any]:
        return self.render_rays(batch["rays"])

    def get_outputs(self, camera: Camera) -> dict[str, Any]:
        """The whole view, rendered in chunks: 'rgb' [H, W, 3], 'alpha' [H, W], 'range' [H, W] (distance along the
        ray; the far bound where nothing is hit), 'depth' [H, W] (camera-space z of the covered part, 0 elsewhere)."""
        out = render_camera(camera, self.render_rays, self.config.render_chunk)
        covered = out["alpha"] > COVERAGE_EPS
        out["depth"] = torch.where(covered, out["range"] / camera.ray_norms().to(out["range"]),
                                   torch.zeros_like(out["range"]))
        return out

    # -- losses and reports --

    def tv_weight_scale(self, step: int) -> float:
        """The TV weights' decay: tv_decay_ratio ** (step / --max-num-iterations), TensoRF's per-step lr_factor."""
        return self.config.tv_decay_ratio ** (step / max(self.max_num_iterations, 1))

    def get_loss_dict(self, outputs: dict[str, Any], batch: Batch, step: int) -> dict[str, Tensor]:
        losses = {"rgb_loss": torch.mean((outputs["rgb"] - batch["image"]) ** 2)}
        losses.update(self.tv_losses(step))
        return losses

    def tv_losses(self, step: int) -> dict[str, Tensor]:
        c = self.config
        weights = {"tv_density": c.tv_weight_density, "tv_appearance": c.tv_weight_appearance}
        if not any(weights.values()):
            return {}
        scale = self.tv_weight_scale(step) * c.tv_scale
        return {f"{name}_loss": weights[name] * scale * value for name, value in self.field.regularizers().items()
                if weights.get(name, 0) > 0}

    def get_metrics_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float]:
        res = self.field.resolution()
        metrics = {"psnr": float(psnr(outputs["rgb"].detach().clamp(0, 1)[None], batch["image"][None])),
                   "samples_per_ray": float(self.num_samples())}
        if res is not None:
            metrics["grid_voxels"] = float(math.prod(res))
        return metrics

    def get_eval_metrics(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float | None]:
        metrics = dict(super().get_eval_metrics(outputs, batch))
        if "range" in batch:
            metrics["depth_abs_rel"] = range_abs_rel(outputs["range"].detach(), outputs["alpha"].detach(),
                                                     batch["range"])
        return metrics

    def get_image_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, Tensor]:
        return {"gt": batch["image"], "render": outputs["rgb"].clamp(0, 1),
                "depth": depth_to_image(outputs["range"], outputs["alpha"])}


def inside_box(points: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    return ((points >= lo) & (points <= hi)).all(dim=-1)


def scene_box(points: Tensor, quantile: float, margin: float) -> tuple[Tensor, Tensor]:
    """The box spanning the `quantile` to 1 - `quantile` range of `points` [P, 3] per axis, grown by `margin` of its
    size on every side."""
    pts = points.double()
    lo, hi = torch.quantile(pts, quantile, dim=0), torch.quantile(pts, 1 - quantile, dim=0)
    pad = (hi - lo).clamp_min(1e-6) * margin
    return (lo - pad).float(), (hi + pad).float()


class GridSchedule(TrainingCallback):
    """TensoRF's schedule around the optimizer step: the alpha mask (and the one crop), the grid's growth to log-spaced
    sizes, and the fresh optimizer with restarted learning rates after each growth. Its state: the mask's resolution
    and the step the field's learning rates restarted from."""

    name = "tensorf_grid"

    def __init__(self, model: TensoRFModel, optimizers: Optimizers):
        self.model = model
        self.optimizers = optimizers
        c = model.config
        count = len(c.upsample_steps)
        logs = torch.linspace(math.log(c.voxels_init), math.log(c.voxels_final), count + 1, dtype=torch.float64)
        self.voxel_schedule = [int(v) for v in torch.round(torch.exp(logs)).long().tolist()[1:]]
        self.mask_resolution: tuple[int, int, int] | None = None
        self.schedule_origin = 0

    def after_step(self, step: int, batch: dict[str, Any], outputs: dict[str, Any]) -> None:
        c, model = self.model.config, self.model
        if step in c.alpha_mask_steps:
            with section("alpha mask"):
                self.update_alpha_mask(crop=step == c.alpha_mask_steps[0])
        if step in c.upsample_steps:
            with section("upsample"):
                voxels = self.voxel_schedule[sorted(c.upsample_steps).index(step)]
                model.field.upsample(voxels_to_resolution(voxels, model.field.lo, model.field.hi))
                if c.lr_upsample_reset:
                    self.schedule_origin = step
                self.restart_optimizers()

    def restart_optimizers(self) -> None:
        for name, params in self.model.field.param_groups().items():
            self.optimizers.restart(name, params, self.schedule_origin)

    @torch.no_grad()
    def update_alpha_mask(self, crop: bool) -> None:
        model, c = self.model, self.model.config
        resolution = model.field.resolution()
        if self.mask_resolution is None or math.prod(resolution) < c.alpha_mask_max_voxels:
            self.mask_resolution = resolution
        model.occupancy.build(model.field.density, model.field.lo, model.field.hi, self.mask_resolution,
                              model.step_size(), c.alpha_mask_threshold)
        bounds = model.occupancy.occupied_bounds()
        if crop and bounds is not None:
            model.field.shrink(*bounds)
            self.restart_optimizers()  # the grids are new tensors (the official code keeps its optimizer on the old)

    def state_dict(self) -> dict[str, Any]:
        return {"mask_resolution": self.mask_resolution, "schedule_origin": self.schedule_origin}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if not state:
            return
        self.mask_resolution = None if state["mask_resolution"] is None else tuple(state["mask_resolution"])
        self.schedule_origin = int(state["schedule_origin"])
        for name in self.model.field.param_groups():
            self.optimizers.schedule_origin[name] = self.schedule_origin


def tensorf_optimizers(grid_lr: float = 0.02, network_lr: float = 1e-3,
                       decay_ratio: float = 0.1) -> dict[str, ParamGroupConfig]:
    """TensoRF's Adam: `lr_init` 0.02 for the planes and lines, `lr_basis` 1e-3 for the basis and the MLP, betas
    (0.9, 0.99), decaying to `lr_decay_target_ratio` 0.1 of that over the run."""
    return {name: ParamGroupConfig(lr, eps=1e-8, betas=(0.9, 0.99), lr_final=lr * decay_ratio)
            for name, lr in (("field_grids", grid_lr), ("field_networks", network_lr))}


method = MethodSpec(
    name="tensorf",
    description="TensoRF (VM-split grids, NDC rays), the official LLFF recipe: 128^3 -> 640^3 voxels, alpha mask, "
                "TV losses, 4096 rays x 25,000 steps; no white background.",
    config=TrainConfig(method_name="tensorf", model=TensoRFModelConfig(), optimizers=tensorf_optimizers(),
                       max_num_iterations=25000),
)



CPU_STEPS = 3000
"""The CPU recipe's run length (`cpu_recipe`): 3,000 steps of 1,024 rays, about six passes over IUI3-RedSea's
training pixels at downscale 8. The schedule below is written for it and scales with a method's own length."""


def cpu_recipe(model: TensoRFModelConfig, steps: int = CPU_STEPS) -> TensoRFModelConfig:
    """TensoRF's recipe cut to fit a CPU hour (docs/methods/tensorf.md, "On a CPU"): spherical-harmonic shading
    instead of the MLP (TensoRF's own `SH` mode), a 64^3 -> 200^3 grid at twice the voxel size a step and at most 128
    samples a ray, 1,024 rays a step; growth and alpha masks at the same fractions of a `steps`-step run as the
    official schedule's (2,000 ... 5,500 and 2,500 of 25,000)."""
    scale = steps / CPU_STEPS
    return replace(model, radiance=replace(model.radiance, shading="sh"), batch_size=1024, voxels_init=64 ** 3,
                   voxels_final=200 ** 3, upsample_steps=tuple(round(s * scale) for s in (240, 360, 480, 660)),
                   alpha_mask_steps=(round(300 * scale),), step_ratio=2.0, max_samples=128)


def cpu_method(parent: MethodSpec, description: str, steps: int = CPU_STEPS) -> MethodSpec:
    """`parent` (a TensoRF-field method) on the CPU recipe of `steps` steps, registered as `<parent>-cpu`."""
    name = f"{parent.name}-cpu"
    return MethodSpec(name=name, description=description,
                      config=replace(parent.config, method_name=name, max_num_iterations=steps,
                                     model=cpu_recipe(parent.config.model, steps)))


cpu = cpu_method(method, "tensorf cut to fit a CPU hour: spherical-harmonic shading (no MLP), a 64^3 -> 200^3 grid, "
                         "at most 128 samples a ray, 1,024 rays x 3,000 steps; the schedule's shape scaled to the run.")
