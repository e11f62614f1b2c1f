"""One view of a trained model as an image, with the water control.

The water control changes the medium at render time only (the model is read, never written):

    I_k = J exp(-k beta_D z) + B (alpha (1 - exp(-k beta_B z)) + (1 - alpha) [k > 0])

J the water-free image (URI, no background), alpha its coverage, z the range in dataset units (range x
dataset_scale), beta_D, beta_B the learned betas ray-averaged per pixel, B the veiling light chosen in the GUI. With
k = 1 and B the learned B_inf this is the model's own formation (`fields/medium.py` `form_underwater_image`), so the
viewer shows the model's UWI; k = 0 removes the water (open water, at infinite range, then goes dark too: I_0 = J,
the URI); k > 1 is murkier water.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.fields.medium import form_underwater_image
from uw3dgs.utils.visualize import depth_to_image

MEDIUM_OUTPUTS = ("UWI", "URI", "depth", "attenuation", "backscatter")
"""What the output switch offers for a model with a medium: the underwater image, the water-free one, the range
(turbo, near = red), and the formation's two terms exp(-k beta_D z) and B (...) as RGB images."""
PLAIN_OUTPUTS = ("RGB", "depth")
"""... and for a model without one (3dgs, uw3dgs-no-medium)."""


@dataclass(frozen=True)
class Water:
    """The water control: `k` >= 0 scales beta_D and beta_B; `b_inf` (RGB in [0, 1]) replaces the learned B_inf,
    None keeps it."""

    k: float = 1.0
    b_inf: tuple[float, float, float] | None = None


def has_medium(model: Any) -> bool:
    """Whether the model renders water (a uw3dgs model with its medium on)."""
    return getattr(model, "medium", None) is not None


def available_outputs(model: Any) -> tuple[str, ...]:
    return MEDIUM_OUTPUTS if has_medium(model) else PLAIN_OUTPUTS


def learned_b_inf(model: Any) -> tuple[float, float, float] | None:
    """The model's B_inf (RGB), None without a medium."""
    if not has_medium(model):
        return None
    r, g, b = (float(x) for x in model.medium.b_inf.detach().cpu().clamp(0, 1))
    return r, g, b


def form_with_water(uri: Tensor, alpha: Tensor, ranges: Tensor, beta_d: Tensor, beta_b: Tensor, b_inf: Tensor,
                    dataset_scale: float, k: float) -> dict[str, Tensor]:
    """The formation with the betas scaled by `k` (see the module's docstring): 'uwi', 'attenuation', 'backscatter'
    [H, W, 3] from `uri` [H, W, 3], `alpha` [H, W], `ranges` [H, W] (world units), betas [H, W, 3] (per dataset
    unit) and `b_inf` [3]. k = 1 is exactly `form_underwater_image`; k = 0 gives the URI."""
    if k < 0:
        raise ValueError(f"the water factor k must be >= 0, got {k}")
    if k == 0:
        return {"uwi": uri, "attenuation": torch.ones_like(uri), "backscatter": torch.zeros_like(uri)}
    # k = 1 is the model's own image bit for bit: 1.0 * beta is beta exactly
    return form_underwater_image(uri, alpha, ranges, k * beta_d, k * beta_b, b_inf, dataset_scale)


@torch.no_grad()
def render_outputs(model: Any, camera: Camera, water: Water = Water()) -> dict[str, Tensor]:
    """The model seen from `camera`, without gradient, in its evaluation form whatever its train/eval mode (no PAUP
    training branch, no random background), without touching its state or the torch RNG: 'uri' [H, W, 3] (the
    radiance over the background for a model without medium), 'alpha', 'range' [H, W], and with a medium 'uwi',
    'attenuation', 'backscatter' [H, W, 3] formed with `water`."""
    with torch.random.fork_rng(devices=[camera.viewmat.device] if camera.viewmat.device.type == "cuda" else []):
        weights = model.depth_weights() if hasattr(model, "depth_weights") else None
        out = model.render(camera, depth_weights=weights)
        result = {"uri": out["radiance"], "alpha": out["alpha"], "range": out["range"]}
        if not has_medium(model):
            background = 1.0 if getattr(model.config, "background", "black") == "white" else 0.0
            result["uri"] = out["radiance"] + (1.0 - out["alpha"][..., None]) * background
            return result
        beta_d, beta_b = model.ray_betas(camera, out["range"])
        b_inf = model.medium.b_inf if water.b_inf is None else torch.tensor(water.b_inf).to(model.medium.b_inf)
        result.update(form_with_water(out["radiance"], out["alpha"], out["range"], beta_d, beta_b, b_inf,
                                      model.dataset_scale, water.k))
        return result


def to_image(outputs: dict[str, Tensor], output: str) -> np.ndarray:
    """The output switch's choice as an image [H, W, 3] uint8 (colours clipped to [0, 1])."""
    key = {"UWI": "uwi", "URI": "uri", "RGB": "uri", "attenuation": "attenuation", "backscatter": "backscatter"}
    if output == "depth":
        image = depth_to_image(outputs["range"], outputs["alpha"])
    elif output in key and key[output] in outputs:
        image = outputs[key[output]]
    else:
        raise ValueError(f"unknown output {output!r}; this model has {', '.join(sorted(outputs))}")
    return (image.detach().float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


def render_image(model: Any, camera: Camera, output: str, water: Water = Water()) -> np.ndarray:
    """`render_outputs` then `to_image`: what the viewer shows, [H, W, 3] uint8."""
    return to_image(render_outputs(model, camera, water), output)
