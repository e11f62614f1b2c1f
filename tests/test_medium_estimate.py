"""The SfM-point medium estimate: point observations, the homogeneous fit, and the synthetic scene."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.fields.medium_estimate import (
    _project,
    clean_colors,
    color_ranges,
    dark_pixels,
    estimate_medium,
    find_open_water,
    fit_backscatter,
    fit_backscatter_residual,
    fit_medium,
    observe_points,
    open_water_color,
)
from uw3dgs.fields.medium_identifiability import (
    IdentifiabilityConfig,
    assess_medium,
    bootstrap_observations,
    far_end,
    recoverable_range,
)
from uw3dgs.options import OptionError

TRUE_D, TRUE_B = torch.tensor([0.4, 0.2, 0.12]), torch.tensor([0.3, 0.25, 0.2])
TRUE_BINF = torch.tensor([0.05, 0.25, 0.35])  # the built-in scene's medium


def look_at_camera(center, width=40, height=30) -> Camera:
    """A camera at `center` looking down -z (world), OpenCV axes."""
    R = torch.tensor([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # world-to-camera rotation
    viewmat = torch.eye(4)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ torch.tensor(center, dtype=torch.float32)
    K = torch.tensor([[30.0, 0, width / 2], [0, 30.0, height / 2], [0, 0, 1]])
    return Camera(viewmat, K, width, height)


def test_observe_points_reads_the_projected_pixel_and_the_range():
    cams = [look_at_camera([0.0, 0.0, 5.0]), look_at_camera([1.0, 0.5, 3.0])]
    images = [torch.rand(30, 40, 3), torch.rand(30, 40, 3)]
    points = torch.tensor([[0.13, 0.21, 0.0], [-1.0, 0.7, 1.0], [30.0, 0.0, 0.0], [0.0, 0.0, 6.0]])
    idx, colors, ranges = observe_points(points, cams, images)
    expected = []
    for k, cam in enumerate(cams):  # brute force in float64
        vm, K = cam.viewmat.double().numpy(), cam.K.double().numpy()
        for i, p in enumerate(points.double().numpy()):
            pc = vm[:3, :3] @ p + vm[:3, 3]
            if pc[2] <= 0:
                continue  # behind the camera (point 3 for both)
            u, v = (K @ (pc / pc[2]))[:2]
            if 0 <= u < cam.width and 0 <= v < cam.height:  # point 2: outside both; 1: outside the 2nd
                centre = -vm[:3, :3].T @ vm[:3, 3]
                expected.append((i, images[k][int(v), int(u)], np.linalg.norm(p - centre)))
    assert idx.tolist() == [e[0] for e in expected] and len(expected) == 3
    torch.testing.assert_close(colors, torch.stack([e[1] for e in expected]))
    torch.testing.assert_close(ranges, torch.tensor([e[2] for e in expected], dtype=torch.float32))


def test_estimate_without_multi_view_points_names_the_fix():
    cams = [look_at_camera([0.0, 0.0, 5.0]), look_at_camera([1.0, 0.5, 3.0])]
    images = [torch.rand(30, 40, 3), torch.rand(30, 40, 3)]
    points = torch.tensor([[0.0, 0.0, 9.0], [0.1, 0.0, 0.0]])  # behind both cameras; seen by 2 < 3 views
    with pytest.raises(ValueError, match="--model.medium.init prior"):
        estimate_medium(points, torch.rand(2, 3), cams, images, dataset_scale=1.0)


def underwater_observations(num_points: int, views: int, z_range: tuple[float, float], seed: int):
    """Points each seen at `views` random ranges through the built-in scene's medium; a tenth of them black
    (shadows, crevices: what Sea-thru's backscatter estimate relies on), the rest random colours."""
    g = torch.Generator().manual_seed(seed)
    clean = 0.9 * torch.rand(num_points, 3, generator=g)
    clean[: num_points // 10] *= 0.001
    point = torch.arange(num_points).repeat_interleave(views)
    z = z_range[0] + (z_range[1] - z_range[0]) * torch.rand(len(point), generator=g)
    color = clean[point] * torch.exp(-TRUE_D * z[:, None]) + TRUE_BINF * (1 - torch.exp(-TRUE_B * z[:, None]))
    return clean, point, z, color


def test_dark_pixels_are_the_darkest_share_of_each_range_bin():
    g = torch.Generator().manual_seed(4)
    z, color = 1 + 9 * torch.rand(1000, generator=g), torch.rand(1000, 3, generator=g)
    dark_z, dark_color = dark_pixels(z, color, bins=4, share=0.02)
    expected = []
    for lo, hi in zip(*[torch.quantile(z, torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0]))[i:][:4] for i in (0, 1)],
                      strict=True):  # brute force: sort each quarter of the ranges by brightness
        members = [(float(color[m].sum()), m) for m in range(1000) if lo <= z[m] <= hi and (z[m] > lo or lo == z.min())]
        expected += [m for _, m in sorted(members)[: int(0.02 * len(members))]]
    assert len(dark_z) == len(expected) == 20
    torch.testing.assert_close(dark_color, color[expected])
    torch.testing.assert_close(dark_z, z[expected])


def test_backscatter_fit_recovers_the_curve_from_exact_samples():
    z = torch.linspace(1, 15, 40)
    samples = TRUE_BINF * (1 - torch.exp(-TRUE_B * z[:, None]))
    beta_b, b_inf = fit_backscatter(z, samples, b_inf=TRUE_BINF)
    assert torch.equal(b_inf, TRUE_BINF)
    torch.testing.assert_close(beta_b, TRUE_B, rtol=2e-3, atol=0)
    beta_b, b_inf = fit_backscatter(z, samples)  # 1-15 units: the curve bends enough to tell B_inf too
    torch.testing.assert_close(b_inf, TRUE_BINF, rtol=0.01, atol=0)
    torch.testing.assert_close(beta_b, TRUE_B, rtol=0.01, atol=0)


