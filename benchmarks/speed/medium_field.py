"""The medium's VM fields read at every pixel: the compiled kernel (uw3dgs), PyTorch channel-major, row-major.

    MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000 python benchmarks/speed/medium_field.py
    python benchmarks/speed/medium_field.py --points 19608

Times forward + backward of beta_D and beta_B at P ray midpoints (`MediumGrid.ray_betas` with S = 1, the
range differentiable as in training; 19,608 = the 172x114 pixels of IUI3-RedSea at --downscale-factor 8),
one thread, best of `--repeats`, each way, and checks the first and last agree. The row-major form, [N, 3R]
features times the basis (how uw3dgs did it first), makes the plane x line products and their backward work on
transposed, strided data; channel-major PyTorch is the reference and the CUDA path; the compiled kernel
(uw3dgs/kernels/vm_field.py, `--model.kernels compiled`) reads both fields in one C++ pass per point. Whole
training steps: `benchmarks/speed/training_step.py`, `benchmarks/speed/step_profile.py`.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from timing import compare_cli  # benchmarks/speed/timing.py, next to this script
from torch import Tensor

from uw3dgs.fields.medium import VM_MODES, MediumGrid, MediumGridConfig, VMField

CHANNEL_MAJOR = VMField.forward
COMPILED = "compiled"
"""The way that reads with the compiled kernel (`--model.kernels compiled`), VMField.forward left channel-major."""


def forward_row_major(field: VMField, x: Tensor) -> Tensor:
    """The baseline, as uw3dgs computed it before: each mode's products transposed to [N, R] and concatenated
    into [N, 3R] features, then times the basis."""
    feats = []
    for m, ((a, b), c) in enumerate(VM_MODES):
        plane_grid = torch.stack([x[:, b], x[:, a]], dim=-1).view(1, -1, 1, 2)
        plane = F.grid_sample(field.planes[m][None], plane_grid, align_corners=True).view(-1, x.shape[0])
        line_grid = torch.stack([torch.zeros_like(x[:, c]), x[:, c]], dim=-1).view(1, -1, 1, 2)
        line = F.grid_sample(field.lines[m][None, :, :, None], line_grid, align_corners=True).view(-1, x.shape[0])
        feats.append((plane * line).T)
    return F.softplus(torch.cat(feats, dim=-1) @ field.basis.T + field.bias)


def field_pass(points: int, compiled: bool, seed: int = 0) -> tuple[Callable[[], None], list[Tensor]]:
    """Forward + backward of both fields at `points` ray midpoints of a random, non-flat medium; the list holds
    the last call's betas and gradients (ranges and every factor)."""
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    medium = MediumGrid(MediumGridConfig(), -torch.ones(3), torch.ones(3), "compiled" if compiled else "torch")
    with torch.no_grad():
        for field in (medium.beta_d, medium.beta_b):
            field.basis.normal_(generator=g)
    dirs = F.normalize(torch.randn(points, 3, generator=g), dim=-1)
    ranges = torch.rand(points, generator=g).requires_grad_()
    weights = torch.rand(points, 6, generator=g)
    last: list[Tensor] = []

    def run() -> None:
        medium.zero_grad()
        ranges.grad = None
        beta_d, beta_b = medium.ray_betas(torch.zeros(3), dirs, ranges)
        (torch.cat([beta_d, beta_b], dim=-1) * weights).sum().backward()
        last[:] = [beta_d.detach(), beta_b.detach(), ranges.grad,
                   *(p.grad for p in medium.parameters() if p.grad is not None)]

    return run, last


def field_pass_with(way: Callable | str, n: int) -> tuple[Callable[[], None], list[Tensor]]:
    VMField.forward = CHANNEL_MAJOR if way == COMPILED else way
    return field_pass(n, compiled=way == COMPILED)


def main() -> None:
    compare_cli(__doc__, "--points", 19_608, "beta_D and beta_B at {n} points, forward + backward, R = 16, G = 64, "
                "1 thread", {"row-major (first)": forward_row_major, "channel-major PyTorch": CHANNEL_MAJOR,
                             "compiled kernel (uw3dgs)": COMPILED},
                field_pass_with)


if __name__ == "__main__":
    main()
