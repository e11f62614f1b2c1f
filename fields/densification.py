"""3DGS adaptive density control: clone, split, prune and opacity reset (Kerbl et al. 2023, Sec. 5).

Runs as a training callback: after each backward it accumulates the screen-space gradient of every
visible Gaussian; every `refine_every` steps it densifies where the average gradient is large and
prunes what is transparent or too big; every `reset_opacity_every` steps it lowers all opacities.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from uw3dgs.engine.callbacks import TrainingCallback
from uw3dgs.engine.optimizers import Optimizers
from uw3dgs.fields.gaussians import PARAM_NAMES, GaussianField
from uw3dgs.render.projection import quat_to_rotmat


@dataclass(frozen=True)
class DensificationConfig:
    refine_start: int = 500
    """First step that densifies or prunes."""
    refine_every: int = 100
    """Steps between densification events."""
    refine_stop: int | None = None
    """Last densification step (and opacity reset), at most half of --max-num-iterations; None = half
    (15k of 30k, as 3DGS). The cap keeps a shortened run's schedule sane: a method that pins 15,000 for its
    40,000 steps still stops at 3,000 in a 6,000-step run."""
    grad_threshold: float = 0.0002
    """Average screen-space gradient (normalised device coordinates, as 3DGS) above which a Gaussian grows."""
    percent_dense: float = 0.01
    """Gaussians larger than this fraction of the scene extent are split, smaller ones cloned."""
    split_samples: int = 2
    """New Gaussians per split one."""
    min_opacity: float = 0.005
    """Gaussians more transparent than this are pruned."""
    reset_opacity_every: int = 3000
    """Steps between opacity resets; 0 disables them."""
    reset_opacity_value: float = 0.01
    """Opacities are clamped down to this at a reset."""
    prune_screen_size: float = 0.15
    """After the first reset, prune Gaussians whose screen radius exceeded this fraction of the image."""
    prune_world_size: float = 0.1
    """After the first reset, prune Gaussians larger than this fraction of the scene extent."""


class Densifier(TrainingCallback):
    name = "densification"

    def __init__(self, config: DensificationConfig, gaussians: GaussianField, optimizers: Optimizers,
                 scene_extent: float, max_num_iterations: int):
        self.config = config
        self.gaussians = gaussians
        self.optimizers = optimizers
        self.scene_extent = scene_extent
        half = max_num_iterations // 2
        self.refine_stop = half if config.refine_stop is None else min(config.refine_stop, half)
        self._reset_stats(gaussians.num_gaussians)

    def _reset_stats(self, n: int) -> None:
        self.grad_accum = torch.zeros(n)
        self.visible_count = torch.zeros(n)
        self.max_radii = torch.zeros(n)

    # -- statistics --

    def after_backward(self, step: int, outputs: dict[str, Any]) -> None:
        if step > self.refine_stop:
            return
        means2d: Tensor = outputs["means2d"]
        if means2d.grad is None:
            return
        width, height = outputs["image_size"]
        visible = (outputs["radii"] > 0).cpu()
        # 3DGS thresholds the gradient with respect to NDC coordinates: d/d(ndc) = d/d(pixel) * size / 2
        grad = means2d.grad.detach().cpu() * torch.tensor([width / 2.0, height / 2.0])
        self.grad_accum[visible] += grad[visible].norm(dim=-1)
        self.visible_count[visible] += 1
        radius = outputs["radii"].detach().cpu().float() / max(width, height)
        self.max_radii[visible] = torch.maximum(self.max_radii[visible], radius[visible])

    # -- events --

    def after_step(self, step: int, outputs: dict[str, Any]) -> None:
        c = self.config
        if c.refine_start <= step <= self.refine_stop and step % c.refine_every == 0:
            self.densify_and_prune(step)
        if c.reset_opacity_every > 0 and step > 0 and step % c.reset_opacity_every == 0 and step <= self.refine_stop:
            self.reset_opacity()

    @torch.no_grad()
    def densify_and_prune(self, step: int) -> None:
        c = self.config
        g = self.gaussians
        avg_grad = self.grad_accum / self.visible_count.clamp_min(1)
        grow = avg_grad >= c.grad_threshold
        max_scale = torch.exp(g.scales.detach().cpu()).max(dim=-1).values
        small = max_scale <= c.percent_dense * self.scene_extent
        clone, split = grow & small, grow & ~small

        n_before = g.num_gaussians
        # both from the Gaussians as they were, before either set of new ones is appended
        cloned, split_off = self._clone_values(clone), self._split_values(split)
        self._append(cloned)
        self._append(split_off)
        # split originals are removed; so is what is transparent and, after the first reset, too big
        keep = torch.ones(g.num_gaussians, dtype=torch.bool)
        keep[:n_before][split] = False
        opacity = torch.sigmoid(g.opacities.detach().cpu())
        keep &= opacity >= c.min_opacity
        if c.reset_opacity_every > 0 and step > c.reset_opacity_every:
            scale_now = torch.exp(g.scales.detach().cpu()).max(dim=-1).values
            too_big = scale_now > c.prune_world_size * self.scene_extent
            too_big |= self.max_radii > c.prune_screen_size  # new Gaussians have no history: 0
            keep &= ~too_big
        self._keep(keep)
        self._reset_stats(g.num_gaussians)

    def _clone_values(self, mask: Tensor) -> dict[str, Tensor]:
        return {name: getattr(self.gaussians, name).detach()[mask.to(self.gaussians.means.device)]
                for name in PARAM_NAMES}

    def _split_values(self, mask: Tensor) -> dict[str, Tensor]:
        """Each selected Gaussian becomes `split_samples` smaller ones sampled from its own distribution."""
        g = self.gaussians
        k = self.config.split_samples
        mask = mask.to(g.means.device)
        values = {name: getattr(g, name).detach()[mask].repeat_interleave(k, dim=0) for name in PARAM_NAMES}
        scales = torch.exp(values["scales"])
        rot = quat_to_rotmat(values["quats"])
        offsets = torch.einsum("nij,nj->ni", rot, torch.randn_like(scales) * scales)
        values["means"] = values["means"] + offsets
        values["scales"] = torch.log(scales / (0.8 * k))  # 3DGS shrinks split Gaussians by 1.6 for k = 2
        return values

    def _append(self, values: dict[str, Tensor]) -> None:
        n_new = values["means"].shape[0]
        if n_new == 0:
            return
        current = {name: getattr(self.gaussians, name).detach() for name in PARAM_NAMES}
        swapped = self.gaussians.set_params({name: torch.cat([current[name], values[name]]) for name in PARAM_NAMES})
        for name, (old, new) in swapped.items():
            # new Gaussians start with zero Adam moments
            self.optimizers.replace_param(
                name, old, new, lambda m, n=n_new: torch.cat([m, torch.zeros((n, *m.shape[1:]), dtype=m.dtype,
                                                                                device=m.device)]))
        self.grad_accum = torch.cat([self.grad_accum, torch.zeros(n_new)])
        self.visible_count = torch.cat([self.visible_count, torch.zeros(n_new)])
        self.max_radii = torch.cat([self.max_radii, torch.zeros(n_new)])

    def _keep(self, keep: Tensor) -> None:
        if bool(keep.all()):
            return
        keep_dev = keep.to(self.gaussians.means.device)
        swapped = self.gaussians.set_params({name: getattr(self.gaussians, name).detach()[keep_dev]
                                             for name in PARAM_NAMES})
        for name, (old, new) in swapped.items():
            self.optimizers.replace_param(name, old, new, lambda m: m[keep_dev])

    @torch.no_grad()
    def reset_opacity(self) -> None:
        g = self.gaussians
        limit = torch.logit(torch.tensor(self.config.reset_opacity_value)).item()
        swapped = g.set_params({"opacities": g.opacities.detach().clamp_max(limit)})
        old, new = swapped["opacities"]
        self.optimizers.replace_param("opacities", old, new, torch.zeros_like)

    def state_dict(self) -> dict[str, Any]:
        return {"grad_accum": self.grad_accum, "visible_count": self.visible_count, "max_radii": self.max_radii}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.grad_accum = state["grad_accum"].clone()
        self.visible_count = state["visible_count"].clone()
        self.max_radii = state["max_radii"].clone()

