"""What docs/training.md and docs/evaluation.md promise one level above a run: one `uw-bench` per grid folder, grid
folders that resume wherever they are, tables that never average different experiments, one safe YAML reader, and
every damaged file, impossible option, full disk or SIGTERM ending in one line (or a clean exit), never a traceback.
Each case on hand-made files or the tiny synthetic scene."""

from __future__ import annotations

import dataclasses
import errno
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml
from conftest import run_command, tiny_train_config, train

from uw3dgs.bench.cell import State, _move_aside, cell_state, expected_config
from uw3dgs.bench.grid import GridError, load_grid
from uw3dgs.bench.lock import grid_lock
from uw3dgs.cli.bench import entrypoint as uw_bench
from uw3dgs.cli.eval import TableArgs, recorded_train_time, run_table
from uw3dgs.cli.eval import entrypoint as uw_eval
from uw3dgs.cli.export import entrypoint as uw_export
from uw3dgs.cli.render import entrypoint as uw_render
from uw3dgs.cli.train import entrypoint as uw_train
from uw3dgs.cli.viewer import entrypoint as uw_viewer
from uw3dgs.config import config_to_dict, load_config
from uw3dgs.datamanagers.synthetic.cli import entrypoint as uw_synth
from uw3dgs.engine.checkpoint import list_checkpoints, load_checkpoint
from uw3dgs.engine.run_folder import RunFolderError, RunLock
from uw3dgs.engine.trainer import TRAIN_TIME_FILE
from uw3dgs.utils import io as uw_io
from uw3dgs.utils.safe_yaml import YamlFileError, load_yaml

SYNTH_ARGS = "[--datamanager.scene.width, 40, --datamanager.scene.height, 30, --datamanager.scene.num-views, 10]"
BOMB = "".join(f"{chr(98 + k)}: &{chr(98 + k)} [{', '.join([f'*{chr(97 + k)}'] * 9)}]\n" for k in range(9))
BOMB = 'a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]\n' + BOMB


def grid_text(out: Path, steps: int = 10, seeds: str = "[0]", datasets: str | None = None) -> str:
    datasets = datasets or f"  tiny: {{datamanager: synthetic, args: {SYNTH_ARGS}}}\n"
    return (f"output_dir: {out}\nmethods: [3dgs]\ndatasets:\n{datasets}seeds: {seeds}\n"
            f"args: [--max-num-iterations, {steps}, --steps-per-save, 5, --steps-per-eval-image, 1000, "
            "--steps-per-eval-all-images, 1000]\n")


def one_line_error(out: str) -> str:
    """The command's error line (uw-train adds a line on how to see the traceback)."""
    lines = [line for line in out.strip().splitlines() if line.strip() and not line.startswith("(set UW3DGS_DEBUG")]
    assert lines and lines[-1].startswith("error: ") and "Traceback" not in out, out
    return lines[-1]


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory, cache_dir, tiny_scene_config) -> Path:
    """A finished 10-step 3dgs run (checkpoints at 5 and 10), evaluated; tests copy it before changing it."""
    config = tiny_train_config(tmp_path_factory.mktemp("trained") / "outputs", cache_dir, tiny_scene_config,
                               steps=10, timestamp="done")
    run = train(dataclasses.replace(config, steps_per_save=5)).run_dir
    uw_eval([str(run / "config.yml"), "--device", "cpu"])
    return run


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def copy_run(run: Path, where: Path) -> Path:
    shutil.copytree(run, where)
    return where


# ---- one safe YAML reader ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("text, key, lines", [
    ("methods: [3dgs]\ndatasets:\n  reef: {}\n  reef: {data: other}\nseeds: [0]\n", "'reef'", "lines 3 and 4"),
    ("methods: [3dgs]\ndatasets: {s: {}}\nseeds: [0]\nargs: [--seed, 1]\nargs: [--max-num-iterations, 9]\n",
     "'args'", "lines 4 and 5"),
    ("methods: [3dgs]\ndatasets: {s: {args: [], args: []}}\nseeds: [0]\n", "'args'", "lines 2 and 2"),
])
def test_a_duplicate_key_in_a_grid_file_is_refused_naming_it_and_both_lines(tmp_path, text, key, lines):
    path = tmp_path / "g.yaml"
    path.write_text(text)
    with pytest.raises(GridError) as err:
        load_grid(path)
    assert str(path) in str(err.value) and f"key {key} is given twice" in str(err.value) and lines in str(err.value)


