"""The BSDF-sampling baseline converges to what Mitsuba's own `path` integrator computes."""

import mitsuba as mi
import pytest

from guiding.render.integrator import GuidedPathIntegrator

from guiding.experiments.validation import Z_LIMIT, pass_means, z_scores


def test_brdf_matches_mitsuba_path(cornell):
    ours = pass_means(cornell, GuidedPathIntegrator(), passes=24, spp=32, seed=1)
    reference = pass_means(cornell, mi.load_dict({"type": "path", "max_depth": 16}), passes=24, spp=32, seed=2)
    z = z_scores(ours, reference)
    assert (z < Z_LIMIT).all(), f"z-scores {z}, means {ours.mean(0)} vs {reference.mean(0)}"
    # The test must be able to fail: the standard error is small next to the signal.
    assert (ours.std(axis=0, ddof=1) / len(ours) ** 0.5 < 0.02 * reference.mean(axis=0)).all()


@pytest.mark.parametrize("max_depth", [1, 2, 3])
def test_max_depth_means_what_mitsuba_means(cornell, max_depth):
    props = mi.Properties()
    props["max_depth"] = max_depth
    ours = pass_means(cornell, GuidedPathIntegrator(props), passes=12, spp=16, seed=3)
    reference = pass_means(cornell, mi.load_dict({"type": "path", "max_depth": max_depth}), passes=12, spp=16, seed=4)
    z = z_scores(ours, reference)
    assert (z < Z_LIMIT).all(), f"z-scores {z}, means {ours.mean(0)} vs {reference.mean(0)}"
