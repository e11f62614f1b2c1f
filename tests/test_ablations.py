"""The paper's Table 2 ablations and the `uw3dgs-paper` preset: each differs from its parent in exactly what its name
says, read off the resolved configs of the registered methods."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Any

import pytest
import torch

import uw3dgs.methods.uw3dgs.model as uw3dgs_model
from uw3dgs.registry import METHODS

ABLATION_FIELDS = {
    "no-paup": {"model.use_paup", "optimizers.paup"},
    "no-medium": {"model.use_medium", "model.beta_loss_weight", "model.depth_loss_weight"},
    "no-lbeta": {"model.medium.learn_beta", "model.beta_loss_weight"},
    "no-lz": {"model.depth_loss_weight", "model.uncertainty_weighted_depth"},
}
"""Table 2's rows: what removing one part changes (no-lz: the paper's "unweighted depth computation" too)."""

PAPER_FIELDS = {"model.medium.init", "model.medium.flat_start", "model.medium.factor_penalty",
                "model.medium.factor_penalty_weight",
                "model.paup.normalize_scores", "model.paup.monotone_scorer",
                "model.paup.attenuation_weight", "model.paup.uwi_from_enhanced", "model.paup.prune_schedule",
                "model.paup.prune_min_probability"}
"""Where `uw3dgs-paper` switches `uw3dgs` back to the paper's text (prune_every stays 1 in both)."""


def flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    """Dotted path -> leaf value of a config: dataclass fields and dict keys are descended into."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        items = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    elif isinstance(value, dict):
        items = value
    else:
        return {prefix: value}
    out: dict[str, Any] = {}
    for name, child in items.items():
        out.update(flatten(child, f"{prefix}.{name}" if prefix else str(name)))
    return out


def differing_fields(a: Any, b: Any) -> set[str]:
    """Dotted paths whose values differ, or that only one of the two configs has (the method's name aside); an
    optimizer group's settings count as one field, `optimizers.GROUP`."""
    flat_a, flat_b = flatten(a), flatten(b)
    keys = (flat_a.keys() | flat_b.keys()) - {"method_name"}
    missing = object()
    differ = {k for k in keys if flat_a.get(k, missing) != flat_b.get(k, missing)}
    return {".".join(k.split(".")[:2]) if k.startswith("optimizers.") else k for k in differ}


def test_flatten_sees_nested_and_dict_differences():
    base = METHODS["uw3dgs"].config
    changed = dataclasses.replace(base, model=dataclasses.replace(
        base.model, paup=dataclasses.replace(base.model.paup, prune_every=7)))
    assert differing_fields(base, changed) == {"model.paup.prune_every"}
    fewer = dataclasses.replace(base, optimizers={k: v for k, v in base.optimizers.items() if k != "means"})
    assert differing_fields(base, fewer) == {"optimizers.means"}


@pytest.mark.parametrize("parent", ["uw3dgs", "uw3dgs-paper"])
@pytest.mark.parametrize("suffix", sorted(ABLATION_FIELDS))
def test_each_ablation_differs_from_its_parent_in_what_its_name_says(parent, suffix):
    ablation = METHODS[f"{parent}-{suffix}"].config
    assert ablation.method_name == f"{parent}-{suffix}"
    assert differing_fields(METHODS[parent].config, ablation) == ABLATION_FIELDS[suffix]


def test_the_paper_preset_differs_from_uw3dgs_in_the_paper_knobs_only():
    paper, ours = METHODS["uw3dgs-paper"].config, METHODS["uw3dgs"].config
    assert differing_fields(ours, paper) == PAPER_FIELDS
    assert paper.model.medium.init == "prior" and paper.model.medium.beta_prior == (0.1, 0.15, 0.2)
    medium = paper.model.medium
    assert (medium.flat_start, medium.factor_penalty, medium.factor_penalty_weight) == ("zero-basis", "norm", 0.001)
    p = paper.model.paup
    assert (p.prune_schedule, p.prune_every, p.prune_quantile, p.prune_min_probability) == ("every", 1, 0.95, 0.0)
    assert (p.normalize_scores, p.monotone_scorer, p.attenuation_weight, p.uwi_from_enhanced) == \
        (False, False, 1.0, True)



def started(name: str, make_config, monkeypatch) -> Any:
    """Method `name`'s model on the tiny scene right after the fresh-run start (`initialize_from_data`), with a stand-in
    for the point-based estimate (fields/medium_estimate.py, tested on its own): a medium unlike beta_prior and
    colours unlike the points'."""
    spec = METHODS[name].config
    base = make_config(steps=1)
    datamanager = base.datamanager.setup(data=None)
    scene, train = datamanager.scene, datamanager.train_indices
    estimate = SimpleNamespace(beta_d=torch.tensor([0.4, 0.2, 0.12]), beta_b=torch.tensor([0.3, 0.25, 0.2]),
                               b_inf=torch.tensor([0.05, 0.25, 0.35]), clean_colors=scene.point_colors.flip(-1),
                               observations=(None, None, torch.linspace(1.0, 8.0, 50)), open_water=None)
    monkeypatch.setattr(uw3dgs_model, "estimate_from_views", lambda *args, **kwargs: (estimate, None))
    medium = dataclasses.replace(spec.model.medium, report=False)
    model = dataclasses.replace(spec.model, gaussians=base.model.gaussians, medium=medium).setup(
        scene=scene, train_indices=train)
    model.initialize_from_data(scene, train)
    return model


@pytest.mark.parametrize("parent", ["uw3dgs", "uw3dgs-paper"])
def test_no_lbeta_starts_where_its_parent_starts_and_holds_the_betas(parent, make_config, monkeypatch):
    """The same starting medium and colours (the estimate and its de-hazed colours for `uw3dgs`, beta_prior and the
    points' colours for `uw3dgs-paper`); only the betas are not learned."""
    full, ablated = (started(name, make_config, monkeypatch) for name in (parent, f"{parent}-no-lbeta"))
    probe = torch.rand(300, 3) * (full.medium.box_max - full.medium.box_min) + full.medium.box_min
    for a, b in zip(full.medium.betas(probe), ablated.medium.betas(probe), strict=True):
        torch.testing.assert_close(a, b)
    torch.testing.assert_close(full.medium.b_inf, ablated.medium.b_inf)
    torch.testing.assert_close(full.gaussians.sh0, ablated.gaussians.sh0)
    assert "medium_beta" in full.param_groups() and "medium_beta" not in ablated.param_groups()
    start = torch.tensor(METHODS[parent].config.model.medium.beta_prior if parent == "uw3dgs-paper" else
                         [0.4, 0.2, 0.12])
    torch.testing.assert_close(ablated.medium.betas(probe)[0], start.expand(300, 3), rtol=1e-4, atol=1e-5)
