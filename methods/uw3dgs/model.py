"""`uw3dgs`: 3DGS plus the learnable underwater image formation module and Physics-Aware Uncertainty Pruning
(UW-3DGS, the paper), and its ablations as configs of the same model.

Without the PAUP branch (`uw3dgs-no-paup`) every Gaussian's uncertainty U_i is 0 and its physics-aware uncertainty
score PUS_i is 1: L_beta and L_z are then unweighted and the depth is the plain composited one.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Annotated, Any

import torch
from torch import Tensor, nn

from uw3dgs.cameras import Camera
from uw3dgs.config import Target, target
from uw3dgs.data.datamanager import Batch
from uw3dgs.data.scene import SceneData
from uw3dgs.engine.callbacks import StepSchedule, TrainingCallback
from uw3dgs.engine.config import TrainConfig
from uw3dgs.engine.optimizers import Optimizers, ParamGroupConfig
from uw3dgs.fields.medium import MediumField, MediumFieldConfig, MediumGrid, MediumGridConfig
from uw3dgs.fields.medium_estimate import MediumEstimate, dehazed_colors, estimate_from_views, observe_points
from uw3dgs.fields.medium_evidence import EvidenceReport, combine_by_evidence
from uw3dgs.fields.medium_identifiability import IdentifiabilityReport, assess_medium
from uw3dgs.fields.medium_multiview import observe_and_estimate
from uw3dgs.medium.formation import Water, form_underwater_image, form_with_water
from uw3dgs.medium.water_verdict import WaterVerdict, far_range, water_verdict
from uw3dgs.methods.gaussian_splatting import (
    COVERAGE_EPS,
    GaussianSplattingModel,
    GaussianSplattingModelConfig,
    gaussian_optimizers,
)
from uw3dgs.methods.uw3dgs.depth_consistency import depth_consistency
from uw3dgs.methods.uw3dgs.paup import PAUP, PAUPConfig, combine_views, observe_view, relaxed_keep_mask
from uw3dgs.methods.uw3dgs.paup.branch import PER_GAUSSIAN_BUFFERS
from uw3dgs.metrics.medium import medium_eval_summary, restored_image_metrics
from uw3dgs.models.field_slot import field_slot
from uw3dgs.options import check_number
from uw3dgs.registry import MethodSpec
from uw3dgs.render import Splats, masked_l1, rasterize
from uw3dgs.render.sh import rgb_to_sh
from uw3dgs.strategy import DefaultStrategy, DensificationConfig, DensityControl
from uw3dgs.utils.console import info
from uw3dgs.utils.profiling import section
from uw3dgs.utils.visualize import apply_colormap, depth_to_image

WEAK_MEDIUM = ("what training does with the parameters not identifiable here: they start at this estimate, and "
               "L_beta (--model.beta-loss-weight) pulls beta_D and beta_B toward it at the Gaussians all through "
               "training, so they stay near it unless the images say otherwise; read them (and the colours of the "
               "URI) with the spread above. B_inf is learned from the images.")
"""The report's last line when a parameter is weak: what the model does about it, and why."""


def weak_medium_action(report: IdentifiabilityReport) -> str:
    """WEAK_MEDIUM when the report calls a parameter not identifiable, else ''."""
    return WEAK_MEDIUM if any(not check.identifiable for check in report.checks) else ""


