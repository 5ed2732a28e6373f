"""Which refined bins are sampled and which still learn (ours-plus's sub-bins, `guiding.guides.grid.refinement`)."""

import drjit as dr
import mitsuba as mi
import numpy as np

from guiding.guides.directions import SphereBins
from guiding.guides.grid.refinement import REFINE_VISITS, SAMPLING_GAIN, SETTLED_VISITS, BinRefinement

R = 4
ENTRIES = 2 * 8       # two cells of 2·2² bins
CONCENTRATED, EVEN, RARE = 0, 1, 2


def _refinement() -> BinRefinement:
    """Entries 0 (its light in one sub-bin), 1 (light filling the bin evenly) and 2 (bright but rarely visited)
    hold half, a quarter and a quarter of their cell's policy."""
    refinement = BinRefinement(SphereBins(2), ENTRIES, R, share=0.2, capacity=4)
    policy = np.full(ENTRIES, 0.01)
    policy[[CONCENTRATED, EVEN, RARE]] = 0.5, 0.25, 0.25
    visits = np.full(ENTRIES, 1e6)
    visits[RARE] = REFINE_VISITS * R * R - 1
    stats = refinement.update(mi.Float(policy), mi.Float(np.ones(ENTRIES)), mi.Float64(visits))
    assert stats["refined_bins"] == 2, "the rarely visited bright entry is not refined yet"
    return refinement


def _learn(refinement: BinRefinement, sums: np.ndarray, visits_per_sub: float) -> dict:
    """Give the two refined entries' sub-bins these mean targets, then update."""
    refinement.acc_sum = mi.Float64(sums.ravel() * visits_per_sub)
    refinement.acc_count = mi.Float64(np.full(sums.size, visits_per_sub))
    policy = np.full(ENTRIES, 0.01)
    policy[[CONCENTRATED, EVEN]] = 0.5, 0.25
    return refinement.update(mi.Float(policy), mi.Float(np.ones(ENTRIES)), mi.Float64(np.full(ENTRIES, 1e6)))


def _bits(refinement: BinRefinement, mask: mi.UInt32) -> list[bool]:
    return list(np.array(refinement._bit(mask, dr.arange(mi.UInt32, 3), mi.Bool(True))))


def test_concentrated_bins_are_sampled_and_even_ones_settle():
    refinement = _refinement()
    sums = np.ones((4, R * R))
    sums[0, 5] = 1000.0                            # entry 0: one bright sub-bin
    sums[1] = 1 + 0.01 * np.arange(R * R)          # entry 1: within 15 % everywhere
    stats = _learn(refinement, sums, SETTLED_VISITS - 1)
    assert _bits(refinement, refinement.sampling_mask) == [True, False, False]
    assert _bits(refinement, refinement.learning_mask) == [True, True, False], "too few visits to settle yet"
    probability = np.array(refinement.probability)[:2 * R * R].reshape(2, R * R)
    gain = R * R * (probability ** 2).sum(1)
    assert gain[0] >= SAMPLING_GAIN > gain[1]
    stats = _learn(refinement, sums, SETTLED_VISITS)
    assert _bits(refinement, refinement.learning_mask) == [True, False, False], "the even entry settles"
    assert stats["sampled_refined_bins"] == 1 and stats["settled_refined_bins"] == 1
    # A settled entry records nothing more; a learning one does.
    refinement.accumulate(mi.UInt32(CONCENTRATED, EVEN), mi.UInt32(3, 3), mi.Float(2.0, 2.0), mi.Bool(True))
    added = np.array(refinement.pass_targets).reshape(-1, 2)
    assert added[3].tolist() == [2.0, 1.0] and added[R * R + 3].tolist() == [0.0, 0.0]
    # and stays settled though its light changes
    sums[1, 0] = 1000.0
    _learn(refinement, sums, SETTLED_VISITS)
    assert _bits(refinement, refinement.learning_mask) == [True, False, False]
