"""The per-pass sums of `pass_sums`: the scatter mode a table gets from its size and the thread count, and the
sums, which must come out the same whichever mode added them (the learned tables, and the images, may not depend
on the thread count or the table's size)."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from guiding.guides import pass_sums
from guiding.guides.pass_sums import (EXPAND_BYTES, add_target, copied_per_thread, copies, entry_sums, footprint,
                                      planned_footprint)


def _added(entries: int, index: np.ndarray, target: np.ndarray, mode: dr.ReduceMode, monkeypatch) -> np.ndarray:
    monkeypatch.setattr(pass_sums, "copied_per_thread", lambda sums: mode)
    sums = pass_sums.pass_sums(entries)
    add_target(sums, mi.UInt32(index), mi.Float(target), mi.Bool(target != 7))
    total, count = entry_sums(sums, dr.arange(mi.UInt32, entries))
    return np.stack([np.array(total), np.array(count)])


def test_tables_beyond_drjits_threshold_are_expanded_while_their_copies_fit():
    """Dr.Jit's own limit counts entries (10⁶); ours bounds the bytes of the copies: the widest float64 table whose
    copies, one per thread, fit in EXPAND_BYTES (4 Mi values on two threads: the SD-tree's recorded sums, 2²¹ values
    once its recording trees pass 2¹⁷ nodes, are within it) is added into without atomics, and a wider one beyond
    Dr.Jit's limit is left to atomics; a table within Dr.Jit's limit is copied whatever the thread count."""
    threads = copies(dr.zeros(mi.Float64, 2))
    widest = EXPAND_BYTES // (8 * threads)
    if widest > dr.expand_threshold():       # on up to 8 threads
        fitting = dr.zeros(mi.Float64, widest)
        assert copied_per_thread(fitting) == dr.ReduceMode.Expand
        assert footprint(fitting) == 8 * widest * threads
    too_large = dr.zeros(mi.Float64, max(widest, dr.expand_threshold()) + 2)
    assert copied_per_thread(too_large) == dr.ReduceMode.Local
    assert footprint(too_large) == 8 * dr.width(too_large)
    small = dr.zeros(mi.Float64, 1024)
    assert copied_per_thread(small) == dr.ReduceMode.Expand
    assert footprint(small) == 8 * 1024 * threads
    assert planned_footprint(512) == footprint(small)


@pytest.mark.parametrize("entries", [1 << 10, 1 << 20])
def test_sums_are_the_same_whichever_mode_added_them(entries, monkeypatch):
    """One scatter of a million float32 targets, many of them into the same entries, added with copies per thread
    and with atomics: the float64 sums and the counts are equal to the last bit, and equal to NumPy's. (Exact in
    any order while an entry's float64 sum holds every bit of its targets: here 65 536 targets spanning 2^10.)"""
    rng = np.random.default_rng(entries)
    index = rng.integers(0, entries, size=1 << 20).astype(np.uint32)
    index[: 1 << 16] = 3                                       # one entry hit by 65 536 lanes
    target = (rng.uniform(0.5, 4, size=1 << 20) * 2.0 ** rng.integers(0, 8, size=1 << 20)).astype(np.float32)
    target[::97] = 7                                           # inactive lanes: added nowhere
    expanded = _added(entries, index, target, dr.ReduceMode.Expand, monkeypatch)
    atomic = _added(entries, index, target, dr.ReduceMode.Local, monkeypatch)
    assert np.array_equal(expanded, atomic)
    active = target != 7
    expected_total = np.bincount(index[active], weights=target[active].astype(np.float64), minlength=entries)
    expected_count = np.bincount(index[active], minlength=entries)
    assert np.allclose(expanded[0], expected_total, rtol=1e-12, atol=0)
    assert np.array_equal(expanded[1], expected_count)