def test_fit_recovers_a_known_medium_from_exact_observations():
    """Points seen at several ranges each (2-12 units), some of them black: exact data pins all nine numbers."""
    clean, point, z, color = underwater_observations(300, 8, (2.0, 12.0), seed=0)
    beta_d, beta_b, b_inf = fit_medium(point, color, z, residual=False).medium
    torch.testing.assert_close(beta_d, TRUE_D, rtol=0.02, atol=0)
    torch.testing.assert_close(b_inf, TRUE_BINF, rtol=0.03, atol=0)
    torch.testing.assert_close(beta_b, TRUE_B, rtol=0.05, atol=0)
    torch.testing.assert_close(clean_colors(point, color, z, beta_d, beta_b, b_inf), clean, atol=0.02, rtol=0)


def test_fit_with_the_veiling_light_known_recovers_the_betas_over_a_short_range_of_distances():
    """Over 3-6 units the backscatter curve alone hardly tells B_inf from beta_B; with B_inf given (open water)
    the betas come out of 8-bit observations. A joint fit with free clean colours would not pin beta_B here:
    a little less backscatter and brighter colours explain the data as well."""
    _, point, z, color = underwater_observations(300, 6, (3.0, 6.0), seed=1)
    color = (color * 255).round() / 255  # 8-bit images
    beta_d, beta_b, b_inf = fit_medium(point, color, z, b_inf=TRUE_BINF, residual=False).medium
    assert torch.equal(b_inf, TRUE_BINF)
    torch.testing.assert_close(beta_d, TRUE_D, rtol=0.03, atol=0)
    torch.testing.assert_close(beta_b, TRUE_B, rtol=0.05, atol=0)


