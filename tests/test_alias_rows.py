"""The alias tables of `alias_rows`: every bin's density field is the probability with which `sample` draws it,
that probability is the bin's share of its row's weight, and bins of zero weight are never drawn; on rows with
zero-weight bins, one heavy bin, heavy tails, uniform rows and sizes that are not powers of two."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from guiding.guides.alias_rows import SLOT_FIELDS, build, density, drawn_probability, pick, sample


def _rows(size: int, rows: int, rng) -> np.ndarray:
    weight = rng.exponential(size=(rows, size)) ** 8          # heavy-tailed
    weight[rng.random((rows, size)) < 0.3] = 0
    weight[:, 0] += 1e-30
    weight[1] = 0
    weight[1, -1] = 1                                          # all weight in the last bin
    weight[2] = 0
    weight[2, 0] = 1                                           # all weight in the first bin
    weight[3] = 0.7                                            # uniform
    return weight.astype(np.float32)


def _fields(slots: mi.Float, size: int):
    table = np.array(slots).reshape(-1, size, SLOT_FIELDS)
    return table[..., 0], table[..., 1].view(np.uint32), table[..., 2], table[..., 3]


@pytest.mark.parametrize("size", [2, 3, 7, 288, 512])   # a record has B = 2·D² ≥ 2 bins
def test_alias_table_draws_each_bin_with_its_density(size):
    rng = np.random.default_rng(size)
    weight = _rows(size, 40, rng)
    scale = rng.uniform(0.5, 2.0, size=weight.shape).astype(np.float32)
    slots = build(mi.Float(weight.ravel()), size, mi.Float(scale.ravel()))
    threshold, alias, own, aliased = _fields(slots, size)
    assert ((threshold >= 0) & (threshold <= 1)).all() and (alias < size).all()
    drawn = drawn_probability(slots, size)
    # The density field is the drawn probability times the scale, and the alias's field is its bin's.
    assert np.allclose(own, drawn * scale, rtol=1e-6, atol=1e-37)
    assert (own[drawn > 0] > 0).all()
    assert np.array_equal(aliased, np.take_along_axis(own, alias.astype(np.int64), axis=1))
    # The drawn probability is the bin's share of the row (up to float32 thresholds).
    share = weight.astype(np.float64) / weight.astype(np.float64).sum(axis=1, keepdims=True)
    assert np.allclose(drawn, share, rtol=1e-5, atol=1e-7)
    # A bin of zero weight is never drawn: threshold 0 in its own slot, and nobody's alias where it counts.
    zero = weight == 0
    assert (threshold[zero] == 0).all() and (drawn[zero] == 0).all()


def test_samples_follow_the_density():
    """Drawn bins match the densities (each bin within five standard deviations of its expected count), and
    `sample` returns the density field `density` reads for the bin it drew."""
    size, rows, n = 288, 4, 2_000_000
    rng = np.random.default_rng(7)
    weight = _rows(size, rows, rng)
    slots = build(mi.Float(weight.ravel()), size)
    row = mi.UInt32(rng.integers(0, rows, n))
    u = mi.Point2f(mi.Float(rng.random(n, dtype=np.float32)), mi.Float(rng.random(n, dtype=np.float32)))
    k, drawn_density = sample(slots, row, size, u, mi.Bool(True))
    assert np.array_equal(np.array(drawn_density), np.array(density(slots, row, size, k, mi.Bool(True))))
    counts = np.zeros((rows, size))
    np.add.at(counts, (np.array(row), np.array(k)), 1)
    expected = _fields(slots, size)[2] * np.bincount(np.array(row), minlength=rows)[:, None]
    assert (counts[expected == 0] == 0).all()
    assert (np.abs(counts - expected) <= 5 * np.sqrt(expected) + 1).all()


def test_what_is_left_of_a_pick_is_uniform_in_each_bin_drawn():
    """`pick` draws the bins `sample` draws from the same slot and threshold sample, and what it leaves of the
    threshold sample is uniform on [0, 1) whichever bin was drawn (each of 16 intervals within five standard
    deviations of its expected count), so a draw may go on inside the bin with it."""
    size, n = 5, 1_000_000
    rng = np.random.default_rng(11)
    weight = np.array([[0.1, 3.0, 0.0, 1.0, 0.45]], dtype=np.float32)
    slots = build(mi.Float(weight.ravel()), size)
    u = mi.Point2f(mi.Float(rng.random(n, dtype=np.float32)), mi.Float(rng.random(n, dtype=np.float32)))
    row = mi.UInt32(np.zeros(n, dtype=np.uint32))
    j = dr.minimum(mi.UInt32(u.x * size), size - 1)
    k, drawn_density, rest = pick(slots, row, size, j, u.y, mi.Bool(True))
    plain_k, plain_density = sample(slots, row, size, u, mi.Bool(True))
    assert np.array_equal(np.array(k), np.array(plain_k))
    assert np.array_equal(np.array(drawn_density), np.array(plain_density))
    rest = np.array(rest)
    assert ((rest >= 0) & (rest < 1)).all()
    for bin_drawn in np.unique(np.array(k)):
        counts = np.bincount((rest[np.array(k) == bin_drawn] * 16).astype(int), minlength=16)
        expected = counts.sum() / 16
        assert (np.abs(counts - expected) <= 5 * np.sqrt(expected)).all(), (bin_drawn, counts)
    assert set(np.unique(np.array(k))) == {0, 1, 3, 4}
