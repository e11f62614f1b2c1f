"""The scripts in benchmarks/: the analysis ones (benchmarks/analysis/) that read trained runs agree with uw-eval
and invert the medium; the speed ones (benchmarks/speed/) compare implementations that agree."""

from __future__ import annotations

import copy
import dataclasses
import importlib.util
import json
import re
import sys
from pathlib import Path

import pytest
import torch
from conftest import as_uw3dgs, tiny_train_config

from uw3dgs.data.scene import GroundTruth
from uw3dgs.engine.evaluator import load_trained
from uw3dgs.engine.trainer import Trainer

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load_script(name: str):
    """benchmarks/speed/NAME.py or benchmarks/analysis/NAME.py, loaded as `python benchmarks/GROUP/NAME.py` would."""
    (path,) = [p for p in (BENCHMARKS / "speed" / f"{name}.py", BENCHMARKS / "analysis" / f"{name}.py") if p.exists()]
    if str(path.parent) not in sys.path:  # the speed scripts import their siblings (timing.py, ...), as python does
        sys.path.insert(0, str(path.parent))
    spec = importlib.util.spec_from_file_location(f"benchmark_{name}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def uw3dgs_run(tiny_uw3dgs_trainer):
    """The session's 20-step uw3dgs run (conftest)."""
    return tiny_uw3dgs_trainer


def cells(row: str) -> list[str]:
    return [c.strip() for c in row.strip("|").split("|")]


def test_unseen_pixels_agrees_with_uw_eval(uw3dgs_run):
    script = load_script("unseen_pixels")
    summary = uw3dgs_run.eval_all(20)
    nothing_large = [cells(r) for r in script.view_rows(uw3dgs_run.run_dir / "config.yml", large=float("inf"))]
    assert len(nothing_large) == len(uw3dgs_run.datamanager.test_indices)
    full = [float(r[6]) for r in nothing_large]
    assert sum(full) / len(full) == pytest.approx(summary["psnr"], abs=0.01)
    assert sum(float(r[5]) for r in nothing_large) / len(full) == pytest.approx(summary["psnr_covisible"], abs=0.01)
    assert all(r[3:7] == r[7:11] and r[11] == "0" for r in nothing_large)  # nothing switched off: same numbers
    # every Gaussian switched off: the render is open water alone, B_inf everywhere
    everything = [cells(r) for r in script.view_rows(uw3dgs_run.run_dir / "config.yml", large=-1.0)]
    b_inf = uw3dgs_run.model.medium.b_inf.detach()
    for row, batch in zip(everything, uw3dgs_run.datamanager.test_batches(), strict=True):
        water = -10 * torch.log10((b_inf.clamp(0, 1) - batch["image"]).square().mean())
        assert float(row[10]) == pytest.approx(float(water), abs=0.01)
        assert row[7] in ("0.00", "-")


def test_roc_auc_against_brute_force_with_ties():
    script = load_script("paup_scores")
    gen = torch.Generator().manual_seed(0)
    scores = torch.randint(0, 6, (60,), generator=gen).float()  # many ties
    positive = torch.rand(60, generator=gen) < 0.3
    pairs = [(a, b) for a in scores[positive].tolist() for b in scores[~positive].tolist()]
    by_hand = sum(1.0 if a > b else 0.5 if a == b else 0.0 for a, b in pairs) / len(pairs)
    assert script.roc_auc(scores, positive) == pytest.approx(by_hand)
    assert script.roc_auc(scores, torch.zeros(60, dtype=torch.bool)) is None


def test_paup_scores_count_the_floaters_uw_eval_counts(uw3dgs_run):
    script = load_script("paup_scores")
    model, scene = copy.deepcopy(uw3dgs_run.model), uw3dgs_run.datamanager.scene
    train = uw3dgs_run.datamanager.train_indices
    with pytest.raises(SystemExit, match="no PAUP statistics"):
        script.score_rows(model, scene, train)
    model.refresh_paup_statistics(scene.cameras[train[0]])
    rows = [cells(r) for r in script.score_rows(model, scene, train)]
    names = ["big, floating (floater_ratio)", "big, floating, true surface (floater_ratio_gt)"]
    assert [r[0] for r in rows][::2] == names
    model.eval()
    summary = model.get_eval_summary(scene)
    assert int(rows[0][1]) / model.num_gaussians == pytest.approx(summary["floater_ratio"])
    assert int(rows[2][1]) / model.num_gaussians == pytest.approx(summary["floater_ratio_gt"])
    assert all(int(r[6]) <= int(r[1]) for r in rows)


def test_uri_error_bands_cover_every_pixel_and_dehazing_inverts_formation(uw3dgs_run):
    script = load_script("uri_error")
    rows = [cells(r) for r in script.band_table(uw3dgs_run.run_dir / "config.yml", [0, 3, 6], set(), False)]
    *bands, total = rows
    assert sum(float(r[1].rstrip("%")) for r in bands) == pytest.approx(100, abs=0.5)
    summary = uw3dgs_run.eval_all(20)
    assert float(total[2]) <= summary["uri_psnr"] + 0.01  # PSNR of the pooled error <= the mean per-view PSNR
    # the range column: rendered minus true range, pooled over the covered pixels that have a surface
    errors = []
    for batch in uw3dgs_run.datamanager.test_batches():
        with torch.no_grad():
            outputs = uw3dgs_run.model.get_outputs(batch["camera"])
        surface = (outputs["alpha"] > 0.5) & batch["range"].isfinite()
        errors.append(outputs["range"][surface] - batch["range"][surface])
    assert float(total[5]) == pytest.approx(float(torch.cat(errors).double().mean()), abs=0.006)
    # every de-hazing variant covers the same pixels (the range column does not depend on it)
    for flags in ((True, False), (False, True), (True, True)):
        variant = [cells(r) for r in script.band_table(uw3dgs_run.run_dir / "config.yml", [0, 3, 6], set(), *flags)]
        assert [(r[0], r[1], r[5]) for r in variant] == [(r[0], r[1], r[5]) for r in rows], flags
    model = uw3dgs_run.model
    camera = uw3dgs_run.datamanager.cameras[uw3dgs_run.datamanager.test_indices[0]]
    # the trained (not flat) medium re-read along the rays at the rendered ranges is the one the render used
    with torch.no_grad():
        outputs = model.get_outputs(camera)
        relearned = script.learned_medium_at(model, camera, outputs["range"])
    covered = outputs["alpha"] > 0.5
    assert float(relearned[0].std(dim=(0, 1)).min()) > 0  # the field varies: the check below means something
    dehazed = script.dehaze(outputs, outputs["range"], *relearned, model.dataset_scale)
    assert torch.allclose(dehazed[covered], outputs["uri"][covered], atol=1e-4)
    # with the model's own medium passed as the truth, de-hazing its UWI gives back its URI as well
    model.medium.set_homogeneous(torch.tensor([0.4, 0.2, 0.1]), torch.tensor([0.3, 0.25, 0.2]),
                                 torch.tensor([0.05, 0.25, 0.35]))
    with torch.no_grad():
        outputs = model.get_outputs(camera)
    own = {"beta_D": [0.4, 0.2, 0.1], "beta_B": [0.3, 0.25, 0.2], "B_inf": [0.05, 0.25, 0.35]}
    own_truth = GroundTruth(torch.empty(0), torch.empty(0), own)
    dehazed = script.dehaze(outputs, outputs["range"], *own_truth.medium_tensors(), model.dataset_scale)
    covered = outputs["alpha"] > 0.5
    assert torch.allclose(dehazed[covered], outputs["uri"][covered], atol=1e-4)


def test_uri_error_in_front_share_flags_gaussians_nearer_than_the_true_surface(uw3dgs_run):
    script = load_script("uri_error")
    model, dm = uw3dgs_run.model, uw3dgs_run.datamanager
    batch = next(iter(dm.test_batches()))
    camera, true_range = batch["camera"], batch["range"]
    with torch.no_grad():
        covered = model.get_outputs(camera)["alpha"] > 0.5
        trained = script.in_front_share(model, camera, true_range, 0.05)[covered]
        everything = script.in_front_share(model, camera, true_range, -1e6)[covered]  # any centre ahead counts
        nothing = script.in_front_share(model, camera, true_range, 1.0)[covered]  # none nearer than 0 x range
        # the same Gaussians pulled halfway to the camera (each stays on its own ray, so on its own pixel)
        means = model.gaussians.means
        original = means.detach().clone()
        centre = camera.center.to(means.dtype)
        means.copy_(centre + 0.5 * (original - centre))
        pulled = script.in_front_share(model, camera, true_range, 0.05)[covered]
        means.copy_(original)
    assert bool(covered.any())
    assert torch.allclose(everything, torch.ones_like(everything), atol=1e-5)
    assert torch.allclose(nothing, torch.zeros_like(nothing), atol=1e-6)
    # initialised on the seabed, 20 steps later the Gaussians still mostly sit on it; pulled in, all are in front
    assert float(trained.mean()) < 0.3
    assert float(pulled.mean()) > 0.95
    rows = [cells(r) for r in script.band_table(uw3dgs_run.run_dir / "config.yml", [0, 3, 6], set())]
    assert all(0.0 <= float(r[6].rstrip("%")) <= 100.0 for r in rows if r[6] != "-")


def test_scripts_read_a_chosen_checkpoint_and_name_the_saved_steps_otherwise(uw3dgs_run):
    config = uw3dgs_run.run_dir / "config.yml"
    assert load_trained(config, step=20)[3].name == "step-000020.ckpt"
    with pytest.raises(FileNotFoundError, match=r"no checkpoint of step 7 \(saved: 20\)"):
        load_trained(config, step=7)
    script = load_script("unseen_pixels")
    assert script.view_rows(config, large=2.0, step=20) == script.view_rows(config, large=2.0)


def test_uri_error_refuses_a_run_without_a_water_free_render(tmp_path, cache_dir, tiny_scene_config):
    trainer = Trainer(tiny_train_config(tmp_path, cache_dir, tiny_scene_config, steps=20, timestamp="plain"))
    trainer.setup()
    trainer.train()
    with pytest.raises(SystemExit, match="renders no water-free image.*pass a uw3dgs run"):
        load_script("uri_error").band_table(trainer.run_dir / "config.yml", [0, 3], set())


@pytest.fixture
def keep_threads():
    """The speed scripts time one thread (torch.set_num_threads(1)); the rest of the suite keeps its threads."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize(("name", "size"), [("sh_eval", "--gaussians"), ("medium_field", "--points"),
                                            ("adam_fused", "--gaussians"), ("ssim_blur", "--height")])
def test_speed_scripts_compare_implementations_that_agree(name, size, monkeypatch, capsys, keep_threads):
    monkeypatch.setattr(sys, "argv", [name, size, "300", "--repeats", "1"])
    load_script(name).main()
    agreement = float(capsys.readouterr().out.rsplit("agree to ", 1)[1].split()[0])
    assert agreement < 1e-5


def test_training_step_times_every_way_and_leaves_the_current_code_installed(uw3dgs_run, monkeypatch, capsys,
                                                                              keep_threads):
    import uw3dgs.fields.gaussians as gaussians_module
    from uw3dgs.fields.medium import VMField

    sh, medium = gaussians_module.eval_sh_split, VMField.forward
    monkeypatch.setattr(sys, "argv", ["training_step", str(uw3dgs_run.run_dir / "config.yml"), "--repeats", "1"])
    load_script("training_step").main()
    rows = [line for line in capsys.readouterr().out.splitlines() if "ms per step" in line]
    assert len(rows) == 7 and rows[0].split()[0] == "now"
    assert gaussians_module.eval_sh_split is sh and VMField.forward is medium


def test_paup_cost_times_the_same_run_with_and_without_the_branch(tmp_path, cache_dir, tiny_scene_config,
                                                                   monkeypatch, capsys, keep_threads):
    config = as_uw3dgs(tiny_train_config(tmp_path, cache_dir, tiny_scene_config, steps=20, timestamp="paup"))
    paup = dataclasses.replace(config.model.paup, start=10, every=5)
    trainer = Trainer(dataclasses.replace(config, model=dataclasses.replace(config.model, paup=paup)))
    trainer.setup()
    trainer.train()
    script = load_script("paup_cost")
    # the way without the branch trains as uw3dgs-no-paup does: no masked render, no L_PAPSL, no PAUP pruning
    batch = trainer.datamanager.next_train()
    with_branch = trainer.model.get_outputs(batch["camera"])
    # "PAUP in PyTorch" is the run's config with --model.kernels torch: the masked render a frozen render, its L1
    # PyTorch's (what that policy gives PAUP, set here on the built model)
    assert script.PAUP_IN_PYTORCH.configure(trainer.config).model.kernels == "torch"
    trainer.model.paup.scorer.kernels, trainer.model.paup.fused_masked_l1 = "torch", False
    in_pytorch = trainer.model.get_outputs(batch["camera"])
    assert type(in_pytorch["uri_enhanced_l1"].grad_fn).__name__ != type(with_branch["uri_enhanced_l1"].grad_fn).__name__
    script.without_paup(trainer)
    without = trainer.model.get_outputs(batch["camera"])
    assert "uri_enhanced" in with_branch and "uri_enhanced" not in without and "pus" not in without
    assert "paup_loss" not in trainer.model.get_loss_dict(without, batch, 21)
    assert all(getattr(cb, "extra_pruning", None) is None for cb in trainer.callbacks)
    monkeypatch.setattr(sys, "argv", ["paup_cost", str(trainer.run_dir / "config.yml"), "--steps", "3",
                                      "--rounds", "1", "--enhanced-every", "2"])
    script.main()
    rows = [line for line in capsys.readouterr().out.splitlines() if "ms per step" in line]
    ways = ["without PAUP (uw3dgs-no-paup)", "with PAUP (uw3dgs)", "PAUP in PyTorch",
            "with PAUP, I_UR^Enh every 2 steps"]
    assert [row.strip()[:len(way) + 1] for row, way in zip(rows, ways, strict=True)] == [f"{w} " for w in ways]
    assert rows[0].rstrip().endswith("1.00x")


@pytest.mark.slow  # trains runs in process
def test_viewer_slowdown_runs_every_setting(tmp_path, cache_dir, tiny_scene_config, monkeypatch, capsys,
                                            keep_threads):
    import json
    import socket
    from types import SimpleNamespace

    tiny = as_uw3dgs(tiny_train_config(tmp_path, cache_dir, tiny_scene_config, steps=3))
    script = load_script("viewer_slowdown")
    monkeypatch.setattr(script, "METHODS", {"uw3dgs": SimpleNamespace(config=tiny)})
    with socket.socket() as s:  # a free port for the viewer
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setattr(sys, "argv", ["viewer_slowdown", "--steps", "3", "--repeats", "1", "--port", str(port)])
    script.main()
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert [r["setting"] for r in rows] == ["off", "noclient", "simulated"]
    assert rows[0]["frames"] == 0 and rows[1]["frames"] == 0 and rows[2]["frames"] >= 1
    assert all(r["steps"] == 3 and r["steps_per_s"] > 0 for r in rows)


def test_step_profile_attributes_forward_and_backward_to_their_sections():
    """A hand-made step: the backward of the ops inside a section goes to it (through autograd's sequence numbers),
    nested sections count for the outermost, and ops outside every section are nobody's."""
    from torch.profiler import profile

    from uw3dgs.utils.profiling import section

    script = load_script("step_profile")
    x = torch.randn(200_000, requires_grad=True)
    with profile() as prof:
        with section("heavy"):
            y = torch.sin(x).exp()
            with section("inner"):  # nested: counted for "heavy"
                y = y * 3
        with section("light"):
            z = y.sum()  # its backward is a view (expand): next to nothing
        (z + torch.cos(x).sum()).backward()  # cos is in no section
    times = script.by_section(prof.events())
    assert set(times) == {"heavy", "light"}
    assert times["heavy"][0] > 0 and times["heavy"][1] > times["light"][1] > 0
    # heavy's backward runs sin, exp and mul backward over 200,000 values; nothing of cos's backward is in it
    assert times["heavy"][1] > 10 * times["light"][1]


def test_step_profile_prints_one_table_per_size_for_every_method(uw3dgs_run, monkeypatch, capsys, keep_threads):
    monkeypatch.setattr(sys, "argv", ["step_profile", str(uw3dgs_run.run_dir / "config.yml"), "--downscales", "1",
                                      "--sizes", "1.0", "0.5", "--steps", "2", "--enhanced-every", "2"])
    load_script("step_profile").main()
    tables = [t.strip() for t in capsys.readouterr().out.split("\n\n") if t.strip().startswith("downscale")]
    assert len(tables) == 2
    counts = [int(t.split(" Gaussians")[0].rsplit(" ", 1)[1].replace(",", "")) for t in tables]
    assert counts == [uw3dgs_run.model.num_gaussians, round(0.5 * uw3dgs_run.model.num_gaussians)]
    for table in tables:
        rows = {cells(r)[0]: cells(r)[1:] for r in table.splitlines()[3:]}
        assert table.splitlines()[1].count("`") == 8  # 3dgs, uw3dgs-no-paup, uw3dgs, uw3dgs every 2
        assert rows["medium"][0] == "-" and rows["medium"][1] != "-" and rows["medium"][2] != "-"
        assert rows["PAUP: scores + masked render"][:2] == ["-", "-"]
        # every other step without I_UR^Enh (steps 3,101-3,102 of a run whose PAUP starts at 500): PUS alone there
        assert rows["PAUP: scores"][2] == "-" and rows["PAUP: scores"][3] != "-"
        assert all(v != "-" for v in rows["rasterize"] + rows["sh colours"] + rows["Adam"])
        wall = [float(v.strip("*").split("*")[0]) for v in rows["**step, no profiler**"]]
        assert all(w > 0 for w in wall)


@pytest.mark.slow  # trains runs in process
def test_medium_recovery_prints_one_row_per_variant_and_reuses_its_runs(tmp_path, cache_dir, capsys):
    script = load_script("medium_recovery")
    argv = ["--steps", "5", "--variants", "default", "plume-homogeneous", "--output-dir", str(tmp_path),
            "--cache-dir", str(cache_dir), "--scene", "width=48", "--scene", "height=36", "--scene", "num_views=12"]
    script.main(argv)
    out = capsys.readouterr().out
    lines = [line for line in out.splitlines() if line.startswith("|")]
    table, fields = [cells(r) for r in lines if r.count("|") == 9], [cells(r) for r in lines if r.count("|") == 5]
    assert table[0] == ["variant", "estimate err % beta_D / beta_B / B_inf (R/G/B)", "with residual term",
                        "trained err % beta_D / beta_B / B_inf (R/G/B)", "input PSNR", "URI PSNR",
                        "not identifiable", "bar met"]
    assert [r[0] for r in table[2:]] == ["default", "plume-homogeneous"]
    for row in table[2:]:  # three parameters, three channels each, in every error column
        assert all([len(p.split("/")) for p in cell.split(";")] == [3, 3, 3] for cell in row[1:4])
        assert float(row[4]) > 0 and float(row[5]) > 0
    # the varying medium alone gets the field table: the estimate and the trained field, three places each
    assert [r[:2] for r in fields[2:]] == [["plume-homogeneous", "estimate"], ["plume-homogeneous", "trained"]]
    assert all(len(cell.split(" / ")) == 3 for r in fields[2:] for cell in r[2:])
    # and the spread of the trained field: a homogeneous one has none, and no correlation with the truth
    spread = [cells(r) for r in lines if r.count("|") == 7]
    assert spread[2][0] == "plume-homogeneous" and spread[2][1] == spread[2][3] == "0/0/0"
    # no correlation, and no amplitude against the plume's true spread
    assert spread[2][2] == spread[2][4] == "-/-/- ; 0.00/0.00/0.00"
    assert float(spread[2][-1]) > 0  # the UWI's PSNR
    # the grid in homogeneous water: its spread over the seabed (std / mean, %) and whether it stays flat
    (flat,) = [cells(r) for r in lines if r.count("|") == 6][2:]
    trained = json.loads((tmp_path / "default" / "row.json").read_text())["trained"]["spread"]
    ratios = [s / m for p in ("beta_D", "beta_B") for s, m in zip(trained[p]["std"], trained[p]["mean"], strict=True)]
    assert flat[0] == "default" and float(flat[3]) == pytest.approx(100 * max(ratios), abs=0.05)
    assert flat[4] == ("yes" if max(ratios) <= script.FLAT_BAR else "no (bar 5%)")
    # and the URI where the water leaves the seabed recoverable (the report's range), as well as on the whole image
    recoverable = [cells(r) for r in lines if r.count("|") == 8]
    assert [r[0] for r in recoverable[2:]] == ["default", "plume-homogeneous"]
    assert all(len(r[1].split("/")) == 3 and 0 <= float(r[3]) <= 100 for r in recoverable[2:])
    saved = json.loads((tmp_path / "default" / "row.json").read_text())
    assert saved["recoverable"]["uri_psnr"] > 0 and len(saved["recoverable_range"]) == 3
    assert saved["trained"]["spread"]["beta_D"]["corr"] == [None, None, None]  # a flat truth: no correlation
    assert saved["trained"]["errors"]["B_inf"] == pytest.approx(  # B_inf is scored as uw-eval scores it
        [abs(saved["eval"][f"b_inf_{c}"] - t) / t for c, t in zip("rgb", (0.05, 0.25, 0.35), strict=True)], rel=1e-5)
    # a flat truth: the field's error at the seabed and along the rays are the same for the (flat) estimate
    assert saved["estimate"]["errors_ray_mean"]["beta_D"] == pytest.approx(saved["estimate"]["errors"]["beta_D"])
    (tmp_path / "default" / "estimate.json").unlink()  # a finished variant is read back, not estimated or trained
    script.main(argv)
    assert [line for line in capsys.readouterr().out.splitlines() if line.startswith("|")] == lines


@pytest.mark.slow  # trains a run in process
def test_medium_recovery_survey_rows_start_from_the_combined_estimate(tmp_path, cache_dir, capsys):
    """A survey variant trains with --model.medium.init multiview; its row's start is the run's combined medium
    (notes/medium_evidence.json), scored and judged by that evidence, not by the single-image report."""
    script = load_script("medium_recovery")
    name = "survey-2-passes-no-open-water"
    assert script.VARIANTS[name] == ({"pass_altitudes": (3.0, 6.0), "open_water": False}, script.MULTIVIEW)
    argv = ["--steps", "5", "--variants", name, "--output-dir", str(tmp_path), "--cache-dir", str(cache_dir),
            "--scene", "width=48", "--scene", "height=36", "--scene", "num_views=12", "--scene", "num_points=600",
            "--seeds", "1"]
    script.main(argv)
    out = capsys.readouterr().out
    row = json.loads((tmp_path / "s1" / name / "row.json").read_text())
    evidence = json.loads(next((tmp_path / "s1" / name).glob("**/notes/medium_evidence.json")).read_text())
    # --seeds: a run per seed in OUTPUT_DIR/sSEED, trained with that seed, its row labelled with it
    config = next((tmp_path / "s1" / name).glob("**/config.yml")).read_text()
    assert re.search(r"^seed: 1$", config, re.MULTILINE)
    start = row["start"]
    for key, parameter in (("beta_d", "beta_D"), ("beta_b", "beta_B"), ("b_inf", "B_inf")):
        values = [c["value"] for c in evidence["checks"] if c["name"] == parameter]
        assert start["medium"][key] == pytest.approx(values)
        assert start["sources"][parameter] == [c["source"] for c in evidence["checks"] if c["name"] == parameter]
    assert start["weak"] == [f"{c['name']} {c['channel']}" for c in evidence["checks"]
                             if c["source"] == "not identified"]
    (line,) = [cells(r) for r in out.splitlines() if r.startswith(f"| {name} (seed 1) |") and r.count("|") == 9]
    assert line[1] == " ; ".join(script.percents(start["errors"][p]) for p in script.PARAMETERS)


def test_quality_ranking_ranks_methods_and_correlates_with_the_truth(tmp_path, monkeypatch, capsys):
    """Spearman's rho against scipy's (ties included), and the script on three methods' fake results: a score that
    orders the runs as uri_psnr does gets +1, one that reverses them -1."""
    from scipy.stats import spearmanr

    script = load_script("quality_ranking")
    g = torch.Generator().manual_seed(0)
    a, b = torch.randint(0, 5, (30,), generator=g).double().numpy(), torch.rand(30, generator=g).double().numpy()
    assert script.spearman(a, b) == pytest.approx(spearmanr(a, b).statistic, abs=1e-12)
    for k, method in enumerate(("good", "middle", "bad")):
        for seed in range(2):
            run = tmp_path / method / f"s{seed}"
            run.mkdir(parents=True)
            (run / "config.yml").write_text("_type: x\n")
            psnr = 30.0 - 5 * k + seed * 0.1
            results = {"uri_psnr": psnr, "uri_uciqe": psnr / 100, "uri_uiqm": -psnr, "clean_uciqe": 0.3,
                       "clean_uiqm": 3.0}
            (run / "eval").mkdir()
            (run / "eval" / "results.json").write_text(json.dumps({"method_name": method, "results": results}))
    monkeypatch.setattr(sys, "argv", ["quality_ranking.py", str(tmp_path)])
    script.main()
    out = capsys.readouterr().out
    assert "uri_psnr                     good (30.050) > middle (25.050) > bad (20.050)" in out
    assert "uri_uciqe                    +1.00" in out and "uri_uiqm                     -1.00" in out
    monkeypatch.setattr(sys, "argv", ["quality_ranking.py", str(tmp_path), "--without", "bad"])
    script.main()
    assert "4 runs, 2 methods" in capsys.readouterr().out
