"""`uw-export`: the 3DGS PLY layout read back with plyfile (names, order, count, values after the 3DGS activations,
the dataset frame), the SH layout, the medium JSON against the model's own medium, and the errors."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import train

from uw3dgs.cli.export import ExportArgs, run_export
from uw3dgs.cli.export import entrypoint as uw_export
from uw3dgs.engine.evaluator import load_trained
from uw3dgs.export.ply import PROPERTIES, gaussian_rows, write_ply

plyfile = pytest.importorskip("plyfile", reason="plyfile reads the PLY back (the dev extra installs it)")


def read_ply(path: Path) -> tuple[list[str], np.ndarray]:
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    names = [p.name for p in vertex.properties]
    return names, np.stack([np.asarray(vertex[name], dtype=np.float64) for name in names], axis=1)


def fake_gaussians(n: int = 4, degree: int = 3, active: int = 3) -> SimpleNamespace:
    g = torch.Generator().manual_seed(0)
    k = (degree + 1) ** 2 - 1
    return SimpleNamespace(
        num_gaussians=n, means=torch.randn(n, 3, generator=g), scales=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g), opacities=torch.randn(n, generator=g),
        sh0=torch.randn(n, 1, 3, generator=g),
        # coefficient k of channel c is 100 c + k + 1: the layout is readable off the values
        shN=(100.0 * torch.arange(3)[None, None, :] + torch.arange(1, k + 1)[None, :, None]).repeat(n, 1, 1),
        active_sh_degree=torch.tensor(active))


def test_rows_undo_the_normalisation_and_keep_the_3dgs_layout(tmp_path):
    gaussians = fake_gaussians()
    center, scale = (10.0, -20.0, 5.0), 2.5
    # a Gaussian placed at a known dataset point comes back there
    known = torch.tensor([12.5, -17.5, 7.5])
    gaussians.means[0] = (known - torch.tensor(center)) / scale
    write_ply(tmp_path / "g.ply", gaussian_rows(gaussians, center, scale))
    names, rows = read_ply(tmp_path / "g.ply")
    assert names == list(PROPERTIES) and len(PROPERTIES) == 62 and rows.shape == (4, 62)
    col = {name: i for i, name in enumerate(names)}
    np.testing.assert_allclose(rows[0, [col["x"], col["y"], col["z"]]], known.numpy(), rtol=1e-6)
    np.testing.assert_allclose(rows[:, :3], (gaussians.means.double() * scale + torch.tensor(center)).numpy(),
                               rtol=1e-6)
    assert np.all(rows[:, 3:6] == 0)
    # after the 3DGS activations: sigmoid(opacity), exp(scale) x the normalisation's scale, the quaternion as is
    np.testing.assert_allclose(1 / (1 + np.exp(-rows[:, col["opacity"]])), torch.sigmoid(gaussians.opacities),
                               rtol=1e-6)
    np.testing.assert_allclose(np.exp(rows[:, col["scale_0"]:col["scale_2"] + 1]),
                               (torch.exp(gaussians.scales) * scale).numpy(), rtol=1e-5)
    np.testing.assert_allclose(rows[:, col["rot_0"]:col["rot_3"] + 1], gaussians.quats.numpy(), rtol=1e-6)
    np.testing.assert_allclose(rows[:, col["f_dc_0"]:col["f_dc_2"] + 1], gaussians.sh0[:, 0].numpy(), rtol=1e-6)
    for c in range(3):  # f_rest channel by channel, 15 coefficients each
        for k in range(15):
            assert rows[1, col[f"f_rest_{c * 15 + k}"]] == 100 * c + k + 1


def test_sh_above_the_rendered_degree_is_zero_and_a_lower_degree_is_padded(tmp_path):
    rows = gaussian_rows(fake_gaussians(active=1), (0.0, 0.0, 0.0), 1.0)
    rest = rows[:, 9:54].reshape(-1, 3, 15)
    assert np.all(rest[:, :, :3] != 0) and np.all(rest[:, :, 3:] == 0)
    rows = gaussian_rows(fake_gaussians(degree=1, active=1), (0.0, 0.0, 0.0), 1.0)
    rest = rows[:, 9:54].reshape(-1, 3, 15)
    assert rows.shape[1] == 62 and np.all(rest[:, :, :3] != 0) and np.all(rest[:, :, 3:] == 0)


@pytest.fixture(scope="module")
def uw3dgs_run(tiny_uw3dgs_trainer) -> Path:
    """The config.yml of the session's 20-step uw3dgs run (conftest)."""
    return tiny_uw3dgs_trainer.run_dir / "config.yml"