@dataclass(frozen=True)
class UW3DGSModelConfig(GaussianSplattingModelConfig):
    _target: Target = target(lambda: UW3DGSModel)
    medium: Annotated[MediumFieldConfig, field_slot("medium")] = field(default_factory=MediumGridConfig)
    """The medium field: a registered field of kind 'medium', chosen by its subcommand: 'medium-grid' (VM grids, the
    paper; the default) or 'medium-homogeneous' (one value per channel); its knobs are --model.medium.*."""
    use_medium: bool = True
    """False renders plain 3DGS (the no-medium ablation): the Gaussians must explain the water themselves."""
    beta_loss_weight: float = 0.05
    """Weight of L_beta (pull of beta toward its prior at the Gaussian centres + VM factor norms)."""
    beta_loss_samples: int = 4096
    """Gaussian centres drawn per step to estimate L_beta's mean over all centres."""
    depth_loss_weight: float = 0.05
    """Weight of L_z = mean_i (1 - U_i) |z(p_i) - zhat_i| over visible Gaussians, in units of the median depth."""
    use_paup: bool = True
    """False removes the PAUP branch (the no-paup ablation): no masked render, no L_PAPSL, no pruning by
    uncertainty, U = 0 and PUS = 1 everywhere."""
    paup: PAUPConfig = field(default_factory=PAUPConfig)
    uncertainty_weighted_depth: bool = True
    """Composite depth with PAUP's (1 - U_i) weights (the paper's Eq. base_depth); False: the plain depth."""

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
        self.train_cameras = [scene.cameras[i] for i in train_indices]
        self.paup = PAUP(config.paup, self.num_gaussians, config.kernels) if config.use_paup else None
        self.medium: MediumField | None = None
        self.medium_report: IdentifiabilityReport | None = None
        """The report on the starting estimate (`initialize_from_data`; None: not made, or a loaded run)."""
        self.medium_evidence: EvidenceReport | None = None
        """init 'multiview': where each parameter of the start came from (`initialize_from_data`)."""
        self.water: WaterVerdict | None = None
        """The verdict on the starting estimate: is there water at all (`initialize_from_data`; None: not made)."""
        self.register_buffer("water_free", torch.tensor(False))
        """True: the scene has little or no water, and the model renders without its medium (the URI is the UWI);
        set once before training (`initialize_from_data`), kept in checkpoints."""
        if config.use_medium:
            centers = torch.stack([scene.cameras[i].center for i in train_indices]).float()
            self.medium = config.medium.setup(points=scene.points, camera_centers=centers, kernels=config.kernels)
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
        known = scene.gt.medium_tensors() if mc.init == "truth" else None
        estimate, water = estimate_from_views(mc, scene, train_indices, known=known)
        if known is not None:
            info("medium: the true one (gt/medium.json), an oracle for analysis")
        else:
            why = estimate.open_water.reason if estimate.open_water is not None else ""
            source = f"read off the far end of the ranges (no open water: {why or 'not looked for'})" \
                if water is None else f"read off open water: ({', '.join(f'{x:.3f}' for x in water.tolist())})"
            info(f"medium estimate: B_inf {source}")
            self.water = water_verdict(estimate.beta_d, estimate.beta_b, far_range(estimate.observations[2]),
                                       mc.no_water_level)
            info(f"water: {self.water.line()}")
            if not self.water.little_water and max(*self.water.depth_d, *self.water.depth_b) < mc.water_check_below:
                self.water = self._multiview_water(self.water, estimate, scene, train_indices)
            if self.water.little_water and mc.collapse_without_water:
                self.water_free.fill_(True)
                info("water: uw3dgs renders without a medium here, as 3dgs does (the medium report is skipped; "
                     "--model.medium.no-collapse-without-water learns a medium anyway)")
                return
            if mc.report:
                self.medium_report = assess_medium(*estimate.observations, estimate.fit, water, mc.dark_bins,
                                                   mc.dark_share, mc.estimate_residual, mc.identifiability,
                                                   positions=estimate.positions, open_water=estimate.open_water)
                for line in [*self.medium_report.lines(), weak_medium_action(self.medium_report)]:
                    if line:
                        info(f"medium report: {line}")
            if mc.init == "multiview":
                estimate = self._combine_by_evidence(estimate, water, scene, train_indices)
        # with learn_beta False the betas are held at this start: the no-L_beta ablation keeps the same start
        # (medium and de-hazed colours) as its full method and differs from it in L_beta alone
        self.medium.set_homogeneous(estimate.beta_d, estimate.beta_b, estimate.b_inf)
        # L_beta then keeps the field near what the data says, not near a constant that may be far off
        # (docs/methods/uw3dgs.md: pulled toward beta_prior, red beta_D drifts away from the truth)
        self.medium.set_prior(estimate.beta_d, estimate.beta_b)
        factor = None if self.medium_evidence is None else self.medium_evidence.factor
        if factor is not None:  # the multi-view field fit found and pinned a medium that varies in space
            self.medium.set_factor(lambda x: factor(x.double()).float(), scene.points.float())
            info("medium evidence: the betas start varying across the scene as the field fit found them")
            if isinstance(self.medium, MediumGrid) and mc.factor_penalty == "norm":
                info("medium evidence: the factor penalty 'norm' pulls a varying field toward flat "
                     "(docs/medium-varying.md): add --model.medium.flat-start constant-factors "
                     "--model.medium.factor-penalty roughness")
        with torch.no_grad():
            self.gaussians.sh0.copy_(rgb_to_sh(estimate.clean_colors.clamp(0, 1))[:, None, :])

    def _multiview_water(self, single: WaterVerdict, estimate: MediumEstimate, scene: SceneData,
                         train_indices: list[int]) -> WaterVerdict:
        """The verdict from the multi-view fit (B_inf held at the estimate's) where it could fit, on beta_D's bootstrap
        95% bound, taken for beta_B too; the single-image verdict (`single`) where it could not or where that still
        shows water. beta_B's own fit is not used: backscatter saturated at every range the views see adds one colour
        to every surface, which the surfaces' own colours absorb, so it fits a dry scene as well as none; and water
        that scatters light also attenuates it (beam attenuation = absorption + scattering)."""
        cameras, images = [scene.cameras[i] for i in train_indices], [scene.images[i] for i in train_indices]
        fit = observe_and_estimate(scene.points, cameras, images, self.dataset_scale, self.config.medium.multiview,
                                   estimate.b_inf)
        if fit.upper is None:
            info("water: the multi-view check could not fit (too few surfaces seen at several ranges)")
            return single
        beta_d = torch.tensor(fit.upper[0])
        bound = water_verdict(beta_d, beta_d, single.far_range, single.level,
                              source="the multi-view fit (beta_D's 95% bound, for beta_B too)")
        info(f"water: {bound.line()}")
        return bound if bound.little_water else single

    def _combine_by_evidence(self, estimate: MediumEstimate, water: Tensor | None, scene: SceneData,
                             train_indices: list[int]) -> MediumEstimate:
        """init 'multiview': the single-image `estimate` with each parameter taken from the evidence that pins it
        (fields/medium_evidence.py), its points' colours de-hazed with that medium; the verdicts logged and kept."""
        mc = self.config.medium
        cameras, images = [scene.cameras[i] for i in train_indices], [scene.images[i] for i in train_indices]
        self.medium_evidence = combine_by_evidence(
            estimate, self.medium_report, water,
            lambda b_inf: observe_and_estimate(scene.points, cameras, images, self.dataset_scale, mc.multiview, b_inf))
        for line in [*self.medium_evidence.multiview_lines, *self.medium_evidence.lines()]:
            info(f"medium evidence: {line}")
        medium = self.medium_evidence.medium
        observed = observe_points(scene.points.float(), cameras, images)
        factor = self.medium_evidence.factor
        colors = dehazed_colors(scene.points.float(), scene.point_colors, cameras, self.dataset_scale, medium,
                                observed, scene.cameras if mc.dehaze_unseen_with_all_poses else None,
                                None if factor is None else factor(scene.points.double()))
        return dataclasses.replace(estimate, beta_d=medium[0], beta_b=medium[1], b_inf=medium[2],
                                   clean_colors=colors)

    def run_notes(self) -> dict[str, dict]:
        """'medium_report': the identifiability report on the estimate the run started from
        (`--model.medium.report`); 'water': the verdict on whether there is water at all, and whether the model
        renders without a medium ('collapsed')."""
        notes = {}
        if self.water is not None:
            notes["water"] = {**self.water.to_json(), "collapsed": bool(self.water_free)}
        if self.medium_evidence is not None:
            notes["medium_evidence"] = self.medium_evidence.to_json()
        report = self.medium_report
        if report is not None:
            notes["medium_report"] = {**report.to_json(), "lines": report.lines(), "weak": weak_medium_action(report)}
        return notes

    def checkpoint_defaults(self) -> dict[str, Tensor]:
        """A checkpoint from before the water verdict has no 'water_free': it rendered with its medium; one from
        before the varying start has a grid medium with no 'prior_factor': its L_beta targets were flat; one from
        before the roughness was measured from the start has no 'planes_start', 'lines_start': it measured from 0."""
        defaults = {"water_free": torch.tensor(False)}
        if isinstance(self.medium, MediumGrid):
            defaults["medium.prior_factor"] = torch.ones_like(self.medium.prior_factor)
            defaults["medium.prior_varies"] = torch.tensor(False)
            defaults.update({f"medium.{key}": torch.zeros_like(value) for key, value in self.medium.state_dict().items()
                             if key.endswith(("planes_start", "lines_start"))})
        return defaults

    @property
    def renders_medium(self) -> bool:
        """Whether images are formed through the medium (a medium, and not judged water-free)."""
        return self.medium is not None and not bool(self.water_free)

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        groups = super().param_groups()
        if self.medium is not None:
            groups.update(self.medium.param_groups())
        if self.paup is not None:
            groups["paup"] = list(self.paup.scorer.parameters())
        return groups

    def state_keys_resized_in_training(self) -> set[str]:
        keys = super().state_keys_resized_in_training()
        return keys if self.paup is None else keys | {f"paup.{name}" for name in PER_GAUSSIAN_BUFFERS}

    def get_training_callbacks(self, optimizers: Optimizers, max_num_iterations: int) -> list[TrainingCallback]:
        if self.paup is None:
            return super().get_training_callbacks(optimizers, max_num_iterations)
        strategy = DefaultStrategy(self.config.densification, self.scene_extent, max_num_iterations)
        return [StepSchedule("sh_degree", self.gaussians), StepSchedule("paup", self.paup),
                DensityControl(strategy, self.gaussians, optimizers, extra_pruning=self.paup)]

    def depth_weights(self) -> Tensor | None:
        """PAUP's (1 - U_i) [N] for the composited depth, None for the plain depth (no PAUP, no statistics yet, or
        --model.uncertainty-weighted-depth False)."""
        if self.paup is None or not self.config.uncertainty_weighted_depth or not self.paup.has_statistics:
            return None
        return self.paup.depth_weights()

    def get_outputs(self, camera: Camera) -> dict[str, Any]:
        """`render`'s outputs with the water: 'uri' [H, W, 3] the water-free radiance (the rendered one), 'rgb'
        [H, W, 3] the underwater image formed from it; with a medium also 'attenuation', 'backscatter', 'beta_d',
        'beta_b' [H, W, 3] (the betas ray-averaged per pixel, per dataset unit)."""
        weights = self.depth_weights()
        if self.training and self.paup is not None and self.paup.active:
            outputs = self.render_with_paup(camera, weights)
        else:
            outputs = self.render(camera, depth_weights=weights)
        uri = outputs["uri"] = outputs.pop("radiance")
        if not self.renders_medium:
            outputs["rgb"] = self.over_background(uri, outputs["alpha"])
            return outputs
        radiance, alpha = uri, outputs["alpha"]
        if "alpha_enhanced" in outputs:  # the paper's wiring: the UWI formed from I_UR^Enh
            radiance, alpha = outputs["uri_enhanced"], outputs["alpha_enhanced"]
        with section("medium"):
            beta_d, beta_b = self.ray_betas(camera, outputs["range"])
            formed = form_underwater_image(radiance, alpha, outputs["range"], beta_d, beta_b, self.medium.b_inf,
                                           self.dataset_scale)
        outputs.update(rgb=formed["uwi"], attenuation=formed["attenuation"], backscatter=formed["backscatter"],
                       beta_d=beta_d, beta_b=beta_b)
        return outputs

    def render_view(self, camera: Camera, water: Water | None = None) -> dict[str, Tensor]:
        """`Model.render_view`: the evaluation form whatever the mode (no PAUP training branch); with a medium the
        underwater image formed with `water` as 'rgb', the water-free radiance as 'uri', and the formation's two
        terms (none for a scene judged water-free)."""
        if not self.renders_medium:
            return super().render_view(camera)
        out = self.render(camera, depth_weights=self.depth_weights())
        beta_d, beta_b = self.ray_betas(camera, out["range"])
        formed = form_with_water(out["radiance"], out["alpha"], out["range"], beta_d, beta_b, self.medium.b_inf,
                                 self.dataset_scale, water or Water())
        return {"rgb": formed["uwi"], "uri": out["radiance"], "alpha": out["alpha"], "range": out["range"],
                "attenuation": formed["attenuation"], "backscatter": formed["backscatter"]}

    def veiling_light(self) -> Tensor | None:
        return self.medium.b_inf.detach() if self.renders_medium else None

    def export_medium(self, dataset_center: tuple[float, float, float], dataset_scale: float,
                      samples: int) -> dict | None:
        """None without a medium, or for a scene judged water-free (no medium is rendered)."""
        return self.medium.summary(dataset_center, dataset_scale, samples) if self.renders_medium else None

    def render_with_paup(self, camera: Camera, depth_weights: Tensor | None) -> dict[str, Any]:
        """Training render from PAUP's start: `render`'s outputs (the UWI is formed from this full I_UR, as
        evaluation renders it) and 'pus' [N] for L_beta's weights; on the steps of `--model.paup.enhanced-every`
        also I_UR^Enh, its L1 to I_UR and m (`add_enhanced_render`), which L_PAPSL reads. Refreshes the statistics
        first when they are due."""
        if self.paup.refresh_due:
            with section("PAUP: statistics"):
                self.refresh_paup_statistics(camera)
            depth_weights = self.depth_weights()
        outputs = self.render(camera, depth_weights=depth_weights)
        if self.paup.enhanced_due:
            self.add_enhanced_render(outputs, camera)
        else:  # L_beta still weighs by PUS: the weighted sum alone (no phi, no mask; nothing trains the scorer)
            with section("PAUP: scores"), torch.no_grad():
                outputs["pus"] = self.paup.pus()
        return outputs

    def add_enhanced_render(self, outputs: dict[str, Any], camera: Camera) -> None:
        """Add to `render`'s `outputs` of `camera` 'uri_enhanced' [H, W, 3] I_UR^Enh, the Gaussians rendered with
        their opacities times the keep mask s_i (a relaxed draw of Bernoulli(1 - m_i), or 1 - m_i;
        `--model.paup.mask`), and 'uri_enhanced_l1', L1(I_UR, I_UR^Enh); and 'pus', 'floater_probability' [N].
        By default I_UR^Enh is frozen, so L_PAPSL trains the scorer alone (`render_masked`); with
        `--model.paup.uwi-from-enhanced` (the paper's wiring) it is rendered with gradients to the Gaussians and
        its coverage added as 'alpha_enhanced' [H, W], from which `get_outputs` forms the UWI."""
        with section("PAUP: scores + masked render"):
            pus, m = self.paup.scores()
            c = self.config.paup
            keep = 1.0 - m if c.mask == "expected" else relaxed_keep_mask(1.0 - m, c.mask_temperature)
            if c.uwi_from_enhanced:
                enhanced = self.render(camera, keep=keep, colors=outputs["colors"])
                # the image loss trains this render: density control reads its screen-space gradient
                outputs.update(uri_enhanced=enhanced["radiance"], alpha_enhanced=enhanced["alpha"],
                               means2d=enhanced["means2d"],
                               uri_enhanced_l1=(outputs["radiance"] - enhanced["radiance"]).abs().mean())
            else:
                outputs["uri_enhanced"], outputs["uri_enhanced_l1"] = self.render_masked(camera, keep, outputs)
        outputs.update(pus=pus, floater_probability=m)

    def render_masked(self, camera: Camera, keep: Tensor, full: dict[str, Any]) -> tuple[Tensor, Tensor]:
        """(I_UR^Enh [H, W, 3], L1(I_UR, I_UR^Enh) = mean |I_UR - I_UR^Enh|): the Gaussians of the full render `full`
        (`render`'s outputs) again, frozen, with their opacities times `keep` [N]; the L1 carries a gradient to `keep`
        only. The same view and geometry with opacities scaled down, so the full render's projection and tile lists
        hold. One compiled pass where the backend has it (`rasterize.masked_l1`; `--model.paup.kernel`), else a
        render and the mean."""
        target = full["radiance"].detach()
        if self.paup.fused_masked_l1:
            with torch.no_grad():
                opacities = torch.sigmoid(self.gaussians.opacities)  # as `render` activates them
            fused = masked_l1(full["raster"], opacities * keep, full["colors"], target, camera, self.config.raster)
            if fused is not None:
                return fused
        enhanced = self.render(camera, keep=keep, frozen=True, colors=full["colors"],
                               projection=full["raster"])["radiance"]
        return enhanced, (target - enhanced).abs().mean()

    def nearest_train_cameras(self, camera: Camera, count: int) -> list[Camera]:
        """The `count` training cameras whose centres are nearest `camera`'s (itself included when it is one)."""
        centers = torch.stack([c.center for c in self.train_cameras])
        order = (centers - camera.center.to(centers)).norm(dim=-1).argsort()[:count]
        return [self.train_cameras[int(i)].to(camera.viewmat.device) for i in order]

    @torch.no_grad()
    def refresh_paup_statistics(self, camera: Camera) -> None:
        """U, P of every Gaussian from no-gradient renders of the K training views nearest `camera`."""
        c = self.config.paup
        means = self.gaussians.means
        opacities = torch.sigmoid(self.gaussians.opacities)
        beta_d = self.medium.betas(means)[0] if self.renders_medium else None
        weights = self.depth_weights()
        views = []
        for view in self.nearest_train_cameras(camera, c.num_views):
            out = self.render(view, depth_weights=weights)
            views.append(observe_view(out["weight_sum"], out["pixel_count"], out["colors"],
                                      out["means2d"], out["radii"], (means - view.center).norm(dim=-1),
                                      out["range"], out["alpha"], opacities, beta_d, self.dataset_scale,
                                      COVERAGE_EPS, c.attenuation_weight))
        self.paup.update(*combine_views(views, c.opacity_variance_weight, c.color_variance_weight))

    def ray_betas(self, camera: Camera, ranges: Tensor) -> tuple[Tensor, Tensor]:
        """beta_D, beta_B [H, W, 3] averaged along each pixel's ray from the camera to `ranges` [H, W]."""
        dirs = camera.ray_directions().reshape(-1, 3)
        beta_d, beta_b = self.medium.ray_betas(camera.center.to(dirs.dtype), dirs, ranges.reshape(-1))
        shape = (*ranges.shape, 3)
        return beta_d.reshape(shape), beta_b.reshape(shape)

    def depth_consistency(self, outputs: dict[str, Any], camera: Camera) -> Tensor:
        """L_z (uw3dgs/metrics/depth_consistency.py) of this view's render, weighted by PAUP's (1 - U_i) where it
        has them (a scalar)."""
        return depth_consistency(outputs["range"], self.gaussians.means, outputs["means2d"], outputs["radii"],
                                 camera.center, self.depth_weights(), self.config.kernels)

    def get_loss_dict(self, outputs: dict[str, Any], batch: Batch, step: int) -> dict[str, Tensor]:
        losses = super().get_loss_dict(outputs, batch, step)
        c = self.config
        if self.renders_medium and c.beta_loss_weight > 0:
            means, picked = self.gaussians.means.detach(), None
            if len(means) > c.beta_loss_samples:  # an unbiased estimate of the mean over all centres
                picked = torch.randint(len(means), (c.beta_loss_samples,), device=means.device)
                means = means[picked]
            weights = self.beta_loss_weights(outputs, picked)
            with section("loss: L_beta"):
                losses["beta_loss"] = c.beta_loss_weight * self.medium.regularizer(means, weights)
        if c.depth_loss_weight > 0:
            with section("loss: L_z"):
                losses["depth_loss"] = c.depth_loss_weight * self.depth_consistency(outputs, batch["camera"])
        if "uri_enhanced" in outputs:
            with section("loss: L_PAPSL"):
                losses["paup_loss"] = self.paup.loss(outputs["uri_enhanced_l1"], outputs["floater_probability"])
        return losses

    @staticmethod
    def beta_loss_weights(outputs: dict[str, Any], picked: Tensor | None) -> Tensor | None:
        """PUS_i of the Gaussians whose centres L_beta reads (`picked` indices, None = all), from the step's PAUP
        render (with or without I_UR^Enh) and detached (a weight, not a target: L_beta must not train the scorer);
        None (PUS = 1) when the step had no PAUP branch."""
        if "pus" not in outputs:
            return None
        pus = outputs["pus"].detach()
        return pus if picked is None else pus[picked]

    def eval_report(self, notes: dict[str, dict]) -> dict[str, Any]:
        """'water': the water verdict made before training (`notes['water']`) and again on the learned medium over
        the same ranges, both printed; nothing for a run without that note."""
        before = notes.get("water")
        if not isinstance(before, dict):
            return {}
        info(f"water, before training: {before['line']}")
        if before.get("collapsed"):
            info("water: the model rendered without a medium (judged water-free before training): its URI is its UWI")
            return {"water": {**before, "learned": None}}
        learned = self.medium_summary()
        verdict = water_verdict(learned["beta_d"], learned["beta_b"], before["far_range"], before["level"],
                                source="the learned medium")
        info(f"water, learned medium: {verdict.line()}")
        return {"water": {**before, "learned": verdict.to_json()}}

    def medium_summary(self) -> dict[str, Tensor]:
        """Learned B_inf and the mean of beta_D, beta_B over the Gaussian centres (per channel); zeros for a scene
        judged water-free (the model renders no medium there)."""
        if self.medium is None:
            return {}
        if not self.renders_medium:
            zeros = self.medium.b_inf.detach() * 0
            return {"b_inf": zeros, "beta_d": zeros, "beta_b": zeros}
        with torch.no_grad():
            beta_d, beta_b = self.medium.betas(self.gaussians.means)
        return {"b_inf": self.medium.b_inf.detach(), "beta_d": beta_d.mean(0), "beta_b": beta_b.mean(0)}

    def get_metrics_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float]:
        """Adds B_inf and this view's ray-averaged beta_D, beta_B (cheap: already computed for rendering)."""
        metrics = super().get_metrics_dict(outputs, batch)
        if self.paup is not None:
            scorer = self.paup.scorer
            metrics.update({"paup/w_u": float(scorer.w_u.detach()), "paup/w_p": float(scorer.w_p.detach()),
                            "paup/pruned_last_event": float(self.paup.last_pruned),
                            "paup/pruned_total": float(self.paup.pruned_total)})
            if "floater_probability" in outputs:
                metrics["paup/mean_floater_probability"] = float(outputs["floater_probability"].detach().mean())
        if "beta_d" not in outputs:  # no medium rendered
            return metrics
        values = {"b_inf": self.medium.b_inf.detach(), "beta_d": outputs["beta_d"].detach().mean((0, 1)),
                  "beta_b": outputs["beta_b"].detach().mean((0, 1))}
        for name, value in values.items():
            for channel, v in zip("rgb", value.tolist(), strict=True):
                metrics[f"medium/{name}_{channel}"] = v
        return metrics

    def get_eval_metrics(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float | None]:
        """3DGS's metrics of the UWI ('rgb'), and with a medium the URI's no-reference UCIQE and UIQM (`uri_uciqe`,
        `uri_uiqm`, on every scene) and, where the scene has clean images, its PSNR, SSIM and LPIPS against them."""
        metrics = super().get_eval_metrics(outputs, batch)
        if self.medium is not None:
            metrics.update(restored_image_metrics(outputs["uri"], batch))
        return metrics

    def get_eval_summary(self, scene: SceneData) -> dict[str, float | None]:
        """3DGS's (the floater ratios), PAUP's `pruned_share` (Gaussians it removed over the run / all ever created),
        the learned medium and its error against the ground truth (synthetic scenes), relative, per channel."""
        out: dict[str, float | None] = dict(super().get_eval_summary(scene))
        if self.paup is not None:
            out["pruned_share"] = self.paup.pruned_share
        return {**out, **medium_eval_summary(self.medium_summary(), scene)}

    def get_image_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, Tensor]:
        images = {"gt": batch["image"], "uwi": outputs["rgb"].clamp(0, 1), "uri": outputs["uri"].clamp(0, 1),
                  "depth": depth_to_image(outputs["range"], outputs["alpha"])}
        if "attenuation" in outputs:
            images["attenuation"] = outputs["attenuation"].clamp(0, 1)
            images["backscatter"] = outputs["backscatter"].clamp(0, 1)
        if "clean_image" in batch:
            images["gt_clean"] = batch["clean_image"]
        if self.paup is not None and self.paup.has_statistics:
            images.update(self.paup_images(batch["camera"]))
        return images

    @torch.no_grad()
    def paup_images(self, camera: Camera) -> dict[str, Tensor]:
        """'uri_enhanced': I_UR^Enh with every opacity times its expected keep probability 1 - m_i (what PAUP
        would drop shows as missing); 'uncertainty': U_i splatted (blending-weighted mean per pixel), colour-mapped
        over [0, max U]."""
        _, m = self.paup.scores()
        enhanced = self.render(camera, keep=1.0 - m)["radiance"].clamp(0, 1)
        means, scales, quats, opacities = self.gaussians.activated()
        u = self.paup.filled()[0]
        out = rasterize(Splats(means, quats, scales, opacities, u[:, None]), camera, self.config.raster)
        mean_u = out.render[..., 0] / out.alpha.clamp_min(COVERAGE_EPS)
        top = float(u.max().clamp_min(1e-12))
        covered = out.alpha > COVERAGE_EPS
        return {"uri_enhanced": enhanced, "uncertainty": apply_colormap(mean_u, vmin=0.0, vmax=top, mask=covered)}

    def get_histograms(self) -> dict[str, Tensor]:
        if self.paup is None or not self.paup.has_statistics:
            return {}
        with torch.no_grad():
            pus, m = self.paup.scores()
        return {"paup/floater_probability": m, "paup/pus": pus, "paup/uncertainty": self.paup.uncertainty,
                "paup/implausibility": self.paup.implausibility}