def test_a_merge_key_is_not_a_duplicate(tmp_path):
    data = load_yaml(tmp_path / "x.yaml", "base: &b {a: 1, b: 2}\nmine:\n  <<: *b\n  a: 3\n")
    assert data["mine"] == {"a": 3, "b": 2}


def test_an_alias_bomb_is_refused_at_once_everywhere(tmp_path, capsys):
    start = time.perf_counter()
    with pytest.raises(YamlFileError, match="aliases expand to more than"):
        load_yaml(tmp_path / "bomb.yaml", BOMB)
    grid = tmp_path / "grid.yaml"
    grid.write_text("methods: [3dgs]\ndatasets: {s: {}}\nseeds: [0]\n" + BOMB)
    with pytest.raises(GridError, match="aliases expand"):
        load_grid(grid)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yml").write_text("_type: uw3dgs.engine.config.TrainConfig\n" + BOMB)
    with pytest.raises(ValueError, match="aliases expand"):
        load_config(run / "config.yml")
    assert time.perf_counter() - start < 2.0
    with pytest.raises(YamlFileError, match="refers to the value that contains it"):
        load_yaml(tmp_path / "loop.yaml", "a: &a [*a]\n")


@pytest.mark.parametrize("content, needle", [
    ("seed: [unclosed\n", "not valid plain YAML (line"),
    ("seed: !!python/object/apply:os.system [ls]\n", "no Python tags"),
    (BOMB, "aliases expand"),
])
def test_a_damaged_cell_config_in_uw_bench_is_one_line_and_the_folder_is_kept(tmp_path, capsys, content, needle):
    out = tmp_path / "out"
    grid = tmp_path / "grid.yaml"
    grid.write_text(grid_text(out))
    cell = load_grid(grid).cells()[0]
    cell.run_dir.mkdir(parents=True)
    (cell.run_dir / "config.yml").write_text(content)
    state, why = cell_state(cell)
    assert state is State.CONFLICT and str(cell.run_dir / "config.yml") in why and needle in why
    assert "never deletes" in why and "delete that" not in why
    code, stdout, stderr = run_command(uw_bench, [str(grid), "--no-table"], capsys)
    assert code == 1 and "Traceback" not in stdout + stderr and needle in stderr
    assert (cell.run_dir / "config.yml").read_text() == content


# ---- the grid file ---------------------------------------------------------------------------------------------------


def test_a_dataset_name_starting_with_a_dot_is_refused(tmp_path):
    path = tmp_path / "g.yaml"
    path.write_text("methods: [3dgs]\ndatasets: {.reef: {}}\nseeds: [0]\n")
    with pytest.raises(GridError, match=r"dataset name '.reef' starts with a dot .* rename it, e.g. 'reef'"):
        load_grid(path)


def test_a_seed_beyond_64_bits_is_one_line(tmp_path, capsys):
    path = tmp_path / "g.yaml"
    path.write_text(f"methods: [3dgs]\ndatasets: {{s: {{}}}}\nseeds: [0, {2**64}]\n")
    with pytest.raises(GridError, match=f"`seeds`: {2**64} is not a 64-bit seed"):
        load_grid(path)
    code, out, _ = run_command(uw_train, ["3dgs", "--seed", str(2**70), "--output-dir", str(tmp_path)], capsys)
    assert code == 2 and "--seed must be a whole number from 0 to 2**64 - 1" in one_line_error(out)


# ---- one uw-bench per grid folder; a held run is never moved -------------------------------------------------------


def test_a_second_uw_bench_on_a_held_grid_folder_refuses_naming_the_holder(tmp_path, capsys):
    out = tmp_path / "out"
    grid = tmp_path / "grid.yaml"
    grid.write_text(grid_text(out))
    lock = grid_lock(out)
    lock.acquire()  # another uw-bench (flock: a second open file of one process conflicts like another process)
    try:
        code, stdout, _ = run_command(uw_bench, [str(grid)], capsys)
    finally:
        lock.release()
    line = one_line_error(stdout)
    assert code == 2 and f"{out} is in use by another uw-bench (pid {os.getpid()}" in line and "--output-dir" in line
    assert not (out / "tiny").exists()  # nothing planned, nothing trained


