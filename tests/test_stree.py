"""The S-tree of the SD-tree (Müller et al. 2017): midpoint splits along cycling axes, the locator's start table,
the doubling schedule of the iterations and the threshold that scales with the image."""

import mitsuba as mi
import numpy as np
import pytest

from guiding.guides.trees.sdtree import SDTreeGuide
from guiding.guides.trees.stree import STree, iteration_length, stree_locate
from guiding.render.integrator import GuidedPathIntegrator
from tree_helpers import doubling_schedule


def test_stree_splits_at_midpoints_cycling_axes():
    stree = STree([0, 0, 0], [1, 1, 1])
    lo = stree.lo[0]
    size = stree.hi[0][0] - lo[0]
    # 100 vertices, threshold 30: the root splits (x), each half (50) splits (y), the quarters (25) do not.
    sources = stree.refine([100.0], threshold=30)
    assert stree.n_leaves == 4 and sources.tolist() == [0, 0, 0, 0]
    assert stree.axis[0] == 0 and stree.axis[stree.child[0]] == 1
    assert np.isclose(stree.split_value(0), lo[0] + size / 2)
    arrays = stree.to_device()
    points = np.array([[0.2, 0.2, 0.5], [0.2, 0.8, 0.5], [0.8, 0.2, 0.5], [0.8, 0.8, 0.5]])
    leaf = stree_locate(arrays, mi.Point3f(*[mi.Float(points[:, i]) for i in range(3)])).numpy()
    assert sorted(leaf.tolist()) == [0, 1, 2, 3]
    # A count equal to the threshold does not split; above it, the leaf splits along z (its axis).
    counts = np.zeros(4)
    counts[leaf[0]] = 30.0
    counts[leaf[3]] = 31.0
    sources = stree.refine(counts, threshold=30)
    assert stree.n_leaves == 5
    assert sorted(sources.tolist()) == sorted([0, 1, 2, 3, int(leaf[3])])
    arrays = stree.to_device()
    high = points[3:4].repeat(2, 0) * [1, 1, 0] + [[0, 0, 0.2], [0, 0, 0.8]]
    split_leaves = stree_locate(arrays, mi.Point3f(*[mi.Float(high[:, i]) for i in range(3)])).numpy()
    assert split_leaves[0] != split_leaves[1]
    assert (sources[split_leaves] == leaf[3]).all()     # both children inherit the parent's D-tree
    # Whatever the threshold, a leaf of one vertex or fewer does not split: 100 vertices make at most 7 levels.
    bounded = STree([0, 0, 0], [1, 1, 1])
    bounded.refine([100.0], threshold=0.0)
    assert bounded.n_leaves == 128 and max(bounded.depth) == 7


def test_stree_locate_from_the_start_table_finds_every_leaf():
    """The start table skips the first 3·START_LEVELS levels of the descent: on a tree with leaves above, at and far
    below that depth, every position finds the leaf a full descent from the root finds."""
    from guiding.experiments import guide_state
    from guiding.guides.trees.stree import START_LEVELS

    rng = np.random.default_rng(7)
    stree = STree([-1, 0, 2], [3, 1, 2.5])
    stree.refine([3000.0], threshold=50)       # 6 levels, then some leaves far deeper than 15 and others not at all
    stree.refine(np.where(rng.random(stree.n_leaves) < 0.1, rng.lognormal(13, 1, stree.n_leaves), 0), threshold=50)
    assert min(stree.depth) < 3 * START_LEVELS < max(stree.depth)
    state = guide_state._stree_state(stree)
    points = rng.uniform(stree.lo[0], stree.hi[0], (4000, 3))
    found = stree_locate(stree.to_device(), mi.Point3f(*[mi.Float(points[:, i]) for i in range(3)])).numpy()
    expected = [guide_state.cell_of_point({**state, "locator": "stree"}, point) for point in points]
    assert found.tolist() == expected


def test_doubling_schedule():
    assert doubling_schedule(8)[:4] == [(0, 8), (8, 24), (24, 56), (56, 120)]
    # With a budget of 64 spp, the third iteration (32 spp) could not be doubled: it runs to the end (40 spp).
    assert doubling_schedule(8, 64) == [(0, 8), (8, 24), (24, 64)]
    assert doubling_schedule(8, 8) == [(0, 8)]
    assert doubling_schedule(1, 1000)[-1][1] == 1000
    assert iteration_length(8, 1, 8, 64) == (16, False) and iteration_length(8, 2, 24, 64) == (40, True)
    assert iteration_length(8, 5, 248) == (256, False)     # without a budget no iteration is the last


def test_stree_threshold_grows_with_the_square_root_of_the_paths(cornell):
    """Tom94's c·sqrt(spp/4) at 1280 × 720, and c·sqrt(paths / (4·1280·720)) at any size: 375·sqrt(spp) at
    80 × 45; ``c_pixels`` set to the image's size gives the unscaled c·sqrt(spp/4)."""
    from guiding.render.progressive import Budget, render

    guide = SDTreeGuide()
    assert guide.stree_threshold(1280 * 720 * 4) == pytest.approx(12000)
    assert guide.stree_threshold(1280 * 720 * 64) == pytest.approx(12000 * 4)
    assert guide.stree_threshold(80 * 45 * 16) == pytest.approx(375 * 4)
    assert SDTreeGuide(c_pixels=80 * 45).stree_threshold(80 * 45 * 16) == pytest.approx(12000 * 2)
    # In a render, the paths are those the iteration's passes traced (pixels × spp).
    result = render(cornell, GuidedPathIntegrator(guide=guide), Budget(spp=56, pass_spp=8), seed=2)
    pixels = int(np.prod(cornell.sensors()[0].film().crop_size()))
    for it in result.iterations[:2]:
        assert it.guide["paths_recorded"] == pixels * it.spp
        assert it.guide["stree_threshold"] == pytest.approx(12000 * np.sqrt(pixels * it.spp / (4 * 1280 * 720)))
