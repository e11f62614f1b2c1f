"""floater_ratio: big Gaussians in front of the surface in at least half of the training views that see them."""

from __future__ import annotations

import json

import pytest
import torch

from uw3dgs.cameras import Camera
from uw3dgs.cli.eval import EvalArgs, run_eval
from uw3dgs.data.scene import GroundTruth, SceneData
from uw3dgs.engine.trainer import Trainer
from uw3dgs.methods.gaussian_splatting import GaussianSplattingModelConfig
from uw3dgs.methods.uw3dgs import UW3DGSModelConfig
from uw3dgs.metrics.floaters import floater_ratio, floater_votes, floating_in_view, seen_in_view


def look_down_camera(center, width=40, height=30, focal=40.0) -> Camera:
    """A camera at `center` looking down -z (world), OpenCV axes."""
    R = torch.tensor([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # world-to-camera rotation
    viewmat = torch.eye(4)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ torch.tensor(center, dtype=torch.float32)
    K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]])
    return Camera(viewmat, K, width, height)


# ---- the pure functions, by hand ---------------------------------------------------------------------------------

def test_seen_in_view_needs_the_centre_inside_in_front_and_blended():
    means2d = torch.tensor([[2.5, 1.5], [-0.2, 1.0], [3.9, 2.9], [1.0, 1.0], [1.0, 1.0], [0.0, 3.0]])
    radii = torch.tensor([1, 1, 1, 0, 1, 1], dtype=torch.int32)
    pixel_count = torch.tensor([3, 3, 0, 3, 3, 3], dtype=torch.int32)
    in_front = torch.tensor([True, True, True, True, False, True])
    pixels, seen = seen_in_view(means2d, radii, pixel_count, in_front, width=4, height=3)
    assert pixels.tolist() == [[2, 1], [-1, 1], [3, 2], [1, 1], [1, 1], [0, 3]]
    # outside (u = -1), never blended, radius 0, behind the camera, below the image (v = 3 of 3 rows)
    assert seen.tolist() == [True, False, False, False, False, False]


def test_floating_in_view_compares_with_the_surface_at_the_centre_pixel():
    surface = torch.tensor([[10.0, 10.0, 10.0], [10.0, 20.0, float("inf")]])  # [H = 2, W = 3]
    pixels = torch.tensor([[0, 0], [0, 0], [1, 1], [2, 1], [2, 1], [7, 9]])
    own = torch.tensor([8.9, 9.1, 17.9, 1e6, 1.0, 1.0])
    seen = torch.tensor([True, True, True, True, False, False])
    # 8.9 < 0.9 x 10; 9.1 is within 10% of it; 17.9 < 18; anything is in front of open water (inf); unseen: never
    # (also when its pixel lies outside the image)
    assert floating_in_view(own, pixels, seen, surface).tolist() == [True, False, True, True, False, False]


