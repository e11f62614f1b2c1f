"""`uw-bench GRID.yaml`: the grid file and its cells, the thread budget, a grid of tiny runs killed midway and run
again (finished cells skipped, the interrupted one resumed), --jobs 2 and the Ray executor giving the same numbers
as --jobs 1, and the presets in configs/."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import QUICK_REPORT_ARGS

from uw3dgs.bench.cell import LOG_NAME, State, cell_state, config_differences
from uw3dgs.bench.executors import local_threads
from uw3dgs.bench.grid import GridError, load_grid, select_cells
from uw3dgs.engine.checkpoint import list_checkpoints

REPO = Path(__file__).resolve().parents[1]
SHARED_SCENE = REPO.parent / "shared" / "data" / "seathru-nerf" / "IUI3-RedSea"
QUICK = ", ".join(QUICK_REPORT_ARGS)

TINY_GRID = """
output_dir: {out}
methods: [3dgs, uw3dgs]
datasets:
  tiny:
    datamanager: synthetic
    args: [--datamanager.scene.width, 40, --datamanager.scene.height, 30, --datamanager.scene.num-views, 10]
seeds: [0, 1]
args: [--max-num-iterations, {steps}, --steps-per-save, 10, --steps-per-eval-image, 1000,
       --steps-per-eval-all-images, 1000]
method_args: {{uw3dgs: [{quick_report}]}}
metrics: [psnr, ssim, uri_psnr, num_gaussians]
"""


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# ---- the grid file ---------------------------------------------------------------------------------------------------


def test_cells_are_the_product_with_datamanager_flags_after_the_subcommand(tmp_path):
    grid = load_grid(write(tmp_path / "g.yaml", """
output_dir: out
data_root: /data
methods: [3dgs, uw3dgs]
datasets:
  reef: {data: reef, args: [--downscale-factor, 4]}
  synth: {datamanager: synthetic, args: [--datamanager.scene.marine-snow, 20]}
seeds: [0, 1, 2]
args: [--max-num-iterations, 100, --model.paup.no-monotone-scorer]
variants: {plain: [], att: [--model.paup.attenuation-weight, 1]}
"""))
    cells = grid.cells()
    assert len(cells) == 2 * 2 * 2 * 3
    assert len({c.run_dir for c in cells}) == len(cells)
    cell = next(c for c in cells if (c.dataset, c.method, c.variant, c.seed) == ("synth", "uw3dgs", "att", 2))
    assert cell.run_dir == Path("out/synth/uw3dgs/att-s2")
    assert cell.label == "uw3dgs [att]" and cell.name == "synth/uw3dgs [att]/s2"
    argv = list(cell.argv)
    assert argv[0] == "uw3dgs"
    assert argv.index("synthetic") < argv.index("--datamanager.scene.marine-snow")
    assert argv.index("--model.paup.attenuation-weight") < argv.index("synthetic")
    assert argv[argv.index("--timestamp") + 1] == "att-s2" and argv[argv.index("--seed") + 1] == "2"
    reef = next(c for c in cells if c.dataset == "reef")
    assert reef.argv[reef.argv.index("--data") + 1] == "/data/reef"
    assert load_grid(tmp_path / "g.yaml", data_root=Path("/else")).cells()[0].argv[-1] == "/else/reef"


def test_cells_are_selected_by_method_dataset_variant_and_seed(tmp_path):
    grid = load_grid(write(tmp_path / "g.yaml", """