def seabed_observations(num_points: int, views: int, z_range: tuple[float, float], darkest: tuple[float, float],
                        seed: int, medium: tuple[Tensor, Tensor, Tensor]):
    """8-bit observations of a seabed with no black surface: a tenth of the points as dark as `darkest` (albedo
    range), the rest brighter; each point seen `views` times within +-20% of its own range in `z_range`."""
    beta_d, beta_b, b_inf = medium
    g = torch.Generator().manual_seed(seed)
    clean = darkest[0] + 0.6 * torch.rand(num_points, 3, generator=g)
    clean[: num_points // 10] = darkest[0] + (darkest[1] - darkest[0]) * torch.rand(num_points // 10, 3, generator=g)
    point = torch.arange(num_points).repeat_interleave(views)
    base = z_range[0] + (z_range[1] - z_range[0]) * torch.rand(num_points, generator=g)
    z = (base[point] * (0.8 + 0.4 * torch.rand(len(point), generator=g))).clamp(*z_range)
    color = clean[point] * torch.exp(-beta_d * z[:, None]) + b_inf * (1 - torch.exp(-beta_b * z[:, None]))
    return point, (color * 255).round() / 255, z


DIVE = (torch.tensor([0.30, 0.10, 0.07]), torch.tensor([0.24, 0.20, 0.17]), torch.tensor([0.08, 0.30, 0.42]))


def test_the_residual_term_recovers_a_medium_whose_darkest_surfaces_reflect_8_to_12_percent():
    """A scene the plain fit fails on: seen from 3.5 to 22 m, no open water, darkest surfaces 8-12%. The plain fit takes
    them for backscatter and saturates it early (red beta_B 3x too high); with Sea-thru's residual term every
    number is within 10%, and B_inf comes from the far end of the ranges."""
    point, color, z = seabed_observations(3000, 8, (3.5, 22.0), (0.08, 0.12), seed=0, medium=DIVE)
    plain = fit_medium(point, color, z, residual=False)
    assert float(plain.beta_b[0]) > 3 * float(DIVE[1][0])
    fit = fit_medium(point, color, z, residual=True)
    for value, truth in zip(fit.medium, DIVE, strict=True):
        torch.testing.assert_close(value, truth, rtol=0.10, atol=0)
    assert bool((fit.residual > 0.05).all())  # J' ~ the darkest albedo, 0.08-0.12


def test_the_residual_fit_is_exact_on_exact_samples_and_the_bic_keeps_the_plain_fit_for_black_surfaces():
    z = torch.linspace(2, 20, 60)
    beta_d, beta_b, b_inf = DIVE
    j_prime = torch.tensor([0.1, 0.05, 0.0])
    samples = b_inf * (1 - torch.exp(-beta_b * z[:, None])) + j_prime * torch.exp(-beta_d * z[:, None])
    rb, rv, rj = fit_backscatter_residual(z, samples, beta_d)
    torch.testing.assert_close(rb, beta_b, rtol=2e-3, atol=0)
    torch.testing.assert_close(rv, b_inf, rtol=2e-3, atol=0)
    torch.testing.assert_close(rj, j_prime, rtol=0, atol=2e-3)
    # near-black dark points (albedo < 0.001): the residual is that small, and the medium within 1% of the truth
    _, point, z, color = underwater_observations(300, 8, (2.0, 12.0), seed=0)
    fit = fit_medium(point, color, z, residual=True)
    assert float(fit.residual.max()) < 1e-3
    for value, truth in zip(fit.medium, (TRUE_D, TRUE_B, TRUE_BINF), strict=True):
        torch.testing.assert_close(value, truth, rtol=0.01, atol=0)
    # 8-bit samples of black surfaces: the one more parameter does not pay, the plain fit is kept
    color = (color * 255).round() / 255
    assert torch.equal(fit_medium(point, color, z, residual=True).residual, torch.zeros(3))


def test_bootstrap_resamples_points_with_all_their_observations():
    point = torch.tensor([2, 0, 1, 0, 2, 2])
    ids, rows = bootstrap_observations(point, torch.Generator().manual_seed(0))
    # every new point holds exactly the observations of one original point
    for new in ids.unique():
        originals = point[rows[ids == new]].unique()
        assert len(originals) == 1
        assert int((ids == new).sum()) == int((point == originals[0]).sum())
    assert int(ids.max()) + 1 == 3 and len(ids) == len(rows)


def test_the_report_flags_a_narrow_bright_scene_and_passes_a_wide_dark_one():
    """Seen from 3 to 4 m with no surface darker than 30%: the backscatter cannot be told from the surfaces, and
    the report says so for beta_B and B_inf, before training. The wide scene with black shadows is identifiable,
    but for red beta_B: its backscatter is faint (B_inf 0.05), and were the shadows 3% (`dark_albedo`), their own
    light would move it by about 25%, which no image can rule out."""
    fast = dict(resamples=5, steps=60, max_observations=4000)
    point, color, z = seabed_observations(800, 6, (3.0, 4.0), (0.3, 0.4), seed=1, medium=DIVE)
    fit = fit_medium(point, color, z, residual=True)
    report = assess_medium(point, color, z, fit, None, 10, 0.01, residual=True, **fast)
    assert all(report.weak("beta_B")) and any(report.weak("B_inf"))
    text = "\n".join(report.lines())
    assert "beta_B" in text and "optical depths" in text and "no open water in view" in text
    assert report.to_json()["checks"][3]["name"] == "beta_B"

    _, point, z, color = underwater_observations(800, 6, (2.0, 12.0), seed=2)
    fit = fit_medium(point, color, z, b_inf=TRUE_BINF, residual=True)
    report = assess_medium(point, color, z, fit, TRUE_BINF, 10, 0.01, residual=True, **fast)
    assert report.weak("beta_D") + report.weak("beta_B") + report.weak("B_inf") == [False] * 3 + [True] + [False] * 5
    assert report.checks[3].reason.startswith("2") and "reflect 3%" in report.checks[3].reason, report.lines()


def test_every_point_is_dehazed_even_those_too_few_views_see():
    """A 5x5 grid of seabed points seen from 3-6 units fixes the medium; a point only the highest camera sees
    gets J from its one observation, a point no camera sees is taken as seen from the nearest one. None keeps
    its underwater colour (the model would add the water twice)."""
    cams = [look_at_camera([0.0, 0.0, 3.0 + k]) for k in range(4)]
    grid = torch.stack(torch.meshgrid(torch.linspace(-1, 1, 5), torch.linspace(-1, 1, 5), indexing="ij"), -1)
    points = torch.cat([torch.cat([grid.reshape(-1, 2), torch.zeros(25, 1)], 1),
                        torch.tensor([[3.5, 0.0, 0.0], [0.0, 0.0, 10.0]])])  # seen by the top camera; by none
    clean = 0.9 * torch.rand(len(points), 3, generator=torch.Generator().manual_seed(2)) ** 2
    clean[:25:3] = 0.0  # black seabed points (shadows): the backscatter samples

    def underwater(j: Tensor, z: Tensor) -> Tensor:
        return j * torch.exp(-TRUE_D * z[..., None]) + TRUE_BINF * (1 - torch.exp(-TRUE_B * z[..., None]))

    images = []
    for cam in cams:  # the points land in distinct pixels; the rest of the image is black
        idx, _, ranges = observe_points(points, [cam], [torch.zeros(30, 40, 3)])
        p_cam = points[idx] @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
        uv = (p_cam[:, :2] / p_cam[:, 2:]) @ cam.K[:2, :2].T + cam.K[:2, 2]
        image = torch.zeros(30, 40, 3)
        image[uv[:, 1].floor().long(), uv[:, 0].floor().long()] = underwater(clean[idx], ranges)
        images.append(image)
    seen_by = torch.bincount(observe_points(points, cams, images)[0], minlength=len(points))
    assert seen_by[:25].min() == 4 and seen_by[25] == 1 and seen_by[26] == 0
    colors = torch.rand(len(points), 3)
    colors[26] = underwater(clean[26], torch.tensor(4.0))  # the nearest camera is 4 units from it
    estimate = estimate_medium(points, colors, cams, images, dataset_scale=1.0, b_inf=TRUE_BINF, dark_bins=4)
    assert estimate.fitted_points == 25
    torch.testing.assert_close(estimate.beta_d, TRUE_D, rtol=0.02, atol=0)
    torch.testing.assert_close(estimate.clean_colors, clean, atol=0.01, rtol=0)


def test_a_point_only_other_views_see_is_dehazed_at_the_range_they_see_it_from():
    """SfM colours a point from every view it matched, test views included. A point no training camera sees,
    but two other cameras do (4 and 6 units off), is de-hazed at their mean range, 5; without those poses at
    the range to the nearest training camera, which leaves water in its colour."""
    train = [look_at_camera([0.0, 0.0, 3.0 + k]) for k in range(4)]
    others = [look_at_camera([20.0, 0.0, 4.0]), look_at_camera([20.0, 0.0, 6.0])]
    grid = torch.stack(torch.meshgrid(torch.linspace(-1, 1, 5), torch.linspace(-1, 1, 5), indexing="ij"), -1)
    points = torch.cat([torch.cat([grid.reshape(-1, 2), torch.zeros(25, 1)], 1), torch.tensor([[20.0, 0, 0]])])
    torch.testing.assert_close(color_ranges(points, train + others)[25], torch.tensor(5.0))
    torch.testing.assert_close(color_ranges(points, train)[25], torch.tensor(20.0 ** 2 + 3.0 ** 2).sqrt())
    clean = 0.9 * torch.rand(len(points), 3, generator=torch.Generator().manual_seed(2)) ** 2
    clean[:25:3] = 0.0  # black seabed points (shadows): the backscatter samples
    underwater = clean * torch.exp(-TRUE_D * 5.0) + TRUE_BINF * (1 - torch.exp(-TRUE_B * 5.0))
    images = []
    for cam in train:  # the grid points as the training cameras see them, through the true medium
        idx, row, col = _project(points, cam)
        ranges = (points[idx] - cam.center).norm(dim=-1)[:, None]
        image = torch.zeros(30, 40, 3)
        image[row, col] = clean[idx] * torch.exp(-TRUE_D * ranges) + TRUE_BINF * (1 - torch.exp(-TRUE_B * ranges))
        images.append(image)
    kwargs = dict(dataset_scale=1.0, b_inf=TRUE_BINF, dark_bins=4)
    with_poses = estimate_medium(points, underwater, train, images, sfm_cameras=train + others, **kwargs)
    torch.testing.assert_close(with_poses.clean_colors[25], clean[25], atol=0.01, rtol=0)
    train_only = estimate_medium(points, underwater, train, images, **kwargs)
    assert (train_only.clean_colors[25] - clean[25]).abs().max() > 0.1


def test_open_water_color_is_the_median_of_the_cells_no_point_lands_in():
    """Top half of the view: open water (one colour, a little noise); bottom half: textured seabed with points."""
    cam = look_at_camera([0.0, 0.0, 5.0], width=64, height=48)
    g = torch.Generator().manual_seed(0)
    water = torch.tensor([0.05, 0.25, 0.35])
    image = torch.rand(48, 64, 3, generator=g)
    image[:24] = water + 0.01 * torch.randn(24, 64, 3, generator=g)
    # points on the plane z = 0 that land in the bottom half, one per 4x4 pixels
    v, u = torch.meshgrid(torch.arange(24, 48, 4) + 0.5, torch.arange(0, 64, 4) + 0.5, indexing="ij")
    points = torch.stack([(u - 32) / 30 * 5, -(v - 24) / 30 * 5, torch.zeros_like(u)], dim=-1).reshape(-1, 3)
    found = open_water_color(points, [cam], [image], cells=8, min_share=0.01)
    torch.testing.assert_close(found, water, atol=0.003, rtol=0)
    assert open_water_color(points, [cam], [image], cells=8, min_share=0.6) is None  # half the view < 60%
    everywhere = torch.cat([points, points * torch.tensor([1.0, -1.0, 1.0])])  # mirrored into the top half
    assert open_water_color(everywhere, [cam], [image], cells=8, min_share=0.01) is None


def test_estimate_start_sets_a_flat_medium_and_dehazed_colours(make_config):
    """`--model.medium.init estimate`: the model starts from the fit, the same everywhere, colours de-hazed."""
    import dataclasses

    from uw3dgs.registry import METHODS
    from uw3dgs.render.sh import rgb_to_sh

    spec = METHODS["uw3dgs"].config
    base = make_config(steps=1)
    medium = dataclasses.replace(spec.model.medium, init="estimate")
    model_config = dataclasses.replace(spec.model, medium=medium, gaussians=base.model.gaussians)
    datamanager = base.datamanager.setup(data=None)
    scene, train = datamanager.scene, datamanager.train_indices
    model = model_config.setup(scene=scene, train_indices=train)
    prior = torch.tensor(medium.beta_prior)
    inside = torch.rand(500, 3) * (model.medium.box_max - model.medium.box_min) + model.medium.box_min
    for beta in model.medium.betas(inside):  # no fit until training: flat at the prior
        torch.testing.assert_close(beta, prior.expand(500, 3), rtol=1e-5, atol=0)
    model.initialize_from_data(scene, train)  # the Trainer's hook on a fresh run
    cameras, images = [scene.cameras[i] for i in train], [scene.images[i] for i in train]
    water = open_water_color(scene.points, cameras, images, medium.open_water_cells, medium.open_water_min_share,
                             medium.open_water_max_std, medium.open_water_min_uniform)
    assert water is not None  # the built-in scene's views show open water at the top
    expected = estimate_medium(scene.points, scene.point_colors, cameras, images, scene.dataset_scale,
                               b_inf=water, sfm_cameras=scene.cameras)
    beta_d, beta_b = model.medium.betas(inside)
    torch.testing.assert_close(beta_d, expected.beta_d.expand(500, 3), rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(beta_b, expected.beta_b.expand(500, 3), rtol=1e-4, atol=1e-6)
    # L_beta now pulls toward the estimate, not toward beta_prior
    torch.testing.assert_close(model.medium.prior_d, expected.beta_d, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(model.medium.prior_b, expected.beta_b, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(model.medium.b_inf.detach(), expected.b_inf)
    torch.testing.assert_close(model.gaussians.sh0[:, 0], rgb_to_sh(expected.clean_colors.clamp(0, 1)))
    assert expected.fitted_points > 0.5 * len(scene.points)
    # the fit explains the water: every channel's attenuation is closer to the truth than the prior is,
    # and the veiling light is the open water's colour
    truth = torch.tensor(scene.gt.medium["beta_D"])
    assert ((expected.beta_d - truth).abs() < (prior - truth).abs()).all()
    torch.testing.assert_close(expected.b_inf, torch.tensor(scene.gt.medium["B_inf"]), atol=2 / 255, rtol=0)


def test_truth_start_is_the_scene_medium_and_needs_one(make_config):
    """`--model.medium.init truth` (synthetic scenes): the true medium, colours de-hazed with it; elsewhere an error."""
    import dataclasses

    import pytest

    from uw3dgs.registry import METHODS
    from uw3dgs.render.sh import rgb_to_sh

    spec = METHODS["uw3dgs"].config
    base = make_config(steps=1)
    medium = dataclasses.replace(spec.model.medium, init="truth")
    model_config = dataclasses.replace(spec.model, medium=medium, gaussians=base.model.gaussians)
    scene, train = (dm := base.datamanager.setup(data=None)).scene, dm.train_indices
    model = model_config.setup(scene=scene, train_indices=train)
    model.initialize_from_data(scene, train)
    truth = [torch.tensor(scene.gt.medium[k]) for k in ("beta_D", "beta_B", "B_inf")]
    points = torch.rand(200, 3) * (model.medium.box_max - model.medium.box_min) + model.medium.box_min
    for learned, true in zip((*model.medium.betas(points), model.medium.b_inf.detach()), truth, strict=True):
        torch.testing.assert_close(learned, true.expand_as(learned), rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(model.medium.prior_d, truth[0])
    cameras, images = [scene.cameras[i] for i in train], [scene.images[i] for i in train]
    expected = estimate_medium(scene.points, scene.point_colors, cameras, images, scene.dataset_scale,
                               sfm_cameras=scene.cameras, known=tuple(truth))
    torch.testing.assert_close(model.gaussians.sh0[:, 0], rgb_to_sh(expected.clean_colors.clamp(0, 1)))
    # de-hazed with the true medium, the points' colours are nearer their clean colours (mean of the clean images
    # at their projections) than their underwater ones are
    index, clean, _ = observe_points(scene.points.float(), cameras, [scene.gt.clean_images[i] for i in train])
    seen = torch.unique(index)
    total = torch.zeros(len(scene.points), 3).index_add_(0, index, clean)
    mean_clean = (total / torch.bincount(index, minlength=len(scene.points)).clamp_min(1)[:, None])[seen]
    dehazed_error = (expected.clean_colors[seen] - mean_clean).abs().mean()
    assert dehazed_error < 0.5 * (scene.point_colors[seen].float() - mean_clean).abs().mean()
    with pytest.raises(ValueError, match="init truth needs a scene that knows its medium"):
        model_config.setup(scene=dataclasses.replace(scene, gt=None), train_indices=train)


def test_holes_in_the_points_over_seabed_are_not_open_water():
    """Failure (A): a view with no water, the seabed textured everywhere and the points missing over a few
    cells. Those cells were taken as open water (B_inf read off seabed); with the evidence check (most empty cells
    one colour) they are not, and the reason says so. A view whose top half is water (one colour, a little noise)
    still reads B_inf off it."""
    cam = look_at_camera([0.0, 0.0, 5.0], width=64, height=48)
    g = torch.Generator().manual_seed(0)
    seabed = torch.rand(48, 64, 3, generator=g)
    v, u = torch.meshgrid(torch.arange(0, 48, 4) + 0.5, torch.arange(0, 64, 4) + 0.5, indexing="ij")
    points = torch.stack([(u - 32) / 30 * 5, -(v - 24) / 30 * 5, torch.zeros_like(u)], dim=-1).reshape(-1, 3)
    holes = torch.ones(len(points), dtype=torch.bool)
    holes[torch.tensor([5, 40, 41, 100, 150, 170])] = False  # six 4x4 px cells (of 8 px cells: some half empty)
    points_with_holes = points[holes]
    trusting = find_open_water(points_with_holes, [cam], [seabed], cells=16, min_share=0.01)
    assert trusting.color is not None  # the behaviour before: any empty cell is water
    found = find_open_water(points_with_holes, [cam], [seabed], cells=16, min_share=0.01, max_std=0.02,
                            min_uniform=0.5)
    assert found.color is None and found.uniform_share == 0.0 and found.empty_cells == 6
    assert "one colour" in found.reason and "not water" in found.reason
    assert open_water_color(points_with_holes, [cam], [seabed], 16, 0.01, 0.02, 0.5) is None

    water = torch.tensor([0.05, 0.25, 0.35])
    view = seabed.clone()
    view[:24] = water + 0.005 * torch.randn(24, 64, 3, generator=g)
    below = points_with_holes[points_with_holes[:, 1] < 0]  # the points land in the bottom half only
    found = find_open_water(below, [cam], [view], cells=16, min_share=0.01, max_std=0.02, min_uniform=0.5)
    assert found.reason == "" and found.uniform_share > 0.7
    torch.testing.assert_close(found.color, water, atol=0.003, rtol=0)


def test_without_open_water_b_inf_comes_from_the_far_end_and_the_report_says_how_well():
    """No open water: B_inf is read off the far end of the ranges, where every colour converges to it. On exact
    formation-model observations seen from 2 to 30 units, the two readings there bracket it: the black surfaces'
    plateau (B_inf fitted with beta_B to them) from below, within exp(-beta_B 30) <= 0.3% of B_inf (blue, beta_B
    0.2), so within 1% (the 1-D searches' grid is finer), and the median colour beyond the 90% range from above,
    the surfaces' own signal there J exp(-beta_D z) <= 5% of their colour (blue, z >= 25), under 10% of B_inf. The
    estimate, their middle, is within half their distance of the truth (plus the 1% of the fit), under 5%, and
    the report's far-end checks pass. Over 3-4 units (the narrow scene) B_inf is flagged with the reasons: not off
    open water (and why not), the far end is not veiled, the readings leave it wide open."""
    _, point, z, color = underwater_observations(600, 8, (2.0, 30.0), seed=3)
    plain = fit_medium(point, color, z, residual=False)
    torch.testing.assert_close(plain.b_inf, TRUE_BINF, rtol=0.01, atol=0)
    z_far, transmission, far_color = far_end(z, color, plain.beta_d, 0.9)
    assert z_far > 25 and float(transmission.max()) < 0.05
    torch.testing.assert_close(far_color, TRUE_BINF, rtol=0.1, atol=0)  # the veiled end's median colour
    assert bool((far_color >= (1 - 0.003) * TRUE_BINF).all())  # from above (the backscatter there within 0.3%)
    fit = fit_medium(point, color, z, residual=False, far_quantile=0.9)
    torch.testing.assert_close(fit.veil_below, plain.b_inf)
    torch.testing.assert_close(fit.veil_above, far_color)
    half = (fit.veil_above - fit.veil_below).abs() / 2
    assert bool(((fit.b_inf - TRUE_BINF).abs() <= half + 0.01 * TRUE_BINF).all())
    torch.testing.assert_close(fit.b_inf, TRUE_BINF, rtol=0.05, atol=0)
    torch.testing.assert_close(fit.beta_d, TRUE_D, rtol=0.05, atol=0)
    fast = dict(resamples=5, steps=60, max_observations=4000)
    report = assess_medium(point, color, z, fit, None, 10, 0.01, residual=False, **fast)
    assert not report.open_water
    assert not any("far end" in c.reason for c in report.checks if c.name == "B_inf"), report.lines()

    point, color, z = seabed_observations(800, 6, (3.0, 4.0), (0.3, 0.4), seed=1, medium=DIVE)
    fit = fit_medium(point, color, z, residual=False, far_quantile=0.9)
    holes = find_open_water(torch.zeros(0, 3), [look_at_camera([0.0, 0.0, 5.0])], [torch.rand(30, 40, 3)], cells=8,
                            min_share=0.01, max_std=0.02, min_uniform=0.5)  # no point at all: textured holes
    report = assess_medium(point, color, z, fit, None, 10, 0.01, residual=False, open_water=holes, **fast)
    weak = [c for c in report.checks if c.name == "B_inf" and not c.identifiable]
    assert len(weak) == 3
    for check in weak:  # red: both readings agree on a wrong value, the other checks catch it
        assert "no open water in view" in check.reason or "not off open water" in check.reason
    assert any("read off the far end of the ranges, not off open water" in c.reason and "not water" in c.reason
               and "its two readings there" in c.reason for c in weak)
    assert all(not c.identifiable and "B_inf that is not pinned" in c.reason for c in report.checks
               if c.name != "B_inf")  # the betas are fitted with it held
    assert any("the veiling light is not reached" in c.reason for c in weak)
    assert "not water" in report.lines()[3]


def varying_medium_observations(num_points: int, views: int, gain: float, seed: int):
    """8-bit observations of points on the plane z = 0 (x in -6..6, y in -2..2) seen from 2 to 12 units, a tenth
    of them black, through the built-in scene's medium times a factor 1 + gain (x > 0): a turbid cloud over one
    half of the seabed that every ray to a point there crosses. Returns point, colour, range, positions."""
    g = torch.Generator().manual_seed(seed)
    positions = torch.stack([12 * torch.rand(num_points, generator=g) - 6, 4 * torch.rand(num_points, generator=g) - 2,
                             torch.zeros(num_points)], dim=-1)
    clean = 0.9 * torch.rand(num_points, 3, generator=g)
    clean[torch.randperm(num_points, generator=g)[: num_points // 10]] *= 0.001
    factor = 1 + gain * (positions[:, 0] > 0).float()
    point = torch.arange(num_points).repeat_interleave(views)
    z = 2 + 10 * torch.rand(len(point), generator=g)
    beta_d, beta_b = TRUE_D * factor[point, None], TRUE_B * factor[point, None]
    color = clean[point] * torch.exp(-beta_d * z[:, None]) + TRUE_BINF * (1 - torch.exp(-beta_b * z[:, None]))
    return point, (color * 255).round() / 255, z, positions


def test_the_report_flags_a_medium_that_varies_in_space():
    """Failure (B): a homogeneous fit to a medium twice as turbid over one half of the seabed is stable
    under the bootstrap, so the other checks call it identifiable. The halves of the scene fitted on their own
    disagree, and the report flags every beta as varying in space. The same scene with a homogeneous medium
    (gain 0) is not flagged."""
    config = IdentifiabilityConfig(resamples=5, steps=60, max_observations=4000)
    point, color, z, positions = varying_medium_observations(800, 6, gain=1.0, seed=0)
    fit = fit_medium(point, color, z, b_inf=TRUE_BINF, residual=False)
    report = assess_medium(point, color, z, fit, TRUE_BINF, 10, 0.01, residual=False, config=config,
                           positions=positions)
    assert report.varies_in_space and min(report.spatial_disagreement["beta_D"]) > config.spatial_tolerance
    for check in report.checks:
        if check.name == "B_inf":
            assert check.identifiable  # read off open water
        else:
            assert not check.identifiable and "varies in space" in check.reason and "VM grid" in check.reason
    assert "varies in space" in report.lines()[-1]
    without = assess_medium(point, color, z, fit, TRUE_BINF, 10, 0.01, residual=False, config=config)
    assert without.spatial_disagreement is None and not without.varies_in_space
    # the same halves, judged with a tolerance no bootstrap spread meets: far apart, but not told from the estimate's
    # own noise, which the line says instead of calling the medium homogeneous
    strict = assess_medium(point, color, z, fit, TRUE_BINF, 10, 0.01, residual=False, positions=positions,
                           config=dataclasses.replace(config, tolerance=1e-6))
    assert not strict.varies_in_space and strict.spatial_undecided and not report.spatial_undecided
    assert "cannot tell whether the medium varies" in strict.lines()[-1] and "homogeneous" not in strict.lines()[-1]

    point, color, z, positions = varying_medium_observations(800, 6, gain=0.0, seed=0)
    fit = fit_medium(point, color, z, b_inf=TRUE_BINF, residual=False)
    report = assess_medium(point, color, z, fit, TRUE_BINF, 10, 0.01, residual=False, config=config,
                           positions=positions)
    assert not report.varies_in_space and max(report.spatial_disagreement["beta_D"]) < 0.1, report.lines()
    assert all(c.identifiable or (c.name, c.channel) == ("beta_B", "R") for c in report.checks), report.lines()
    assert "varies in space" not in report.checks[3].reason  # red beta_B: black shadows or 3%, no image can tell


@pytest.mark.slow
@pytest.mark.parametrize("open_water", [True, False])
def test_the_built_in_scene_keeps_its_estimate_and_verdicts_and_without_water_reads_no_seabed(open_water, cache_dir):
    """The full-size built-in scene (docs/medium-recovery.md, row `default`): B_inf read off its open water, the
    estimate and the verdicts as documented (beta_D G, B and every beta_B weak, B_inf identifiable, nothing varying
    in space). Without open water (row `no-open-water`) B_inf was read off holes in the points over seabed (red
    88% off); now it is read off the far end of the ranges (4/3/5% off), and the report flags blue, whose far end
    is not veiled, saying why."""
    from uw3dgs.datamanagers.synthetic import SyntheticDataManagerConfig
    from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig
    from uw3dgs.fields.medium_estimate import estimate_from_views
    from uw3dgs.registry import METHODS

    knobs = METHODS["uw3dgs"].config.model.medium
    datamanager = SyntheticDataManagerConfig(scene=SyntheticSceneConfig(open_water=open_water),
                                             cache_dir=cache_dir).setup(data=None)
    scene = datamanager.scene
    estimate, water = estimate_from_views(knobs, scene, datamanager.train_indices)
    report = assess_medium(*estimate.observations, estimate.fit, water, knobs.dark_bins, knobs.dark_share, False,
                           positions=estimate.positions, open_water=estimate.open_water)
    weak = [f"{c.name} {c.channel}" for c in report.checks if not c.identifiable]
    truth = torch.tensor(scene.gt.medium["B_inf"])
    assert not report.varies_in_space
    if open_water:
        torch.testing.assert_close(water, truth, atol=1 / 255, rtol=0)
        torch.testing.assert_close(estimate.beta_d, torch.tensor([0.4186, 0.2041, 0.1277]), atol=2e-4, rtol=0)
        torch.testing.assert_close(estimate.beta_b, torch.tensor([0.3339, 0.2525, 0.1995]), atol=2e-4, rtol=0)
        assert weak == ["beta_D G", "beta_D B", "beta_B R", "beta_B G", "beta_B B"]
    else:
        assert water is None and "not water" in estimate.open_water.reason
        torch.testing.assert_close(estimate.b_inf, truth, rtol=0.06, atol=0)
        assert "B_inf B" in weak and "B_inf R" not in weak
        assert all("not off open water" in c.reason for c in report.checks if c.name == "B_inf" and c.reason)
        # red beta_B, 34% off: the dark patches' own 3% albedo is read as backscatter (the dark-albedo check's case)
        assert "beta_B R" in weak and "reflect 3%" in report.checks[3].reason


FAST = dict(resamples=5, steps=60, max_observations=4000)


def test_a_b_inf_of_a_few_grey_levels_is_flagged_but_its_betas_keep_their_verdicts():
    """Jerlov type I's red B_inf is 1.4 grey levels of an 8-bit image: read off open water it is 1 (28% off), and no
    bootstrap sees it. Rounding leaves up to half a grey level, so a B_inf of 2 grey levels is +-25% (> 15%) and
    flagged, saying so; its error (under half a grey level) is under what the images resolve, so the betas fitted
    with it are not flagged for it. Green and blue (13 and 77 grey levels) pass."""
    water = (torch.tensor([0.4, 0.2, 0.12]), torch.tensor([0.3, 0.25, 0.2]), torch.tensor([0.006, 0.05, 0.3]))
    read = (water[2] * 255).round() / 255  # the open water's 8-bit colour: red 2 grey levels (0.0078, 31% off)
    _, point, z, _ = underwater_observations(400, 6, (2.0, 12.0), seed=5)
    clean = 0.9 * torch.rand(400, 3, generator=torch.Generator().manual_seed(5))
    color = clean[point] * torch.exp(-water[0] * z[:, None]) + water[2] * (1 - torch.exp(-water[1] * z[:, None]))
    color = (color * 255).round() / 255
    fit = fit_medium(point, color, z, b_inf=read, residual=False)
    report = assess_medium(point, color, z, fit, read, 10, 0.01, residual=False, **FAST)
    b_inf = [c for c in report.checks if c.name == "B_inf"]
    assert [c.identifiable for c in b_inf] == [False, True, True]
    assert "2.0 grey levels" in b_inf[0].reason and "+-25%" in b_inf[0].reason
    assert not any("not pinned" in c.reason for c in report.checks), report.lines()
    coarse = assess_medium(point, color, z, fit, read, 10, 0.01, residual=False, grey_level=1 / 4095, **FAST)
    assert "grey levels" not in coarse.checks[6].reason  # 12-bit images resolve it


def test_beta_d_over_a_short_span_of_optical_depths_is_flagged_for_colour_drift():
    """Jerlov type I's green beta_D (0.043 per unit) is read over 0.37 optical depths: a 5-8% drift of the surfaces'
    colours with range that is not the water's moves it by 15-20% (24% off after training), while the bootstrap
    and the other backscatter model see nothing. Exact data through water that clear in green (0.03 per unit, 0.24
    optical depths between the 10% and 90% range) passes the other checks and is flagged for the drift alone, with
    the span; red and blue (3.2 and 1.6 optical depths) are not, nor is green without drift (`color_drift` 0)."""
    water = (torch.tensor([0.4, 0.03, 0.2]), torch.tensor([0.3, 0.03, 0.2]), torch.tensor([0.05, 0.25, 0.35]))
    _, point, z, _ = underwater_observations(400, 6, (2.0, 12.0), seed=6)
    clean = 0.9 * torch.rand(400, 3, generator=torch.Generator().manual_seed(6))
    clean[:40] *= 0.001
    color = clean[point] * torch.exp(-water[0] * z[:, None]) + water[2] * (1 - torch.exp(-water[1] * z[:, None]))
    fit = fit_medium(point, color, z, b_inf=water[2], residual=False)
    report = assess_medium(point, color, z, fit, water[2], 10, 0.01, residual=False, **FAST)
    beta_d = [c for c in report.checks if c.name == "beta_D"]
    assert [c.identifiable for c in beta_d] == [True, False, True], report.lines()
    assert beta_d[1].reason.startswith("over 0.24 optical depths a 6% drift") and "by 25%" in beta_d[1].reason
    assert beta_d[1].spread <= 0.15 and beta_d[1].assumption <= 0.15  # only the drift flags it
    none = assess_medium(point, color, z, fit, water[2], 10, 0.01, residual=False, color_drift=0.0, **FAST)
    assert none.checks[1].identifiable


def test_beta_b_is_flagged_where_dark_surfaces_own_light_would_be_a_large_share_of_the_backscatter():
    """No check sees whether the darkest surfaces are black. If they reflect 3% (the synthetic scene's dark
    patches), their light, attenuated with beta_D, is read as backscatter: where the backscatter is faint (the
    built-in scene's red, B_inf 0.05) that moves beta_B by about 25% (`no-open-water` red beta_B is 32% off after
    training), where it is bright (turbid water, B_inf 0.6-0.7) by 3%. The check asks the question of the dark
    samples, black or not: it flags the faint channel, saying why, and not the bright water."""
    for medium, flagged in (((TRUE_D, TRUE_B, TRUE_BINF), [True, False, False]),
                            ((torch.tensor([0.5, 0.5, 0.7]), torch.tensor([0.5, 0.5, 0.7]),
                              torch.tensor([0.6, 0.7, 0.6])), [False, False, False])):
        point, color, z = seabed_observations(600, 6, (2.0, 12.0), (0.0, 0.001), seed=2, medium=medium)
        fit = fit_medium(point, color, z, b_inf=medium[2], residual=False)
        report = assess_medium(point, color, z, fit, medium[2], 10, 0.01, residual=False, **FAST)
        assert [s > 0.15 for s in report.dark_floor_shift] == flagged
        beta_b = [c for c in report.checks if c.name == "beta_B"]
        assert [not c.identifiable for c in beta_b] == flagged, report.lines()
        assert all("reflect 3%" in c.reason and "read as backscatter" in c.reason
                   for c, f in zip(beta_b, flagged, strict=True) if f)


def test_the_recoverable_range_is_where_a_typical_seabed_colour_falls_below_one_grey_level():
    """Beyond ln(255 J) / beta_D a seabed colour J sends under one grey level through the water: the images hold no
    trace of it. Exact data (clean colours known, so the de-hazed median is J), points each seen at one range: the
    range per channel is that formula with the median clean colour, and the share of points beyond it is counted;
    the report prints both."""
    medium = (torch.tensor([0.6, 0.8, 1.2]), torch.tensor([0.6, 0.8, 1.2]), torch.tensor([0.85, 0.9, 0.85]))
    g = torch.Generator().manual_seed(7)
    clean = 0.2 + 0.6 * torch.rand(300, 3, generator=g)
    point = torch.arange(300).repeat_interleave(3)
    z = 1 + 9 * torch.rand(300, generator=g)[point] * (0.9 + 0.1 * torch.rand(900, generator=g))
    color = clean[point] * torch.exp(-medium[0] * z[:, None]) + medium[2] * (1 - torch.exp(-medium[1] * z[:, None]))
    fit = fit_medium(point, color, z, b_inf=medium[2], residual=False)
    fit.beta_d, fit.beta_b = medium[0], medium[1]  # the formula, not the fit, is under test
    reach, beyond = recoverable_range(point, color, z, fit, 1 / 255)
    expected = torch.log(255 * clean.double().median(dim=0).values) / medium[0].double()
    torch.testing.assert_close(reach, expected, rtol=1e-3, atol=0)
    nearest = torch.stack([z[point == p].min() for p in range(300)]).double()
    torch.testing.assert_close(beyond, (nearest[:, None] > reach).double().mean(0))
    assert 0.05 < float(beyond[0]) < float(beyond[2]) < 0.95  # blue, the most attenuated, is lost first
    report = assess_medium(point, color, z, fit, medium[2], 10, 0.01, residual=False, **FAST)
    assert "recoverable to range" in report.lines()[4] and report.recoverable_range == reach.tolist()


@pytest.mark.parametrize(("option", "value"), [("grey_level", 0.0), ("grey_level", 1.0), ("color_drift", -0.1),
                                               ("dark_albedo", -0.01)])
def test_the_report_refuses_an_option_out_of_range_naming_it(option, value):
    """The last checks' knobs (`--model.medium.identifiability.*`) are checked when the config is built."""
    with pytest.raises(OptionError, match=option):
        IdentifiabilityConfig(**{option: value})
