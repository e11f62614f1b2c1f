"""3DGS adaptive density control: clone, split, prune and opacity reset (Kerbl et al. 2023, Sec. 5).

After each backward, `step_post_backward` accumulates the screen-space gradient of every visible Gaussian;
after each optimizer step, `step_post_optimizer` densifies every `refine_every` steps where the average
gradient is large, prunes what is transparent or too big, and lowers all opacities every
`reset_opacity_every` steps. The statistics live on the Gaussians' device (no host sync per step).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from uw3dgs.options import CheckedConfig, check_number
from uw3dgs.strategy.base import GaussianParameters, OptimizerSurgery
from uw3dgs.strategy.ops import append, duplicated, remove_all_but, reset_opacity, split_samples

State = dict[str, Tensor]
"""'grad_accum' [N] (summed NDC gradient norms), 'visible_count' [N], 'max_radii' [N] (largest screen
radius as a share of the image's larger side), on the Gaussians' device."""


@dataclass(frozen=True)
class DensificationConfig(CheckedConfig):
    refine_start: int = 500
    """First step that densifies or prunes."""
    refine_every: int = 100
    """Steps between densification events."""
    refine_stop: int | None = None
    """Last densification step (and opacity reset), at most half of --max-num-iterations; None = half
    (15k of 30k, as 3DGS). The cap keeps a shortened run's schedule sane: a method that pins 15,000 for its
    40,000 steps still stops at 3,000 in a 6,000-step run."""
    refine_stop_share: float = 0.5
    """The cap on refine_stop (and its default) as a share of --max-num-iterations: 0.5 is the half above."""
    grad_threshold: float = 0.0002
    """Average screen-space gradient (normalised device coordinates, as 3DGS) above which a Gaussian grows."""
    absgrad: bool = False
    """Grow by each view's per-pixel screen-space gradients summed in absolute value (AbsGS, WaterSplatting), not
    by the gradient of the sum, whose per-pixel parts can cancel; grad_threshold then applies to that sum (about
    4x 3DGS's 0.0002 is usual). Needs a renderer that reports them (`absgrad` of `step_post_backward`)."""
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
    prune_screen_size: float | None = 0.15
    """After the first reset, prune Gaussians whose screen radius exceeded this fraction of the image; None: never."""
    prune_world_size: float = 0.1
    """After the first reset, prune Gaussians larger than this fraction of the scene extent."""
    late_min_opacity: float | None = None
    """After the last densification event, prune Gaussians more transparent than this every refine_every steps
    (WaterSplatting's post-densification cull); None: never (3DGS)."""

    def check_options(self) -> None:
        check_number(self, "refine_start", ge=0, integer=True)
        check_number(self, "refine_every", ge=1, integer=True)
        check_number(self, "refine_stop", ge=0, integer=True, optional=True)
        check_number(self, "refine_stop_share", gt=0, le=1)
        check_number(self, "grad_threshold", ge=0)
        check_number(self, "percent_dense", gt=0)
        check_number(self, "split_samples", ge=1, integer=True)
        check_number(self, "min_opacity", ge=0, lt=1)
        check_number(self, "reset_opacity_every", ge=0, integer=True)
        check_number(self, "reset_opacity_value", gt=0, lt=1)
        check_number(self, "prune_screen_size", gt=0, optional=True)
        check_number(self, "prune_world_size", gt=0)
        check_number(self, "late_min_opacity", ge=0, lt=1, optional=True)


class DefaultStrategy:
    """3DGS's density control for one run: `scene_extent` in world units, the run's length in steps."""

    def __init__(self, config: DensificationConfig, scene_extent: float, max_num_iterations: int):
        self.config = config
        self.scene_extent = scene_extent
        cap = int(max_num_iterations * config.refine_stop_share)  # 0.5: exactly max_num_iterations // 2
        self.refine_stop = cap if config.refine_stop is None else min(config.refine_stop, cap)

    def initialize_state(self, gaussians: GaussianParameters) -> State:
        """Zero statistics for the Gaussians as they are now."""
        n, device = gaussians.means.shape[0], gaussians.means.device
        return {"grad_accum": torch.zeros(n, device=device), "visible_count": torch.zeros(n, device=device),
                "max_radii": torch.zeros(n, device=device)}

    # -- statistics --

    @torch.no_grad()
    def step_post_backward(self, state: State, step: int, means2d: Tensor, radii: Tensor,
                           image_size: tuple[int, int], absgrad: Tensor | None = None) -> None:
        """Accumulate one view's statistics: `means2d` [N, 2] (pixels, with `.grad` from this backward),
        `radii` [N] (pixels, 0 = not visible), `image_size` (width, height); `absgrad` [N, 2] the per-pixel
        gradients summed in absolute value (pixels), read instead of `means2d.grad` with the `absgrad` option."""
        if self.config.absgrad and absgrad is None:
            raise ValueError("--model.densification.absgrad: this method's renderer does not report absolute "
                             "screen-space gradients; set it to False")
        screen_grad = absgrad if self.config.absgrad else means2d.grad
        if step > self.refine_stop or screen_grad is None:
            return
        width, height = image_size
        visible = radii > 0
        # 3DGS thresholds the gradient with respect to NDC coordinates: d/d(ndc) = d/d(pixel) * size / 2
        grad = screen_grad.detach() * torch.tensor([width / 2.0, height / 2.0], device=means2d.device)
        # whole-array updates that add 0 (and take the maximum with 0) where not visible: the same numbers as
        # updating the visible entries through boolean indexing, without its gathers and scatters
        zero = grad.new_zeros(())
        state["grad_accum"] += torch.where(visible, grad.norm(dim=-1), zero)
        state["visible_count"] += visible
        radius = radii.detach().float() / max(width, height)
        torch.maximum(state["max_radii"], torch.where(visible, radius, zero), out=state["max_radii"])

    # -- events --

    def is_refine_step(self, step: int) -> bool:
        """Whether `step_post_optimizer` densifies and prunes at `step`."""
        c = self.config
        return c.refine_start <= step <= self.refine_stop and step % c.refine_every == 0

    def is_late_prune_step(self, step: int) -> bool:
        """Whether `step` is on the densification cadence after the last densification event: where another
        criterion (PAUP) or `late_min_opacity` may still prune, with nothing grown."""
        return step > self.refine_stop and step % self.config.refine_every == 0

    def prunes_at(self, step: int) -> bool:
        """Whether `step_post_optimizer` may remove Gaussians at `step` by this strategy's own rules."""
        late = self.config.late_min_opacity is not None and self.is_late_prune_step(step)
        return self.is_refine_step(step) or late

    def step_post_optimizer(self, gaussians: GaussianParameters, optimizers: OptimizerSurgery, state: State,
                            step: int, remove: Tensor | None = None) -> Tensor | None:
        """Densify and prune, or reset opacities, when the schedule says so at `step`. `remove` [N] (bool) names
        Gaussians another criterion prunes at this event (PAUP's floaters); outside densification events they are
        pruned alone. Returns the event's `origin` map (see `densify_and_prune`), None when nothing changed size."""
        c = self.config
        origin = None
        if self.is_refine_step(step):
            origin = self.densify_and_prune(gaussians, optimizers, state, step, remove)
        elif c.late_min_opacity is not None and self.is_late_prune_step(step):
            transparent = torch.sigmoid(gaussians.opacities.detach()) < c.late_min_opacity
            remove = transparent if remove is None else remove | transparent
            origin = self.prune(gaussians, optimizers, state, remove)
        elif remove is not None and bool(remove.any()):
            origin = self.prune(gaussians, optimizers, state, remove)
        if c.reset_opacity_every > 0 and step > 0 and step % c.reset_opacity_every == 0 and step <= self.refine_stop:
            reset_opacity(gaussians, optimizers, c.reset_opacity_value)
        return origin

    @torch.no_grad()
    def densify_and_prune(self, gaussians: GaussianParameters, optimizers: OptimizerSurgery, state: State,
                          step: int, remove: Tensor | None = None) -> Tensor:
        """Clone, split and prune; Gaussians in `remove` [N] (bool) are pruned too and never grow. Returns `origin`
        [N'] (long): for each Gaussian after the event, its index before it, -1 for the ones it created."""
        c = self.config
        g = gaussians
        avg_grad = state["grad_accum"] / state["visible_count"].clamp_min(1)
        grow = avg_grad >= c.grad_threshold
        if remove is not None:
            grow &= ~remove
        max_scale = torch.exp(g.scales.detach()).max(dim=-1).values
        small = max_scale <= c.percent_dense * self.scene_extent
        clone, split = grow & small, grow & ~small

        n_before = g.means.shape[0]
        # both from the Gaussians as they were, before either set of new ones is appended
        cloned, split_off = duplicated(g, clone), split_samples(g, split, c.split_samples)
        append(g, optimizers, cloned)
        append(g, optimizers, split_off)
        # split originals are removed; so is what is transparent and, after the first reset, too big
        keep = torch.ones(g.means.shape[0], dtype=torch.bool, device=g.means.device)
        keep[:n_before][split] = False
        if remove is not None:
            keep[:n_before] &= ~remove
        keep &= torch.sigmoid(g.opacities.detach()) >= c.min_opacity
        if c.reset_opacity_every > 0 and step > c.reset_opacity_every:
            scale_now = torch.exp(g.scales.detach()).max(dim=-1).values
            too_big = scale_now > c.prune_world_size * self.scene_extent
            # new Gaussians have no screen-size history: 0
            max_radii = torch.cat([state["max_radii"], state["max_radii"].new_zeros(len(keep) - n_before)])
            if c.prune_screen_size is not None:
                too_big |= max_radii > c.prune_screen_size
            keep &= ~too_big
        remove_all_but(g, optimizers, keep)
        state.update(self.initialize_state(g))
        origin = torch.cat([torch.arange(n_before, device=keep.device),
                            torch.full((len(keep) - n_before,), -1, dtype=torch.long, device=keep.device)])
        return origin[keep]

    @torch.no_grad()
    def prune(self, gaussians: GaussianParameters, optimizers: OptimizerSurgery, state: State,
              remove: Tensor) -> Tensor:
        """Remove the Gaussians in `remove` [N] (bool) with their optimizer state, nothing else. Returns `origin`
        [N'] (long), each survivor's index before."""
        keep = ~remove
        remove_all_but(gaussians, optimizers, keep)
        state.update(self.initialize_state(gaussians))
        return torch.arange(len(keep), device=keep.device)[keep]