def test_a_run_folder_held_by_a_training_is_never_moved(tmp_path):
    out = tmp_path / "out"
    grid = tmp_path / "grid.yaml"
    grid.write_text(grid_text(out))
    cell = load_grid(grid).cells()[0]
    cell.run_dir.mkdir(parents=True)
    (cell.run_dir / "config.yml").write_text(yaml.safe_dump(expected_config(cell)))  # no checkpoint yet: 'restart'
    assert cell_state(cell)[0] is State.RESTART
    held = RunLock(cell.run_dir)
    held.acquire()
    try:
        state, why = cell_state(cell)
        assert state is State.CONFLICT and "in use by another training (pid" in why
        with pytest.raises(RunFolderError, match="in use by another training"):
            _move_aside(cell.run_dir)
        assert (cell.run_dir / "config.yml").is_file()
    finally:
        held.release()


def fake_finished_cell(cell, output_dir_then: Path) -> None:
    """The cell's folder as a finished, evaluated run leaves it (written under another output_dir)."""
    config = expected_config(cell)
    config["output_dir"] = str(output_dir_then)
    cell.run_dir.mkdir(parents=True)
    (cell.run_dir / "config.yml").write_text(yaml.safe_dump(config))
    (cell.run_dir / "checkpoints").mkdir()
    (cell.run_dir / "checkpoints" / "step-000010.ckpt").write_bytes(b"")
    (cell.run_dir / "eval").mkdir()
    (cell.run_dir / "eval" / "results.json").write_text(json.dumps({
        "experiment_name": cell.dataset, "method_name": cell.method, "results": {"psnr": 20.0, "train_steps": 10},
        "checkpoint": str(output_dir_then / "checkpoints" / "step-000010.ckpt"), "data": {}}))


def test_a_moved_grid_folder_resumes_and_advice_never_deletes(tmp_path, capsys):
    grid = tmp_path / "grid.yaml"
    grid.write_text(grid_text(tmp_path / "moved"))
    cell = load_grid(grid).cells()[0]
    fake_finished_cell(cell, tmp_path / "first-place")
    assert cell_state(cell) == (State.DONE, "trained and evaluated")
    code, stdout, stderr = run_command(uw_bench, [str(grid), "--no-table"], capsys)
    assert code == 0 and "1 done" in stderr
    longer = tmp_path / "longer.yaml"
    longer.write_text(grid_text(tmp_path / "moved", steps=20))
    state, why = cell_state(load_grid(longer).cells()[0])
    assert state is State.CONFLICT and "max_num_iterations (10 in the run, 20 in the grid)" in why
    assert "delete" not in why.replace("never deletes", "") and "move that folder aside" in why


@pytest.mark.slow
def test_two_uw_bench_processes_on_one_folder(tmp_path, cache_dir):
    """The second refuses at once, naming the folder and the first's pid; the first trains every cell once and
    finishes with exit 0, its table intact."""
    out = tmp_path / "out"
    grid = tmp_path / "grid.yaml"
    grid.write_text(grid_text(out, steps=30, seeds="[0, 1]"))
    env = {**os.environ, "UW3DGS_CACHE": str(cache_dir), "OMP_WAIT_POLICY": "passive"}
    command = [sys.executable, "-m", "uw3dgs.cli.bench", str(grid)]
    first = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 900  # a busy machine builds the compiled kernels slowly
    cells = load_grid(grid).cells()
    while not (cells[0].run_dir / ".uw-train.lock").is_file():  # the first cell trains
        assert first.poll() is None, first.communicate()[0]
        assert time.monotonic() < deadline
        time.sleep(0.05)
    second = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert second.returncode == 2, second.stdout + second.stderr
    assert f"{out} is in use by another uw-bench (pid {first.pid} on" in second.stdout
    output, _ = first.communicate(timeout=1800)
    assert first.returncode == 0, output
    for cell in cells:
        assert (cell.run_dir / "bench.log").read_text().count("uw3dgs.cli.train") == 1
        assert [p.name for p in list_checkpoints(cell.run_dir)][-1] == "step-000030.ckpt"
    assert not list(out.glob("tiny/3dgs/.*"))  # nothing moved aside
    assert "| `3dgs` | 2 |" in (out / "table.md").read_text()


# ---- tables that never average different experiments -----------------------------------------------------------


def table_run(root: Path, name: str, method: str, psnr: object, data: dict, steps: int = 100,
              scene: str = "reef") -> Path:
    run = root / name
    run.mkdir(parents=True)
    (run / "config.yml").write_text(f"_type: uw3dgs.engine.config.TrainConfig\nmethod_name: {method}\n")
    (run / "eval").mkdir()
    (run / "eval" / "results.json").write_text(json.dumps({
        "experiment_name": scene, "method_name": method, "checkpoint": "step-000100.ckpt",
        "results": {"psnr": psnr, "ssim": 0.9, "train_steps": steps}, "data": data}))
    return run


