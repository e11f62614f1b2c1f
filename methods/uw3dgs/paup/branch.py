"""The PAUP branch of one model: its knobs, the learned scorer, the per-Gaussian statistics it keeps, and the
hard pruning it asks density control for (it implements `uw3dgs.strategy.ExtraPruning`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor, nn

from uw3dgs.kernels.policy import Kernels
from uw3dgs.methods.uw3dgs.paup.scorer import FloaterScorer
from uw3dgs.options import CheckedConfig, check_number
from uw3dgs.strategy.base import DensityEvents

PER_GAUSSIAN_BUFFERS = ("uncertainty", "implausibility", "raw_uncertainty", "measured")


@dataclass(frozen=True)
class PAUPConfig(CheckedConfig):
    start: int = 500
    """First step with the PAUP branch (statistics, the masked render, L_PAPSL, pruning)."""
    every: int = 100
    """Steps between refreshes of the statistics U, P (from the views nearest the step's training view)."""
    enhanced_every: int = 1
    """Steps between renders of I_UR^Enh and its L_PAPSL term (1: every step, as the paper; N: every N-th step
    from `start`, a CPU speed knob, docs/performance.md). The steps between still weigh L_beta by PUS; the
    statistics' refresh and the pruning keep their own cadence."""
    num_views: int = 5
    """K: training views (nearest camera centres, the current one included) the statistics are taken over."""
    opacity_variance_weight: float = 0.4
    """w_alpha in U = w_alpha Var(effective opacity) + w_c Var(colour)."""
    color_variance_weight: float = 0.6
    """w_c in U."""
    init_score_weight: float = 0.5
    """Starting value of the learned w_u and w_p in PUS = w_u U + w_p P."""
    hidden_units: int = 32
    """Width of phi's hidden layer (m = sigmoid(phi(PUS)))."""
    init_floater_score: float = 4.0
    """PUS at which phi starts at m = 1/2 (the paper is silent on phi's start; it starts rising with the score, so
    that "higher PUS = more likely a floater" holds before it has learned anything)."""
    init_sharpness: float = 2.0
    """Starting slope: m = sigmoid(init_sharpness (PUS - init_floater_score))."""
    monotone_scorer: bool = True
    """phi non-decreasing in PUS (its weights through a softplus), so m ranks Gaussians as PUS does. False: phi
    unconstrained, as the paper writes it; L_PAPSL then turns m against the floaters (docs/methods/uw3dgs.md)."""
    normalize_scores: bool = True
    """Express U and P in units of their mean over the Gaussians a refresh measured, so w_u = w_p = 0.5 weighs
    them alike (raw U is ~1e-5 and raw P ~0.2 on the built-in scene; docs/methods/uw3dgs.md). Not the median:
    on a clean surface most U are ~0 and the median unit would blow noise up. False: the raw sum the paper
    writes."""
    attenuation_weight: float = 0.0
    """Weight of P's attenuation term a_i (1 - exp(-beta_D d_i)): 0 keeps the depth term only (the default: the
    attenuation term is largest for the far opaque seabed, and with it PUS ranks the floaters near chance; docs/
    methods/uw3dgs.md, "Is m a floater score?"); the paper: 1."""
    mask: Literal["concrete", "expected"] = "concrete"
    """The keep mask s_i on the opacities of I_UR^Enh: "concrete", a relaxed-Bernoulli draw s_i ~ 1 - m_i (the
    paper's Gumbel-Softmax), or "expected", s_i = 1 - m_i (deterministic). Gradients reach phi, w_u and w_p
    through either."""
    mask_temperature: float = 0.5
    """Temperature of the "concrete" keep mask (lower: closer to hard 0/1 draws)."""
    loss_weight: float = 0.1
    """Weight of L_PAPSL = L1(I_UR, I_UR^Enh) + keep_penalty mean(1 - m) + mlp_penalty ||phi||^2."""
    keep_penalty: float = 0.01
    """lambda_s: pushes m up (pruning) where the image does not need a Gaussian."""
    mlp_penalty: float = 0.001
    """lambda_w: weight decay of phi."""
    prune_quantile: float = 0.95
    """tau, the quantile of m at and above which a pruning removes measured Gaussians (so at most 1 - q of them),
    if their m is also above prune_min_probability. The paper: 0.95 in its method section (the reading here),
    "the median" (0.5) in its implementation details."""
    prune_min_probability: float = 0.5
    """m a Gaussian must exceed to be pruned (this project's floor; the paper has none: 0)."""
    prune_schedule: Literal["densification", "every"] = "densification"
    """When PAUP hard-prunes: "densification" (this project's reading) at density-control events, while
    densification runs (and after it with prune_after_densification); "every" (the paper's tau, "updated per
    iteration") every prune_every steps from `start` to the end of the run, whatever density control does."""
    prune_every: int = 1
    """Steps between prunings with prune_schedule "every" (1: every step, the paper)."""
    prune_after_densification: bool = False
    """With prune_schedule "densification": go on pruning after densification stops (at refine-stop), on its
    cadence (every refine-every steps), removing floaters only; False: prune at densification events only."""
    uwi_from_enhanced: bool = False
    """True (the paper's wiring): I_UR^Enh is rendered with gradients to the Gaussians, the training UWI (so the
    image loss) is formed from it, and L_PAPSL's L1 term reaches the Gaussians through both I_UR and I_UR^Enh.
    False: the UWI is formed from the full I_UR, as evaluation renders it, and I_UR^Enh is a frozen render whose
    L1 trains the scorer alone (docs/methods/uw3dgs.md: the paper's wiring lets the URI collapse)."""

    def check_options(self) -> None:
        check_number(self, "start", ge=0, integer=True)
        check_number(self, "every", ge=1, integer=True)
        check_number(self, "enhanced_every", ge=1, integer=True)
        check_number(self, "num_views", ge=2, integer=True)
        check_number(self, "opacity_variance_weight", ge=0)
        check_number(self, "color_variance_weight", ge=0)
        check_number(self, "init_score_weight", gt=0)
        check_number(self, "hidden_units", ge=1, integer=True)
        check_number(self, "init_floater_score", ge=0)
        check_number(self, "init_sharpness", gt=0)
        check_number(self, "attenuation_weight", ge=0)
        check_number(self, "mask_temperature", gt=0)
        check_number(self, "loss_weight", ge=0)
        check_number(self, "keep_penalty", ge=0)
        check_number(self, "mlp_penalty", ge=0)
        check_number(self, "prune_quantile", gt=0, lt=1)
        check_number(self, "prune_min_probability", ge=0, lt=1)
        check_number(self, "prune_every", ge=1, integer=True)


class PAUP(nn.Module):
    """Per-Gaussian statistics (buffers, so checkpoints carry them and they follow densification), the scorer,
    and counters of what it pruned. A Gaussian without statistics of its own (new from densification, or never
    yet in view of a refresh) scores with the median U and median P of those that have them, and is never
    hard-pruned."""

    def __init__(self, config: PAUPConfig, num_gaussians: int, kernels: Kernels = "compiled"):
        super().__init__()
        self.config = config
        self.scorer = FloaterScorer(config.hidden_units, config.init_score_weight, config.init_floater_score,
                                    config.init_sharpness, config.monotone_scorer, kernels)
        self.fused_masked_l1 = kernels == "compiled"
        """The masked render and its L1 in one compiled pass where the rasterizer backend has it (`kernels`)."""
        self.register_buffer("uncertainty", torch.zeros(num_gaussians))
        self.register_buffer("implausibility", torch.zeros(num_gaussians))
        self.register_buffer("raw_uncertainty", torch.zeros(num_gaussians))
        """U as measured (not normalised): the (1 - U) depth weights read it, a weight in [0.75, 1] as the paper
        defines U (variances of values in [0, 1]); the unit-mean U would zero the weight of half the Gaussians."""
        self.register_buffer("measured", torch.zeros(num_gaussians, dtype=torch.bool))
        self.register_buffer("pruned_total", torch.tensor(0, dtype=torch.long))
        """Gaussians removed by PAUP over the run."""
        self.register_buffer("created_total", torch.tensor(num_gaussians, dtype=torch.long))
        """Gaussians that ever existed in the run (initial ones + all densification created)."""
        self.register_buffer("last_pruned", torch.tensor(0, dtype=torch.long))
        self.step = 0
        self._filled: tuple[Tensor, Tensor, Tensor, bool] | None = None
        """(U, P, raw U with neutral values, any measured): read several times a step, so kept until the
        statistics change (`update`, `reindex`, loading, a device move)."""

    # -- schedule --

    def set_step(self, step: int) -> None:
        self.step = step

    def prunes_at(self, step: int, strategy: DensityEvents) -> bool:
        """Whether PAUP hard-prunes at `step` (`select`), on `prune_schedule`: at `strategy`'s density-control
        events, or every `prune_every` steps from `start`."""
        c = self.config
        if c.prune_schedule == "every":
            return step >= c.start and (step - c.start) % c.prune_every == 0
        return strategy.is_refine_step(step) or (c.prune_after_densification and strategy.is_late_prune_step(step))

    @property
    def active(self) -> bool:
        return self.step >= self.config.start

    @property
    def refresh_due(self) -> bool:
        """This step refreshes the statistics (every `every` steps from `start`)."""
        return self._due_every(self.config.every)

    @property
    def enhanced_due(self) -> bool:
        """This step renders I_UR^Enh and adds L_PAPSL (every `enhanced_every` steps from `start`)."""
        return self._due_every(self.config.enhanced_every)

    def _due_every(self, steps: int) -> bool:
        return self.active and (self.step - self.config.start) % steps == 0

    @property
    def has_statistics(self) -> bool:
        return self._filled_statistics()[3]

    # -- statistics and scores --

    def update(self, uncertainty: Tensor, implausibility: Tensor, measured: Tensor) -> None:
        """Store a refresh's U, P [N] for the Gaussians it measured (`measured` [N] bool), in units of their mean
        over those with `normalize_scores`; the others keep what they had."""
        self._filled = None
        self.raw_uncertainty[measured] = uncertainty[measured].to(self.raw_uncertainty.dtype)
        if self.config.normalize_scores and bool(measured.any()):
            uncertainty = uncertainty / uncertainty[measured].mean().clamp_min(1e-12)
            implausibility = implausibility / implausibility[measured].mean().clamp_min(1e-12)
        self.uncertainty[measured] = uncertainty[measured].to(self.uncertainty.dtype)
        self.implausibility[measured] = implausibility[measured].to(self.implausibility.dtype)
        self.measured |= measured

    def filled(self) -> tuple[Tensor, Tensor]:
        """(U, P) [N] with the neutral values (medians over measured Gaussians) where unmeasured."""
        return self._filled_statistics()[:2]

    def _filled_statistics(self) -> tuple[Tensor, Tensor, Tensor, bool]:
        if self._filled is None:
            values, known = (self.uncertainty, self.implausibility, self.raw_uncertainty), self.measured
            any_known = bool(known.any())
            if any_known and not bool(known.all()):
                values = tuple(torch.where(known, v, v[known].median()) for v in values)
            self._filled = (*values, any_known)
        return self._filled

    def pus(self) -> Tensor:
        """PUS [N] = w_u U + w_p P, differentiable in w_u and w_p (phi is not run)."""
        return self.scorer.score(*self.filled())

    def scores(self) -> tuple[Tensor, Tensor]:
        """(PUS [N], m [N]), differentiable in the scorer's parameters."""
        pus = self.pus()
        return pus, self.scorer(pus)

    def depth_weights(self) -> Tensor:
        """(1 - U) [N] clamped to [0, 1], U as measured (never normalised; the median of the measured ones where
        unmeasured): each Gaussian's weight in the composited depth and in L_z."""
        return (1.0 - self._filled_statistics()[2]).clamp(0.0, 1.0)

    def loss(self, image_l1: Tensor, floater_probability: Tensor) -> Tensor:
        """Weighted L_PAPSL (scalar): L1(I_UR, I_UR^Enh) + lambda_s mean_i(1 - m_i) + lambda_w ||phi||^2, given the
        first term, `image_l1` (the mean absolute difference, computed with the masked render)."""
        c = self.config
        return c.loss_weight * (image_l1 + c.keep_penalty * (1 - floater_probability).mean()
                                + c.mlp_penalty * self.scorer.weight_penalty())

    # -- hard pruning (uw3dgs.strategy.ExtraPruning) --

    @torch.no_grad()
    def select(self, step: int) -> Tensor | None:
        """`candidates()`, counted as pruned; None before PAUP starts."""
        self.last_pruned.zero_()
        if step < self.config.start or not self.has_statistics:
            return None
        remove = self.candidates()
        self.last_pruned.fill_(int(remove.sum()))
        self.pruned_total += self.last_pruned
        return remove

    @torch.no_grad()
    def candidates(self) -> Tensor:
        """[N] bool: the measured Gaussians whose m is at or above the prune quantile of m and above the minimum
        probability; at most floor((1 - q) N) of them (the largest m first). What an event would prune now."""
        m = self.scores()[1]
        n = len(m)
        rank = min(n, max(1, math.ceil(self.config.prune_quantile * n)))
        threshold = torch.kthvalue(m, rank).values
        remove = self.measured & (m >= threshold) & (m > self.config.prune_min_probability)
        limit = math.floor((1.0 - self.config.prune_quantile) * n)
        if int(remove.sum()) > limit:
            top = torch.where(remove, m, torch.full_like(m, -1.0)).topk(limit).indices
            remove = torch.zeros_like(remove)
            remove[top] = True
        return remove

    @torch.no_grad()
    def reindex(self, origin: Tensor) -> None:
        """Follow density control: survivors keep their statistics, new Gaussians have none."""
        self._filled = None
        old = origin >= 0
        for name in PER_GAUSSIAN_BUFFERS:
            values = getattr(self, name)
            moved = torch.zeros(len(origin), dtype=values.dtype, device=values.device)
            moved[old] = values[origin[old]]
            setattr(self, name, moved)
        self.created_total += int((~old).sum())

    @property
    def pruned_share(self) -> float:
        """Gaussians PAUP removed over the run / all Gaussians ever created."""
        return float(self.pruned_total) / max(1, int(self.created_total))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        """Checkpoints hold however many Gaussians training had reached: resize before loading."""
        self._filled = None
        for name in PER_GAUSSIAN_BUFFERS:
            if prefix + name in state_dict:
                setattr(self, name, torch.empty_like(state_dict[prefix + name]))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _apply(self, fn, *args, **kwargs):
        self._filled = None  # .to(device) replaces the buffers
        return super()._apply(fn, *args, **kwargs)
