"""The compiled direction-medium MLP (`uw3dgs/kernels/direction_mlp.py`) against its module: `DirectionMedium`'s
nn.Sequential with PyTorch's sigmoid and softplus under autograd, in float64, outputs and every weight gradient."""

from __future__ import annotations

import pytest
import torch

from uw3dgs.fields.direction_medium import DirectionMedium, DirectionMediumConfig
from uw3dgs.kernels.direction_mlp import direction_mlp
from uw3dgs.render.sh import sh_basis


def reference(medium: DirectionMedium, basis: torch.Tensor) -> torch.Tensor:
    """[P, 9] the packed water of the module's nn.Sequential and PyTorch's activations (autograd throughout)."""
    raw = medium.mlp(basis)
    sigmas = torch.nn.functional.softplus(raw[:, 3:] + medium.config.density_bias)
    return torch.cat([torch.sigmoid(raw[:, :3]), sigmas], dim=1)


def medium_and_inputs(pixels: int, hidden: int, density_bias: float, seed: int = 0):
    torch.manual_seed(seed)
    medium = DirectionMedium(DirectionMediumConfig(hidden_dim=hidden, density_bias=density_bias)).double()
    with torch.no_grad():  # outputs on both sides of softplus's threshold where the bias puts them there
        medium.mlp[-1].bias[3:] += torch.linspace(-1.0, 1.0, 6, dtype=torch.float64)
        medium.mlp[0].weight.mul_(2.0)
    dirs = torch.nn.functional.normalize(torch.randn(pixels, 3, dtype=torch.float64), dim=-1)
    return medium, sh_basis(3, dirs), torch.randn(pixels, 9, dtype=torch.float64)


# pixel counts: below one SIMD vector, not a multiple of the SIMD width, several blocks with a short last one
@pytest.mark.parametrize("pixels", [5, 37, 1001])
@pytest.mark.parametrize(("dtype", "tolerance"), [(torch.float64, 1e-12), (torch.float32, 1e-5)])
@pytest.mark.parametrize("density_bias", [0.0, 19.5])  # 19.5: raw values on both sides of softplus's threshold 20
def test_compiled_mlp_equals_the_module(pixels: int, dtype: torch.dtype, tolerance: float, density_bias: float):
    """Outputs and the gradients of every weight and bias against the float64 module, relative to each tensor's
    largest value."""
    medium, basis, weights = medium_and_inputs(pixels, 16, density_bias)
    want = reference(medium, basis)
    want_grads = torch.autograd.grad((want * weights).sum(), list(medium.parameters()))
    compiled = DirectionMedium(medium.config, kernels="compiled").to(dtype)
    compiled.load_state_dict(medium.state_dict())
    params = [p for layer in compiled.mlp if isinstance(layer, torch.nn.Linear) for p in (layer.weight, layer.bias)]
    got = direction_mlp(basis.to(dtype), *params, density_bias)
    got_grads = torch.autograd.grad((got * weights.to(dtype)).sum(), params)
    for g, w in zip([got, *got_grads], [want, *want_grads], strict=True):
        assert g.dtype == dtype and g.shape == w.shape
        assert float((g.detach().double() - w.detach()).abs().max()) <= tolerance * float(w.detach().abs().max())


def test_compiled_mlp_is_the_fields_path_and_bitwise_the_same_on_any_thread_count():
    """`DirectionMedium.packed` takes the compiled kernel under 'compiled' and PyTorch under 'torch' (the same numbers
    to float rounding); with enough pixels for several chunks of the backward, 1 and 2 threads give bitwise the same
    outputs and gradients."""
    medium, _, _ = medium_and_inputs(1, 32, 0.0)
    medium = medium.float()
    dirs = torch.nn.functional.normalize(torch.randn(150, 140, 3), dim=-1)
    weights = torch.randn(150, 140, 9)

    def run(kernels: str) -> list[torch.Tensor]:
        medium.kernels = kernels
        out = medium.packed(dirs)
        made_by = type(out.grad_fn.next_functions[0][0]).__name__  # out: a view of the function's output
        assert made_by == ("_DirectionMLPBackward" if kernels == "compiled" else "_WaterHeadsBackward")
        return [out.detach(), *torch.autograd.grad((out * weights).sum(), list(medium.parameters()))]

    threads, runs = torch.get_num_threads(), []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            runs.append(run("compiled"))
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(runs[0], runs[1], strict=True))
    for a, b in zip(runs[0], run("torch"), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5 * float(b.abs().max()))


def test_compiled_mlp_gradcheck_and_its_input_contract():
    """gradcheck on a tiny case (every weight); an input that needs a gradient is refused (the kernel gives it none)
    and an input width that is no SH encoding is named."""
    torch.manual_seed(0)
    x = sh_basis(1, torch.nn.functional.normalize(torch.randn(7, 3, dtype=torch.float64), dim=-1))
    w1, b1, w2, b2 = (torch.randn(*shape, dtype=torch.float64, requires_grad=True)
                      for shape in ((3, 4), (3,), (9, 3), (9,)))
    assert torch.autograd.gradcheck(lambda *w: direction_mlp(x, *w, 0.5), (w1, b1, w2, b2))
    with pytest.raises(ValueError, match="no gradient to its input"):
        direction_mlp(x.clone().requires_grad_(True), w1, b1, w2, b2, 0.0)
    with pytest.raises(RuntimeError, match="1, 4, 9 or 16"):
        direction_mlp(x[:, :2].contiguous(), w1[:, :2].contiguous(), b1, w2, b2, 0.0)
