"""Per-parameter-group Adam optimizers and learning-rate schedules.

The method names its parameter groups (`Model.param_groups()`); the config gives each group a
learning rate and an optional schedule. One Adam per group, as nerfstudio does, so densification can
resize one group's parameters and Adam moments without touching the others.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from uw3dgs.options import CheckedConfig, OptionError, check_number
from uw3dgs.utils.profiling import section


@dataclass(frozen=True)
class ParamGroupConfig(CheckedConfig):
    lr: float
    eps: float = 1e-15
    """Adam epsilon; 3DGS uses 1e-15 so that tiny gradients still move parameters."""
    scale_by_scene_extent: bool = False
    """Multiply the learning rates by the scene's extent (3DGS does so for Gaussian positions)."""
    lr_final: float | None = None
    """If set, the rate decays log-linearly from lr to lr_final (3DGS's position schedule); else constant."""
    decay_steps: int | None = None
    """Steps of the decay; None follows --max-num-iterations."""
    betas: tuple[float, float] = (0.9, 0.999)
    """Adam's moment decay rates (PyTorch's defaults)."""
    max_grad_norm: float | None = None
    """If set, the group's gradients are scaled down to at most this total norm before each step (nerfstudio's
    max_norm); else left as they are."""

    def check_options(self) -> None:
        check_number(self, "lr", ge=0)  # 0 freezes the group (e.g. the oracle medium of --model.medium.init truth)
        check_number(self, "eps", ge=0)
        check_number(self, "lr_final", gt=0, optional=True)
        check_number(self, "decay_steps", ge=1, integer=True, optional=True)
        check_number(self, "betas", ge=0, lt=1, each=True)
        check_number(self, "max_grad_norm", gt=0, optional=True)
        if self.lr_final is not None and self.lr == 0:
            raise OptionError("lr", "must be > 0 when lr_final is set (the rate decays from lr to lr_final on a "
                                    "log scale), got 0")


def exponential_decay(step: int, lr_init: float, lr_final: float, max_steps: int) -> float:
    t = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1 - t) + math.log(lr_final) * t)


def _fusable(params: list[nn.Parameter]) -> bool:
    """Adam's fused kernel (one pass per tensor instead of one per operation; timings in docs/performance.md)
    where PyTorch has one for these tensors; the same update to float rounding."""
    return all(p.device.type in ("cpu", "cuda") and p.dtype in (torch.float32, torch.float64) for p in params)


class Optimizers:
    """Named Adam optimizers, one per parameter group, with their schedules."""

    def __init__(self, configs: dict[str, ParamGroupConfig], params: dict[str, list[nn.Parameter]],
                 scene_extent: float, max_num_iterations: int):
        missing = set(params) - set(configs)
        if missing:
            raise ValueError(f"no optimizer config for parameter group(s) {sorted(missing)}")
        self.configs = configs
        self.max_num_iterations = max_num_iterations
        self.base_lr = {n: c.lr * (scene_extent if c.scale_by_scene_extent else 1.0) for n, c in configs.items()
                        if n in params}
        self.optimizers = {n: self._adam(n, p) for n, p in params.items()}
        self.schedule_origin: dict[str, int] = {}
        """Per group, the step its decay restarted from (`restart`); 0 where it never did."""

    def _adam(self, name: str, params: list[nn.Parameter]) -> torch.optim.Adam:
        config = self.configs[name]
        return torch.optim.Adam(params, lr=self.base_lr[name], eps=config.eps, betas=tuple(config.betas),
                                fused=_fusable(params))

    def lr(self, name: str, step: int) -> float:
        config = self.configs[name]
        if config.lr_final is None:
            return self.base_lr[name]
        scale = self.base_lr[name] / config.lr
        steps = config.decay_steps or self.max_num_iterations
        return exponential_decay(step - self.schedule_origin.get(name, 0), self.base_lr[name],
                                 config.lr_final * scale, steps)

    def restart(self, name: str, params: list[nn.Parameter], step: int) -> None:
        """A fresh Adam (no moments) for group `name` over `params`, its decay starting again after `step` (TensoRF
        does so whenever its grids are resampled)."""
        self.optimizers[name] = self._adam(name, params)
        self.schedule_origin[name] = step

    def set_step(self, step: int) -> None:
        for name, opt in self.optimizers.items():
            for group in opt.param_groups:
                group["lr"] = self.lr(name, step)

    def zero_grad(self) -> None:
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)

    @section("Adam")
    def step(self) -> None:
        for name, opt in self.optimizers.items():
            max_norm = self.configs[name].max_grad_norm
            if max_norm is not None:
                torch.nn.utils.clip_grad_norm_([p for g in opt.param_groups for p in g["params"]], max_norm)
            opt.step()

    def state_dict(self) -> dict[str, Any]:
        return {name: opt.state_dict() for name, opt in self.optimizers.items()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for name, opt in self.optimizers.items():
            fused = [group["fused"] for group in opt.param_groups]
            opt.load_state_dict(state[name])
            # loading takes the saved groups' flags: keep the kernel this optimizer was built with (a checkpoint
            # of an unfused Adam resumes fused, and the resumed steps equal an uninterrupted fused run's)
            for group, flag in zip(opt.param_groups, fused, strict=True):
                group["fused"] = flag
                for param in group["params"] if flag else ():
                    if "step" in opt.state.get(param, {}):
                        opt.state[param]["step"] = opt.state[param]["step"].to(param.device, torch.float32)

    # -- surgery for densification: parameters change size, Adam moments must follow --

    def replace_param(self, name: str, old: nn.Parameter, new: nn.Parameter, moments_fn) -> None:
        """Swap `old` for `new` in group `name`; `moments_fn(tensor) -> tensor` maps each Adam moment."""
        opt = self.optimizers[name]
        state = opt.state.pop(old, None)
        for group in opt.param_groups:
            group["params"] = [new if p is old else p for p in group["params"]]
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                state[key] = moments_fn(state[key])
            opt.state[new] = state