def test_export_of_a_trained_run_matches_its_checkpoint(uw3dgs_run, tmp_path):
    ply, medium_path, count = run_export(ExportArgs(load_config=uw3dgs_run, output=tmp_path / "scene.ply",
                                                    medium_samples=3))
    _, datamanager, model, _ = load_trained(uw3dgs_run)
    scene = datamanager.scene
    names, rows = read_ply(ply)
    assert names == list(PROPERTIES) and count == len(rows) == model.num_gaussians
    means, scales, _, opacities = model.gaussians.activated()
    np.testing.assert_allclose(rows[:, :3], (means.double() * scene.dataset_scale
                                             + torch.tensor(scene.dataset_center)).detach().numpy(), rtol=1e-5,
                               atol=1e-6)
    np.testing.assert_allclose(1 / (1 + np.exp(-rows[:, PROPERTIES.index("opacity")])), opacities.detach().numpy(),
                               rtol=1e-5)
    i = PROPERTIES.index("scale_0")
    np.testing.assert_allclose(np.exp(rows[:, i:i + 3]), (scales * scene.dataset_scale).detach().numpy(), rtol=1e-5)
    # scene.medium.json: B_inf and the beta fields of the model, sampled on the grid of its box (dataset frame)
    assert medium_path == tmp_path / "scene.medium.json"
    medium = json.loads(medium_path.read_text())
    assert medium["kind"] == "grid" and medium["shape"] == [3, 3, 3]
    np.testing.assert_allclose(medium["b_inf"], model.medium.b_inf.detach().numpy(), rtol=1e-6)
    box_min, box_max = model.medium.box_min, model.medium.box_max
    np.testing.assert_allclose(medium["bounds_min"], (box_min.double() * scene.dataset_scale
                                                      + torch.tensor(scene.dataset_center)).numpy(), rtol=1e-6)
    beta_d, beta_b = model.medium.betas(torch.stack([box_max, (box_min + box_max) / 2]))
    np.testing.assert_allclose(medium["beta_d"][2][2][2], beta_d[0].detach().numpy(), rtol=1e-5)
    np.testing.assert_allclose(medium["beta_b"][1][1][1], beta_b[1].detach().numpy(), rtol=1e-5)
    # a second export into the folder keeps the first one's medium: each is named after its PLY
    before = medium_path.read_bytes()
    _, other, _ = run_export(ExportArgs(load_config=uw3dgs_run, output=tmp_path / "other.ply", medium_samples=2))
    assert other == tmp_path / "other.medium.json" and json.loads(other.read_text())["shape"] == [2, 2, 2]
    assert medium_path.read_bytes() == before


def test_a_method_without_medium_writes_no_medium_json(make_config, tmp_path):
    run = train(make_config(steps=10)).run_dir
    _, medium, count = run_export(ExportArgs(load_config=run / "config.yml", output=tmp_path / "s.ply"))
    assert medium is None and not list(tmp_path.glob("*.json")) and count > 0


def test_errors_name_the_cause_and_the_fix(make_config, tmp_path, capsys):
    config = make_config(steps=10)
    run = train(config).run_dir
    (tmp_path / "file").write_text("")
    with pytest.raises(SystemExit) as exit_:
        uw_export([str(run / "config.yml"), "--output", str(tmp_path / "file" / "scene.ply")])
    assert exit_.value.code == 2 and "--output" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        uw_export([str(run / "config.yml"), "--output", str(tmp_path / "scene.ply"), "--medium-samples", "1"])
    assert "--medium-samples must be at least 2, got 1" in capsys.readouterr().out
    for ckpt in (run / "checkpoints").iterdir():
        ckpt.unlink()
    with pytest.raises(SystemExit):
        uw_export([str(run / "config.yml"), "--output", str(tmp_path / "scene.ply")])
    out = capsys.readouterr().out
    assert "holds no checkpoint" in out and "train it first" in out
    assert not (tmp_path / "scene.ply").exists()
