"""The path fallback (:mod:`guiding.render.path_fallback`): its prediction of a strategy's error, its decision, the
weights of the image it makes, and renders with it agreeing with Mitsuba's ``path``."""

import mitsuba as mi
import numpy as np
import pytest

from guiding.experiments.validation import assert_means_agree, path_render_means
from guiding.guides.methods import make_guide
from guiding.metrics import mae_tonemapped
from guiding.render.integrator import GuidedPathIntegrator
from guiding.render.iterations import IterationImages
from guiding.render.path_fallback import GUIDE, PATH, PassImage, PathFallback, predicted_mae
from guiding.render.progressive import Budget, render


def _noisy(rng, mean: np.ndarray, sigma: np.ndarray, spp: int) -> np.ndarray:
    """A pass image of ``spp`` samples of per-sample standard deviation ``sigma`` around ``mean``."""
    return mean + sigma / np.sqrt(spp) * rng.standard_normal(mean.shape)


def test_predicted_mae_is_the_mae_of_an_image_of_that_many_spp():
    rng = np.random.default_rng(1)
    mean = rng.uniform(0.01, 3.0, (64, 64, 3))
    sigma = mean * rng.uniform(0.5, 4.0, (64, 64, 1))
    first, second = _noisy(rng, mean, sigma, 8), _noisy(rng, mean, sigma, 32)
    for spp in (64, 4096):
        measured = mae_tonemapped(_noisy(rng, mean, sigma, spp), mean)
        assert predicted_mae(mean, first, 8, second, 32, spp) == pytest.approx(measured, rel=0.05)
    # Four times the spp, half the noise (the tone map is nearly linear at that noise).
    ratio = predicted_mae(mean, first, 8, second, 32, 4096) / predicted_mae(mean, first, 8, second, 32, 16384)
    assert ratio == pytest.approx(2.0, rel=0.02)


def _fallback_with(rng, guide_sigma: float, guide_cost: float, path_sigma: float, path_cost: float):
    """A check that saw two guided and two path passes of 16 spp around a grey image."""
    mean = np.full((32, 32, 3), 0.5)
    fallback = PathFallback(None, checked=True)
    fallback.comparing = True
    for strategy, sigma, cost in ((fallback.guided, guide_sigma, guide_cost), (fallback.path_passes, path_sigma,
                                                                               path_cost)):
        strategy.extend(PassImage(_noisy(rng, mean, np.full_like(mean, sigma), 16), 16, 16 * cost)
                        for _ in range(2))
    return fallback, mean


@pytest.mark.parametrize("budget", ["spp", "seconds"])
def test_the_check_takes_the_lower_error_at_equal_spp_or_at_equal_time(budget):
    """A guide with half path's noise per sample at four times its cost per sample: at equal spp it wins; at equal
    time path renders four times the spp, as good (here, with a margin: five times the cost)."""
    rng = np.random.default_rng(2)
    fallback, mean = _fallback_with(rng, guide_sigma=0.5, guide_cost=5e-3, path_sigma=1.0, path_cost=1e-3)
    spp_left, seconds_left = (1000, None) if budget == "spp" else (None, 10.0)
    decision = fallback.decide(mean, 64, 1.0, spp_left, seconds_left, share_before=0.1)
    assert decision.chosen == (GUIDE if budget == "spp" else PATH)
    assert decision.guide_seconds_per_spp == pytest.approx(5e-3) and decision.path_seconds_per_spp == pytest.approx(1e-3)
    assert not fallback.renders_path if budget == "spp" else fallback.renders_path


def test_the_share_before_the_decision_comes_from_spp_and_times_alone():
    rng = np.random.default_rng(3)
    fallback, _ = _fallback_with(rng, guide_sigma=0.5, guide_cost=4e-3, path_sigma=1.0, path_cost=1e-3)
    assert fallback.share_before(100, spp_budget=400, seconds_left=None) == 0.25
    # 0.9 s left at the cheaper strategy's 1 ms per spp: 900 spp more.
    assert fallback.share_before(100, spp_budget=None, seconds_left=0.9) == pytest.approx(100 / 1000)
    # The images do not enter: other noise, the same share.
    other, _ = _fallback_with(rng, guide_sigma=3.0, guide_cost=4e-3, path_sigma=0.1, path_cost=1e-3)
    assert other.share_before(100, None, 0.9) == fallback.share_before(100, None, 0.9)


def test_a_split_image_weighs_its_two_parts_by_the_share():
    images = IterationImages("last")
    before = [np.full((2, 2, 3), v) for v in (1.0, 3.0)]
    after = [np.full((2, 2, 3), v) for v in (10.0, 20.0, 40.0)]
    for image, spp in zip(before, (8, 8)):
        images.add_pass(mi.TensorXf(image), spp)
    images.split(0.25)
    for image, spp in zip(after, (8, 16, 8)):
        images.add_pass(mi.TensorXf(image), spp)
    image, spp, _ = images.image()
    expected = 0.25 * 2.0 + 0.75 * (10 * 8 + 20 * 16 + 40 * 8) / 32
    assert spp == 48 and np.allclose(image, expected)


def _fallback_integrator(method: str) -> GuidedPathIntegrator:
    return mi.load_dict({"type": "guided_path", "method": method, "nee": True, "path_fallback": True})


def test_path_fallback_needs_nee():
    props = mi.Properties()
    props["path_fallback"] = True
    with pytest.raises(ValueError, match="set nee too"):
        GuidedPathIntegrator(props, guide=make_guide("ours"))


RENDERS = 16


@pytest.mark.parametrize("budget", [Budget(spp=128, pass_spp=8, growing_passes=False),
                                    Budget(seconds=0.4, pass_spp=8, exclude_passes=2)], ids=["spp", "seconds"])
def test_renders_with_the_fallback_agree_with_path(cornell, budget):
    """Whatever each render decided, the mean of its image is path's: the decision never weighs the images."""
    means, chosen = [], set()
    for seed in range(RENDERS):
        integrator = _fallback_integrator("ours-plus")
        result = render(cornell, integrator, budget, seed=seed, progress=False)
        assert result.path_fallback is not None and result.path_fallback["share_before"] is not None
        chosen.add(result.path_fallback["chosen"])
        means.append(result.image.mean(axis=(0, 1)))
    assert_means_agree(np.array(means), path_render_means(cornell, RENDERS, 128), note=f"({chosen})")