methods: [3dgs, uw3dgs]
datasets: {reef: {data: reef}, synth: {}}
seeds: [0, 1, 2]
variants: {plain: [], att: [--model.paup.attenuation-weight, 1]}
"""))
    assert select_cells(grid) == grid.cells()
    chosen = select_cells(grid, methods=["uw3dgs"], variants=["plain"], seeds=[0, 2])
    assert [c.name for c in chosen] == ["reef/uw3dgs [plain]/s0", "reef/uw3dgs [plain]/s2",
                                        "synth/uw3dgs [plain]/s0", "synth/uw3dgs [plain]/s2"]
    assert [c.name for c in select_cells(grid, datasets=["synth"], variants=["att"], seeds=[1])] == [
        "synth/3dgs [att]/s1", "synth/uw3dgs [att]/s1"]
    with pytest.raises(GridError, match=r"--methods uw3gds: not in the grid, whose methods are 3dgs, uw3dgs"):
        select_cells(grid, methods=["uw3gds"])
    with pytest.raises(GridError, match=r"--seeds 5: not in the grid, whose seeds are 0, 1, 2"):
        select_cells(grid, seeds=[5])
    plain = load_grid(write(tmp_path / "p.yaml", "methods: [3dgs]\ndatasets: {s: {}}\nseeds: [0]\n"))
    with pytest.raises(GridError, match=r"--variants att: not in the grid, whose variants are none"):
        select_cells(plain, variants=["att"])


@pytest.mark.parametrize("text, needle", [
    ("methods: [3dgs]\ndatasets: {s: {}}\nseeds: [0]\nepochs: 3\n", "unknown key(s) ['epochs']"),
    ("methods: [3dgs]\ndatasets: {s: {}}\n", "`seeds` is missing"),
    ("methods: []\ndatasets: {s: {}}\nseeds: [0]\n", "`methods` must be a non-empty list"),
    ("methods: [3dgs]\ndatasets: {s: {}}\nseeds: [0, 0]\n", "lists an entry twice"),
    ("methods: [3dgs]\ndatasets: {s: {path: x}}\nseeds: [0]\n", "dataset 's' must be a mapping with keys"),
    ("methods: [3dgs]\ndatasets: {a/b: {}}\nseeds: [0]\n", "must be one folder name"),
    ("methods: [3dgs]\ndatasets: {s: {}}\nseeds: [0]\nargs: {steps: 3}\n", "must be a list of uw-train flags"),
    ("methods: [3dgs\n", "not valid plain YAML"),
])
def test_a_bad_grid_file_names_the_file_and_the_fix(tmp_path, text, needle):
    path = write(tmp_path / "g.yaml", text)
    with pytest.raises(GridError) as err:
        load_grid(path)
    assert str(path) in str(err.value) and needle in str(err.value)


def test_datamanager_flags_need_a_named_datamanager(tmp_path):
    grid = load_grid(write(tmp_path / "g.yaml", "methods: [3dgs]\ndatasets: {s: {}}\nseeds: [0]\n"
                                                "args: [--datamanager.scene.width, 40]\n"))
    with pytest.raises(GridError, match="name the datamanager it belongs to with `datamanager:`"):
        grid.cells()


def test_a_missing_grid_file_names_the_presets():
    with pytest.raises(FileNotFoundError, match="does-not-exist.yaml does not exist; .* demo, .*paper-ablation"):
        load_grid(Path("does-not-exist.yaml"))


def test_a_preset_is_found_by_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert [c.method for c in load_grid(Path("demo")).cells()] == ["3dgs", "uw3dgs"]


def test_threads_are_divided_and_never_oversubscribed():
    assert local_threads(1, None, 8) == 8
    assert local_threads(3, None, 8) == 2
    assert local_threads(2, 4, 8) == 4
    with pytest.raises(ValueError, match="would oversubscribe"):
        local_threads(3, None, 2)
    with pytest.raises(ValueError, match="the most that fits is --threads-per-job 4"):
        local_threads(2, 5, 8)


# ---- a grid of tiny runs ---------------------------------------------------------------------------------------------


def bench(*args: str, env: dict[str, str], **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "uw3dgs.cli.bench", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, **kwargs)


def results_of(out: Path) -> dict[str, dict]:
    """Every cell's eval results but the wall time."""
    return {str(p.relative_to(out)): {k: v for k, v in json.loads(p.read_text())["results"].items()
                                      if k != "train_seconds"}
            for p in sorted(out.glob("*/*/*/eval/results.json"))}


