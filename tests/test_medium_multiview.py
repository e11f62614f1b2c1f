"""The multi-view medium estimate (fields/medium_multiview.py), its combination with the single-image estimate by
evidence (fields/medium_evidence.py) and the synthetic survey that passes over the seabed at several altitudes."""

from __future__ import annotations

import dataclasses
import math
import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from uw3dgs.cameras import Camera
from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig, cache_key
from uw3dgs.datamanagers.synthetic.rendering import beta_field
from uw3dgs.fields.medium_estimate import MediumEstimate
from uw3dgs.fields.medium_evidence import (
    DARK_PIXELS,
    FAR_END,
    NOT_IDENTIFIED,
    OPEN_WATER,
    RANGE_DIVERSITY,
    combine_by_evidence,
)
from uw3dgs.fields.medium_identifiability import ParameterCheck
from uw3dgs.fields.medium_multiview import (
    MultiviewCheck,
    MultiviewConfig,
    MultiviewEstimate,
    _deeper,
    _drift_sensitivity,
    fit_multiview,
    multiview_estimate,
    point_spans,
    visible_observations,
)
from uw3dgs.options import OptionError

BETA_D, BETA_B, B_INF = (0.30, 0.10, 0.07), (0.24, 0.20, 0.17), (0.08, 0.30, 0.42)


def surveyed_points(num_points: int = 500, views: int = 5, span: tuple[float, float] = (1.5, 3.0),
                    noise: float = 0.01, outliers: float = 0.05, single: float = 0.2, seed: int = 0,
                    medium: tuple = (BETA_D, BETA_B, B_INF)):
    """Observations of points with known clean colours in [0.1, 0.8] (dark, not black) through a known medium:
    each point seen `views` times at ranges from near (3-8 units) to near x its span ratio (`span`), a `single`
    share of them at one range only; Gaussian noise, an `outliers` share of observations replaced by random
    colours, 8-bit rounding. Returns (point ids [M], colours [M, 3], ranges [M], whether the point has one range
    [P])."""
    g = torch.Generator().manual_seed(seed)
    bd, bb, b = (torch.tensor(x, dtype=torch.float64) for x in medium)
    clean = 0.1 + 0.7 * torch.rand(num_points, 3, generator=g, dtype=torch.float64)
    near = 3 + 5 * torch.rand(num_points, generator=g, dtype=torch.float64)
    ratio = span[0] + (span[1] - span[0]) * torch.rand(num_points, generator=g, dtype=torch.float64)
    t = torch.rand(num_points, views, generator=g, dtype=torch.float64)
    t[:, 0], t[:, 1] = 0.0, 1.0
    z = near[:, None] * ratio[:, None] ** t
    one = torch.rand(num_points, generator=g) < single
    z[one] = near[one, None]
    point, z = torch.arange(num_points).repeat_interleave(views), z.reshape(-1)
    color = clean[point] * torch.exp(-bd * z[:, None]) + b * (1 - torch.exp(-bb * z[:, None]))
    color = color + noise * torch.randn(color.shape, generator=g, dtype=torch.float64)
    bad = torch.rand(len(z), generator=g) < outliers
    color[bad] = torch.rand(int(bad.sum()), 3, generator=g, dtype=torch.float64)
    return point, (color.clamp(0, 1) * 255).round() / 255, z, one


def relative_errors(medium) -> torch.Tensor:
    """[3 parameters, 3 channels] |estimate - truth| / truth."""
    truth = torch.tensor([BETA_D, BETA_B, B_INF], dtype=torch.float64)
    return (torch.stack([m.double() for m in medium]) - truth).abs() / truth


