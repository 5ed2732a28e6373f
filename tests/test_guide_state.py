"""What `render --save-guide` saves and `show-guide` draws: the directional distribution a trained guide samples
from, read from the guide itself (guiding.experiments.guide_state), for the grid guide and the SD-tree."""

import math

import numpy as np
import pytest

from guiding.experiments import guide_state
from guiding.guides.methods import make_guide
from guiding.experiments.testing import train
from tree_helpers import lookup_np


@pytest.fixture(scope="module")
def grid_guide(cornell):
    return train(cornell, make_guide("ours"), spp=16)


@pytest.fixture(scope="module")
def sdtree_guide():
    from guiding.scenes import load_scene

    return train(load_scene("cornell", scale=0.25), make_guide("sdtree"), spp=64)


def test_grid_state_is_the_guides_policy(grid_guide, tmp_path):
    import mitsuba as mi

    state = guide_state.capture(grid_guide)
    guide_state.save(tmp_path / "guide.npz", state)
    loaded = guide_state.load(tmp_path / "guide.npz")
    np.testing.assert_array_equal(loaded["policy"], state["policy"])
    record = grid_guide.record_table
    policy = record.policy.numpy().reshape(record.cells, -1)
    cell = guide_state.best_cell(loaded)
    assert loaded["weight"][cell] > 0 and not np.allclose(policy[cell], policy[cell].mean())   # it learned
    # At each bin's centre the density is that bin's policy entry over the bin's solid angle 4π/B.
    centres = record.bins.centres().numpy().T
    np.testing.assert_allclose(guide_state.density(loaded, cell, centres), policy[cell] * record.bins.count
                               / (4 * math.pi), rtol=1e-6)
    assert np.mean(guide_state.density_image(loaded, cell, 720, 360)) * 4 * math.pi == pytest.approx(1, rel=0.02)
    # Points find the cell the guide itself looks up.
    points = np.random.default_rng(0).uniform(-1, 1, (50, 3))
    expected = record.cell(mi.Point3f(points[:, 0], points[:, 1], points[:, 2])).numpy()
    assert [guide_state.cell_of_point(loaded, p) for p in points] == expected.tolist()


def test_sdtree_state_is_the_density_of_its_dtrees(sdtree_guide):
    state = guide_state.capture(sdtree_guide)
    forest = sdtree_guide._sampling_host
    assert state["kind"] == "dtrees" and guide_state.cell_count(state) == forest.n_trees > 1
    rng = np.random.default_rng(1)
    uv = rng.random((2000, 2))
    directions = guide_state.square_directions(uv[:, 0], uv[:, 1])
    for tree in range(forest.n_trees):
        _, pdf = lookup_np(forest, np.full(len(uv), tree), uv)      # the SD-tree's own density on its square
        np.testing.assert_allclose(guide_state.density(state, tree, directions), pdf / (4 * math.pi), rtol=1e-6)
        total = np.mean(guide_state.density_image(state, tree, 512, 256)) * 4 * math.pi
        assert total == pytest.approx(1, rel=0.02)
    # A point (inside the S-tree's root box) lies in the box of the D-tree that guides it.
    for point in rng.uniform(state["stree_lo"][0], state["stree_hi"][0], (20, 3)):
        low, high = guide_state.cell_bounds(state, guide_state.cell_of_point(state, point))
        assert (low <= point).all() and (point <= high).all()


def test_quadtree_grid_state_finds_the_cells_the_guide_uses(cornell):
    import mitsuba as mi

    guide = train(cornell, make_guide("quadtree-grid-S4"), spp=16)
    state = guide_state.capture(guide)
    assert state["kind"] == "dtrees" and guide_state.cell_count(state) == 4 ** 3
    cell = guide_state.best_cell(state)
    assert np.mean(guide_state.density_image(state, cell, 512, 256)) * 4 * math.pi == pytest.approx(1, rel=0.02)
    points = np.random.default_rng(2).uniform(-1, 1, (50, 3))
    expected = guide._cells.cell(mi.Point3f(points[:, 0], points[:, 1], points[:, 2])).numpy()
    assert [guide_state.cell_of_point(state, p) for p in points] == expected.tolist()


def test_a_guide_that_learns_nothing_has_no_state():
    from guiding.errors import GuidingError

    with pytest.raises(GuidingError, match="learns no directional distribution"):
        guide_state.capture(make_guide("brdf"))
