"""The progressive renderer: budgets, per-pass statistics, and no recompilation across passes."""

import numpy as np
import pytest


from guiding.errors import GuidingError
from guiding.integrator import GuidedPathIntegrator
from guiding.render import Budget, pass_seed, render


def test_spp_budget_is_exact(cornell):
    result = render(cornell, GuidedPathIntegrator(), Budget(spp=21, pass_spp=8))
    assert [p.spp for p in result.passes] == [8, 8, 5]
    assert result.spp == 21
    assert np.isfinite(result.image).all() and result.image.shape[2] == 3


def test_seconds_budget_stops_within_one_pass(cornell):
    budget = Budget(seconds=1.0, pass_spp=4)
    result = render(cornell, GuidedPathIntegrator(), budget)
    counted = result.counted_seconds()
    last = result.passes[-1].counted_seconds
    assert counted >= budget.seconds
    assert counted - last < budget.seconds  # the last pass started before the budget was spent


def test_excluded_passes_are_not_counted(cornell):
    result = render(cornell, GuidedPathIntegrator(), Budget(seconds=0.3, pass_spp=2, exclude_passes=3))
    assert len(result.passes) > 3
    counted = sum(p.counted_seconds for p in result.passes[3:])
    assert result.counted_seconds() == pytest.approx(counted)
    assert counted < result.seconds - sum(p.seconds for p in result.passes[:3]) + 1e-9


def test_kernel_count_does_not_grow_with_passes(cornell):
    result = render(cornell, GuidedPathIntegrator(), Budget(spp=12 * 4, pass_spp=4))
    launched = {p.kernels_launched for p in result.passes}
    assert len(launched) == 1, launched
    assert all(p.kernels_compiled == 0 for p in result.passes[1:]), [p.kernels_compiled for p in result.passes]


def test_passes_use_distinct_seeds():
    seeds = {pass_seed(s, i) for s in range(3) for i in range(200)}
    assert len(seeds) == 600


def test_hit_rate_is_a_fraction(cornell):
    result = render(cornell, GuidedPathIntegrator(), Budget(spp=8))
    assert 0 < result.hit_rate < 1


@pytest.mark.parametrize("kwargs", [dict(spp=0), dict(seconds=-1.0), dict(), dict(spp=4, seconds=1.0),
                                    dict(spp=4, pass_spp=0)])
def test_bad_budgets_are_rejected(kwargs):
    with pytest.raises(GuidingError):
        Budget(**kwargs)
