"""The cut points of `cdf_rows` pick the bin the full binary search picks, for every sample, on rows with zero-weight
bins, one heavy bin, heavy tails and sizes that are not powers of two."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from guiding.guides.cdf_rows import LOW_BITS, WINDOW, cut_count, cut_points, full_search, normalised_cdf, sample_rows


def _rows(size: int, rows: int, rng) -> np.ndarray:
    weight = rng.exponential(size=(rows, size)) ** 8          # heavy-tailed: intervals wider than the window
    weight[rng.random((rows, size)) < 0.3] = 0
    weight[:, 0] += 1e-30
    weight[1] = 0
    weight[1, -1] = 1                                          # all weight in the last bin
    weight[2] = 0
    weight[2, 0] = 1                                           # all weight in the first bin
    return weight.astype(np.float32)


@pytest.mark.parametrize("size", [2, 3, 7, 288, 512])   # a record has B = 2·D² ≥ 2 bins
def test_cut_points_agree_with_the_binary_search(size):
    rng = np.random.default_rng(size)
    rows, n = 40, 100_000
    cdf = normalised_cdf(mi.Float(_rows(size, rows, rng).ravel()), size)
    cut = cut_points(cdf, size)
    G = cut_count(size)
    assert dr.width(cut) == rows * G
    below_one = np.nextafter(np.float32(1), np.float32(0))
    u = np.concatenate([rng.random(n - 2000), np.zeros(1000), np.full(1000, below_one)]).astype(np.float32)
    row = mi.UInt32(rng.integers(0, rows, n))
    picked = sample_rows(cdf, cut, row, size, mi.Float(u), mi.Bool(True))
    expected = full_search(cdf, row * size, size, mi.Float(u), mi.Bool(True))
    assert np.array_equal(np.array(picked), np.array(expected))
    if size > WINDOW + 1:   # a row where an interval can pass the window: the fallback search ran, and the window
        interval = np.array(cut)[np.array(row) * G + np.minimum(u * G, G - 1).astype(int)]
        low = interval & ((1 << LOW_BITS) - 1)
        assert (np.array(expected) - low > WINDOW).any() and (np.array(expected) - low <= WINDOW).any()
