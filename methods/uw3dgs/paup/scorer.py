"""The learned part of PAUP: PUS_i = w_u U_i + w_p P_i and the floater probability m_i = sigmoid(phi(PUS_i)),
and the relaxed-Bernoulli keep mask that lets gradients reach them."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from uw3dgs.kernels.paup_scorer import floater_probability
from uw3dgs.kernels.policy import Kernels, use_compiled

MONOTONE_FLOOR = 1e-4
"""Starting weight of the monotone phi's output units that the plain phi starts at 0 (a softplus reaches 0 only
in the limit)."""


class FloaterScorer(nn.Module):
    """w_u, w_p (kept positive through a softplus: they weight L_beta, where a negative PUS would push beta away
    from its prior) and phi, a 2-layer MLP (1 -> hidden -> ReLU -> 1).

    `monotone`: phi's weights pass through a softplus, so m never falls as PUS rises (the paper's reading of m:
    a higher score, a likelier floater). Unconstrained, L_PAPSL teaches phi the opposite (docs/methods/uw3dgs.md,
    "Is m a floater score?"): dropping a floater changes the training image, dropping a hidden Gaussian does not."""

    def __init__(self, hidden_units: int, init_weight: float, init_score: float, init_sharpness: float,
                 monotone: bool = False, kernels: Kernels = "compiled"):
        super().__init__()
        self.kernels = kernels
        """phi compiled where `use_compiled` says so."""
        raw = math.log(math.expm1(init_weight))  # softplus^-1
        self.raw_w_u = nn.Parameter(torch.tensor(raw))
        self.raw_w_p = nn.Parameter(torch.tensor(raw))
        self.monotone = monotone
        # drawn from a copy of the global generator: adding the branch leaves every other random draw of the run
        # as it was (a run whose PAUP never starts is the no-paup run, bit for bit)
        with torch.random.fork_rng(devices=[]):
            self.phi = nn.Sequential(nn.Linear(1, hidden_units), nn.ReLU(), nn.Linear(hidden_units, 1))
        with torch.no_grad():
            # phi starts as sharpness * (PUS - init_score) for PUS >= 0 (m = 1/2 at init_score, rising with the
            # score); the other hidden units start as kinks spread over [0, 2 init_score] with no say yet
            hidden, out = self.phi[0], self.phi[2]
            hidden.weight.fill_(1.0)
            hidden.bias.copy_(-torch.linspace(0.0, 2.0 * init_score, hidden_units))
            out.weight.fill_(MONOTONE_FLOOR if monotone else 0.0)
            out.weight[0, 0] = init_sharpness
            out.bias.fill_(-init_sharpness * init_score)
            if monotone:  # the parameters hold softplus^-1 of the weights
                hidden.weight.copy_(_softplus_inverse(hidden.weight))
                out.weight.copy_(_softplus_inverse(out.weight))

    @property
    def w_u(self) -> Tensor:
        return nn.functional.softplus(self.raw_w_u)

    @property
    def w_p(self) -> Tensor:
        return nn.functional.softplus(self.raw_w_p)

    def phi_weights(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """phi's (hidden weight [h, 1], hidden bias [h], output weight [1, h], output bias [1]) as applied."""
        hidden, out = self.phi[0], self.phi[2]
        w1, w2 = hidden.weight, out.weight
        if self.monotone:
            w1, w2 = nn.functional.softplus(w1), nn.functional.softplus(w2)
        return w1, hidden.bias, w2, out.bias

    def score(self, uncertainty: Tensor, implausibility: Tensor) -> Tensor:
        """PUS [N] from U [N] and P [N]."""
        return self.w_u * uncertainty + self.w_p * implausibility

    def forward(self, pus: Tensor) -> Tensor:
        """m [N] in (0, 1), the probability that each Gaussian is a floater."""
        w1, b1, w2, b2 = self.phi_weights()
        if use_compiled(self.kernels, pus):
            return floater_probability(pus.contiguous(), w1[:, 0].contiguous(), b1, w2[0].contiguous(), b2)
        hidden = torch.relu(nn.functional.linear(pus[:, None], w1, b1))
        return torch.sigmoid(nn.functional.linear(hidden, w2, b2))[:, 0]

    def weight_penalty(self) -> Tensor:
        """||phi||^2: the squared norm of all of phi's weights (as applied) and biases."""
        return sum(t.square().sum() for t in self.phi_weights())


def _softplus_inverse(x: Tensor) -> Tensor:
    return x + torch.log(-torch.expm1(-x))  # log(exp(x) - 1), stable for large x


def relaxed_keep_mask(keep_probability: Tensor, temperature: float) -> Tensor:
    """A Gumbel-Softmax (binary Concrete) sample s [N] in (0, 1) of Bernoulli(keep_probability [N]): s =
    sigmoid((logit p + logit u) / temperature), u ~ U(0, 1), p and u clamped to [1e-6, 1 - 1e-6]; differentiable
    in p. (logit u is logistic noise: s > 1/2 exactly when the Bernoulli draw keeps.) Three element-wise passes and
    three back: at a few hundred thousand Gaussians a step, a dozen separate logs and their backwards cost ms."""
    with torch.no_grad():
        noise = torch.logit(torch.rand_like(keep_probability), eps=1e-6)
    return torch.sigmoid((torch.logit(keep_probability, eps=1e-6) + noise) / temperature)