def test_the_fit_is_exact_on_exact_observations_with_b_inf_free_or_held():
    point, color, z, _ = surveyed_points(200, noise=0.0, outliers=0.0, single=0.0)
    exact = torch.tensor(BETA_D)  # rounding aside: re-make the colours without the 8-bit step
    clean = 0.1 + 0.7 * torch.rand(200, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    veil, beta_b = torch.tensor(B_INF, dtype=torch.float64), torch.tensor(BETA_B, dtype=torch.float64)
    color = clean[point] * torch.exp(-exact.double() * z[:, None]) + veil * (1 - torch.exp(-beta_b * z[:, None]))
    free = fit_multiview(point, color, z)
    assert relative_errors(free.medium).max() < 1e-3
    torch.testing.assert_close(free.clean.double(), clean, atol=1e-3, rtol=0)
    held = fit_multiview(point, color, z, b_inf=torch.tensor([B_INF[0], math.nan, B_INF[2]]))
    assert relative_errors(held.medium).max() < 1e-3
    assert held.b_inf[0] == pytest.approx(B_INF[0]) and held.b_inf[2] == pytest.approx(B_INF[2])


def test_the_fit_is_a_minimum_of_the_robust_cost_that_scipy_cannot_improve():
    """Levenberg-Marquardt with the clean colours eliminated per point against scipy's least_squares on all the
    unknowns at once (its Cauchy loss, same scale) started where ours stopped, on a small problem with outliers:
    scipy finds nothing lower and stays put."""
    from scipy.optimize import least_squares

    point, color, z, _ = surveyed_points(40, views=4, single=0.0, outliers=0.1, seed=1)
    scale = 0.03
    fit = fit_multiview(point, color, z, config=MultiviewConfig(max_iterations=500),
                        loss_scale=torch.full((3,), scale, dtype=torch.float64))
    for c in range(3):
        y, zz, ids = color[:, c].numpy(), z.numpy(), point.numpy()

        def residual(x, y=y, zz=zz, ids=ids):
            bd, bb, b = np.exp(x[:3])
            return x[3:][ids] * np.exp(-bd * zz) + b * (1 - np.exp(-bb * zz)) - y

        ours = np.concatenate([np.log([float(m[c]) for m in fit.medium]), fit.clean[:, c].double().numpy()])
        ref = least_squares(residual, ours, loss="cauchy", f_scale=scale, xtol=1e-15, ftol=1e-15, gtol=1e-15,
                            max_nfev=2_000)
        cost = 0.5 * scale ** 2 * np.log1p((residual(ours) / scale) ** 2).sum()
        assert ref.cost >= cost * (1 - 1e-6)
        np.testing.assert_allclose(np.exp(ours[:3]), np.exp(ref.x[:3]), rtol=1e-3)


@pytest.mark.slow  # whole bootstrapped estimates: tens of seconds each on two cores
def test_the_estimate_recovers_a_known_medium_from_noisy_points_with_outliers_and_single_ranges():
    """500 points x 5 views, 1% noise, 5% outliers, a fifth of the points at one range: every parameter the verdict
    calls identified is within 15% of the truth, every one within 25% (red's veiling light is 20 grey levels under 2.5
    grey levels of noise), and the single-range points do not enter the fit. B_inf is identified in every channel;
    the G and B betas, which a 6% drift of the surfaces' colours over these spans (1.5-3x) would move by more than
    15%, are flagged for it although this data has no drift: the verdict cannot tell."""
    point, color, z, one = surveyed_points(500)
    estimate = multiview_estimate(point, color, z, MultiviewConfig(resamples=8))
    errors = relative_errors(estimate.fit.medium)
    assert estimate.points == int((~one).sum())
    identified = torch.tensor([[estimate.check(n, c).identified for c in range(3)]
                               for n in ("beta_D", "beta_B", "B_inf")])
    assert identified[2].all()
    assert all("drift of the surfaces' colours over each point's ranges" in estimate.check("beta_B", c).reason
               for c in (1, 2))
    assert (errors[identified] < 0.15).all(), errors
    assert (errors < 0.25).all(), errors
    # the robust loss is what keeps the outliers out: least squares on the same data is worse
    plain = fit_multiview(point, color, z, config=MultiviewConfig(loss="l2"))
    assert relative_errors(plain.medium).max() > 2 * errors.max()


def test_every_parameter_is_not_identified_when_every_point_is_seen_over_a_tiny_span():
    point, color, z, _ = surveyed_points(300, span=(1.0, 1.03), single=0.0, outliers=0.0)
    estimate = multiview_estimate(point, color, z, MultiviewConfig(resamples=4))
    assert estimate.span_points == 0
    assert not any(check.identified for check in estimate.checks)
    assert all("span a range ratio" in check.reason for check in estimate.checks)
    assert any("not identified" in line for line in estimate.lines())


def test_a_median_span_ratio_under_one_is_refused_with_the_option_named():
    with pytest.raises(OptionError, match="identify_median_span_ratio"):
        MultiviewConfig(identify_median_span_ratio=0.5)


def test_a_bootstrap_refit_keeps_per_channel_the_deeper_of_its_two_starts():
    """The fit reports its robust cost per channel (recomputed here from its medium and clean colours, Cauchy at its
    scale), and `_deeper` takes each channel's medium from the fit of lower cost: a grid start stopped in a shallower
    valley of a resample is not read as spread (the 3-pass survey's red and green beta_B were, before)."""
    point, color, z, _ = surveyed_points(80, views=4, noise=0.005, outliers=0.0, single=0.0, seed=5)
    fit = fit_multiview(point, color, z)
    bd, bb, b = (m.double() for m in fit.medium)
    pred = fit.clean.double()[point] * torch.exp(-bd * z[:, None]) + b * (1 - torch.exp(-bb * z[:, None]))
    u = (pred - color) / fit.loss_scale.double()
    torch.testing.assert_close(fit.cost, (0.5 * fit.loss_scale.double() ** 2 * torch.log1p(u * u)).sum(0),
                               rtol=1e-4, atol=0)
    other = dataclasses.replace(fit, beta_b=fit.beta_b * 5, cost=fit.cost * torch.tensor([0.5, 2.0, 2.0],
                                                                                          dtype=torch.float64))
    picked = _deeper(fit, other)
    assert picked[1, 0] == pytest.approx(float(other.beta_b[0])) and picked[1, 0] != pytest.approx(float(fit.beta_b[0]))
    torch.testing.assert_close(picked[:, 1:], torch.stack([m.double() for m in fit.medium])[:, 1:])


def test_a_colour_drift_moves_beta_d_by_the_drift_over_the_optical_depth_spanned():
    """Without backscatter (B_inf held at 0) and every point seen at 3 and 6 units, a drift of the direct signal by
    +-d over each point's span is exactly a change of beta_D by d / 3 per unit: the refit must find it."""
    g = torch.Generator().manual_seed(4)
    clean = 0.1 + 0.7 * torch.rand(60, 3, generator=g, dtype=torch.float64)
    point = torch.arange(60).repeat_interleave(2)
    z = torch.tensor([3.0, 6.0], dtype=torch.float64).repeat(60)
    beta_d = torch.tensor(BETA_D, dtype=torch.float64)
    color = clean[point] * torch.exp(-beta_d * z[:, None])
    held = torch.zeros(3, dtype=torch.float64)
    start = (beta_d, torch.tensor(BETA_B, dtype=torch.float64), held)  # the truth: this tests the drift, not the fit
    fit = fit_multiview(point, color, z, b_inf=held, start=start)
    moved = _drift_sensitivity(point, color, z, torch.ones_like(z), held, fit, MultiviewConfig(color_drift=0.06))
    torch.testing.assert_close(moved[0], 0.06 / 3 / beta_d, rtol=1e-3, atol=0)


def test_a_short_span_with_little_noise_is_flagged_for_the_colour_drift_it_cannot_rule_out():
    """Points seen over 1.5-1.7x with 0.2% noise: the bootstrap is tight, but a 6% drift of the surfaces' colours
    would move the G and B backscatter by more than 15%, and the median span is under 2x, so nothing is called
    identified (the forward survey's case: there red beta_B was 28% off with a 10% bootstrap spread). Over 2-3x the
    red and blue betas pass."""
    point, color, z, _ = surveyed_points(300, span=(1.5, 1.7), noise=0.002, outliers=0.0, single=0.0)
    short = multiview_estimate(point, color, z, MultiviewConfig(resamples=4))
    assert all("the median point spans a range ratio of 1.59 (< 2)" in check.reason for check in short.checks)
    for c in (1, 2):
        check = short.check("beta_B", c)
        assert not check.identified and "drift of the surfaces' colours over each point's ranges" in check.reason
        assert short.drift[1][c] > 0.15 and check.spread < 0.15
    point, color, z, _ = surveyed_points(300, span=(2.0, 3.0), noise=0.002, outliers=0.0, single=0.0)
    wide = multiview_estimate(point, color, z, MultiviewConfig(resamples=4))
    assert all(wide.check(name, c).identified for name in ("beta_D", "beta_B") for c in (0, 2))
    betas_rb = [(k, c) for k in (0, 1) for c in (0, 2)]
    assert max(wide.drift[k][c] for k, c in betas_rb) < max(short.drift[k][c] for k, c in betas_rb)


@pytest.mark.slow  # whole bootstrapped estimates: tens of seconds each on two cores
def test_a_medium_that_thickens_across_the_scene_is_flagged_and_homogeneous_water_is_not():
    """Points spread over x in [-5, 5]; the betas are 1.6x thicker where x > 0: the halves of the points disagree and
    every beta is flagged. The same points through homogeneous water pass."""
    point, color, z, _ = surveyed_points(300, noise=0.005, outliers=0.0, single=0.0, seed=2)
    x = torch.linspace(-5, 5, 300, dtype=torch.float64)
    positions = torch.stack([x, 0.3 * torch.rand(300, generator=torch.Generator().manual_seed(4),
                                                 dtype=torch.float64), torch.zeros(300, dtype=torch.float64)], -1)
    config = MultiviewConfig(resamples=3)
    homogeneous = multiview_estimate(point, color, z, config, positions=positions)
    assert not homogeneous.varies_in_space and max(homogeneous.spatial_disagreement) < 0.3
    factor = torch.where(x > 0, 1.6, 1.0)[point][:, None]
    bd, bb, b = (torch.tensor(v, dtype=torch.float64) for v in (BETA_D, BETA_B, B_INF))
    clean = 0.1 + 0.7 * torch.rand(300, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    thick = clean[point] * torch.exp(-bd * factor * z[:, None]) + b * (1 - torch.exp(-bb * factor * z[:, None]))
    varying = multiview_estimate(point, thick, z, config, positions=positions)
    assert varying.varies_in_space
    assert not any(c.identified for c in varying.checks if c.name != "B_inf")
    assert all("varies in space" in c.reason for c in varying.checks if c.name != "B_inf")


def test_dry_points_are_reported_in_absolute_units_not_as_exploding_ratios():
    """No water (beta = 0): the fit's betas are near 0, where a spread or a difference of the halves relative to them
    is meaningless (the fox read "2907608263% apart"); the lines give them per unit of range instead."""
    point, color, z, _ = surveyed_points(300, single=0.0, outliers=0.0, medium=((0.0,) * 3, (0.0,) * 3, B_INF))
    positions = torch.rand(300, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    estimate = multiview_estimate(point, color, z, MultiviewConfig(resamples=3), positions=positions)
    assert max(estimate.fit.beta_d.tolist()) < 0.01
    text = "\n".join(estimate.lines() + [c.reason for c in estimate.checks])
    assert "per unit" in text
    percents = [float(p) for p in re.findall(r"(\d+)%", text)]
    assert max(percents) <= 1000, text  # RELATIVE_READABLE: bigger ratios are written in absolute units


def test_points_seen_at_one_range_only_give_no_fit_and_say_why():
    point, color, z, _ = surveyed_points(50, single=1.0)
    estimate = multiview_estimate(point, color, z)
    assert estimate.fit is None and estimate.points == 0
    assert not any(check.identified for check in estimate.checks)


def test_visible_observations_hide_a_point_behind_another_and_read_blurred_colours_for_near_views():
    K = torch.tensor([[20.0, 0, 10], [0, 20.0, 10], [0, 0, 1]])
    near_cam = Camera(torch.eye(4), K, 20, 20)
    far = torch.eye(4)
    far[2, 3] = 2.0  # 2 units further back: world z = -2 at the centre
    far_cam = Camera(far, K, 20, 20)
    points = torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, 2.0], [1.0, 1.0, 4.0]], dtype=torch.float64)
    image = torch.zeros(20, 20, 3)
    image[10, 10] = 1.0  # one bright pixel where point 0 lands in the near view
    point, color, z = visible_observations(points, [near_cam, far_cam], [image, image], depth_cell=2,
                                           match_footprint=False)
    assert 0 not in point.tolist()  # point 1 lies in front of it along the same pixels
    assert sorted(point.tolist()) == [1, 1, 2, 2]
    torch.testing.assert_close(z[point == 1], torch.tensor([2.0, 4.0], dtype=torch.float64))
    hidden_off = visible_observations(points, [near_cam], [image], depth_cell=0, match_footprint=False)
    assert hidden_off[0].tolist() == [0, 1, 2] and hidden_off[1][0].tolist() == [1.0, 1.0, 1.0]
    # matched footprints: the near view of point 1 (range 2, farthest 4) is read blurred, the far one not
    _, blurred, ranges = visible_observations(points[1:2], [near_cam, far_cam], [image, image], depth_cell=0)
    assert float(blurred[0, 0]) < 1.0 and float(blurred[0, 0]) > 0.0