def test_floater_ratio_counts_big_ones_floating_in_at_least_half_the_views_that_see_them():
    # median largest scale 1: big means above 2 (exactly 2 is not big)
    max_scale = torch.tensor([3.0, 3.0, 3.0, 3.0, 2.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    seen = torch.tensor([4, 3, 0, 2, 4, 4, 4, 4, 4, 4, 4])
    floating = torch.tensor([2, 1, 0, 2, 4, 4, 4, 4, 0, 0, 0])
    # 0: 2 of 4 (half) floats; 1: 1 of 3 does not; 2: seen by no view, not floating; 3: 2 of 2;
    # 4: exactly twice the median is not big; 5-7: floating but small; all 11 are the denominator
    assert floater_ratio(max_scale, floating, seen) == pytest.approx(2 / 11)
    assert floater_ratio(torch.zeros(0), torch.zeros(0), torch.zeros(0)) is None


def test_floater_votes_over_views():
    """Three views. Against the rendered surface: Gaussian 0 is big and seen by two of them (not blended in the
    third), floating in one of those two: a floater. Gaussian 1 is big, seen by all three and floats in one: not.
    Gaussian 2 is big and behind every camera: no view sees it. Gaussians 3-6 are small (and float everywhere)."""
    cameras = [look_down_camera([0.0, 0.0, 5.0], width=8, height=6, focal=4.0) for _ in range(3)]
    means = torch.tensor([[0.0, 0.0, 2.0], [0.5, 0.5, 1.0], [0.0, 0.0, 6.0],
                          [0.2, 0.0, 4.0], [0.0, 0.2, 4.0], [-0.2, 0.0, 4.0], [0.0, -0.2, 4.0]])
    # ranges: Gaussian 0 3, Gaussian 1 4.06, Gaussians 3-6 1.02; view 1: Gaussians 0 and 1 are within 10% of the
    # surface or behind it, view 2: Gaussian 1 is (4.06 > 0.9 x 4.4)
    surfaces = [10.0, 3.2, 4.4]
    blended = [[1, 1, 1, 1, 1, 1, 1], [1, 1, 1, 1, 1, 1, 1], [0, 1, 1, 1, 1, 1, 1]]

    def render(k: int, camera: Camera) -> dict:
        uv, _ = camera.project(means)
        count = torch.tensor(blended[k], dtype=torch.int32)
        return {"range": torch.full((6, 8), surfaces[k]), "means2d": uv, "radii": count, "pixel_count": count}

    calls = iter(range(3))
    truth = [torch.full((6, 8), 3.2), torch.full((6, 8), 10.0), torch.full((6, 8), 10.0)]
    votes = floater_votes(means, cameras, lambda camera: render(next(calls), camera), truth)
    assert votes["seen"].tolist() == [2, 3, 0, 3, 3, 3, 3]
    assert votes["floating"].tolist() == [1, 1, 0, 3, 3, 3, 3]
    assert votes["floating_gt"].tolist() == [1, 2, 0, 3, 3, 3, 3]
    max_scale = torch.tensor([1.0, 1.0, 1.0, 0.1, 0.1, 0.1, 0.1])
    assert floater_ratio(max_scale, votes["floating"], votes["seen"]) == pytest.approx(1 / 7)
    # truth: Gaussian 1 floats in views 1, 2 of 3 (4.06 < 9) and not in view 0 (4.06 > 0.9 x 3.2): a floater too
    assert floater_ratio(max_scale, votes["floating_gt"], votes["seen"]) == pytest.approx(2 / 7)


# ---- a hand-made model through the real renderer -----------------------------------------------------------------

HEIGHT = 3.0
"""The cameras' height above the seabed plane z = 0."""


def plane_scene():
    """An opaque plane of small Gaussians under three downward cameras; over it 3 big semi-transparent floaters, 2
    big flat Gaussians lying on the plane (big, not floating), 3 small semi-transparent ones in front (floating, not
    big), 1 big one behind the cameras and 1 far to the side (seen by no view). Returns (scene, scales, opacities,
    the number of floaters)."""
    xs = torch.arange(-1.6, 1.6001, 0.05)
    ys = torch.arange(-1.2, 1.2001, 0.05)
    gx, gy = torch.meshgrid(xs, ys, indexing="ij")
    plane = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.zeros(gx.numel())], dim=-1)
    # all inside every view, apart on screen (their footprints barely overlap)
    floaters = torch.tensor([[-0.5, -0.35, 1.0], [0.7, -0.35, 1.0], [0.1, 0.3, 1.5]])
    on_plane = torch.tensor([[-0.9, 0.6, 0.05], [0.9, 0.6, 0.05]])
    small_front = torch.tensor([[0.1, -0.35, 1.0], [-0.5, 0.45, 1.0], [0.7, 0.45, 1.0]])
    unseen = torch.tensor([[0.0, 0.0, 2.0 * HEIGHT], [20.0, 0.0, 1.0]])
    means = torch.cat([plane, floaters, on_plane, small_front, unseen])
    scales = torch.cat([torch.full((len(plane), 3), 0.04), torch.full((3, 3), 0.15),
                        torch.tensor([[0.2, 0.2, 0.01]]).repeat(2, 1), torch.full((3, 3), 0.04),
                        torch.full((2, 3), 0.3)])
    opacities = torch.cat([torch.full((len(plane),), 0.99), torch.full((3,), 0.3), torch.full((2,), 0.99),
                           torch.full((3,), 0.3), torch.full((2,), 0.9)])
    cameras = [look_down_camera([x, y, HEIGHT]) for x, y in ((0.0, 0.0), (0.25, 0.0), (0.0, -0.2))]
    n = len(cameras)
    true_ranges = torch.stack([HEIGHT * c.ray_norms() for c in cameras])  # the plane, exactly
    gt = GroundTruth(clean_images=torch.zeros(n, 30, 40, 3), ranges=true_ranges,
                     medium={"beta_D": [0.4, 0.2, 0.1], "beta_B": [0.3, 0.2, 0.2], "B_inf": [0.1, 0.2, 0.3]})
    scene = SceneData(name="plane", image_names=[f"{i:04d}.png" for i in range(n)], images=torch.zeros(n, 30, 40, 3),
                      cameras=cameras, points=means, point_colors=torch.full_like(means, 0.5), near=0.1, far=10.0,
                      gt=gt)
    return scene, scales, opacities, len(floaters)


