"""The one policy choosing between the compiled CPU kernels and their PyTorch references (`--model.kernels`)."""

from __future__ import annotations

from typing import Literal

from torch import Tensor

from uw3dgs.kernels.build import runs_on

Kernels = Literal["compiled", "torch"]
"""'compiled': each compiled CPU kernel where it runs (CPU tensors of float32 or float64, the module built), its
PyTorch reference elsewhere (on CUDA, or where the build failed); 'torch': the PyTorch references everywhere (the
tests' oracle; the same numbers to float rounding, slower on CPU)."""


def use_compiled(kernels: Kernels, tensor: Tensor) -> bool:
    """Whether a kernel should run compiled on `tensor` under the policy `kernels`."""
    return kernels == "compiled" and runs_on(tensor)