def uw3dgs_optimizers(paup: bool) -> dict[str, ParamGroupConfig]:
    """The paper's rates: 0.05 opacity, 0.005 scaling, 0.001 rotation, 0.001 medium; 3DGS elsewhere; PAUP's scorer
    (w_u, w_p, phi; the paper gives no rate) at Adam's usual 0.001."""
    groups = {**gaussian_optimizers(opacity_lr=0.05, scaling_lr=0.005, rotation_lr=0.001),
              "medium_beta": ParamGroupConfig(0.001), "medium_b_inf": ParamGroupConfig(0.001)}
    return {**groups, "paup": ParamGroupConfig(0.001)} if paup else groups


def _method(name: str, description: str, model: UW3DGSModelConfig) -> MethodSpec:
    config = TrainConfig(method_name=name, model=model, optimizers=uw3dgs_optimizers(model.use_paup),
                         max_num_iterations=40000)
    return MethodSpec(name, description, config)


def preset(parent: MethodSpec, name: str, description: str, **model_overrides: Any) -> MethodSpec:
    """`parent` with its model's fields `model_overrides` replaced, and the PAUP optimizer group dropped where the
    preset has no PAUP branch: every other setting is the parent's."""
    model = dataclasses.replace(parent.config.model, **model_overrides)
    optimizers = {group: value for group, value in parent.config.optimizers.items()
                  if model.use_paup or group != "paup"}
    return MethodSpec(name, description, dataclasses.replace(parent.config, method_name=name, model=model,
                                                             optimizers=optimizers))


