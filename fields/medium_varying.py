"""A medium that varies across the scene, read off how each surface point's colour changes with range.

The homogeneous multi-view fit (fields/medium_multiview.py) flags a medium whose halves of the scene disagree; this
module fits the variation itself from the same observations:

    beta_D(x) = beta_D f(x),  beta_B(x) = beta_B f(x),  f > 0 smooth, its nodes' geometric mean 1,

one f for both betas (a change in turbidity, the particles, scales attenuation and backscatter together). f is a
bilinear grid of K x K nodes over the points' two main axes (across the seabed for a survey; constant along the
third: a layer near the seabed is not seen from one altitude, docs/medium-recovery.md). An observation at range z
sees the mean m of f along its ray from the camera to the point (midpoint rule), so its colour is the homogeneous
model at the path length m z:

    I = J exp(-beta_D m z) + B_inf (1 - exp(-beta_B m z)),   m = Phi c,

with c the node values and Phi [M, K^2] each ray's mean bilinear weights, computed once. beta_D, beta_B, B_inf per
channel, log c and one J per point and channel are fitted jointly by Levenberg-Marquardt under the homogeneous fit's
robust loss (the J eliminated per point by the Schur complement), from the homogeneous fit (c = 1), with a penalty
on the differences of neighbouring log c (`field_smoothness`) that fills nodes no ray crosses and a row that holds
the mean of log c at 0 (the split between beta and f).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from uw3dgs.fields.medium_identifiability import bootstrap_observations, principal_axes
from uw3dgs.fields.medium_multiview import (
    CHANNELS,
    MultiviewConfig,
    MultiviewFit,
    _clean_given,
    _per_point,
    _robust,
)


@dataclass
class FactorField:
    """f(x) [N] > 0 at world points x [N, 3]: bilinear over a K x K grid of nodes along two axes through `center`,
    clamped to the border outside (constant along the third axis)."""

    center: Tensor
    """[3] world units."""
    axes: Tensor
    """[2, 3] unit vectors."""
    ticks: Tensor
    """[2, K] increasing node coordinates along each axis (world units from `center`)."""
    values: Tensor
    """[K, K] the factor at the nodes (node (i, j) at (ticks[0, i], ticks[1, j]))."""

    @classmethod
    def around(cls, positions: Tensor, nodes: int) -> FactorField:
        """A flat field (f = 1) over `positions` [P, 3] along their two main axes, its nodes at evenly spaced
        quantiles of the points' coordinates from the 1st to the 99th percentile: nodes are dense where the points
        are (a survey's points thin out with range)."""
        positions = positions.double()
        center = positions.mean(0)
        axes = principal_axes(positions).double()
        coords = (positions - center) @ axes.T
        q = torch.linspace(0.01, 0.99, nodes, dtype=torch.float64)
        ticks = torch.quantile(coords, q, dim=0).T.contiguous()  # [2, K]
        ticks = torch.maximum(ticks, ticks[:, :1] + 1e-6 * torch.arange(nodes, dtype=torch.float64))
        ticks = torch.cummax(ticks, dim=1).values + 1e-9 * torch.arange(nodes, dtype=torch.float64)
        return cls(center, axes, ticks, torch.ones(nodes, nodes, dtype=torch.float64))

    @property
    def nodes(self) -> int:
        return self.values.shape[0]

    def weights(self, x: Tensor) -> Tensor:
        """[N, K^2] the bilinear weights of the nodes at world points x [N, 3] (each row sums to 1)."""
        k = self.nodes
        coords = (x.double() - self.center) @ self.axes.T  # [N, 2]
        index, frac = [], []
        for a in range(2):
            t = self.ticks[a]
            c = coords[:, a].clamp(float(t[0]), float(t[-1]))
            i0 = (torch.searchsorted(t, c.contiguous(), right=True) - 1).clamp(0, k - 2)
            index.append(i0)
            frac.append((c - t[i0]) / (t[i0 + 1] - t[i0]))
        out = torch.zeros(len(x), k * k, dtype=torch.float64)
        for di in (0, 1):
            for dj in (0, 1):
                w = (frac[0] if di else 1 - frac[0]) * (frac[1] if dj else 1 - frac[1])
                out.scatter_add_(1, ((index[0] + di) * k + index[1] + dj)[:, None], w[:, None])
        return out

    def __call__(self, x: Tensor) -> Tensor:
        return self.weights(x) @ self.values.reshape(-1)

    def ray_weights(self, starts: Tensor, ends: Tensor, samples: int) -> Tensor:
        """[M, K^2] the mean node weights along each segment from starts [M, 3] to ends [M, 3] (midpoint rule, this
        many samples): m = ray_weights @ values is the mean of f along the segment."""
        starts, ends = starts.double(), ends.double()
        total = torch.zeros(len(starts), self.nodes ** 2, dtype=torch.float64)
        for s in range(samples):
            total += self.weights(starts + (ends - starts) * ((s + 0.5) / samples))
        return total / samples

    def with_values(self, values: Tensor) -> FactorField:
        return FactorField(self.center, self.axes, self.ticks, values.reshape(self.nodes, self.nodes))

    def to_json(self) -> dict:
        return {"center": self.center.tolist(), "axes": self.axes.tolist(), "ticks": self.ticks.tolist(),
                "values": self.values.tolist()}


def _node_differences(k: int) -> Tensor:
    """[E + 1, K^2]: a row per pair of neighbouring nodes (their difference), and one row for the mean (the gauge)."""
    rows = []
    for i in range(k):
        for j in range(k):
            for di, dj in ((1, 0), (0, 1)):
                if i + di < k and j + dj < k:
                    row = torch.zeros(k * k, dtype=torch.float64)
                    row[i * k + j], row[(i + di) * k + j + dj] = -1.0, 1.0
                    rows.append(row)
    rows.append(torch.full((k * k,), 1.0 / (k * k), dtype=torch.float64))
    return torch.stack(rows)


@dataclass
class VaryingFit:
    """The fitted medium: beta_D, beta_B (where f = 1) and B_inf [3], the factor field, the points' clean colours."""

    beta_d: Tensor
    beta_b: Tensor
    b_inf: Tensor
    factor: FactorField
    clean: Tensor
    """[P, 3]"""
    iterations: int


def _varying_model(theta: Tensor, u: Tensor, clean: Tensor, point: Tensor, z: Tensor, phi: Tensor,
                   derivatives: bool = True) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """(prediction [C, M], d/dJ [C, M], d/d(theta, u) [C, M, 9 + K^2]) for theta [C, 3] = log(beta_D, beta_B, B_inf),
    u [K^2] = log c, clean colours [C, P]; the derivatives None unless asked for."""
    beta_d, beta_b, b_inf = theta.exp().unbind(-1)
    c = u.exp()
    zm = z * (phi @ c)
    direct = torch.exp(-beta_d[:, None] * zm)
    veiled = torch.exp(-beta_b[:, None] * zm)
    j = clean[:, point]
    pred = j * direct + b_inf[:, None] * (1 - veiled)
    if not derivatives:
        return pred, None, None
    channels = theta.shape[0]
    grad = torch.zeros(channels, len(z), 3 * channels + len(u), dtype=torch.float64)
    d_direct = -j * beta_d[:, None] * direct  # d pred / d (m z) through the direct term, [C, M]
    d_veiled = b_inf[:, None] * beta_b[:, None] * veiled
    for ch in range(channels):
        grad[ch, :, 3 * ch] = d_direct[ch] * zm
        grad[ch, :, 3 * ch + 1] = d_veiled[ch] * zm
        grad[ch, :, 3 * ch + 2] = pred[ch] - j[ch] * direct[ch]
    grad[:, :, 3 * channels:] = ((d_direct + d_veiled) * z)[..., None] * (phi * c)[None]
    return pred, direct, grad


def fit_varying(point: Tensor, color: Tensor, z: Tensor, phi: Tensor, start: MultiviewFit, factor: FactorField,
                weight: Tensor | None = None, held: Tensor | None = None, config: MultiviewConfig | None = None,
                init: VaryingFit | None = None) -> VaryingFit:
    """Fit the varying medium (module doc) to observations color [M, 3] of points point [M] (ids 0..P-1, every id
    present) at ranges z [M] whose rays have mean node weights phi [M, K^2] (`FactorField.ray_weights`), from the
    homogeneous `start` (its loss scale too) with f flat, or from the varying fit `init` (a bootstrap refit).
    `held` [3] bool keeps B_inf of those channels at the start's. Float64; the betas per unit of z."""
    config = config or MultiviewConfig()
    point, z, phi = point.long(), z.double(), phi.double()
    color = color.double().T.contiguous()
    weight = torch.ones_like(z) if weight is None else weight.double()
    num_points, k2 = int(point.max()) + 1, phi.shape[1]
    first = start.medium if init is None else (init.beta_d, init.beta_b, init.b_inf)
    theta = torch.stack([t.double() for t in first], dim=-1).clamp_min(1e-6).log()  # [C, 3]
    u = torch.zeros(k2, dtype=torch.float64) if init is None else init.factor.values.reshape(-1).double().log()
    clean = _clean_given(theta, point, z * (phi @ u.exp()), color, weight, num_points)
    free = torch.ones(3 * 3 + k2, dtype=torch.float64)
    if held is not None:
        free[torch.arange(3)[held.bool()] * 3 + 2] = 0.0
    scale = start.loss_scale.double()[:, None]
    rows = _node_differences(int(round(math.sqrt(k2))))
    # the smoothness penalty in units of the data: per pair of nodes, `field_smoothness` times the robust cost of one
    # observation at the loss scale, times the observations per node
    lam = config.field_smoothness * float(weight.sum()) / k2 * float(scale.square().mean())
    prior_h = lam * rows.T @ rows

    def cost(theta: Tensor, u: Tensor, clean: Tensor) -> Tensor:
        r = _varying_model(theta, u, clean, point, z, phi, derivatives=False)[0] - color
        return (weight * _robust(r, scale, config.loss)[0]).sum() + 0.5 * u @ prior_h @ u

    current, damping, iterations = cost(theta, u, clean), 1e-3, 0
    while iterations < config.max_iterations:
        iterations += 1
        pred, dj, dt = _varying_model(theta, u, clean, point, z, phi)
        r = pred - color
        w = weight * _robust(r, scale, config.loss)[1]
        dt = dt * free
        hjj = _per_point(w * dj * dj, point, num_points)  # [C, P]
        weighted = w[..., None] * dt
        hjt = _per_point((weighted * dj[..., None]).transpose(-1, -2), point, num_points)  # [C, G, P]
        htt = torch.bmm(weighted.transpose(1, 2), dt).sum(0)  # [G, G], as matrix products (BLAS)
        htt[9:, 9:] += prior_h
        gj = _per_point(w * dj * r, point, num_points)
        gt = (weighted * r[..., None]).sum((0, 1))
        gt[9:] += prior_h @ u
        hjj_d = (hjj * (1 + damping)).clamp_min(1e-300)
        htt_d = htt + damping * torch.diag(torch.diagonal(htt)) + torch.diag(1 - free)
        schur = htt_d - torch.einsum("cip,cjp->ij", hjt / hjj_d[:, None], hjt)
        rhs = gt - torch.einsum("cip,cp->i", hjt, gj / hjj_d)
        step = -torch.linalg.solve(schur + 1e-12 * torch.eye(len(free), dtype=torch.float64), rhs) * free
        step_j = -(gj + torch.einsum("cip,i->cp", hjt, step)) / hjj_d
        new_theta = theta + step[:9].view(3, 3).clamp(-2.0, 2.0)
        new_u, new_clean = u + step[9:].clamp(-1.0, 1.0), clean + step_j
        new = cost(new_theta, new_u, new_clean)
        if new < current:
            gain = float((current - new) / current.clamp_min(1e-300))
            theta, u, clean, current = new_theta, new_u, new_clean, new
            damping = max(damping / 3, 1e-9)
            if gain < 1e-7 or float(step.abs().max()) < 1e-6:  # a settled fit; its bootstrap spread is 1e-2
                break
        else:
            damping *= 4
            if damping > 1e8:
                break
    beta_d, beta_b, b_inf = theta.exp().unbind(-1)
    return VaryingFit(beta_d, beta_b, b_inf, factor.with_values(u.exp()), clean.T, iterations)


@dataclass
class VaryingEstimate:
    """The varying fit with its bootstrap: per channel, the relative half-width (5-95%) of beta_D(x), beta_B(x) at
    the fitted points (their median over the points) and of B_inf."""

    fit: VaryingFit
    spread: dict[str, list[float]]
    """'beta_D', 'beta_B', 'B_inf' -> [3]."""
    identified: dict[str, list[bool]]
    """The same keys: spread within the tolerance."""
    factor_range: tuple[float, float]
    """The 5th and 95th percentile of f over the fitted points."""

    @property
    def all_betas_identified(self) -> bool:
        return all(self.identified["beta_D"]) and all(self.identified["beta_B"])

    def lines(self) -> list[str]:
        lo, hi = self.factor_range
        out = [f"multi-view field: the betas vary x{lo:.2f}-x{hi:.2f} across the fitted points "
               f"({self.fit.factor.nodes}x{self.fit.factor.nodes} nodes over the points' main axes)"]
        for name, values in (("beta_D", self.fit.beta_d), ("beta_B", self.fit.beta_b), ("B_inf", self.fit.b_inf)):
            parts = ", ".join(f"{CHANNELS[c]} {float(values[c]):.3f} +-{self.spread[name][c]:.0%}" for c in range(3))
            verdict = "identified by range diversity" if all(self.identified[name]) else "not identified (spread)"
            out.append(f"multi-view field {name} at f = 1 ({parts}): {verdict}")
        return out

    def to_json(self) -> dict:
        return {"medium": {"beta_D": self.fit.beta_d.tolist(), "beta_B": self.fit.beta_b.tolist(),
                           "B_inf": self.fit.b_inf.tolist()},
                "factor": self.fit.factor.to_json(), "spread": self.spread, "identified": self.identified,
                "factor_range": list(self.factor_range)}


def varying_estimate(point: Tensor, color: Tensor, z: Tensor, starts: Tensor, ends: Tensor, weight: Tensor,
                     start: MultiviewFit, positions: Tensor, held: Tensor | None = None,
                     config: MultiviewConfig | None = None) -> VaryingEstimate:
    """The varying fit of observations (ids `point` [M] 0..P-1, colours [M, 3], ranges z [M], rays from starts
    [M, 3] to ends [M, 3] in world units, weights [M]) from the homogeneous fit `start`, over a field spanning
    `positions` [P, 3], with `config.field_resamples` bootstrap refits over points, each started from the whole
    fit (from the homogeneous start each would take as many iterations as the whole fit): their spread is the
    noise around the whole fit's valley of the cost, not a search for another."""
    config = config or MultiviewConfig()
    factor = FactorField.around(positions, config.field_nodes)
    phi = factor.ray_weights(starts, ends, config.field_samples)
    fit = fit_varying(point, color, z, phi, start, factor, weight, held, config)
    generator = torch.Generator().manual_seed(config.seed)
    here = positions.double()
    fields, veils = [], []
    for _ in range(config.field_resamples):
        ids, picked = bootstrap_observations(point, generator)
        refit = fit_varying(ids, color[picked], z[picked], phi[picked], start, factor, weight[picked], held, config,
                            init=fit)
        f = refit.factor(here)[:, None]
        fields.append(torch.stack([refit.beta_d.double() * f, refit.beta_b.double() * f]))  # [2, P, 3]
        veils.append(refit.b_inf.double())
    f = fit.factor(here)[:, None]
    whole = torch.stack([fit.beta_d.double() * f, fit.beta_b.double() * f])
    q = torch.tensor([0.05, 0.95], dtype=torch.float64)
    lo, hi = torch.quantile(torch.stack(fields), q, dim=0)
    field_spread = ((hi - lo) / 2 / whole.clamp_min(1e-9)).median(dim=1).values  # [2, 3]
    vlo, vhi = torch.quantile(torch.stack(veils), q, dim=0)
    veil_spread = (vhi - vlo) / 2 / fit.b_inf.double().clamp_min(1e-9)
    spread = {"beta_D": field_spread[0].tolist(), "beta_B": field_spread[1].tolist(), "B_inf": veil_spread.tolist()}
    identified = {name: [s <= config.tolerance for s in values] for name, values in spread.items()}
    if held is not None:
        identified["B_inf"] = [False if h else i for h, i in zip(held.tolist(), identified["B_inf"], strict=True)]
    ends_f = torch.quantile(fit.factor(here), q)
    return VaryingEstimate(fit, spread, identified, (float(ends_f[0]), float(ends_f[1])))