@pytest.mark.slow
def test_a_selection_runs_only_its_cells_and_the_rest_are_listed(tmp_path, cache_dir):
    out = tmp_path / "out"
    grid_file = write(tmp_path / "grid.yaml", TINY_GRID.format(out=out, steps=5, quick_report=QUICK))
    env = {**os.environ, "UW3DGS_CACHE": str(cache_dir), "OMP_WAIT_POLICY": "passive"}
    typo = bench(str(grid_file), "--methods", "3dgs", "uw3gds", "--dry-run", env=env)
    output, _ = typo.communicate(timeout=120)
    assert typo.returncode == 2 and "--methods uw3gds: not in the grid, whose methods are 3dgs, uw3dgs" in output
    dry = bench(str(grid_file), "--methods", "3dgs", "--seeds", "0", "--dry-run", env=env)
    output, _ = dry.communicate(timeout=120)
    assert dry.returncode == 0 and "1 of them selected" in output
    assert "tiny/3dgs/s0: new (" in output and output.count(", not selected)") == 3
    run = bench(str(grid_file), "--methods", "3dgs", "--seeds", "0", "--threads-per-job", "1", env=env)
    output, _ = run.communicate(timeout=300)
    assert run.returncode == 0, output
    assert list(results_of(out)) == ["tiny/3dgs/s0/eval/results.json"]
    table = (out / "table.md").read_text()
    assert "| `3dgs` | 1 |" in table and "`uw3dgs`" not in table.split("Not in the table")[0]
    assert "tiny/uw3dgs/s1: not selected: not chosen by --methods/--datasets/--variants/--seeds" in table


@pytest.fixture(scope="module")
def killed_and_resumed(tmp_path_factory, cache_dir):
    """The 2 methods x 1 scene x 2 seeds grid with --jobs 1, stopped (SIGTERM) while its third cell trains, then run
    again to the end. Returns (grid file, output dir, env, what the first run left, the second run's output)."""
    root = tmp_path_factory.mktemp("bench")
    out = root / "out"
    grid_file = write(root / "grid.yaml", TINY_GRID.format(out=out, steps=20, quick_report=QUICK))
    env = {**os.environ, "UW3DGS_CACHE": str(cache_dir), "OMP_WAIT_POLICY": "passive"}
    cells = load_grid(grid_file).cells()
    victim = cells[2]  # uw3dgs s0: the slowest to train, so the stop lands mid-run
    # one thread a cell, as in the --jobs 2 and Ray runs compared with it: how PyTorch splits a reduction or a matrix
    # product among threads depends on the CPU, so numbers are bitwise equal only at equal threads (docs/grids.md)
    first = bench(str(grid_file), "--jobs", "1", "--threads-per-job", "1", env=env)
    deadline = time.monotonic() + 300
    while not (victim.run_dir / "status.json").is_file():
        assert first.poll() is None, f"uw-bench ended before the stop: {first.communicate()[0]}"
        assert time.monotonic() < deadline
        time.sleep(0.02)
    first.send_signal(signal.SIGTERM)
    output, _ = first.communicate(timeout=300)
    assert first.returncode == 130, output
    left = {"checkpoints": {c.name: [p.name for p in list_checkpoints(c.run_dir)] for c in cells},
            "mtimes": {c.name: [p.stat().st_mtime_ns for p in list_checkpoints(c.run_dir)] for c in cells[:2]},
            "states": {c.name: cell_state(c)[0] for c in cells}, "output": output}
    second = bench(str(grid_file), "--jobs", "1", "--threads-per-job", "1", env=env)
    output2, _ = second.communicate(timeout=600)
    assert second.returncode == 0, output2
    return grid_file, out, env, left, output2


@pytest.mark.slow
def test_a_killed_grid_resumes_and_skips_finished_cells(killed_and_resumed):
    grid_file, out, _, left, output = killed_and_resumed
    cells = load_grid(grid_file).cells()
    states = left["states"]
    assert [states[c.name] for c in cells] == [State.DONE, State.DONE, State.RESUME, State.NEW], left["output"]
    assert "run the same uw-bench command again to resume them" in left["output"]
    stopped_at = left["checkpoints"][cells[2].name]
    assert stopped_at and stopped_at[-1] != "step-000020.ckpt"
    # finished cells are not retrained: their checkpoints are the same files, their logs hold one training
    assert {c.name: [p.stat().st_mtime_ns for p in list_checkpoints(c.run_dir)] for c in cells[:2]} == left["mtimes"]
    for cell in cells[:2]:
        assert (cell.run_dir / LOG_NAME).read_text().count("uw3dgs.cli.train") == 1
    log = (cells[2].run_dir / LOG_NAME).read_text()
    assert log.count("uw3dgs.cli.train") == 2 and "--resume" in log and "Stopped by SIGTERM" in log
    assert all(cell_state(c)[0] is State.DONE for c in cells)
    assert len(results_of(out)) == 4
    table = (out / "table.md").read_text()
    assert "| `3dgs` | 2 |" in table and "| `uw3dgs` | 2 |" in table
    assert (out / "table.tex").read_text().startswith("\\begin{tabular}") and (out / "table.csv").is_file()
    assert table in output  # printed too