ABLATIONS: dict[str, tuple[str, Any]] = {
    "no-paup": ("no PAUP branch, no L_PAPSL (U = 0, PUS = 1)", lambda model: {"use_paup": False}),
    "no-medium": ("plain 3DGS rendering (no underwater module), so no L_beta, no L_z",
                  lambda model: {"use_medium": False, "beta_loss_weight": 0.0, "depth_loss_weight": 0.0}),
    "no-lbeta": ("no L_beta: beta_D, beta_B held at their start (B_inf still learned)",
                 lambda model: {"medium": dataclasses.replace(model.medium, learn_beta=False),
                                "beta_loss_weight": 0.0}),
    "no-lz": ("no L_z, depth without the (1 - U) weight",
              lambda model: {"depth_loss_weight": 0.0, "uncertainty_weighted_depth": False}),
}
"""The paper's Table 2: ablation suffix -> (what it removes, the model fields it sets given the parent's model).
Each differs from its parent in exactly these fields (and the PAUP optimizer group for no-paup)."""


def ablation(parent: MethodSpec, suffix: str) -> MethodSpec:
    """`parent`'s ablation `suffix` (a key of ABLATIONS), named PARENT-SUFFIX."""
    removes, overrides = ABLATIONS[suffix]
    return preset(parent, f"{parent.name}-{suffix}", f"Ablation of {parent.name}: {removes}.",
                  **overrides(parent.config.model))


