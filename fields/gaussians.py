"""The 3D Gaussian scene model: means, scales, rotations, opacities and SH colour coefficients."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from uw3dgs.config import InstantiateConfig, Target, target
from uw3dgs.kernels.policy import Kernels, use_compiled
from uw3dgs.kernels.sh_colors import sh_colors
from uw3dgs.options import check_number
from uw3dgs.registry import FieldSpec
from uw3dgs.render.sh import MAX_DEGREE, eval_sh_split, rgb_to_sh
from uw3dgs.utils.profiling import section

PARAM_NAMES = ("means", "scales", "quats", "opacities", "sh0", "shN")


@dataclass(frozen=True)
class GaussianFieldConfig(InstantiateConfig):
    _target: Target = target(lambda: GaussianField)
    sh_degree: int = 3
    """Highest spherical-harmonics degree of the view-dependent colour."""
    sh_degree_interval: int = 1000
    """Steps between raising the active SH degree by one (3DGS's progressive schedule)."""
    init_opacity: float = 0.1
    """Opacity of every initial Gaussian."""
    init_scale_neighbours: int = 3
    """Initial scale = mean distance to this many nearest initial points (isotropic)."""

    def check_options(self) -> None:
        super().check_options()
        check_number(self, "sh_degree", ge=0, le=MAX_DEGREE, integer=True)
        check_number(self, "sh_degree_interval", ge=1, integer=True)
        check_number(self, "init_opacity", gt=0, lt=1)
        check_number(self, "init_scale_neighbours", ge=1, integer=True)


def mean_neighbour_distance(points: Tensor, k: int, chunk: int = 2048) -> Tensor:
    """Mean distance of each point to its k nearest others (chunked brute force: no extra dependency)."""
    out = torch.empty(len(points), dtype=points.dtype)
    k = min(k, len(points) - 1)
    if k < 1:
        return torch.ones(len(points), dtype=points.dtype)
    for start in range(0, len(points), chunk):
        d = torch.cdist(points[start:start + chunk], points)
        nearest = d.topk(k + 1, largest=False).values[:, 1:]  # drop the point itself
        out[start:start + chunk] = nearest.mean(dim=1)
    return out


class GaussianField(nn.Module):
    """N anisotropic Gaussians; parameters are stored unconstrained (log-scale, logit opacity).

    Built as `config.setup(points=[P, 3], colors=[P, 3] in [0, 1], kernels=...)`: one Gaussian per initial point;
    `kernels` (the model's `--model.kernels`) chooses the compiled colours or PyTorch's."""

    param_names = PARAM_NAMES
    """The per-Gaussian parameters (each [N, ...]), in the order density control and checkpoints use."""

    def __init__(self, config: GaussianFieldConfig, points: Tensor, colors: Tensor, kernels: Kernels = "compiled"):
        super().__init__()
        self.config = config
        self.kernels = kernels
        n = len(points)
        if n == 0:
            raise ValueError("cannot initialise Gaussians from an empty point cloud")
        points = points.float()
        dist = mean_neighbour_distance(points, config.init_scale_neighbours).clamp_min(1e-7)
        num_rest = (config.sh_degree + 1) ** 2 - 1
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
        self.means = nn.Parameter(points.clone())
        self.scales = nn.Parameter(torch.log(dist)[:, None].repeat(1, 3))
        self.quats = nn.Parameter(quats)
        self.opacities = nn.Parameter(torch.logit(torch.full((n,), config.init_opacity)))
        self.sh0 = nn.Parameter(rgb_to_sh(colors.float().clamp(0, 1))[:, None, :])
        self.shN = nn.Parameter(torch.zeros(n, num_rest, 3))
        # a buffer, so checkpoints carry it and a loaded model renders with the degree it trained with
        self.register_buffer("active_sh_degree", torch.tensor(0))

    @property
    def num_gaussians(self) -> int:
        return self.means.shape[0]

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {name: [getattr(self, name)] for name in PARAM_NAMES}

    def set_step(self, step: int) -> None:
        self.active_sh_degree.fill_(min(step // self.config.sh_degree_interval, self.config.sh_degree))

    def colors(self, camera_center: Tensor) -> Tensor:
        """View-dependent RGB of every Gaussian seen from `camera_center`, [N, 3], >= 0."""
        with section("sh colours"):
            degree = int(self.active_sh_degree)
            if use_compiled(self.kernels, self.means):
                return sh_colors(self.means, camera_center, self.sh0[:, 0], self.shN, degree)
            dirs = torch.nn.functional.normalize(self.means - camera_center, dim=-1)
            return (eval_sh_split(degree, self.sh0[:, 0], self.shN, dirs) + 0.5).clamp_min(0.0)

    def activated(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(means, scales, quaternions, opacities) as the rasterizer takes them. The quaternions (w, x, y, z) are the
        parameters as they are, not normalised: every backend normalises them itself, with the gradient through
        it, so normalising here too would only add passes over N x 4 values and their backward."""
        return self.means, torch.exp(self.scales), self.quats, torch.sigmoid(self.opacities)

    def set_params(self, values: dict[str, Tensor]) -> dict[str, tuple[nn.Parameter, nn.Parameter]]:
        """Replace parameters by new tensors (densification); returns name -> (old, new) for the optimizer."""
        swapped = {}
        for name, value in values.items():
            old = getattr(self, name)
            new = nn.Parameter(value.detach().contiguous(), requires_grad=old.requires_grad)
            setattr(self, name, new)
            swapped[name] = (old, new)
        return swapped

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        """Checkpoints hold however many Gaussians training had reached: resize before loading."""
        for name in PARAM_NAMES:
            if prefix + name in state_dict:
                setattr(self, name, nn.Parameter(torch.empty_like(state_dict[prefix + name])))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

field_spec = FieldSpec("gaussians", "3D Gaussians with SH colour (3DGS)", GaussianFieldConfig(), kind="gaussians")