def data(path: str = "/data/reef", fingerprint: str = "f1", downscale: int = 8, split: str = "s1") -> dict:
    return {"path": path, "fingerprint": fingerprint, "downscale_factor": downscale,
            "resolution": [800 // downscale, 600 // downscale], "split": {"fingerprint": split}}


def table(root: Path, capsys, fmt: str = "json") -> tuple[object, str]:
    text = run_table(TableArgs(runs=(root,), format=fmt, eval=False))
    return (json.loads(text) if fmt == "json" else text), capsys.readouterr().err


def test_runs_of_one_experiment_are_seeds_of_one_row(tmp_path, capsys):
    for seed in range(3):
        table_run(tmp_path, f"s{seed}", "3dgs", 30.0 + seed, data())
    rows, _ = table(tmp_path, capsys)
    assert [(r["scene"], r["method"], r["n"], r["psnr_mean"]) for r in rows] == [("reef", "3dgs", 3, 31.0)]


@pytest.mark.parametrize("other, label", [
    (data(downscale=4), "downscale"),
    (data(path="/elsewhere/reef"), "data /elsewhere/reef"),
    (data(fingerprint="f2"), "data fingerprint f2"),
    (data(split="s2"), "split s2"),
])
def test_runs_on_different_data_are_never_averaged(tmp_path, capsys, other, label):
    table_run(tmp_path, "a", "3dgs", 30.0, data())
    table_run(tmp_path, "b", "3dgs", 20.0, other)
    table_run(tmp_path, "c", "uw3dgs", 31.0, data())
    rows, messages = table(tmp_path, capsys)
    assert len(rows) == 3 and all(r["n"] == 1 for r in rows)
    scenes = {r["scene"] for r in rows}
    assert len(scenes) == 2 and any(label in s for s in scenes) and all(s.startswith("reef [") for s in scenes)
    assert "reef: its runs were trained on different data" in messages
    md, _ = table(tmp_path, capsys, "md")
    assert "Notes:" in md and label in md


def test_runs_of_different_lengths_are_rows_of_their_own(tmp_path, capsys):
    table_run(tmp_path, "a", "3dgs", 30.0, data(), steps=6000)
    table_run(tmp_path, "b", "3dgs", 31.0, data(), steps=6000)
    table_run(tmp_path, "c", "3dgs", 20.0, data(), steps=2000)
    rows, messages = table(tmp_path, capsys)
    assert {(r["method"], r["n"]) for r in rows} == {("3dgs [6000 steps]", 2), ("3dgs [2000 steps]", 1)}
    assert "runs of different lengths (6000, 2000 steps) are rows of their own" in messages


def test_an_infinite_or_unreadable_metric_keeps_its_column(tmp_path, capsys):
    table_run(tmp_path, "a", "3dgs", float("inf"), data())
    table_run(tmp_path, "b", "uw3dgs", "n/a", data())
    table_run(tmp_path, "c", "uw3dgs", 30.0, data())
    md, messages = table(tmp_path, capsys, "md")
    header = md.splitlines()[0]
    assert "reef: PSNR" in header
    row = next(line for line in md.splitlines() if line.startswith("| `3dgs`"))
    assert "inf" in row
    assert "psnr is 'n/a', not a number: shown as missing" in md and "(n=1)" in md


def test_a_corrupt_train_time_record_falls_back_to_the_checkpoint(tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    checkpoint = run / "checkpoints" / "step-000010.ckpt"
    torch.save({"model": {"w": torch.zeros(1)}, "train_seconds": 12.5}, checkpoint)
    (run / TRAIN_TIME_FILE).write_text("{not json")
    assert recorded_train_time(run, checkpoint) == (12.5, 10)
    (run / TRAIN_TIME_FILE).write_text(json.dumps({"checkpoints": {"10": "garbage"}}))
    assert recorded_train_time(run, checkpoint) == (12.5, 10)


# ---- checkpoints that are not this run's -------------------------------------------------------------------------


class NotAllowed:
    pass


@pytest.mark.parametrize("state, needle", [
    ({}, "is not a uw3dgs checkpoint (it holds keys none"),
    ({"state_dict": {"w": torch.zeros(2)}}, "is not a uw3dgs checkpoint (it holds keys ['state_dict']"),
    ([1, 2], "is not a uw3dgs checkpoint (it holds a list"),
    ({"model": NotAllowed()}, "holds a Python object (test_grid_guarantees.NotAllowed) that the safe loader refuses"),
])
def test_a_checkpoint_that_is_not_uw3dgs_is_one_line(tmp_path, state, needle):
    path = tmp_path / "step-000001.ckpt"
    torch.save(state, path)
    with pytest.raises(RuntimeError) as err:
        load_checkpoint(path)
    assert needle in str(err.value) and "\n" not in str(err.value) and "weights_only" not in str(err.value)


def test_bad_checkpoints_are_one_line_in_every_command(trained_run, tmp_path, capsys):
    """An empty dict, another tool's file, another method's state dict: uw-eval, uw-export, uw-render, uw-viewer and
    --resume each say so in one line; uw-eval table skips that run, names it, and makes the table of the rest."""
    good = copy_run(trained_run, tmp_path / "runs" / "good")
    for name, state in [("empty", {}), ("other-tool", {"state_dict": {"w": torch.zeros(3)}}),
                        ("other-method", {"model": {"medium.b_inf": torch.zeros(3)}})]:
        run = copy_run(trained_run, tmp_path / "runs" / name)
        shutil.rmtree(run / "eval")
        for checkpoint in list_checkpoints(run):
            torch.save(state, checkpoint)
        config = str(run / "config.yml")
        needle = "does not hold the parameters of this run's 3dgs model" if name == "other-method" else \
            "is not a uw3dgs checkpoint"
        for command, argv in [(uw_eval, [config]), (uw_export, [config, "--output", str(tmp_path / "s.ply")]),
                              (uw_render, [config, "--images", str(tmp_path / "frames")]),
                              (uw_viewer, [config, "--port", str(free_port())]),
                              (uw_train, ["--load-config", config, "--resume"])]:
            if command is uw_viewer:
                pytest.importorskip("viser")
            code, out, err = run_command(command, argv, capsys)
            line = one_line_error(out)
            assert code == 2 and str(run / "checkpoints") in line, (command, line)
            if command is not uw_train or name != "other-method":
                assert needle in line, (command, line)
    rows = json.loads(run_table(TableArgs(runs=(tmp_path / "runs",), format="json", device="cpu")))
    skipped = capsys.readouterr().err
    assert [r["n"] for r in rows] == [1] and rows[0]["runs"] == [str(good)]
    for name in ("empty", "other-tool", "other-method"):
        assert f"skipped {tmp_path / 'runs' / name}: cannot be evaluated" in skipped.replace("\n", "")


# ---- impossible options ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fps", ["inf", "1e-9", "nan", "0"])
def test_uw_render_refuses_an_impossible_frame_rate(tmp_path, capsys, fps):
    code, out, _ = run_command(uw_render, [str(tmp_path / "config.yml"), "--fps", fps], capsys)
    assert code == 2 and "--fps must be between 0.01 and 1000 frames per second" in one_line_error(out)


def test_uw_render_says_the_cost_up_front_and_bounds_it(trained_run, tmp_path, capsys, monkeypatch):
    config = str(trained_run / "config.yml")
    start = time.perf_counter()
    code, out, _ = run_command(uw_render, [config, "--path", "spiral", "--num-frames", "1000000000"], capsys)
    line = one_line_error(out)
    assert code == 2 and "1,000,000,000 frame(s): about" in line and "more than --max-hours 24" in line
    assert time.perf_counter() - start < 60 and not (trained_run / "render").exists()
    monkeypatch.setattr(shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(10**9, 10**9 - 10**6, 10**6))
    code, out, _ = run_command(uw_render, [config, "--path", "spiral", "--num-frames", "1000", "--images",
                                           str(tmp_path / "frames")], capsys)
    line = one_line_error(out)
    assert code == 2 and "their PNGs may need up to" in line and "GiB free" in line
    assert not (tmp_path / "frames").exists()


@pytest.mark.parametrize("port", ["70000", "-1", "0"])
def test_uw_viewer_refuses_a_port_that_is_not_one(tmp_path, capsys, port):
    pytest.importorskip("viser")
    code, out, _ = run_command(uw_viewer, [str(tmp_path / "config.yml"), "--port", port], capsys)
    assert code == 2 and f"--port {port} is not a port; give one from 1 to 65535" in one_line_error(out)


def test_uw_synth_refuses_a_scene_that_cannot_fit_in_memory_before_allocating(tmp_path, capsys):
    start = time.perf_counter()
    code, out, _ = run_command(uw_synth, ["--out", str(tmp_path / "s"), "--width", "200000", "--height", "200000"],
                               capsys)
    line = one_line_error(out)
    assert code == 2 and "GiB of memory (--width 200000 x --height 200000" in line and "choose a smaller scene" in line
    assert time.perf_counter() - start < 10 and not (tmp_path / "s").exists()


# ---- a full disk -------------------------------------------------------------------------------------------------


def fill_disk(monkeypatch, suffix: str) -> None:
    """Writes through `atomic_file` to a file whose name ends in `suffix` fail as on a full disk (the OSError of
    write(), which names no file)."""
    real_open = open

    class Full(io.RawIOBase):
        def __init__(self, file):
            self.file = file

        def write(self, data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        def writable(self):
            return True

        def fileno(self):
            return self.file.fileno()

        def close(self):
            self.file.close()
            super().close()

    def opener(path, mode="r", *args, **kwargs):
        file = real_open(path, mode, *args, **kwargs)
        return Full(file) if str(path).endswith(f"{suffix}.tmp") or suffix in Path(path).name else file

    monkeypatch.setattr(uw_io, "open", opener, raising=False)


def test_a_full_disk_is_no_space_left_with_the_path(trained_run, tmp_path, capsys, monkeypatch, make_config):
    fill_disk(monkeypatch, ".ckpt")
    config = dataclasses.replace(make_config(steps=5), steps_per_save=5)
    config_file = tmp_path / "train.yml"
    config_file.write_text(yaml.safe_dump(config_to_dict(config)))
    code, out, _ = run_command(uw_train, ["--load-config", str(config_file)], capsys)
    line = one_line_error(out)
    assert code == 2 and "step-000005.ckpt: No space left on device (the disk is full; free some space)" in line
    assert "enforce fail" not in out and "?" not in line.split(":")[1]
    fill_disk(monkeypatch, ".ply")
    code, out, _ = run_command(uw_export, [str(trained_run / "config.yml"), "--output", str(tmp_path / "s.ply")],
                               capsys)
    assert code == 2 and f"{tmp_path / 's.ply'}: No space left on device" in one_line_error(out)
    fill_disk(monkeypatch, ".png")
    code, out, _ = run_command(uw_render, [str(trained_run / "config.yml"), "--path", "test", "--images",
                                           str(tmp_path / "frames")], capsys)
    line = one_line_error(out)
    assert code == 2 and str(tmp_path / "frames") in line and ".png: No space left on device" in line


# ---- SIGTERM -----------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_sigterm_to_uw_render_and_uw_viewer_is_a_clean_exit(trained_run, tmp_path, cache_dir):
    env = {**os.environ, "UW3DGS_CACHE": str(cache_dir), "COLUMNS": "200"}
    config = str(trained_run / "config.yml")
    video = tmp_path / "v.mp4"
    # thousands of frames, seconds of rendering after the first: still running when the signal comes (the path's
    # poses are made one by one before the first frame, so not more)
    render = subprocess.Popen([sys.executable, "-m", "uw3dgs.cli.render", config, "--path", "spiral",
                               "--num-frames", "5000", "--max-hours", "1e6", "--output", str(video)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 900
    while not list(tmp_path.glob(".v.mp4.*.tmp")):  # ffmpeg is writing the temporary video
        assert render.poll() is None and time.monotonic() < deadline, render.communicate()[0]
        time.sleep(0.05)
    render.send_signal(signal.SIGTERM)
    output, _ = render.communicate(timeout=60)
    assert render.returncode == 143 and "Interrupted" in output and "Traceback" not in output, output
    assert "SIGTERM" not in output.replace("Interrupted", "") and list(tmp_path.iterdir()) == []
    pytest.importorskip("viser")
    viewer = subprocess.Popen([sys.executable, "-m", "uw3dgs.cli.viewer", config, "--port", str(free_port())],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    line = ""
    while "viewer at" not in line:
        line = viewer.stdout.readline()
        assert line or viewer.poll() is None, viewer.communicate()[0]
    viewer.send_signal(signal.SIGTERM)
    output, _ = viewer.communicate(timeout=60)
    assert viewer.returncode == 0 and "Stopped." in output and "Traceback" not in output, output

