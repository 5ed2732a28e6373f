"""The learned BSDF share of the tree guides (guiding/guides/bsdf_fraction.py): the Newton step by hand, its
convergence to the KL minimiser of a problem solved exactly, and the sign of what the render kernel records."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from guiding.guides.trees.bsdf_fraction import MAX_SHARE, MAX_STEP, MIN_SHARE, MIN_VERTICES, LearnedBsdfFraction
from guiding.render.integrator import GuidedPathIntegrator
from guiding.guides.methods import make_guide
from guiding.render.progressive import Budget, render


def _record(fraction, tree, c, s):
    n = len(tree)
    fraction.record(mi.UInt32(tree), mi.Float(np.full(n, c) if np.isscalar(c) else c),
                    mi.Float(np.full(n, s) if np.isscalar(s) else s), dr.full(mi.Bool, True, n))


def test_newton_step_by_hand():
    """N = MIN_VERTICES vertices per tree. Tree 0: G = N·1·0.5, H = N·1·0.25, a step of G/H = 2, clipped to
    MAX_STEP. Tree 1: G = 0, a step of 0. Tree 2: too few vertices; it keeps its share and its sums, and steps once
    the next pass brings enough. Vertices with c = 0 count for nothing."""
    n = MIN_VERTICES
    fraction = LearnedBsdfFraction(3, 0.5)
    _record(fraction, [0] * n, 1.0, 0.5)
    _record(fraction, [1] * n, 1.0, np.resize([0.5, -0.5], n))
    _record(fraction, [2] * (n - 1), 2.0, -0.25)
    _record(fraction, [2] * n, 0.0, -0.25)
    stats = fraction.step()
    assert fraction.host == pytest.approx([0.5 + MAX_STEP, 0.5, 0.5])
    assert stats["bsdf_fraction_steps"] == 2
    _record(fraction, [2], 2.0, -0.25)            # G = N·2·(−0.25), H = N·2·0.0625: −4, clipped
    fraction.step()
    assert fraction.host == pytest.approx([0.5 + MAX_STEP, 0.5, 0.5 - MAX_STEP])
    _record(fraction, [1] * n, 3.0, 0.2)          # G = N·0.6, H = N·0.12: +5, clipped
    _record(fraction, [2] * n, 0.5, -0.4)         # G = −N·0.2, H = N·0.08: −2.5, clipped to the floor
    fraction.step()
    assert fraction.host == pytest.approx([0.5 + MAX_STEP, 0.5 + MAX_STEP, MIN_SHARE])
    for _ in range(3):
        _record(fraction, [0] * n, 1.0, 0.5)
        fraction.step()
    assert fraction.host[0] == pytest.approx(MAX_SHARE)


def test_small_steps_are_exact_and_non_finite_vertices_are_left_out():
    fraction = LearnedBsdfFraction(1, 0.5)
    half = MIN_VERTICES // 2
    c = np.r_[np.full(2 * half, 2.0), np.inf, np.nan]
    s = np.r_[np.full(half, 0.5), np.full(half, -0.45), 0.5, 0.5]     # a step of 0.05/0.4525
    _record(fraction, [0] * len(c), c, s)
    fraction.step()
    g, h = np.sum(2.0 * s[:-2]), np.sum(2.0 * s[:-2] ** 2)
    assert fraction.host[0] == pytest.approx(0.5 + g / h, rel=1e-5)


def test_remap_gives_new_trees_their_sources_share_and_clears_the_sums():
    fraction = LearnedBsdfFraction(2, 0.5)
    fraction.host[:] = [0.3, 0.8]
    _record(fraction, [1] * MIN_VERTICES, 1.0, 0.5)
    fraction.remap(np.array([1, 0, 1]))
    assert fraction.host == pytest.approx([0.8, 0.3, 0.8])
    assert np.array(fraction.shares)[:3] == pytest.approx([0.8, 0.3, 0.8])
    fraction.step()
    assert fraction.host == pytest.approx([0.8, 0.3, 0.8])


def test_steps_converge_to_the_kl_minimiser():
    """Directions of a discrete domain with BSDF density b, D-tree density t and product p: the steps, each from
    vertices drawn from the mixture they sampled with, reach the α that minimises −Σ p·log(α·b + (1 − α)·t)."""
    b = np.array([0.30, 0.25, 0.20, 0.15, 0.05, 0.05])
    t = np.array([0.02, 0.08, 0.10, 0.20, 0.30, 0.30])
    p = np.array([0.20, 0.25, 0.20, 0.15, 0.10, 0.10])

    def derivative(alpha):
        return -np.sum(p * (b - t) / (alpha * b + (1 - alpha) * t))

    low, high = 0.0, 1.0     # the loss is convex: bisection on its derivative
    for _ in range(60):
        mid = (low + high) / 2
        low, high = (mid, high) if derivative(mid) < 0 else (low, mid)
    optimum = (low + high) / 2
    assert MIN_SHARE + 0.1 < optimum < MAX_SHARE - 0.1

    rng = np.random.default_rng(3)
    fraction = LearnedBsdfFraction(1, 0.5)
    for _ in range(12):
        alpha = fraction.host[0]
        m = alpha * b + (1 - alpha) * t
        k = rng.choice(len(m), size=200_000, p=m)
        _record(fraction, np.zeros(len(k), dtype=np.uint32), p[k] / m[k], (b[k] - t[k]) / m[k])
        fraction.step()
    assert fraction.host[0] == pytest.approx(optimum, abs=0.01)


def _floor_scene(emitter: dict) -> mi.Scene:
    """A diffuse floor seen from above, lit by ``emitter`` alone."""
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 64, "height": 64, "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": 0.5},
                  "to_world": mi.ScalarTransform4f().scale([2, 2, 1])},
        "light": emitter})


SMALL_LIGHT = {"type": "rectangle", "emitter": {"type": "area", "radiance": 40.0},
               "to_world": mi.ScalarTransform4f().translate([0.5, 0, 3]).scale(0.3)
               @ mi.ScalarTransform4f().rotate([1, 0, 0], 180)}


@pytest.mark.parametrize("case", ["small light", "uniform sky"])
def test_learned_shares_follow_the_product(case):
    """End to end, through the render kernel's sums: under a small light the D-trees hold the product's peak and
    the shares fall to the floor; under a uniform sky the product is the cosine, which BSDF sampling draws exactly,
    and the shares rise to the ceiling (a sign error in c or s, or H, would send them elsewhere)."""
    scene = _floor_scene(SMALL_LIGHT if case == "small light" else {"type": "constant", "radiance": 1.0})
    guide = make_guide("sdtree-learned")
    render(scene, GuidedPathIntegrator(guide=guide), Budget(spp=1024), seed=4, progress=False)
    shares = guide._fraction.host
    if case == "small light":
        assert np.median(shares) == pytest.approx(MIN_SHARE), np.quantile(shares, [0, 0.5, 1])
    else:
        assert np.median(shares) > MAX_SHARE - 0.05, np.quantile(shares, [0, 0.5, 1])