@pytest.mark.parametrize("config", [GaussianSplattingModelConfig(), UW3DGSModelConfig()], ids=["3dgs", "uw3dgs"])
def test_a_plane_with_known_floaters(config):
    scene, scales, opacities, k = plane_scene()
    model = config.setup(scene=scene, train_indices=list(range(len(scene.cameras))))
    with torch.no_grad():
        model.gaussians.scales.copy_(scales.log())
        model.gaussians.opacities.copy_(torch.logit(opacities))
    n = model.num_gaussians
    summary = model.get_eval_summary(scene)
    assert model.training  # left as it was
    assert summary["floater_ratio"] == k / n
    assert summary["floater_ratio_gt"] == k / n
    # the rendered surface stays on the plane under the semi-transparent ones: both small ones in front and big
    # ones count as floating there; only size tells them apart
    means = model.gaussians.means.detach()
    votes = floater_votes(means, scene.cameras, model.render, list(scene.gt.ranges))
    assert votes["seen"][-2:].tolist() == [0, 0] and bool((votes["seen"][-10:-2] == 3).all())
    assert votes["floating"][-10:].tolist() == [3, 3, 3, 0, 0, 3, 3, 3, 0, 0]
    assert votes["floating_gt"][-10:].tolist() == [3, 3, 3, 0, 0, 3, 3, 3, 0, 0]
    if isinstance(config, UW3DGSModelConfig):  # merged with the medium's numbers
        assert "b_inf_r" in summary and "beta_d_rel_error" in summary
    scene.gt = None  # a real scene: no true ranges, no floater_ratio_gt
    assert "floater_ratio_gt" not in model.get_eval_summary(scene)


# ---- uw-eval -----------------------------------------------------------------------------------------------------

def test_uw_eval_reports_the_floater_ratio(make_config):
    trainer = Trainer(make_config(steps=20, timestamp="floaters"))
    trainer.setup()
    trainer.train()
    out = trainer.run_dir / "metrics.json"
    run_eval(EvalArgs(load_config=trainer.run_dir / "config.yml", output_path=out, save_renders=False))
    saved = json.loads(out.read_text())
    assert saved["notes"] == {}  # 3dgs keeps no notes on how it started
    results = saved["results"]
    for key in ("floater_ratio", "floater_ratio_gt"):  # the synthetic scene knows its true ranges
        assert 0.0 <= results[key] <= 1.0