def test_span_counts_and_ratios():
    count, ratio = point_spans(torch.tensor([0, 0, 2]), torch.tensor([2.0, 5.0, 3.0], dtype=torch.float64), 3)
    assert count.tolist() == [2, 0, 1] and ratio.tolist() == [2.5, 0.0, 1.0]


def _estimate(values: tuple[float, float, float]) -> MediumEstimate:
    beta_d, beta_b, b_inf = (torch.full((3,), v) for v in values)
    return MediumEstimate(beta_d, beta_b, b_inf, torch.zeros(1, 3), 1)


def _multiview(values: tuple[float, float, float], identified: dict[str, list[bool]]) -> MultiviewEstimate:
    result = MultiviewEstimate(None, 100, 100, (1.5, 2.0, 2.5), [False] * 3)
    result.checks = [MultiviewCheck(name, "RGB"[c], values[k], 0.05, identified[name][c],
                                    "" if identified[name][c] else "bootstrap spread +-40% (> 15%)")
                     for k, name in enumerate(("beta_D", "beta_B", "B_inf")) for c in range(3)]
    return result


def _report(identifiable: dict[str, list[bool]]) -> SimpleNamespace:
    return SimpleNamespace(checks=[ParameterCheck(name, "RGB"[c], 0.0, 0.05, 0.0, identifiable[name][c],
                                                  "" if identifiable[name][c] else "no open water in view")
                                   for name in ("beta_D", "beta_B", "B_inf") for c in range(3)])


