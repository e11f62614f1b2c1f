"""The learnable underwater medium: attenuation beta_D, backscatter beta_B and the veiling light B_inf.

Two fields are registered (kind "medium", each a subcommand of `uw-train uw3dgs`):
- `medium-grid` (`MediumGrid`, the paper's): beta_D and beta_B as RGB fields over the scene box, each a
  TensoRF vector-matrix (VM) decomposition read by trilinear interpolation;
- `medium-homogeneous` (`HomogeneousMedium`): one beta_D, beta_B per channel everywhere (SeaSplat's medium).

Image formation (Akkaynak & Treibitz 2018, the paper's Eq. scattering_4), per pixel with range z:
    I_UW = I_UR exp(-beta_D z) + B_inf (1 - exp(-beta_B z)).
beta is per unit of the dataset's own world units; a pixel's beta is the mean of the field at S
points along its ray from the camera to the surface (midpoint rule; S = 1 is the paper's single
query at half the range), which is the Beer-Lambert integral for a medium that varies along the ray.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from uw3dgs.config import InstantiateConfig, Target, target
from uw3dgs.fields.medium_identifiability import IdentifiabilityConfig
from uw3dgs.fields.medium_multiview import MultiviewConfig
from uw3dgs.kernels.policy import Kernels, use_compiled
from uw3dgs.kernels.vm_field import vm_read
from uw3dgs.medium.field import Medium
from uw3dgs.options import check_number
from uw3dgs.registry import FieldSpec

RGB = tuple[float, float, float]
FlatStart = Literal["zero-basis", "constant-factors"]
FactorPenalty = Literal["norm", "roughness"]
# (plane axes, line axis) of TensoRF's three VM modes: XY x Z, XZ x Y, YZ x X
VM_MODES = (((0, 1), 2), ((0, 2), 1), ((1, 2), 0))


def softplus_inverse(y: Tensor) -> Tensor:
    return y + torch.log(-torch.expm1(-y))


@dataclass(frozen=True)
class MediumFieldConfig(InstantiateConfig):
    """Knobs every medium field has: its starting values and how training starts it from the data.

    `setup(points=[P, 3], camera_centers=[C, 3], kernels=...)` builds the field (world units: the initial points and
    the training cameras, which a spatial field uses to place its box; `kernels`, the model's `--model.kernels`)."""

    beta_prior: RGB = (0.1, 0.15, 0.2)
    """Initial value of beta_D and beta_B (R, G, B) per dataset unit, and L_beta's pull target with
    init 'prior' (with 'estimate' the estimate replaces it as both)."""
    b_inf_init: RGB = (0.5, 0.5, 0.5)
    """Initial veiling light B_inf (RGB)."""
    learn_beta: bool = True
    """False fixes beta_D = beta_B = beta_prior (the no-L_beta ablation); B_inf is still learned."""
    init: Literal["prior", "estimate", "multiview", "truth"] = "estimate"
    """Starting medium: 'estimate' (default) = a homogeneous medium fitted to the initial points' colours
    across the training views, the Gaussians' colours de-hazed to match, and L_beta pulling toward it
    (fields/medium_estimate.py; betas stay at beta_prior when learn_beta is False); 'prior' = beta_prior
    and b_inf_init everywhere, colours as they are, L_beta pulling toward beta_prior (the paper); 'truth' =
    as 'estimate' with the scene's true medium (gt/medium.json, synthetic scenes only): an oracle for analysis,
    not a method (zero --optimizers.medium-beta.lr and --optimizers.medium-b-inf.lr keep it there); 'multiview' =
    as 'estimate', each parameter then taken from the evidence that pins it: the single-image estimate or the fit
    of how each point's colour changes with its range across the views (fields/medium_evidence.py,
    docs/medium-estimate.md)."""
    dark_bins: int = 10
    """'estimate' reads beta_B off the darkest observations of the points in this many range bins (Sea-thru)."""
    dark_share: float = 0.01
    """Share of each range bin's observations (the darkest) taken as backscatter alone (surfaces with J ~ 0)."""
    estimate_residual: bool = False
    """'estimate' fits Sea-thru's residual term for dark surfaces that are not black (fields/medium_estimate.py,
    step 4), where it explains the backscatter samples better. Off by default: over the medium-recovery benchmark's
    scene kinds it helps where the darkest surfaces reflect 10-20% and hurts on most water types
    (docs/medium-recovery.md)."""
    open_water_cells: int = 16
    """'estimate' reads B_inf off open water: image cells (this many across the width) that no initial point
    lands in; the betas are then fitted with B_inf fixed. 0 fits B_inf to the dark observations with beta_B."""
    open_water_min_share: float = 0.01
    """Least share of the training pixels in such cells for them to count as open water (else B_inf is fitted)."""
    open_water_max_std: float = 0.02
    """An empty cell looks like open water when its pixels' standard deviation is at most this in every channel
    (colour in [0, 1]; 0.02 is about 5 grey levels of an 8-bit image): water is one colour, seabed has texture."""
    open_water_min_uniform: float = 0.5
    """Least share of the empty cells that must look like open water (`open_water_max_std`) for B_inf to be read
    off them: a hole in the points over textured seabed is not water (docs/medium-report.md, "B_inf without open
    water"). Below it B_inf is fitted from the far, veiled end of the ranges and the identifiability report says
    why. 0 takes every empty cell as water."""
    far_end_quantile: float = 0.9
    """'estimate' without open water reads B_inf off the far, veiled end of the ranges (fields/medium_estimate.py,
    `veiling_light_from_far_end`): the observations beyond this quantile of their ranges. 0 fits B_inf with beta_B
    to the dark observations alone (the behaviour before)."""
    dehaze_unseen_with_all_poses: bool = True
    """An initial point no training view sees got its colour from the other views of the SfM model (COLMAP
    matches the test views too). True de-hazes it at its mean range to the cameras of all views whose image it
    lands in (their poses, never their pixels), as its colour was seen; False at the range to the nearest
    training camera, the strict protocol that uses no test-view pose."""
    report: bool = True
    """'estimate' also judges, before training, which of the estimate's parameters this scene's training views
    constrain (fields/medium_identifiability.py: range span, dark observations, open water, agreement of the halves
    of the scene), prints it and keeps it in the run folder (`notes/medium_report.json`) and in uw-eval's JSON."""
    identifiability: IdentifiabilityConfig = field(default_factory=IdentifiabilityConfig)
    """The report's thresholds."""
    multiview: MultiviewConfig = field(default_factory=MultiviewConfig)
    """init 'multiview': the multi-view fit's knobs (fields/medium_multiview.py)."""
    no_water_level: float = 0.25
    """'estimate' judges whether there is water at all (uw3dgs/medium/water_verdict.py): little or no water when the
    optical depths beta_D*z and beta_B*z at the far end of the ranges stay below this in every channel (the water
    then changes no pixel by more than about this share)."""
    collapse_without_water: bool = True
    """With the verdict 'little or no water', render without a medium (the URI is the UWI, as 3DGS) instead of
    learning water that is not there. False learns the medium anyway."""
    water_check_below: float = 1.0
    """Where the single-image estimate sees water, but no far optical depth of it reaches this, judge again from the
    multi-view fit (--model.medium.multiview.*): little or no water when its beta_D's bootstrap 95% bound stays below
    the level in every channel (water that scatters also attenuates). On a dry scene the surfaces' colours do not
    change with range, while a single image can read haze into shading and texture (up to 0.33 on the fox photos;
    real water: 1.2 and more; docs/evaluation.md, "The water verdict"). The fit costs tens of CPU seconds, hence the
    bound. 0: the single-image verdict alone."""

    def check_options(self) -> None:
        super().check_options()
        check_number(self, "beta_prior", gt=0, each=True)
        check_number(self, "b_inf_init", ge=0, le=1, each=True)
        check_number(self, "dark_bins", ge=1, integer=True)
        check_number(self, "dark_share", gt=0, le=1)
        check_number(self, "open_water_cells", ge=0, integer=True)
        check_number(self, "open_water_min_share", ge=0, le=1)
        check_number(self, "open_water_max_std", ge=0)
        check_number(self, "open_water_min_uniform", ge=0, le=1)
        check_number(self, "far_end_quantile", ge=0, lt=1)
        check_number(self, "no_water_level", ge=0)
        check_number(self, "water_check_below", ge=0)


@dataclass(frozen=True)
class MediumGridConfig(MediumFieldConfig):
    """`medium-grid`: beta_D and beta_B as TensoRF VM-decomposed RGB grids over the scene box (the paper)."""

    _target: Target = target(lambda: MediumGrid.around)
    resolution: int = 64
    """Grid size G per axis of every plane and line."""
    components: int = 16
    """VM components R per mode."""
    init_std: float = 0.1
    """Standard deviation of the random VM factors: the planes and lines with flat_start 'zero-basis', the basis
    with 'constant-factors'."""
    flat_start: FlatStart = "constant-factors"
    """How the field is made flat (at beta_prior, then at the estimate). 'constant-factors' (the default): planes and
    lines 1 everywhere, a random basis, and the bias set so the field equals the start: every factor gets image
    gradients from step 1. 'zero-basis' (the paper's code, `uw3dgs-paper`): random planes and lines and a zero basis,
    so the planes and lines get no gradient from the images, only from the factor penalty; with factor_penalty 'norm'
    they collapse to ~0 within a few hundred steps and the field stays flat for good (docs/medium-varying.md)."""
    factor_penalty: FactorPenalty = "roughness"
    """The VM factors' term in L_beta, factor_penalty_weight x (of both fields): 'roughness' (the default) = the
    squared differences between neighbouring cells of every plane and line's change from the start (flat, or the
    multi-view field fit's): 0 at the start, it penalises only the spatial variation training adds; 'norm' (the
    paper's, `uw3dgs-paper`) = the squared norm of the planes and lines, which pulls them to 0 (with
    'constant-factors', away from the start)."""
    factor_penalty_weight: float = 0.1
    """Weight of the factor penalty inside L_beta (>= 0; L_beta itself is then scaled by beta_loss_weight). 0.1 for
    the roughness: chosen on the survey variants, where 0.001 (the paper's weight on the factor norm) let homogeneous
    water vary by up to 4% and cost its URI 2.3 dB, and 0.1 keeps it within 1% (docs/medium-varying.md, "The
    roughness weight"); `uw3dgs-paper` uses 0.001 with the norm. 0 turns the penalty off."""
    ray_samples: int = 1
    """S: points along each ray averaged for a pixel's beta (1 = the paper's single query)."""
    box_padding: float = 0.1
    """The scene box is the bounds of cameras and initial points, padded by this fraction per side."""
    factor_grid: int = 32
    """A start that varies in space (init 'multiview' where the multi-view field fit pins the betas,
    fields/medium_varying.py): L_beta's targets vary by the fitted factor, kept on a grid of this many cells per axis
    over the box (trilinear reads)."""
    distill_steps: int = 200
    """Such a start is written into the VM factors by this many Adam steps (`distill_lr`) fitting log beta to the
    target at random points of the box and at the initial points."""
    distill_lr: float = 0.02
    """Adam's learning rate for `distill_steps`."""

    def check_options(self) -> None:
        super().check_options()
        check_number(self, "resolution", ge=2, integer=True)
        check_number(self, "factor_grid", ge=2, integer=True)
        check_number(self, "distill_steps", ge=0, integer=True)
        check_number(self, "distill_lr", gt=0)
        check_number(self, "components", ge=1, integer=True)
        check_number(self, "init_std", ge=0)
        check_number(self, "factor_penalty_weight", ge=0)
        check_number(self, "ray_samples", ge=1, integer=True)
        check_number(self, "box_padding", ge=0)


@dataclass(frozen=True)
class HomogeneousMediumConfig(MediumFieldConfig):
    """`medium-homogeneous`: one beta_D, beta_B and B_inf per channel for the whole scene (SeaSplat's medium)."""

    _target: Target = target(lambda: HomogeneousMedium)


class VMField(nn.Module):
    """An RGB field f(x) = softplus(W [plane_m(x) line_m(x)]_m + b) over [-1, 1]^3 (trilinear reads).

    `start` is how the field is flat at `init` (MediumGridConfig.flat_start): 'zero-basis' = random planes and lines,
    W = 0; 'constant-factors' = planes and lines 1 (every feature is 1 everywhere), W random, b = softplus^-1(init) -
    W 1, so that W and the planes and lines all get gradients from the first step."""

    def __init__(self, resolution: int, components: int, init: RGB, init_std: float, start: FlatStart):
        super().__init__()
        g, r = resolution, components
        self.start = start
        if start == "zero-basis":
            self.planes = nn.Parameter(init_std * torch.randn(3, r, g, g))
            self.lines = nn.Parameter(init_std * torch.randn(3, r, g))
            self.basis = nn.Parameter(torch.zeros(3, 3 * r))
        else:
            self.planes = nn.Parameter(torch.ones(3, r, g, g))
            self.lines = nn.Parameter(torch.ones(3, r, g))
            self.basis = nn.Parameter(init_std * torch.randn(3, 3 * r))
        self.bias = nn.Parameter(torch.empty(3))
        # the planes and lines the roughness penalty measures change from: the start (flat, or the field fit's)
        self.register_buffer("planes_start", torch.zeros_like(self.planes))
        self.register_buffer("lines_start", torch.zeros_like(self.lines))
        self.make_flat(torch.tensor(init, dtype=torch.float32))

    @torch.no_grad()
    def make_flat(self, value: Tensor) -> None:
        """Make f = value [3] (> 0) everywhere, the factors as `start` has them: a zero basis, or planes and lines
        of 1 with the basis kept and the bias taking up its constant W 1."""
        if self.start == "zero-basis":
            self.basis.zero_()  # the VM factors add nothing, so the bias alone sets the value
            self.bias.copy_(softplus_inverse(value.to(self.bias)))
        else:
            self.planes.fill_(1.0)
            self.lines.fill_(1.0)
            self.bias.copy_(softplus_inverse(value.to(self.bias)) - self.basis.sum(dim=1))
        self.hold_start()

    @torch.no_grad()
    def hold_start(self) -> None:
        """Take the present planes and lines as the start the roughness penalty measures change from."""
        self.planes_start.copy_(self.planes)
        self.lines_start.copy_(self.lines)

    def features(self, x: Tensor) -> Tensor:
        """[N, 3] points in [-1, 1] -> [3R, N] products of plane (bilinear) and line (linear) reads.

        Channel-major, as grid_sample returns them: transposing to [N, 3R] before the basis product made the
        products and their backward strided, and slower (docs/performance.md, benchmarks/speed/medium_field.py)."""
        feats = []
        for m, ((a, b), c) in enumerate(VM_MODES):
            # grid_sample's grid is (x, y) = (width index, height index): planes are [R, G(axis a), G(axis b)]
            plane_grid = torch.stack([x[:, b], x[:, a]], dim=-1).view(1, -1, 1, 2)
            plane = F.grid_sample(self.planes[m][None], plane_grid, align_corners=True).view(-1, x.shape[0])
            line_grid = torch.stack([torch.zeros_like(x[:, c]), x[:, c]], dim=-1).view(1, -1, 1, 2)
            line = F.grid_sample(self.lines[m][None, :, :, None], line_grid, align_corners=True).view(-1, x.shape[0])
            feats.append(plane * line)
        return torch.cat(feats, dim=0)

    def forward(self, x: Tensor) -> Tensor:
        """f at points x [N, 3] in [-1, 1]^3 -> [N, 3], in PyTorch (grid_sample reads): the reference of the
        compiled kernel (uw3dgs/kernels/vm_field.py), and its path on CUDA."""
        return F.softplus((self.basis @ self.features(x)).T + self.bias)

    def factors(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(planes, lines, basis, bias), as `vm_read` takes a field."""
        return self.planes, self.lines, self.basis, self.bias

    def dense_features(self) -> Tensor:
        """The full [3R, G, G, G] feature grid the factors describe (for tests and inspection)."""
        out = []
        for m, ((a, b), c) in enumerate(VM_MODES):
            plane, line = self.planes[m], self.lines[m]  # [R, G, G] over (a, b), [R, G] over c
            grid = torch.einsum("rij,rk->rijk", plane, line)  # axes (a, b, c)
            order = [0] + [1 + (a, b, c).index(axis) for axis in range(3)]
            out.append(grid.permute(*order))
        return torch.cat(out, dim=0)

    def factor_norm(self) -> Tensor:
        """Squared norm of the planes and lines (scalar)."""
        return self.planes.square().sum() + self.lines.square().sum()

    def factor_roughness(self) -> Tensor:
        """Sum of squared differences between neighbouring cells of the planes (along both axes) and lines (scalar),
        of their change from the start (`hold_start`): 0 at the start, and where they differ from it by a constant.
        From a flat start that is the roughness of the field's factors; from the field fit's start, training's
        additions to it are penalised, not the variation the fit found."""
        planes, lines = self.planes - self.planes_start, self.lines - self.lines_start  # [3, R, G, G], [3, R, G]
        return (planes.diff(dim=-1).square().sum() + planes.diff(dim=-2).square().sum()
                + lines.diff(dim=-1).square().sum())


class MediumField(Medium):
    """What every medium field of `uw3dgs` is (the framework's `Medium`, with a config, L_beta's priors and a start
    from the data): beta_D, beta_B (RGB, >= 0, per dataset unit) readable anywhere in the world, and the veiling
    light B_inf [3]. Subclasses implement `betas` and `beta_parameters`."""

    def __init__(self, config: MediumFieldConfig):
        super().__init__()
        self.config = config
        self.b_inf = nn.Parameter(torch.tensor(config.b_inf_init, dtype=torch.float32))
        # L_beta's pull targets: beta_prior, or the data's estimate once `set_prior` is called
        self.register_buffer("prior_d", torch.tensor(config.beta_prior, dtype=torch.float32))
        self.register_buffer("prior_b", torch.tensor(config.beta_prior, dtype=torch.float32))

    def beta_parameters(self) -> list[nn.Parameter]:
        """The parameters that shape beta_D and beta_B (the optimizer group 'medium_beta')."""
        raise NotImplementedError

    def set_homogeneous(self, beta_d: Tensor | None, beta_b: Tensor | None, b_inf: Tensor) -> None:
        """Make the medium the same everywhere: beta_D, beta_B [3] per dataset unit (None keeps that field),
        B_inf [3]."""
        raise NotImplementedError

    def factor_penalty(self) -> Tensor | None:
        """The field's own regularizer, added to L_beta's pull (None: nothing to add)."""
        return None

    def set_factor(self, factor: Callable[[Tensor], Tensor], points: Tensor) -> None:
        """Make the betas vary as `factor` (world points [N, 3] -> [N] > 0) times their present values, and L_beta
        pull toward that field; `points` [P, 3] are where the scene is (the initial points). A field that cannot vary
        takes the factor's mean over the points."""
        with torch.no_grad():
            mean = factor(points).float().mean().to(self.prior_d)
            d, b = (x[0] for x in self.betas(points[:1].float()))
            self.set_homogeneous(d * mean, b * mean, self.b_inf.detach().clone())
            self.set_prior(self.prior_d * mean, self.prior_b * mean)

    def prior_factor_at(self, points: Tensor) -> Tensor | None:
        """[N, 1] the factor L_beta's targets vary by at `points` [N, 3] (None: they are the same everywhere)."""
        return None

    @torch.no_grad()
    def set_prior(self, beta_d: Tensor, beta_b: Tensor) -> None:
        """Make L_beta pull beta_D and beta_B toward these RGB values [3] instead of beta_prior."""
        self.prior_d.copy_(beta_d.to(self.prior_d))
        self.prior_b.copy_(beta_b.to(self.prior_b))

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        groups = {"medium_b_inf": [self.b_inf]}
        if self.config.learn_beta:
            groups["medium_beta"] = self.beta_parameters()
        return groups

    def regularizer(self, points: Tensor, weights: Tensor | None = None) -> Tensor:
        """L_beta (scalar): pull of both fields toward their priors at `points` [N, 3], weighted per point by
        `weights` [N] (a mean over the points), plus the field's own penalty."""
        beta_d, beta_b = self.betas(points)
        factor = self.prior_factor_at(points)
        prior_d, prior_b = (self.prior_d, self.prior_b) if factor is None else \
            (self.prior_d * factor, self.prior_b * factor)
        dev = (beta_d - prior_d).square().sum(-1) + (beta_b - prior_b).square().sum(-1)
        pull = dev.mean() if weights is None else (weights * dev).mean()
        penalty = self.factor_penalty()
        return pull if penalty is None else pull + penalty


class MediumGrid(MediumField):
    """beta_D, beta_B as VM fields over the box [box_min, box_max] (world units), and B_inf."""

    def __init__(self, config: MediumGridConfig, box_min: Tensor, box_max: Tensor, kernels: Kernels = "compiled"):
        super().__init__(config)
        self.register_buffer("box_min", box_min.float().clone())
        self.register_buffer("box_max", box_max.float().clone())
        args = (config.resolution, config.components, config.beta_prior, config.init_std, config.flat_start)
        self.kernels = kernels
        """Both fields read in one compiled pass where `use_compiled` says so (PyTorch's grid_sample otherwise)."""
        self.beta_d = VMField(*args)
        self.beta_b = VMField(*args)
        g = config.factor_grid
        self.register_buffer("prior_factor", torch.ones(1, 1, g, g, g))
        """L_beta's targets' factor over the box [1, 1, G, G, G] (z, y, x, as grid_sample reads them)."""
        self.register_buffer("prior_varies", torch.tensor(False))
        if not config.learn_beta:
            self.beta_d.requires_grad_(False)
            self.beta_b.requires_grad_(False)

    @classmethod
    def around(cls, config: MediumGridConfig, points: Tensor, camera_centers: Tensor,
               kernels: Kernels = "compiled") -> MediumGrid:
        """A medium whose box holds the cameras [C, 3] and (robustly: 1st-99th percentile) the points [P, 3]."""
        lo = torch.quantile(points.float(), 0.01, dim=0) if len(points) else camera_centers.min(0).values
        hi = torch.quantile(points.float(), 0.99, dim=0) if len(points) else camera_centers.max(0).values
        lo = torch.minimum(lo, camera_centers.min(0).values)
        hi = torch.maximum(hi, camera_centers.max(0).values)
        pad = (hi - lo).clamp_min(1e-6) * config.box_padding
        return cls(config, lo - pad, hi + pad, kernels)

    @torch.no_grad()
    def set_homogeneous(self, beta_d: Tensor | None, beta_b: Tensor | None, b_inf: Tensor) -> None:
        for field_, beta in ((self.beta_d, beta_d), (self.beta_b, beta_b)):
            if beta is not None:
                field_.make_flat(beta.clamp_min(1e-4))
        self.b_inf.copy_(b_inf.to(self.b_inf))

    def beta_parameters(self) -> list[nn.Parameter]:
        return [*self.beta_d.parameters(), *self.beta_b.parameters()]

    def factor_penalty(self) -> Tensor:
        """config.factor_penalty_weight x both fields' VM factor norms (the paper's L_beta term) or roughness
        (config.factor_penalty)."""
        weight = self.config.factor_penalty_weight
        if self.config.factor_penalty == "norm":
            return weight * (self.beta_d.factor_norm() + self.beta_b.factor_norm())
        return weight * (self.beta_d.factor_roughness() + self.beta_b.factor_roughness())

    def box(self) -> tuple[Tensor, Tensor]:
        return self.box_min, self.box_max

    def prior_factor_at(self, points: Tensor) -> Tensor | None:
        if not bool(self.prior_varies):
            return None
        u = self.normalize(points)
        return F.grid_sample(self.prior_factor, u.view(1, -1, 1, 1, 3), align_corners=True).view(-1, 1)

    @torch.enable_grad()
    def set_factor(self, factor: Callable[[Tensor], Tensor], points: Tensor) -> None:
        """The betas become their present (flat) values times `factor`: kept on the box's grid as L_beta's target
        (`factor_grid`), and written into both VM fields by `distill_steps` Adam steps on log beta at random points
        of the box and at `points`, each step a fresh draw."""
        g = self.config.factor_grid
        with torch.no_grad():
            axis = torch.linspace(0, 1, g)
            grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1)  # [G, G, G, 3] as (x, y, z)
            corners = self.box_min + grid.reshape(-1, 3) * (self.box_max - self.box_min)
            self.prior_factor.copy_(factor(corners).float().view(g, g, g).permute(2, 1, 0)[None, None])
            self.prior_varies.fill_(True)
            flat = [x[:1].clone() for x in self.betas(points[:1].float())]
        generator = torch.Generator().manual_seed(0)
        scene = points.float()
        for field_, value in zip((self.beta_d, self.beta_b), flat, strict=True):
            learned = [p.requires_grad for p in field_.parameters()]
            field_.requires_grad_(True)  # also where learn_beta holds the betas: they are held at this start
            optimizer = torch.optim.Adam(field_.parameters(), lr=self.config.distill_lr)
            for _ in range(self.config.distill_steps):
                inside = self.box_min + torch.rand(1024, 3, generator=generator) * (self.box_max - self.box_min)
                where = torch.cat([inside, scene[torch.randint(len(scene), (1024,), generator=generator)]])
                with torch.no_grad():
                    target = (value * self.prior_factor_at(where)).log()
                loss = (field_(self.normalize(where)).clamp_min(1e-8).log() - target).square().mean()
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
            for p, flag in zip(field_.parameters(), learned, strict=True):
                p.requires_grad_(flag)
            field_.hold_start()

    def normalize(self, x: Tensor) -> Tensor:
        """World points [N, 3] -> [-1, 1]^3 box coordinates (clamped: outside the box reads its border)."""
        return ((x - self.box_min) / (self.box_max - self.box_min) * 2 - 1).clamp(-1, 1)

    def betas(self, x: Tensor) -> tuple[Tensor, Tensor]:
        u = self.normalize(x)
        if use_compiled(self.kernels, u):  # both fields in one pass: they share the points' cell lookups
            both = vm_read(u, [self.beta_d.factors(), self.beta_b.factors()])
            return both[:, 0], both[:, 1]
        return self.beta_d(u), self.beta_b(u)

    def ray_betas(self, origin: Tensor, dirs: Tensor, ranges: Tensor) -> tuple[Tensor, Tensor]:
        """The mean over S = ray_samples midpoint samples (the Beer-Lambert integral for a varying medium)."""
        s = self.config.ray_samples
        t = (torch.arange(s, device=dirs.device, dtype=dirs.dtype) + 0.5) / s  # [S]
        points = origin + dirs[:, None, :] * (ranges[:, None, None] * t[None, :, None])  # [P, S, 3]
        beta_d, beta_b = self.betas(points.reshape(-1, 3))
        if s == 1:  # the mean of one sample is the sample: no copy, no backward pass for it
            return beta_d, beta_b
        return beta_d.view(-1, s, 3).mean(dim=1), beta_b.view(-1, s, 3).mean(dim=1)


class HomogeneousMedium(MediumField):
    """One beta_D, beta_B [3] (softplus of a free parameter, so >= 0) and B_inf [3] everywhere."""

    def __init__(self, config: HomogeneousMediumConfig, points: Tensor | None = None,
                 camera_centers: Tensor | None = None, kernels: Kernels = "compiled"):
        super().__init__(config)  # a homogeneous medium needs no box and no kernel: those are not used
        prior = softplus_inverse(torch.tensor(config.beta_prior, dtype=torch.float32))
        self.beta_d_raw = nn.Parameter(prior.clone(), requires_grad=config.learn_beta)
        self.beta_b_raw = nn.Parameter(prior.clone(), requires_grad=config.learn_beta)

    def betas(self, x: Tensor) -> tuple[Tensor, Tensor]:
        shape = (x.shape[0], 3)
        return F.softplus(self.beta_d_raw).expand(shape), F.softplus(self.beta_b_raw).expand(shape)

    def ray_betas(self, origin: Tensor, dirs: Tensor, ranges: Tensor) -> tuple[Tensor, Tensor]:
        return self.betas(dirs)  # the same along every ray

    def beta_parameters(self) -> list[nn.Parameter]:
        return [self.beta_d_raw, self.beta_b_raw]

    @torch.no_grad()
    def set_homogeneous(self, beta_d: Tensor | None, beta_b: Tensor | None, b_inf: Tensor) -> None:
        for raw, beta in ((self.beta_d_raw, beta_d), (self.beta_b_raw, beta_b)):
            if beta is not None:
                raw.copy_(softplus_inverse(beta.to(raw).clamp_min(1e-4)))
        self.b_inf.copy_(b_inf.to(self.b_inf))


grid_spec = FieldSpec("medium-grid", "Underwater medium: beta_D, beta_B as VM-decomposed RGB grids, and B_inf (the "
                      "paper)", MediumGridConfig(), kind="medium")
homogeneous_spec = FieldSpec("medium-homogeneous", "Underwater medium: one beta_D, beta_B and B_inf per channel "
                             "(SeaSplat-style)", HomogeneousMediumConfig(), kind="medium")