@pytest.mark.slow
def test_a_finished_grid_runs_nothing_and_other_settings_are_a_conflict(killed_and_resumed):
    grid_file, out, env, _, _ = killed_and_resumed
    again = bench(str(grid_file), "--jobs", "1", env=env)
    output, _ = again.communicate(timeout=120)
    assert again.returncode == 0 and "4 done" in output and "running" not in output
    changed = write(grid_file.with_name("longer.yaml"), TINY_GRID.format(out=out, steps=30, quick_report=QUICK))
    state, why = cell_state(load_grid(changed).cells()[0])
    assert state is State.CONFLICT and "max_num_iterations (20 in the run, 30 in the grid)" in why


@pytest.mark.slow
def test_two_jobs_give_the_numbers_of_one(killed_and_resumed, tmp_path):
    """Also: the cell that was stopped and resumed has the numbers of an uninterrupted run."""
    grid_file, out, env, _, _ = killed_and_resumed
    run = bench(str(grid_file), "--jobs", "2", "--threads-per-job", "1", "--output-dir", str(tmp_path / "out"), env=env)
    output, _ = run.communicate(timeout=600)
    assert run.returncode == 0, output
    assert results_of(tmp_path / "out") == results_of(out)
    assert (tmp_path / "out" / "table.md").read_text() == (out / "table.md").read_text()


@pytest.mark.slow
def test_the_ray_executor_gives_the_table_of_the_local_one(killed_and_resumed, tmp_path):
    pytest.importorskip("ray", reason="Ray is an optional extra (pip install ray); scripts/install.sh installs it")
    grid_file, out, env, _, _ = killed_and_resumed
    run = bench(str(grid_file), "--executor", "ray", "--ray-address", "local", "--threads-per-job", "1",
                "--output-dir", str(tmp_path / "out"), env=env)
    output, _ = run.communicate(timeout=600)
    assert run.returncode == 0, output
    assert "sending 4 cell(s) to Ray" in output
    assert (tmp_path / "out" / "table.md").read_text() == (out / "table.md").read_text()


# ---- the presets -----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("preset, cells", [
    ("demo", 2), ("paper-table1", 120), ("paper-ablation", 120), ("table1-iui3", 21), ("iui3-resolution", 6),
    ("volumetric-iui3-lengths", 6), ("volumetric-synthetic", 3),
    *(pytest.param(name, cells, marks=pytest.mark.slow) for name, cells in (  # the grids behind docs/results.md
        ("iui3-redsea-x8", 9), ("synthetic-6k", 10), ("synthetic-15k-paup", 6), ("synthetic-marine-snow", 2),
        ("paup-enhanced-every", 9), ("paper-ablation-synthetic", 30), ("paper-ablation-iui3", 30)))])