def test_each_parameter_comes_from_the_evidence_that_pins_it():
    single = _estimate((0.1, 0.2, 0.3))
    report = _report({"beta_D": [True, True, False], "beta_B": [True, False, False],
                      "B_inf": [True, False, False]})
    calls = []

    def fit(b_inf):
        calls.append(b_inf)
        return _multiview((0.5, 0.6, 0.7), {"beta_D": [False, True, True], "beta_B": [False, True, False],
                                            "B_inf": [False, True, False]})

    combined = combine_by_evidence(single, report, None, fit)
    sources = {(c.name, c.channel): c.source for c in combined.checks}
    assert [sources[("B_inf", ch)] for ch in "RGB"] == [FAR_END, RANGE_DIVERSITY, NOT_IDENTIFIED]
    # blue beta_D: the multi-view fit calls it identified, but with a blue B_inf that nothing identifies
    assert [sources[("beta_D", ch)] for ch in "RGB"] == [DARK_PIXELS, RANGE_DIVERSITY, NOT_IDENTIFIED]
    assert [sources[("beta_B", ch)] for ch in "RGB"] == [DARK_PIXELS, RANGE_DIVERSITY, NOT_IDENTIFIED]
    torch.testing.assert_close(combined.medium[2], torch.tensor([0.3, 0.7, 0.3]))
    torch.testing.assert_close(combined.medium[0], torch.tensor([0.1, 0.5, 0.1]))
    # the second multi-view fit holds B_inf where it did not come from range diversity
    assert calls[0] is None and torch.equal(calls[1].isnan(), torch.tensor([False, True, False]))
    assert "not identified" in combined.lines()[0]
    # open water is a measurement: held in the multi-view fit and reported as its source
    calls.clear()
    water = torch.tensor([0.05, 0.25, 0.35])
    combined = combine_by_evidence(single, report, water, fit)
    assert [c.source for c in combined.checks if c.name == "B_inf"] == [OPEN_WATER] * 3
    assert len(calls) == 1 and torch.equal(calls[0], water.double())
    # a medium that varies in space: no homogeneous value is identified, whichever estimate it comes from

    def varying(b_inf):
        result = fit(b_inf)
        result.varies_in_space = True
        return result

    combined = combine_by_evidence(single, report, water, varying)
    assert all(c.source == NOT_IDENTIFIED and "varies in space" in c.reason for c in combined.checks
               if c.name != "B_inf")


