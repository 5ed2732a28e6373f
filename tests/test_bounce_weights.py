"""Heavy tails caught where they arise: the single-bounce weight ``f·cos/p`` of every sampler at real diffuse vertices
of `door-ajar` and `cornell-tilted`, after training on the scene.

Its mean equals the albedo (the density is right at these vertices, not only in the chi-square tests' set-ups), and
it never exceeds the bound its defensive share gives by construction: ρ/α for a one-sample mixture with BSDF
sampling of share α (ρ for BSDF sampling itself). The paper's pure hemi_inv, which has no such share, reached 97·ρ
here (results/grid_unbiasedness.md).
"""

import pytest

from guiding.guides import RULES, SAMPLERS
from guiding.guides.grid.guide import GridGuide
from guiding.guides.methods import make_guide
from guiding.scenes import load_scene
from guiding.experiments.testing import scene_vertices, single_bounce_weights, train

METHODS = ["brdf", "sdtree", "quadtree-grid", "ours-uniform-proposals"] + [f"{rule}-{sampler}" for rule in RULES
                                                                          for sampler in SAMPLERS]
#: Rounding allowed on top of the bound (float32 weights and pdfs).
ROUNDING = 1e-4

_cache = {}


def _vertices(scene_name):
    if scene_name not in _cache:
        scene = load_scene(scene_name, scale=0.1)
        _cache[scene_name] = scene, scene_vertices(scene, 500, seed=3)
    return _cache[scene_name]


def weight_bound(guide) -> float:
    """The largest single-bounce weight over the albedo that the guide's defensive share allows."""
    if isinstance(guide, GridGuide):
        parameters = guide.parameters
        return 1 / (parameters.min_bsdf_share if parameters.sampler.startswith("hemi_rej")
                    else parameters.bsdf_fraction)
    return 1 / getattr(guide, "bsdf_fraction", 1.0)


@pytest.mark.parametrize("scene_name", ["door-ajar", "cornell-tilted"])
@pytest.mark.parametrize("method", METHODS)
def test_single_bounce_weight_is_unbiased_and_bounded(scene_name, method):
    scene, vertices = _vertices(scene_name)
    guide = train(scene, make_guide(method), spp=64, seed=1)
    weights = single_bounce_weights(guide, vertices, samples=2048, scene=scene)
    mean, standard_error = weights.mean_ratio()
    assert abs(mean - 1) < 4 * max(standard_error, 1e-6), f"{method}: mean weight / albedo {mean} ± {standard_error}"
    largest = weights.largest_ratio()
    assert largest <= weight_bound(guide) * (1 + ROUNDING), f"{method}: weight {largest}·ρ"


def test_pure_hemi_inv_is_heavy_tailed():
    """The check can fail: without its BSDF share, hemi_inv exceeds any such bound at door-ajar's vertices."""
    scene, vertices = _vertices("door-ajar")
    guide = train(scene, make_guide("sarsa-hemi_inv", bsdf_fraction=0.0), spp=64, seed=1)
    weights = single_bounce_weights(guide, vertices, samples=2048, scene=scene)
    assert weights.largest_ratio() > 10
    assert weights.second_moment_ratio() > 4
