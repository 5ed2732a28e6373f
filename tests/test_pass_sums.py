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
    """Dr.Jit's own limit counts entries (10⁶); ours bounds the bytes of the copies: a table of 2²¹ float64 values
    (the SD-tree's recorded sums once its recording trees pass 2¹⁷ nodes) is added into without atomics while its
    copies, one per thread, fit in EXPAND_BYTES, and a table whose copies would not is left to atomics."""
    fitting = dr.zeros(mi.Float64, 1 << 21)
    assert dr.width(fitting) > dr.expand_threshold()
    assert 8 * dr.width(fitting) * copies(fitting) <= EXPAND_BYTES      # 16 MiB per copy, a few threads
    assert copied_per_thread(fitting) == dr.ReduceMode.Expand
    assert footprint(fitting) == 8 * dr.width(fitting) * copies(fitting)
    too_large = dr.zeros(mi.Float64, EXPAND_BYTES // 8 + 2)
    assert copied_per_thread(too_large) == dr.ReduceMode.Local
    assert footprint(too_large) == 8 * dr.width(too_large)
    small = dr.zeros(mi.Float64, 1024)
    assert copied_per_thread(small) == dr.ReduceMode.Expand
    assert planned_footprint(512) == footprint(dr.zeros(mi.Float64, 1024))


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