def test_the_survey_passes_look_at_the_same_seabed_from_each_altitude(tmp_path):
    from uw3dgs.datamanagers.synthetic.cameras import _path

    survey = SyntheticSceneConfig(num_views=12, pass_altitudes=(3.0, 6.0))
    centres, headings = _path(survey)
    assert centres[:6, 2].tolist() == [3.0] * 6 and centres[6:, 2].tolist() == [6.0] * 6
    axis = np.stack([np.cos(headings), np.sin(headings), np.zeros(12)], axis=1) * math.sin(math.radians(55)) + \
        np.array([0, 0, -math.cos(math.radians(55))])
    ground = centres + axis * (centres[:, 2] / math.cos(math.radians(55)))[:, None]
    np.testing.assert_allclose(ground[6:, :2], ground[:6, :2], atol=1e-9)  # the same seabed line
    # a scene without the option keeps its cache key; the passes enter it
    assert cache_key(SyntheticSceneConfig()) == "ecf3ad650b29"
    assert cache_key(survey) != cache_key(dataclasses.replace(survey, pass_altitudes=()))
    with pytest.raises(OptionError, match="pass_altitudes"):
        SyntheticSceneConfig(num_views=2, pass_altitudes=(3.0, 4.0, 5.0))


def test_a_survey_at_two_altitudes_sees_its_points_over_twice_the_span_of_one(tmp_path):
    from uw3dgs.data.seathru_layout import read_seathru_layout
    from uw3dgs.datamanagers.synthetic.scene import generate_scene

    small = SyntheticSceneConfig(width=48, height=36, num_views=12, terrain_size=24.0, terrain_resolution=0.04,
                                 num_points=600, open_water=False, num_dark_patches=0)
    medians = []
    for name, passes in (("one", ()), ("two", (3.0, 6.0))):
        scene = read_seathru_layout(generate_scene(dataclasses.replace(small, pass_altitudes=passes),
                                                   tmp_path / name, progress=False))
        point, _, z = visible_observations(scene.points, scene.cameras, scene.images)
        count, ratio = point_spans(point, z, len(scene.points))
        medians.append(float(ratio[count >= 2].median()))
    assert medians[1] > 2.0 > medians[0] + 0.3, medians


