"""Fields chosen by subcommand (their registry names): the homogeneous medium, the slot, and field plugins."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch
import torch.nn.functional as F

from uw3dgs.cli.eval import EvalArgs, run_eval
from uw3dgs.cli.train import parse_config
from uw3dgs.config import config_from_dict, config_to_dict
from uw3dgs.engine.trainer import Trainer
from uw3dgs.fields.medium import HomogeneousMedium, HomogeneousMediumConfig, MediumGridConfig, softplus_inverse
from uw3dgs.metrics.underwater_quality import uiqm
from uw3dgs.registry import FIELDS, METHODS, FieldSpec


def test_homogeneous_medium_is_one_value_per_channel_everywhere():
    medium = HomogeneousMediumConfig().setup(points=torch.rand(10, 3), camera_centers=torch.rand(2, 3))
    prior = torch.tensor(HomogeneousMediumConfig().beta_prior)
    beta_d, beta_b = medium.ray_betas(torch.zeros(3), F.normalize(torch.randn(7, 3), dim=-1), torch.rand(7) * 9)
    torch.testing.assert_close(beta_d, prior.expand(7, 3))
    torch.testing.assert_close(beta_b, prior.expand(7, 3))
    medium.set_homogeneous(torch.tensor([0.4, 0.3, 0.2]), None, torch.tensor([0.1, 0.2, 0.3]))
    beta_d, beta_b = medium.betas(torch.randn(5, 3) * 100)  # anywhere, also far outside any box
    torch.testing.assert_close(beta_d, torch.tensor([0.4, 0.3, 0.2]).expand(5, 3))
    torch.testing.assert_close(beta_b, prior.expand(5, 3))  # None kept beta_B
    torch.testing.assert_close(medium.b_inf.detach(), torch.tensor([0.1, 0.2, 0.3]))
    assert set(medium.param_groups()) == {"medium_b_inf", "medium_beta"}
    frozen = HomogeneousMedium(HomogeneousMediumConfig(learn_beta=False))
    assert set(frozen.param_groups()) == {"medium_b_inf"} and not frozen.beta_d_raw.requires_grad


def test_homogeneous_medium_regularizer_and_gradients_against_float64():
    """L_beta = weighted mean over points of |beta_D - prior_D|^2 + |beta_B - prior_B|^2 (no factors to penalise),
    and its gradient with respect to the raw parameters against finite differences."""
    medium = HomogeneousMedium(HomogeneousMediumConfig()).double()
    with torch.no_grad():
        medium.beta_d_raw.copy_(torch.tensor([0.3, -1.0, 0.5]))
        medium.beta_b_raw.copy_(torch.tensor([-0.2, 0.1, -2.0]))
    medium.set_prior(torch.tensor([0.2, 0.1, 0.05]), torch.tensor([0.3, 0.2, 0.1]))
    points, weights = torch.randn(6, 3, dtype=torch.float64), torch.rand(6, dtype=torch.float64)
    by_hand = ((F.softplus(medium.beta_d_raw) - medium.prior_d).square().sum()
               + (F.softplus(medium.beta_b_raw) - medium.prior_b).square().sum()) * weights.mean()
    torch.testing.assert_close(medium.regularizer(points, weights), by_hand, rtol=1e-12, atol=1e-12)

    medium.regularizer(points, weights).backward()
    for raw, prior in ((medium.beta_d_raw, medium.prior_d), (medium.beta_b_raw, medium.prior_b)):
        # d/d raw of w (softplus(raw) - prior)^2 = 2 w (softplus(raw) - prior) sigmoid(raw)
        analytic = 2 * weights.mean() * (F.softplus(raw.detach()) - prior) * torch.sigmoid(raw.detach())
        torch.testing.assert_close(raw.grad, analytic, rtol=1e-12, atol=1e-12)


def test_medium_subcommand_picks_the_registered_field_and_round_trips():
    config = parse_config(["uw3dgs", "medium-homogeneous", "--model.medium.b-inf-init", "0.1", "0.2", "0.3"])
    assert config.model.medium == HomogeneousMediumConfig(b_inf_init=(0.1, 0.2, 0.3))
    assert config_from_dict(config_to_dict(config)) == config  # config.yml keeps the choice (its _type) and knobs
    assert type(parse_config(["uw3dgs"]).model.medium) is MediumGridConfig  # the paper's grid by default
    # an option of the default field selects it without its token; the method's own defaults are kept
    chosen = parse_config(["uw3dgs-paper", "--model.medium.resolution", "8"]).model.medium
    assert chosen == dataclasses.replace(METHODS["uw3dgs-paper"].config.model.medium, resolution=8)
    # the token may come after other options, and the datamanager's subcommand after it
    config = parse_config(["uw3dgs", "--max-num-iterations", "7", "medium-homogeneous", "synthetic",
                           "--datamanager.scene.width", "40", "--model.medium.no-learn-beta"])
    assert (type(config.model.medium), config.model.medium.learn_beta, config.max_num_iterations,
            config.datamanager.scene.width) == (HomogeneousMediumConfig, False, 7, 40)
    assert type(parse_config(["3dgs", "gaussians"]).model.gaussians) is type(METHODS["3dgs"].config.model.gaussians)
    for argv in (["uw3dgs", "nope"], ["uw3dgs", "gaussians", "gaussians"],  # unknown; a field of another kind
                 ["uw3dgs", "--model.medium-field", "medium-homogeneous"],  # the removed selector option
                 ["uw3dgs", "medium-homogeneous", "--model.medium.resolution", "8"]):  # the grid's knob
        with pytest.raises(SystemExit):
            parse_config(argv)


def test_a_slot_of_a_kind_no_field_is_registered_for_says_so():
    from uw3dgs.models.field_slot import field_choices

    with pytest.raises(ValueError, match="no field of kind 'sonar' is registered"):
        field_choices("sonar")


def test_config_files_with_the_removed_field_name_options_still_load():
    """Runs saved while fields were chosen by a name option (`medium_field: medium-grid`) load: the name was a copy
    of what the field's `_type` says."""
    data = config_to_dict(parse_config(["uw3dgs", "medium-homogeneous"]))
    data["model"] = {**data["model"], "gaussian_field": "gaussians", "medium_field": "medium-homogeneous"}
    assert config_from_dict(data) == parse_config(["uw3dgs", "medium-homogeneous"])
    data["model"]["medium_fieldd"] = "x"  # a typo is still an error
    with pytest.raises(ValueError, match="no option.*medium_fieldd"):
        config_from_dict(data)