def test_presets_expand_and_every_cell_parses(preset, cells, tmp_path):
    if preset.startswith(("paper-", "iui3-", "volumetric-", "table1-")):
        if not SHARED_SCENE.is_dir():
            pytest.skip(f"{SHARED_SCENE} not found (the shared data beside the repository)")
        for scene in ("IUI3-RedSea", "Curasao", "JapaneseGradens-RedSea", "Panama"):  # stand-ins for the scenes
            (tmp_path / scene).symlink_to(SHARED_SCENE)
    run = subprocess.run([sys.executable, "-m", "uw3dgs.cli.bench", str(REPO / "configs" / f"{preset}.yaml"),
                          "--dry-run", "--data-root", str(tmp_path), "--output-dir", str(tmp_path / "out")],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    assert f"{cells} cells in {tmp_path / 'out'}: {cells} new" in run.stderr
    assert run.stdout.count("uw-train ") == cells


def test_method_args_follow_the_grids_args_and_win(tmp_path):
    from uw3dgs.cli.train import parse_config

    grid = load_grid(write(tmp_path / "g.yaml", """
methods: [3dgs, tensorf]
datasets: {synth: {}}
seeds: [0]
args: [--max-num-iterations, 100]
method_args: {tensorf: [--max-num-iterations, 250]}
"""))
    steps = {cell.method: parse_config(list(cell.argv)).max_num_iterations for cell in grid.cells()}
    assert steps == {"3dgs": 100, "tensorf": 250}
    with pytest.raises(GridError, match="method_args"):
        load_grid(write(tmp_path / "bad.yaml", "methods: [3dgs]\ndatasets: {s: {}}\nseeds: [0]\n"
                                               "method_args: {tensorf: [--seed, 1]}\n"))


def test_options_removed_since_a_run_was_saved_are_no_conflict():
    """A run saved while fields were chosen by a name option holds `model.medium_field`; the grid's config no longer
    has it (the field's `_type` says the same): not a difference. Any other option absent from the grid still is."""
    saved = {"model": {"medium_field": "medium-grid", "medium": {"_type": "G", "resolution": 64}}}
    assert config_differences(saved, {"model": {"medium": {"_type": "G", "resolution": 64}}}) == []
    assert config_differences({"model": {**saved["model"], "typo": 1}}, {"model": saved["model"]}) == \
        ["model.typo (1 in the run, '<absent>' in the grid)"]


def test_options_added_since_a_run_was_saved_take_their_defaults_and_are_no_conflict():
    """A run written before an option existed loads with its default (what `--resume` would train with): the same
    settings as a grid that leaves it at the default, and a grid that sets it otherwise still conflicts."""
    import copy

    from uw3dgs.bench.cell import as_loaded
    from uw3dgs.cli.train import parse_config
    from uw3dgs.config import config_to_dict

    grid_side = config_to_dict(parse_config(["uw3dgs", "--max-num-iterations", "20"]))
    old_run = copy.deepcopy(grid_side)
    del old_run["model"]["medium"]["multiview"]["field_nodes"]  # saved before the field fit existed
    assert config_differences(old_run, grid_side) != []  # as written, it is missing
    assert config_differences(as_loaded(old_run), grid_side) == []
    other = config_to_dict(parse_config(["uw3dgs", "--max-num-iterations", "20",
                                         "--model.medium.multiview.field-nodes", "5"]))
    assert config_differences(as_loaded(old_run), other) == \
        ["model.medium.multiview.field_nodes (7 in the run, 5 in the grid)"]
    assert as_loaded({"_type": "no.such.Config"}) == {"_type": "no.such.Config"}  # compared as written


def test_a_run_saved_before_an_option_whose_default_changed_keeps_what_it_ran_with():
    """The VM grid's start and penalty options (EARLIER_DEFAULTS): a run written before they existed ran with the zero
    basis and the factor norm at 0.001, and is read so (not with today's defaults); one that wrote them keeps them."""
    import copy

    from uw3dgs.bench.cell import as_loaded
    from uw3dgs.cli.train import parse_config
    from uw3dgs.config import config_from_dict, config_to_dict

    today = config_to_dict(parse_config(["uw3dgs", "--max-num-iterations", "20"]))
    old_run = copy.deepcopy(today)
    for option in ("flat_start", "factor_penalty", "factor_penalty_weight"):
        del old_run["model"]["medium"][option]
    medium = config_from_dict(old_run).model.medium
    assert (medium.flat_start, medium.factor_penalty, medium.factor_penalty_weight) == ("zero-basis", "norm", 0.001)
    assert config_differences(as_loaded(old_run), today) == [
        "model.medium.flat_start ('zero-basis' in the run, 'constant-factors' in the grid)",
        "model.medium.factor_penalty ('norm' in the run, 'roughness' in the grid)",
        "model.medium.factor_penalty_weight (0.001 in the run, 0.1 in the grid)"]
    assert config_from_dict(today).model.medium == parse_config(["uw3dgs"]).model.medium
