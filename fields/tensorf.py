"""`tensorf`: TensoRF's VM-split radiance field (Chen et al. 2022, `models/tensoRF.py` `TensorVMSplit` and the
shading MLP `MLPRender_Fea` of `models/tensorBase.py`), a field of kind 'radiance'.

Three modes pair a plane with a line (axes XY x Z, XZ x Y, YZ x X). At a point x in box coordinates [-1, 1]^3:
    density = act( sum_m sum_r P^sigma_{m,r}(x_plane) L^sigma_{m,r}(x_line) ),  act = ReLU or softplus(. + shift)
    features = B [ P^c_{m,r}(x_plane) L^c_{m,r}(x_line) ]_{m,r}    (B: the appearance basis, no bias)
    colour = sigmoid(MLP([features, viewdir, PE(features), PE(viewdir)]))    (shading 'mlp', `MLPRender_Fea`)
    colour = relu(sum_k features[c, k] Y_k(viewdir) + 0.5), k < 9              (shading 'sh', `SHRender`)
with bilinear planes and linear lines (grid_sample, align_corners=True), as the official code reads them. On CPU
tensors of float32 or float64 the reads are the compiled kernel's (`uw3dgs/kernels/vm_field.py`, `vm_products`) under
`--model.kernels compiled` (the default); `vm_products` below, with grid_sample, is its reference and the path on
CUDA.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from uw3dgs.config import Target, target
from uw3dgs.kernels import vm_field
from uw3dgs.kernels.policy import Kernels, use_compiled
from uw3dgs.options import OptionError, check_number
from uw3dgs.raymarch.field import RadianceField, RadianceFieldConfig
from uw3dgs.registry import FieldSpec
from uw3dgs.render.sh import num_sh_bases, sh_basis

PLANE_AXES = ((0, 1), (0, 2), (1, 2))
"""TensoRF's `matMode`: the two axes of each mode's plane (first along the plane's width)."""
LINE_AXES = (2, 1, 0)
"""TensoRF's `vecMode`: the axis of each mode's line."""
COMPILED_AXES = tuple((b, a, c) for (a, b), c in zip(PLANE_AXES, LINE_AXES, strict=True))
"""Each mode's (plane row, plane column, line) axes, as the compiled read takes them (planes: [R, G_b, G_a])."""
SH_DEGREE = 2
"""TensoRF's `SHRender` evaluates degree-2 harmonics: 9 coefficients per channel, 27 appearance features."""


def positional_encoding(x: Tensor, freqs: int) -> Tensor:
    """TensoRF's encoding: [sin(2^k x), cos(2^k x)] for k < freqs, [..., 2 * freqs * D]."""
    bands = 2.0 ** torch.arange(freqs, device=x.device, dtype=x.dtype)
    scaled = (x[..., None] * bands).reshape(*x.shape[:-1], freqs * x.shape[-1])
    return torch.cat([torch.sin(scaled), torch.cos(scaled)], dim=-1)


def vm_products(planes: nn.ParameterList, lines: nn.ParameterList, x: Tensor) -> list[Tensor]:
    """Per mode m, the products P_{m,r}(x) L_{m,r}(x) [N, R_m] at points `x` [N, 3] in [-1, 1]^3 (planes
    [1, R_m, G_b, G_a], lines [1, R_m, G_c, 1], TensoRF's layout)."""
    out = []
    for m, ((a, b), c) in enumerate(zip(PLANE_AXES, LINE_AXES, strict=True)):
        plane_uv = torch.stack([x[:, a], x[:, b]], dim=-1).reshape(1, -1, 1, 2)
        line_uv = torch.stack([torch.zeros_like(x[:, c]), x[:, c]], dim=-1).reshape(1, -1, 1, 2)
        p = F.grid_sample(planes[m], plane_uv, align_corners=True)[0, :, :, 0]
        q = F.grid_sample(lines[m], line_uv, align_corners=True)[0, :, :, 0]
        out.append((p * q).T)
    return out


def total_variation(plane: Tensor) -> Tensor:
    """TensoRF's `TVLoss` of one plane [1, R, H, W]: 2 (mean squared vertical + mean squared horizontal
    difference). Not kornia's `total_variation`, which sums absolute differences (tests compare where they meet)."""
    _, r, h, w = plane.shape
    dh = (plane[:, :, 1:] - plane[:, :, :-1]).pow(2).sum() / max(r * (h - 1) * w, 1)
    dw = (plane[:, :, :, 1:] - plane[:, :, :, :-1]).pow(2).sum() / max(r * h * (w - 1), 1)
    return 2 * (dh + dw)


@dataclass(frozen=True)
class TensoRFFieldConfig(RadianceFieldConfig):
    """TensoRF's VM-split field; defaults are the official LLFF configuration (`configs/flower.txt`, `opt.py`)."""

    _target: Target = target(lambda: TensoRFField)
    density_components: tuple[int, int, int] = (16, 4, 4)
    """Components per mode of the density (`n_lamb_sigma`)."""
    appearance_components: tuple[int, int, int] = (48, 12, 12)
    """Components per mode of the appearance (`n_lamb_sh`)."""
    appearance_dim: int = 27
    """Outputs of the appearance basis, the shading MLP's feature input (`data_dim_color`)."""
    init_scale: float = 0.1
    """Standard deviation of the random planes and lines at the start (`init_one_svd`'s scale)."""
    density_activation: Literal["relu", "softplus"] = "relu"
    """Density from the summed VM feature (`fea2denseAct`): 'relu' (LLFF config) or 'softplus' of feature + shift."""
    density_shift: float = -10.0
    """Shift inside the softplus activation (`density_shift`; unused by 'relu')."""
    view_pe: int = 0
    """Frequencies of the view direction's encoding in the shading MLP (`view_pe`)."""
    feature_pe: int = 0
    """Frequencies of the features' encoding in the shading MLP (`fea_pe`)."""
    hidden: int = 128
    """Width of the shading MLP's two hidden layers (`featureC`)."""
    shading: Literal["mlp", "sh"] = "mlp"
    """How features become colour (`shadingMode`): 'mlp' the shading MLP (`MLP_Fea`, the LLFF config); 'sh' the
    features as degree-2 spherical harmonics per channel (`SH`: no network, appearance_dim 27)."""

    def check_options(self) -> None:
        super().check_options()
        for name in ("density_components", "appearance_components"):
            check_number(self, name, ge=1, integer=True, each=True)
        for name in ("appearance_dim", "hidden"):
            check_number(self, name, ge=1, integer=True)
        for name in ("view_pe", "feature_pe"):
            check_number(self, name, ge=0, integer=True)
        check_number(self, "init_scale", ge=0)
        check_number(self, "density_shift")
        if self.shading == "sh" and self.appearance_dim != 3 * num_sh_bases(SH_DEGREE):
            n = num_sh_bases(SH_DEGREE)
            raise OptionError("appearance_dim", f"must be {3 * n} with shading 'sh' (3 channels x {n} harmonics), "
                                                f"got {self.appearance_dim}")


class TensoRFField(RadianceField):
    """VM-split density and appearance grids over the box [lo, hi] with `resolution` (X, Y, Z) vertices; `kernels`
    picks the compiled reads or grid_sample (the model's `--model.kernels`)."""

    def __init__(self, config: TensoRFFieldConfig, lo: Tensor, hi: Tensor, resolution: tuple[int, int, int],
                 kernels: Kernels = "compiled"):
        super().__init__()
        self.config = config
        self.kernels = kernels
        self.register_buffer("lo", lo.detach().clone().float())
        self.register_buffer("hi", hi.detach().clone().float())
        self.density_planes, self.density_lines = self._factors(config.density_components, resolution)
        self.app_planes, self.app_lines = self._factors(config.appearance_components, resolution)
        self.basis = nn.Linear(sum(config.appearance_components), config.appearance_dim, bias=False)
        self.mlp: nn.Sequential | None = None
        if config.shading == "mlp":
            inputs = (config.appearance_dim + 3 + 2 * config.feature_pe * config.appearance_dim
                      + 2 * config.view_pe * 3)
            self.mlp = nn.Sequential(nn.Linear(inputs, config.hidden), nn.ReLU(),
                                     nn.Linear(config.hidden, config.hidden), nn.ReLU(), nn.Linear(config.hidden, 3))
            nn.init.zeros_(self.mlp[-1].bias)

    def _factors(self, components: tuple[int, int, int], res: tuple[int, int, int]):
        s = self.config.init_scale
        planes = nn.ParameterList(nn.Parameter(s * torch.randn(1, r, res[b], res[a]))
                                  for r, (a, b) in zip(components, PLANE_AXES, strict=True))
        lines = nn.ParameterList(nn.Parameter(s * torch.randn(1, r, res[c], 1))
                                 for r, c in zip(components, LINE_AXES, strict=True))
        return planes, lines

    def normalize(self, x: Tensor) -> Tensor:
        return (x - self.lo) / (self.hi - self.lo) * 2 - 1

    def products(self, planes: nn.ParameterList, lines: nn.ParameterList, u: Tensor, summed: bool) -> Tensor:
        """The VM products at points `u` [N, 3] in [-1, 1]^3: [N, sum_m R_m] mode by mode, or with `summed` their sum
        [N]; compiled where `kernels` allows, else grid_sample."""
        if use_compiled(self.kernels, u):
            return vm_field.vm_products(u, [p[0] for p in planes], [q[0, :, :, 0] for q in lines], COMPILED_AXES,
                                        summed)
        products = vm_products(planes, lines, u)
        return sum(p.sum(dim=-1) for p in products) if summed else torch.cat(products, dim=-1)

    def density_feature(self, u: Tensor) -> Tensor:
        return self.products(self.density_planes, self.density_lines, u, summed=True)

    def activate(self, feature: Tensor) -> Tensor:
        if self.config.density_activation == "relu":
            return torch.relu(feature)
        return F.softplus(feature + self.config.density_shift)

    def density(self, x: Tensor) -> Tensor:
        return self.activate(self.density_feature(self.normalize(x)))

    def color(self, x: Tensor, viewdirs: Tensor) -> Tensor:
        c = self.config
        features = self.basis(self.products(self.app_planes, self.app_lines, self.normalize(x), summed=False))
        if self.mlp is None:
            harmonics = sh_basis(SH_DEGREE, viewdirs)  # [N, 9]
            return torch.relu((features.view(len(x), 3, -1) * harmonics[:, None, :]).sum(-1) + 0.5)
        inputs = [features, viewdirs]
        if c.feature_pe > 0:
            inputs.append(positional_encoding(features, c.feature_pe))
        if c.view_pe > 0:
            inputs.append(positional_encoding(viewdirs, c.view_pe))
        return torch.sigmoid(self.mlp(torch.cat(inputs, dim=-1)))

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        grids = [*self.density_lines, *self.density_planes, *self.app_lines, *self.app_planes]
        networks = [*self.basis.parameters(), *([] if self.mlp is None else self.mlp.parameters())]
        return {"field_grids": grids, "field_networks": networks}

    def resolution(self) -> tuple[int, int, int]:
        res = [0, 0, 0]
        for line, c in zip(self.density_lines, LINE_AXES, strict=True):
            res[c] = int(line.shape[2])
        return tuple(res)

    @torch.no_grad()
    def upsample(self, resolution: tuple[int, int, int]) -> None:
        """TensoRF's `up_sampling_VM`: planes bilinearly, lines linearly resampled (align_corners=True)."""
        for planes, lines in ((self.density_planes, self.density_lines), (self.app_planes, self.app_lines)):
            for m, ((a, b), c) in enumerate(zip(PLANE_AXES, LINE_AXES, strict=True)):
                planes[m] = nn.Parameter(F.interpolate(planes[m].data, size=(resolution[b], resolution[a]),
                                                       mode="bilinear", align_corners=True))
                lines[m] = nn.Parameter(F.interpolate(lines[m].data, size=(resolution[c], 1), mode="bilinear",
                                                      align_corners=True))

    @torch.no_grad()
    def shrink(self, lo: Tensor, hi: Tensor) -> None:
        """TensoRF's `shrink`: keep the grid vertices from the one nearest `lo` to the one after the one nearest
        `hi` (per axis), and the box they span."""
        res = torch.tensor(self.resolution(), device=self.lo.device)
        units = (self.hi - self.lo) / (res - 1)
        first = torch.round((lo - self.lo) / units).long().clamp(0, None)
        stop = torch.minimum(torch.round((hi - self.lo) / units).long() + 1, res)
        for planes, lines in ((self.density_planes, self.density_lines), (self.app_planes, self.app_lines)):
            for m, ((a, b), c) in enumerate(zip(PLANE_AXES, LINE_AXES, strict=True)):
                lines[m] = nn.Parameter(lines[m].data[:, :, first[c]:stop[c]].contiguous())
                planes[m] = nn.Parameter(planes[m].data[:, :, first[b]:stop[b], first[a]:stop[a]].contiguous())
        new_lo = self.lo + first * units
        new_hi = self.lo + (stop - 1) * units
        self.lo.copy_(new_lo)
        self.hi.copy_(new_hi)

    def regularizers(self) -> dict[str, Tensor]:
        """'tv_density', 'tv_appearance': the planes' total variation summed over modes (TensoRF's `TV_loss_density`,
        `TV_loss_app` before their 1e-2 factor, which the method applies)."""
        return {"tv_density": sum(total_variation(p) for p in self.density_planes),
                "tv_appearance": sum(total_variation(p) for p in self.app_planes)}


def voxels_to_resolution(voxels: int, lo: Tensor, hi: Tensor) -> tuple[int, int, int]:
    """TensoRF's `N_to_reso`: vertices per axis for about `voxels` cubic voxels over the box [lo, hi]."""
    size = (hi - lo).double()
    voxel = (size.prod() / voxels) ** (1.0 / 3.0)
    return tuple(int(v) for v in (size / voxel).long().tolist())


def samples_for(resolution: tuple[int, int, int], step_ratio: float) -> int:
    """TensoRF's `cal_n_samples`: samples per ray for a grid of `resolution` at `step_ratio` voxels per step."""
    return int(math.sqrt(sum(r * r for r in resolution)) / step_ratio)


field_spec = FieldSpec(name="tensorf", description="TensoRF's VM-split density and appearance grids with its shading "
                       "MLP or spherical harmonics (a radiance field).", config=TensoRFFieldConfig(), kind="radiance")