def test_the_gradient_medium_steps_smoothly_across_the_scene():
    config = SyntheticSceneConfig(medium_profile="gradient", medium_profile_gain=2.0, gradient_length=1.0,
                                  gradient_center=(1.0, 4.0))
    x = np.array([-20.0, 0.0, 1.0, 2.0, 20.0])
    beta_d = beta_field(config, np.stack([x, np.full(5, 4.0), np.zeros(5)], axis=1))[0][:, 0]
    reference = config.beta_D[0]
    np.testing.assert_allclose(beta_d[[0, 2, 4]], [reference, 2.0 * reference, 3.0 * reference], rtol=1e-6)
    assert (np.diff(beta_d) > 0).all()
    assert cache_key(dataclasses.replace(config, gradient_length=3.0)) != cache_key(config)


@pytest.mark.slow  # whole bootstrapped estimates: tens of seconds each on two cores
def test_the_multiview_start_sets_the_combined_medium_and_pulls_toward_it(make_config):
    """`--model.medium.init multiview`: the model starts from the medium combined by evidence, L_beta pulls toward
    it, the colours are de-hazed with it, and the run's notes say where each parameter came from."""
    from uw3dgs.registry import METHODS
    from uw3dgs.render.sh import rgb_to_sh

    spec = METHODS["uw3dgs"].config
    base = make_config(steps=1)
    medium = dataclasses.replace(spec.model.medium, init="multiview", report=False,  # no single-image report: quick
                                 multiview=MultiviewConfig(resamples=2, max_iterations=30))
    model_config = dataclasses.replace(spec.model, medium=medium, gaussians=base.model.gaussians)
    datamanager = base.datamanager.setup(data=None)
    scene, train = datamanager.scene, datamanager.train_indices
    model = model_config.setup(scene=scene, train_indices=train)
    model.initialize_from_data(scene, train)
    evidence = model.medium_evidence
    assert evidence is not None and len(evidence.checks) == 9
    beta_d, beta_b, b_inf = evidence.medium
    torch.testing.assert_close(model.medium.prior_d, beta_d, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(model.medium.prior_b, beta_b, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(model.medium.b_inf.detach(), b_inf)
    # the built-in scene shows open water: B_inf is read off it, as the single-image estimate does
    assert [c.source for c in evidence.checks if c.name == "B_inf"] == [OPEN_WATER] * 3
    sh0 = model.gaussians.sh0[:, 0]
    assert torch.isfinite(sh0).all() and not torch.allclose(sh0, rgb_to_sh(scene.point_colors.float()))
    assert "medium_evidence" in model.run_notes()


@pytest.mark.parametrize(("multi_spread", "expected"), [(0.2, 0.6), (0.8, 0.2)])
def test_a_parameter_neither_estimate_pins_starts_from_the_one_with_the_smaller_spread(multi_spread, expected):
    """Green beta_B: the single-image report flags it (+-50%), the multi-view bootstrap too (+-20% or +-80%): it is
    not identified either way, and starts from the value with the smaller spread."""
    single = _estimate((0.1, 0.2, 0.3))
    everything = {name: [True] * 3 for name in ("beta_D", "beta_B", "B_inf")}
    report = _report({**everything, "beta_B": [True, False, True]})
    report.checks[4] = dataclasses.replace(report.checks[4], spread=0.5)

    def fit(b_inf):
        result = _multiview((0.5, 0.6, 0.7), {**everything, "beta_B": [True, False, True]})
        result.checks[4] = dataclasses.replace(result.checks[4], spread=multi_spread)
        return result

    check = next(c for c in combine_by_evidence(single, report, None, fit).checks
                 if c.name == "beta_B" and c.channel == "G")
    assert check.source == NOT_IDENTIFIED and check.value == pytest.approx(expected)
    assert ("started from the multi-view value" in check.reason) == (multi_spread < 0.5)