def test_help_shows_the_field_subcommands_and_the_chosen_fields_knobs(capsys):
    for argv, present, absent in ((["uw3dgs"], "--model.medium.resolution", None),
                                  (["uw3dgs", "medium-homogeneous"], "--model.medium.b-inf-init",
                                   "--model.medium.resolution")):
        with pytest.raises(SystemExit):
            parse_config([*argv, "--help"])
        out = capsys.readouterr().out
        assert present in out and (absent is None or absent not in out)
        assert argv[1:] or ("medium-homogeneous" in out and "medium-grid" in out)  # the choices, listed


def test_uw3dgs_trains_and_evaluates_with_the_homogeneous_medium(make_config):
    base = make_config(steps=20, timestamp="homogeneous")
    spec = METHODS["uw3dgs"].config
    model = dataclasses.replace(spec.model, medium=HomogeneousMediumConfig(),
                                densification=base.model.densification, gaussians=base.model.gaussians)
    trainer = Trainer(dataclasses.replace(base, method_name="uw3dgs", model=model, optimizers=spec.optimizers))
    trainer.setup()
    assert isinstance(trainer.model.medium, HomogeneousMedium)
    trainer.train()
    results = run_eval(EvalArgs(load_config=trainer.run_dir / "config.yml", save_renders=False))["results"]
    for key in ("psnr", "uri_psnr", "b_inf_r", "beta_d_b", "beta_b_g", "beta_d_rel_error", "uciqe", "uiqm",
                "uri_uciqe", "uri_uiqm", "input_uciqe", "input_uiqm", "clean_uciqe", "clean_uiqm"):
        assert key in results and results[key] == results[key], key  # present and not NaN
    # the no-reference metrics are those of the URI, the UWI, the input and the clean image of each test view
    model = trainer.model.eval()
    views = list(trainer.datamanager.test_batches())
    with torch.no_grad():
        images = {name: [] for name in ("uri", "", "input", "clean")}
        for batch in views:
            outputs = model.get_outputs(batch["camera"])
            images["uri"].append(outputs["uri"].clamp(0, 1))
            images[""].append(outputs["rgb"].clamp(0, 1))
            images["input"].append(batch["image"])
            images["clean"].append(batch["clean_image"])
    for name, batch_images in images.items():
        key = f"{name}_uiqm" if name else "uiqm"
        assert results[key] == pytest.approx(float(uiqm(torch.stack(batch_images)).mean()), rel=1e-6), key
    # started from the estimate, the one-value medium is near the scene's true (homogeneous) one
    assert results["b_inf_rel_error"] < 0.1 and results["beta_d_rel_error"] < 0.25
    saved = json.loads((trainer.run_dir / "eval" / "results.json").read_text())
    assert saved["results"]["beta_d_r"] == results["beta_d_r"]
    # the identifiability report on the starting estimate: in the run folder and in uw-eval's JSON
    note = json.loads((trainer.run_dir / "notes" / "medium_report.json").read_text())
    assert saved["notes"]["medium_report"] == note
    assert {(c["name"], c["channel"]) for c in note["checks"]} == {
        (name, channel) for name in ("beta_D", "beta_B", "B_inf") for channel in "RGB"}
    assert note["lines"][0].startswith("beta_D (") and note["open_water"] in (True, False)


def test_a_field_registered_at_run_time_is_a_subcommand(make_config):
    """The same registry third-party packages fill through the `uw3dgs.fields` entry point (tests/test_packaging.py
    installs a real plugin package): a name, a config, a kind."""

    @dataclasses.dataclass(frozen=True)
    class ClearWaterConfig(HomogeneousMediumConfig):
        beta_prior: tuple[float, float, float] = (0.01, 0.01, 0.01)

    FIELDS.register(FieldSpec("test-clear-water", "Nearly clear water", ClearWaterConfig(), kind="medium"))
    try:
        model = parse_config(["uw3dgs", "test-clear-water"]).model
        assert type(model.medium) is ClearWaterConfig
        medium = model.medium.setup(points=torch.zeros(1, 3), camera_centers=torch.zeros(1, 3))
        torch.testing.assert_close(F.softplus(medium.beta_d_raw), torch.full((3,), 0.01))
        torch.testing.assert_close(medium.beta_d_raw.detach(), softplus_inverse(torch.full((3,), 0.01)))
    finally:
        FIELDS._load().pop("test-clear-water")
