"""The scene field a ray-marching method renders: density and colour at points of a box (registry kind 'radiance').

A field plugin registers `FieldSpec(name, description, config, kind="radiance")` under `uw3dgs.fields`; its config
derives from `RadianceFieldConfig` and is built with `setup(lo=[3], hi=[3], resolution=(X, Y, Z), kernels=...)`: the box
it covers, in the space the method's sampler puts its points in (the world, or NDC), the grid size a grid field starts
at, and the model's `--model.kernels` policy (a field with compiled reads follows it; others may ignore it).
A grid field also implements the optional grid hooks (`resolution`, `upsample`, `shrink`, `regularizers`); a field
without a grid keeps the defaults.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor, nn

from uw3dgs.config import InstantiateConfig


@dataclass(frozen=True)
class RadianceFieldConfig(InstantiateConfig):
    """A radiance field's knobs; `setup(lo=..., hi=..., resolution=..., kernels=...)` builds it over [lo, hi]."""


class RadianceField(nn.Module):
    """Density and view-dependent colour over a box. Buffers `lo`, `hi` [3]: the box it covers now."""

    lo: Tensor
    hi: Tensor

    def density(self, x: Tensor) -> Tensor:
        """Density [N] >= 0 at points `x` [N, 3] inside the box, per unit of the sampler's intervals."""
        raise NotImplementedError

    def color(self, x: Tensor, viewdirs: Tensor) -> Tensor:
        """Colour [N, 3] in [0, 1] at points `x` [N, 3] inside the box seen along unit `viewdirs` [N, 3]."""
        raise NotImplementedError

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        """Named parameter groups (the method's optimizer configs give each its learning rate)."""
        raise NotImplementedError

    def resolution(self) -> tuple[int, int, int] | None:
        """Grid vertices per axis (X, Y, Z), None for a field without a grid."""
        return None

    def upsample(self, resolution: tuple[int, int, int]) -> None:
        """Resample the grid to `resolution` vertices per axis (the parameters are replaced)."""

    def shrink(self, lo: Tensor, hi: Tensor) -> None:
        """Crop the field to the sub-box [lo, hi] of its box (a grid field snaps it to its grid and updates `lo`,
        `hi`). Default: nothing cropped."""

    def regularizers(self) -> dict[str, Tensor]:
        """Unweighted regularisation terms by name (e.g. total variation of the grids). Default: none."""
        return {}
