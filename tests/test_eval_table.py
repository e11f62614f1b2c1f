"""`uw-eval table`: runs found, grouped by scene and method, mean +- std over seeds, the best per column, four
formats, clear errors; and the training time uw-train records (RUN/train_time.json, the checkpoint) that uw-eval
copies into its results and the table shows as train minutes."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import os
import time
from pathlib import Path

import pytest
import torch
from conftest import train_until_killed

from uw3dgs.cli.eval import EvalArgs, run_eval
from uw3dgs.cli.eval import entrypoint as uw_eval
from uw3dgs.engine import results_table as rt
from uw3dgs.engine.checkpoint import checkpoint_path, list_checkpoints
from uw3dgs.engine.trainer import TRAIN_TIME_FILE, Trainer


def fake_run(root: Path, scene: str, method: str, seed: int, results: dict | None,
             checkpoint: str = "step-000100.ckpt") -> Path:
    """A run folder as uw-train and uw-eval leave it, as far as the table reads it: config.yml, eval/results.json."""
    run = root / scene / method / f"seed{seed}"
    run.mkdir(parents=True)
    (run / "config.yml").write_text(f"_type: uw3dgs.engine.config.TrainConfig\nmethod_name: {method}\nseed: {seed}\n")
    if results is not None:
        (run / "eval").mkdir()
        (run / "eval" / "results.json").write_text(json.dumps({
            "experiment_name": scene, "method_name": method, "checkpoint": str(run / "checkpoints" / checkpoint),
            "results": results, "per_image": []}))
    return run


@pytest.fixture
def runs(tmp_path) -> Path:
    """Two scenes; on `reef` 3dgs with three seeds and uw3dgs with two; on `wreck` one run each."""
    root = tmp_path / "outputs"
    for seed, (psnr, lpips, n) in enumerate([(30.0, 0.20, 1000), (31.0, 0.22, 1100), (32.0, 0.24, 1200)]):
        fake_run(root, "reef", "3dgs", seed, {"psnr": psnr, "ssim": 0.9, "lpips_alex": lpips, "num_gaussians": n,
                                              "psnr_std": 3.0, "train_seconds": 600.0, "train_steps": 100})
    for seed, (psnr, lpips, n) in enumerate([(33.0, 0.30, 900), (34.0, None, 950)]):
        fake_run(root, "reef", "uw3dgs", seed, {"psnr": psnr, "ssim": 0.9, "lpips_alex": lpips, "num_gaussians": n,
                                                "uri_psnr": 20.0 + seed, "train_seconds": 1200.0, "train_steps": 100})
    fake_run(root, "wreck", "3dgs", 0, {"psnr": 25.0, "ssim": 0.8, "lpips_alex": 0.3, "num_gaussians": 500,
                                        "train_seconds": None, "train_steps": 100})
    fake_run(root, "wreck", "uw3dgs", 0, {"psnr": 25.004, "ssim": 0.7, "lpips_alex": 0.3, "num_gaussians": 400,
                                          "uri_psnr": 18.0, "train_seconds": 60.0, "train_steps": 100})
    return root


def table_of(root: Path, metrics=None) -> rt.ResultsTable:
    run_dirs, _ = rt.find_runs([root])
    found = [rt.run_from_results(d, rt.read_results(d)) for d in run_dirs]
    return rt.build_table(found, rt.select_metrics(found, metrics)[0])


def test_runs_are_grouped_by_scene_and_method_with_mean_std_n(runs):
    table = table_of(runs)
    assert table.scenes == ["reef", "wreck"] and table.methods == ["3dgs", "uw3dgs"]
    reef = table.groups["reef", "3dgs"]
    assert len(reef.runs) == 3
    assert reef.cells["psnr"] == rt.Cell(31.0, 1.0, 3)  # sample std over the seeds (n - 1)
    assert reef.cells["train_minutes"] == rt.Cell(10.0, 0.0, 3)
    uw = table.groups["reef", "uw3dgs"]
    assert uw.cells["lpips_alex"] == rt.Cell(0.30, None, 1)  # the null LPIPS is missing, not 0
    assert uw.cells["psnr"].mean == 33.5 and uw.cells["psnr"].std == pytest.approx(0.5 ** 0.5)
    assert table.groups["wreck", "3dgs"].cells["psnr"] == rt.Cell(25.0, None, 1)
    assert "train_minutes" not in table.groups["wreck", "3dgs"].cells  # null train_seconds: not made up
    # the default columns, in order; floater_ratio is in no run, so it is dropped
    assert [m.key for m in table.metrics] == ["psnr", "ssim", "lpips_alex", "uri_psnr", "num_gaussians",
                                              "train_minutes"]


def test_the_best_of_every_column_is_marked_in_its_direction(runs):
    best = table_of(runs).best
    assert ("reef", "uw3dgs", "psnr") in best and ("reef", "3dgs", "psnr") not in best  # higher is better
    assert ("reef", "3dgs", "lpips_alex") in best and ("reef", "uw3dgs", "lpips_alex") not in best  # lower
    assert ("reef", "uw3dgs", "num_gaussians") in best  # fewer Gaussians
    assert ("reef", "3dgs", "train_minutes") in best  # faster
    # 25.00 and 25.004 show the same: both bold; equal LPIPS: both bold
    assert {("wreck", "3dgs", "psnr"), ("wreck", "uw3dgs", "psnr")} <= best
    assert {("wreck", "3dgs", "lpips_alex"), ("wreck", "uw3dgs", "lpips_alex")} <= best
    assert ("wreck", "3dgs", "ssim") in best and ("wreck", "uw3dgs", "ssim") not in best
    # a column only one method of the scene has marks nothing
    assert not {key for key in best if key[2] == "uri_psnr"}
    assert ("wreck", "uw3dgs", "train_minutes") not in best
    for key, m in rt.METRICS.items():  # the direction table is explicit for every metric it knows
        assert m.better in ("higher", "lower", None), key
    assert rt.METRICS["ssim"].better == "higher" and rt.METRICS["floater_ratio"].better == "lower"


def test_markdown_is_a_github_table_with_scene_groups(runs, capsys):
    uw_eval(["table", str(runs), "--no-eval"])
    captured = capsys.readouterr()
    lines = captured.out.strip().splitlines()
    assert all(line.startswith("| ") or line.startswith("|---") for line in lines)
    widths = {line.count(" | ") + 1 if line.startswith("| ") else line.count("|") - 1 for line in lines}
    assert len(widths) == 1  # every row has the header's columns
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    assert header[:3] == ["method", "reef: n", "reef: PSNR ↑"]
    assert "wreck: LPIPS ↓" in header and "reef: train minutes ↓" in header
    rows = {r[0]: r for r in ([c.strip() for c in line.strip("|").split("|")] for line in lines[2:])}
    three, uw = rows["`3dgs`"], rows["`uw3dgs`"]
    col = header.index
    assert three[col("reef: n")] == "3" and uw[col("reef: n")] == "2"
    assert three[col("reef: PSNR ↑")] == "31.00 ± 1.00" and uw[col("reef: PSNR ↑")] == "**33.50 ± 0.71**"
    assert three[col("reef: LPIPS ↓")] == "**0.220 ± 0.020**" and uw[col("reef: LPIPS ↓")] == "0.300 (n=1)"
    assert three[col("reef: Gaussians ↓")] == "1,100 ± 100"
    assert three[col("reef: URI PSNR ↑")] == "-" and uw[col("wreck: URI PSNR ↑")] == "18.00"
    assert three[col("wreck: train minutes ↓")] == "-" and uw[col("wreck: train minutes ↓")] == "1.0"


def test_latex_uses_booktabs_multicolumn_scenes_and_bold(runs, capsys):
    uw_eval(["table", str(runs), "--no-eval", "--format", "tex", "--metrics", "psnr,lpips_alex"])
    out = capsys.readouterr().out
    lines = out.strip().splitlines()
    assert lines[0] == r"\begin{tabular}{l" + "r" * 6 + "}" and lines[-1] == r"\end{tabular}"
    for rule in (r"\toprule", r"\midrule", r"\bottomrule"):
        assert out.count(rule) == 1, rule
    assert r"\multicolumn{3}{c}{reef} & \multicolumn{3}{c}{wreck} \\" in out
    assert r"\cmidrule(lr){2-4} \cmidrule(lr){5-7}" in out
    assert r"method & $n$ & PSNR$\uparrow$ & LPIPS$\downarrow$ & $n$ & PSNR$\uparrow$ & LPIPS$\downarrow$ \\" in out
    body = lines[lines.index(r"\midrule") + 1:lines.index(r"\bottomrule")]
    assert [row.count(" & ") for row in body] == [6, 6]
    assert body[1].startswith(r"uw3dgs & 2 & \textbf{33.50 $\pm$ 0.71} & 0.300 (n=1) & 1 & \textbf{25.00}")
    assert rt.tex_escape("a_b & 50%") == r"a\_b \& 50\%"


def test_csv_and_json_are_tidy_rows(runs, capsys):
    uw_eval(["table", str(runs), "--no-eval", "--format", "csv"])
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [(r["scene"], r["method"], r["n"]) for r in rows] == [
        ("reef", "3dgs", "3"), ("reef", "uw3dgs", "2"), ("wreck", "3dgs", "1"), ("wreck", "uw3dgs", "1")]
    assert float(rows[0]["psnr_mean"]) == 31.0 and float(rows[0]["psnr_std"]) == 1.0 and rows[0]["psnr_n"] == "3"
    assert rows[0]["uri_psnr_mean"] == "" and rows[0]["uri_psnr_n"] == "0"  # missing in that group
    assert rows[2]["psnr_std"] == ""  # one run: no std
    assert "floater_ratio_mean" not in rows[0]  # no run has it
    uw_eval(["table", str(runs), "--no-eval", "--format", "json"])
    data = json.loads(capsys.readouterr().out)
    assert [r["method"] for r in data] == ["3dgs", "uw3dgs", "3dgs", "uw3dgs"]
    assert data[1]["lpips_alex_mean"] == 0.30 and data[1]["lpips_alex_n"] == 1 and data[1]["lpips_alex_std"] is None
    assert data[2]["train_minutes_mean"] is None
    assert sorted(Path(p).name for p in data[0]["runs"]) == ["seed0", "seed1", "seed2"]


def test_output_file_and_a_run_named_by_its_config(runs, tmp_path, capsys):
    out = tmp_path / "tables" / "t.md"
    one = runs / "wreck" / "uw3dgs" / "seed0"
    uw_eval(["table", str(one / "config.yml"), str(runs / "reef"), "--no-eval", "--output", str(out)])
    captured = capsys.readouterr()
    assert captured.out == "" and f"table written to {out}" in captured.err
    text = out.read_text()
    assert "reef: PSNR ↑" in text and "wreck: PSNR ↑" in text


def test_no_eval_lists_runs_without_results_as_skipped(runs, tmp_path, capsys):
    bare = fake_run(runs, "reef", "3dgs", 7, None)
    uw_eval(["table", str(runs), "--no-eval", "--format", "csv"])
    captured = capsys.readouterr()
    assert f"skipped {bare}: no eval/results.json (--no-eval); evaluate it with uw-eval {bare / 'config.yml'}" \
        in captured.err
    assert next(csv.DictReader(io.StringIO(captured.out)))["n"] == "3"
    # only unevaluated runs: nothing to show is one line
    with pytest.raises(SystemExit) as exc:
        uw_eval(["table", str(bare), "--no-eval"])
    assert exc.value.code == 2
    assert "error: none of the 1 run(s) found has results to show" in capsys.readouterr().out


def test_a_run_that_cannot_be_evaluated_is_skipped_with_its_reason(runs, capsys):
    broken = fake_run(runs, "reef", "3dgs", 8, None)  # a config.yml and no checkpoint
    uw_eval(["table", str(runs), "--format", "json"])
    captured = capsys.readouterr()
    assert f"evaluating {broken} (1/1; no eval/results.json)" in captured.err
    assert f"skipped {broken}: cannot be evaluated" in captured.err
    assert json.loads(captured.out)[0]["n"] == 3


def test_a_run_still_training_is_skipped_not_evaluated_mid_run(runs, capsys):
    from uw3dgs.engine.run_folder import RunLock

    training = fake_run(runs, "reef", "3dgs", 9, None)
    (training / "checkpoints").mkdir()
    (training / "checkpoints" / "step-000050.ckpt").write_bytes(b"")  # a mid-run checkpoint
    lock = RunLock(training)
    lock.acquire()  # as uw-train holds it from setup to the end of training
    try:
        uw_eval(["table", str(runs), "--format", "json"])
    finally:
        lock.release()
    captured = capsys.readouterr()
    assert f"evaluating {training}" not in captured.err
    assert f"skipped {training}: still training (pid {os.getpid()}" in captured.err
    assert "run uw-eval table again when it has ended" in captured.err
    assert json.loads(captured.out)[0]["n"] == 3


def test_results_of_an_earlier_checkpoint_are_stale(runs, capsys):
    run = runs / "wreck" / "3dgs" / "seed0"
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "step-000200.ckpt").write_bytes(b"")
    data = rt.read_results(run)
    assert rt.stale_results(run, data) == (f"{run / 'eval' / 'results.json'} is of step-000100.ckpt, the run's "
                                           "latest is step-000200.ckpt")
    uw_eval(["table", str(run), "--no-eval"])
    assert "shown as it is (--no-eval)" in capsys.readouterr().err


@pytest.mark.parametrize("case", ["missing path", "no runs", "unknown metric", "output is a folder",
                                  "output under a file", "no metric", "no paths"])
def test_errors_are_one_line(runs, tmp_path, capsys, case):
    empty, other = tmp_path / "empty", tmp_path / "other"
    empty.mkdir()
    other.mkdir()
    argv, expected = {
        "missing path": ([str(tmp_path / "nope")], f"error: {tmp_path / 'nope'} does not exist"),
        "no runs": ([str(empty), str(other)],
                    f"error: no runs (folders holding a config.yml) found under {empty}, {other}"),
        "unknown metric": ([str(runs), "--metrics", "psnr,psrn"],
                           "error: --metrics: unknown metric(s) psrn; these runs have: psnr, ssim, lpips_alex, "
                           "uri_psnr, num_gaussians, train_minutes, train_seconds, train_steps"),
        "output is a folder": ([str(runs), "--output", str(empty)],
                               f"error: --output {empty}: {empty} is a folder; give a file name"),
        "output under a file": ([str(runs), "--output", str(runs / "reef" / "3dgs" / "seed0" / "config.yml" / "t")],
                                "is a file, not a folder"),
        "no metric": ([str(runs), "--metrics", ","], "error: --metrics ',' names no metric"),
        "no paths": ([], "error: uw-eval table: give the runs: run folders, their config.yml, or folders holding runs"),
    }[case]
    with pytest.raises(SystemExit) as exc:
        uw_eval(["table", *argv, "--no-eval"])
    assert exc.value.code == 2
    out = capsys.readouterr().out
    assert expected in out and len(out.strip().splitlines()) == 1, out


def test_a_config_path_under_a_folder_named_table_is_a_run(tmp_path, monkeypatch):
    import uw3dgs.cli.eval as cli

    seen = []
    monkeypatch.setattr(cli, "run_eval", lambda args: seen.append(args.load_config) or {})
    monkeypatch.setattr(cli, "print_results", lambda data: None)
    uw_eval(["table/config.yml"])
    uw_eval(["./table/config.yml", "--no-save-renders"])
    assert seen == [Path("table/config.yml"), Path("table/config.yml")]


# ---- a real run: the time uw-train records, through a kill and a resume, into uw-eval and the table ------------------


def test_training_time_survives_a_resume_and_reaches_the_table(make_config, monkeypatch, tmp_path, capsys):
    original = Trainer.train_step

    def slow(self, step):  # the first segment takes at least 1 s, so a resume that restarted the clock would show
        time.sleep(0.05)
        return original(self, step)

    monkeypatch.setattr(Trainer, "train_step", slow)
    config = make_config(steps=40, timestamp="timed")
    killed = train_until_killed(config, monkeypatch, step=26)  # checkpoint at 20, steps 21-25 lost
    monkeypatch.setattr(Trainer, "train_step", original)
    run = killed.run_dir
    first = json.loads((run / TRAIN_TIME_FILE).read_text())
    s20 = first["checkpoints"]["20"]
    assert first["train_steps"] == 20 and first["train_seconds"] == s20 >= 1.0 and "meaning" in first
    assert torch.load(checkpoint_path(run, 20), weights_only=True)["train_seconds"] == s20

    resumed = Trainer(dataclasses.replace(config, resume=True))
    resumed.setup()
    t0 = time.perf_counter()
    resumed.train()
    segment = time.perf_counter() - t0
    record = json.loads((run / TRAIN_TIME_FILE).read_text())
    s40 = record["checkpoints"]["40"]
    assert record["train_steps"] == 40 and record["checkpoints"]["20"] == s20
    assert 0 < s40 - s20 <= segment < s40  # the resumed segment added to the first, not started from 0
    assert torch.load(checkpoint_path(run, 40), weights_only=True)["train_seconds"] == s40
    assert not [p for p in run.iterdir() if p.name.endswith(".tmp")]

    # uw-eval copies the time of the checkpoint it evaluates
    earlier = run_eval(EvalArgs(load_config=run / "config.yml", step=20, save_renders=False), progress=False)
    assert (earlier["results"]["train_seconds"], earlier["results"]["train_steps"]) == (s20, 20)

    # the table evaluates the run (it has no results yet) and shows it
    uw_eval(["table", str(tmp_path / "outputs"), "--metrics", "psnr,train_minutes,train_steps"])
    captured = capsys.readouterr()
    assert f"evaluating {run} (1/1; no eval/results.json)" in captured.err
    results = json.loads((run / "eval" / "results.json").read_text())["results"]
    assert (results["train_seconds"], results["train_steps"]) == (s40, 40)
    header, _, row = captured.out.strip().splitlines()
    assert header == "| method | synthetic: n | synthetic: PSNR ↑ | synthetic: train minutes ↓ | synthetic: steps |"
    assert row == f"| `3dgs` | 1 | {results['psnr']:.2f} | {s40 / 60:.1f} | 40 |"
    assert (run / "eval" / "renders" / "compare").is_dir()  # evaluated as uw-eval RUN/config.yml does
    mtime = os.stat(run / "eval" / "results.json").st_mtime_ns
    uw_eval(["table", str(run)])  # results of the latest checkpoint: not evaluated again
    assert "evaluating" not in capsys.readouterr().err
    assert os.stat(run / "eval" / "results.json").st_mtime_ns == mtime

    # killed between the checkpoint and the record: uw-eval reads the checkpoint's own time
    (run / TRAIN_TIME_FILE).write_text(json.dumps({**record, "checkpoints": {"20": s20}}))
    out = tmp_path / "r.json"
    assert run_eval(EvalArgs(load_config=run / "config.yml", output_path=out, save_renders=False),
                    progress=False)["results"]["train_seconds"] == s40

    # the record lost or damaged: the checkpoint's own time
    (run / TRAIN_TIME_FILE).unlink()
    assert run_eval(EvalArgs(load_config=run / "config.yml", output_path=out, save_renders=False),
                    progress=False)["results"]["train_seconds"] == s40
    # a checkpoint from before the record: its time is unknown, and so is every later one (never a partial sum)
    state = torch.load(checkpoint_path(run, 40), weights_only=True)
    del state["train_seconds"]
    torch.save(state, checkpoint_path(run, 40))
    older = Trainer(dataclasses.replace(config, resume=True, max_num_iterations=45, steps_per_save=5))
    older.setup()
    older.train()
    assert [p.name for p in list_checkpoints(run)] == ["step-000040.ckpt", "step-000045.ckpt"]
    record = json.loads((run / TRAIN_TIME_FILE).read_text())
    assert record["train_seconds"] is None and record["checkpoints"] == {"40": None, "45": None}
    assert torch.load(checkpoint_path(run, 45), weights_only=True)["train_seconds"] is None
    assert run_eval(EvalArgs(load_config=run / "config.yml", output_path=out, save_renders=False),
                    progress=False)["results"]["train_seconds"] is None
