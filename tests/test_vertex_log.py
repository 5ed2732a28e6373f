"""The Monte Carlo vertex log gives back, in the backward walk, every vertex a path logged, in its own slot.

Inside a symbolic loop, with paths that start logging at different iterations and end at different lengths, so
that the lanes of a packet hold different counts (the path loop's case: a path logs from its first guided vertex on),
and more iterations than the log holds. It fails where a vertex is stored by its lane's count but walked by the
iteration, where the walk misses a path's first vertex, and (by a crash) where a write past ``max_depth`` is not
dropped.
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from guiding.guides.vertex_log import NO_RECORD, VertexLog, walk_backward

MAX_DEPTH = 8
LANES = 1024            # many packets, on any vector width
ITERATIONS = 12         # more than MAX_DEPTH: from the MAX_DEPTH-th iteration on, nothing is logged
STRIDE = 64             # a target is lane·STRIDE + its slot

# The paths' pattern: _skipped and _length take Dr.Jit arrays (the log) and NumPy arrays (what it must give back).


def _skipped(lane, k):
    """Iterations at which a lane has no target: a pattern that differs between neighbouring lanes."""
    return ((lane * 7 + k * 3) % 5 == 0) | (k < lane % 4)


def _length(lane):
    """Iterations a lane's path runs (paths of different lengths)."""
    return 4 + lane % 9


def _weight(lane: mi.UInt32) -> mi.Float:
    """The weight a lane logs at every vertex: another lane's vertex shows in it."""
    return mi.Float(lane % 3 + 1) * 0.25


@dr.syntax
def _log_and_walk(log: VertexLog):
    lane = dr.arange(mi.UInt32, LANES)
    cursor = log.new_paths(LANES)
    k = mi.UInt32(0)
    active = mi.Bool(True)
    while dr.hint(active, max_iterations=ITERATIONS):
        target = dr.select(_skipped(lane, k), NO_RECORD, lane * STRIDE + cursor.n)
        cursor = log.append(cursor, mi.Color3f(0), mi.Color3f(_weight(lane)), mi.Bool(True), target, active)
        k += 1
        active &= k < _length(lane)

    visited = dr.zeros(mi.UInt32, LANES)
    wrong = dr.zeros(mi.UInt32, LANES)
    slots = dr.zeros(mi.UInt32, LANES * MAX_DEPTH)      # how often each (lane, slot) target came back

    def visit(entry, L):
        logged = entry.target != NO_RECORD
        own = entry.target // STRIDE == lane
        dr.scatter_reduce(dr.ReduceOp.Add, visited, 1, lane)
        dr.scatter_reduce(dr.ReduceOp.Add, wrong, 1, lane,
                          (logged & ~own) | dr.any(entry.weight != _weight(lane)))
        dr.scatter_reduce(dr.ReduceOp.Add, slots, 1, lane * MAX_DEPTH + entry.target % STRIDE, logged & own)

    walk_backward(cursor, visit)
    return cursor.n, visited, wrong, slots


def _expected_log() -> tuple[np.ndarray, np.ndarray]:
    """Vertices each lane logs (from its first iteration with a target, in the first MAX_DEPTH iterations), and
    which of its slots hold a target."""
    lane = np.arange(LANES)
    n = np.zeros(LANES, dtype=np.int64)
    slots = np.zeros((LANES, MAX_DEPTH), dtype=np.int64)
    for k in range(ITERATIONS):
        skipped = _skipped(lane, k)
        written = (k < _length(lane)) & (k < MAX_DEPTH) & ((n > 0) | ~skipped)
        slots[lane[written], n[written]] = ~skipped[written]
        n += written
    return n, slots


def _check(log_and_walk) -> None:
    n, visited, wrong, slots = log_and_walk
    counts, expected_slots = _expected_log()
    np.testing.assert_array_equal(n.numpy(), counts)
    np.testing.assert_array_equal(visited.numpy(), counts)
    assert int(dr.sum(wrong)[0]) == 0, f"{int(dr.sum(wrong)[0])} vertices came back with another lane's data"
    np.testing.assert_array_equal(slots.numpy().reshape(LANES, MAX_DEPTH), expected_slots)


@pytest.mark.parametrize("threads", [1, 2, 3, 4])
def test_walk_reads_each_logged_vertex_from_its_own_slot(threads):
    """At every thread count: the render kernel is split into a block per thread, and a slot read before it is
    written shows most at a block's first packets, where the stack holds another function's data."""
    counts, _ = _expected_log()
    assert len(np.unique(counts)) > 3, "the lanes must log different numbers of vertices"
    before = dr.thread_count()
    dr.set_thread_count(threads)
    try:
        _check(_log_and_walk(VertexLog(MAX_DEPTH)))
    finally:
        dr.set_thread_count(before)
