"""Training progress where stderr is not a terminal (a log file): plain periodic lines instead of a bar."""

from __future__ import annotations

from uw3dgs.engine import progress
from uw3dgs.engine.progress import TrainingProgress


def test_a_log_gets_plain_periodic_lines(capsys, monkeypatch):
    monkeypatch.setattr(progress, "PLAIN_LINE_SECONDS", 1e9)  # only the last step's line is due
    with TrainingProgress(total=5, start=0) as bar:
        assert bar.plain  # pytest's stderr is no terminal
        for step in range(1, 6):
            bar.update(step, 0.5, {"psnr": 20.0, "num_gaussians": 1234}, 0.01)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("train ")]
    assert len(lines) == 1 and lines[0].startswith("train 5/5 (100%) | loss 0.5000 | PSNR 20.00 | 1,234 G")
    monkeypatch.setattr(progress, "PLAIN_LINE_SECONDS", 0.0)  # every step's line is due
    with TrainingProgress(total=3, start=0) as bar:
        for step in range(1, 4):
            bar.update(step, 0.5, {}, 0.01)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("train ")]
    assert [line.split(" |")[0] for line in lines] == ["train 1/3 (33%)", "train 2/3 (67%)", "train 3/3 (100%)"]
    assert "min left" in lines[0]