# DESIGN's schedule: densify until 15,000 of the 40,000 steps (3DGS's absolute value, not its half)
method = _method("uw3dgs", "UW-3DGS: 3DGS + learnable underwater image formation (VM-grid beta_D, beta_B, B_inf), "
                 "Physics-Aware Uncertainty Pruning, L_beta, L_z.",
                 UW3DGSModelConfig(densification=DensificationConfig(refine_stop=15000)))
no_paup, no_medium, no_lbeta, no_lz = (ablation(method, suffix) for suffix in ABLATIONS)

PAPER_PAUP: dict[str, Any] = {"normalize_scores": False, "monotone_scorer": False, "attenuation_weight": 1.0,
                              "uwi_from_enhanced": True, "prune_schedule": "every", "prune_every": 1,
                              "prune_min_probability": 0.0}
"""The PAUP knobs `uw3dgs-paper` sets to the paper's text (docs/methods/uw3dgs.md, "The paper as written")."""

paper = preset(method, "uw3dgs-paper", "UW-3DGS as the paper writes it: the medium from beta_prior, raw PUS, "
               "unconstrained phi, P with its attenuation term, the UWI from I_UR^Enh, pruning at the 0.95-quantile "
               "of m every step, the VM factors' norm in L_beta.",
               medium=dataclasses.replace(method.config.model.medium, init="prior", flat_start="zero-basis",
                                          factor_penalty="norm", factor_penalty_weight=0.001),
               paup=dataclasses.replace(method.config.model.paup, **PAPER_PAUP))
paper_no_paup, paper_no_medium, paper_no_lbeta, paper_no_lz = (ablation(paper, suffix) for suffix in ABLATIONS)
