"""The operations density control is made of, each keeping the optimizers' per-Gaussian state in step (as gsplat's
`strategy/ops.py`): copies of Gaussians, splits, appending new ones, removal, the opacity reset. Strategies (and
another pruning criterion such as PAUP, through them) compose these; none keeps state of its own."""

from __future__ import annotations

import torch
from torch import Tensor

from uw3dgs.render.projection import quat_to_rotmat
from uw3dgs.strategy.base import GaussianParameters, OptimizerSurgery


@torch.no_grad()
def duplicated(g: GaussianParameters, mask: Tensor) -> dict[str, Tensor]:
    """Copies of the Gaussians in `mask` [N] (bool): every parameter's selected rows, detached."""
    return {name: getattr(g, name).detach()[mask] for name in g.param_names}


@torch.no_grad()
def split_samples(g: GaussianParameters, mask: Tensor, samples: int) -> dict[str, Tensor]:
    """Each Gaussian in `mask` [N] (bool) as `samples` smaller ones: means drawn from its own distribution, scales
    divided by 0.8 `samples` (3DGS's 1.6 for two), every other parameter copied."""
    values = {name: getattr(g, name).detach()[mask].repeat_interleave(samples, dim=0) for name in g.param_names}
    scales = torch.exp(values["scales"])
    rot = quat_to_rotmat(values["quats"])
    offsets = torch.einsum("nij,nj->ni", rot, torch.randn_like(scales) * scales)
    values["means"] = values["means"] + offsets
    values["scales"] = torch.log(scales / (0.8 * samples))
    return values


@torch.no_grad()
def append(g: GaussianParameters, optimizers: OptimizerSurgery, values: dict[str, Tensor]) -> None:
    """Add Gaussians (`values`: every parameter's new rows) after the existing ones; their Adam moments start at 0."""
    n_new = values["means"].shape[0]
    if n_new == 0:
        return
    current = {name: getattr(g, name).detach() for name in g.param_names}
    swapped = g.set_params({name: torch.cat([current[name], values[name]]) for name in g.param_names})
    for name, (old, new) in swapped.items():
        optimizers.replace_param(name, old, new, lambda m, n=n_new: torch.cat([m, m.new_zeros((n, *m.shape[1:]))]))


@torch.no_grad()
def remove_all_but(g: GaussianParameters, optimizers: OptimizerSurgery, keep: Tensor) -> None:
    """Remove every Gaussian not in `keep` [N] (bool), with its optimizer state."""
    if bool(keep.all()):
        return
    swapped = g.set_params({name: getattr(g, name).detach()[keep] for name in g.param_names})
    for name, (old, new) in swapped.items():
        optimizers.replace_param(name, old, new, lambda m: m[keep])


@torch.no_grad()
def reset_opacity(g: GaussianParameters, optimizers: OptimizerSurgery, value: float) -> None:
    """Clamp every opacity to at most `value` (in (0, 1)); the opacities' Adam moments restart at 0."""
    limit = torch.logit(torch.tensor(value)).item()
    swapped = g.set_params({"opacities": g.opacities.detach().clamp_max(limit)})
    old, new = swapped["opacities"]
    optimizers.replace_param("opacities", old, new, torch.zeros_like)
