"""The Monte Carlo vertex log gives back, in the backward walk, every vertex a path logged, in its own slot.

Inside a symbolic loop, with paths that start logging at different iterations, so that the lanes of a packet hold
different counts (the path loop's case: a path logs from its first guided vertex on). That is where a count of
width 1 goes wrong on Dr.Jit's CPU backend (see ``VertexLog.new_paths``): each lane's vertex lands at its packet's
largest count, and the walk reads slots never written.
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from guiding.guides.vertex_log import NO_RECORD, VertexLog, walk_backward

MAX_DEPTH = 8
LANES = 1024            # many packets, on any vector width
ITERATIONS = 12         # more than MAX_DEPTH: full logs stop logging


def _skipped(lane: mi.UInt32, k: mi.UInt32) -> mi.Bool:
    """Iterations at which a lane has no target: a pattern that differs between neighbouring lanes."""
    return ((lane * 7 + k * 3) % 5 == 0) | (k < lane % 4)


def _target(lane, n):
    return lane * 64 + n


@dr.syntax
def _log_and_walk(log: VertexLog):
    lane = dr.arange(mi.UInt32, LANES)
    cursor = log.new_paths(LANES)
    k = mi.UInt32(0)
    active = mi.Bool(True)
    while dr.hint(active, max_iterations=ITERATIONS):
        target = dr.select(_skipped(lane, k), NO_RECORD, _target(lane, cursor.n))
        weight = mi.Color3f(mi.Float(lane % 3 + 1) * 0.25)
        cursor = log.append(cursor, mi.Color3f(0), weight, mi.Bool(True), target, active)
        k += 1
        active &= k < 4 + lane % 9      # paths of different lengths

    visited = dr.zeros(mi.UInt32, LANES)
    wrong = dr.zeros(mi.UInt32, LANES)
    slots = dr.zeros(mi.UInt32, LANES * MAX_DEPTH)      # how often each (lane, slot) target came back

    def visit(entry, L):
        logged = entry.target != NO_RECORD
        own = entry.target // 64 == lane
        dr.scatter_reduce(dr.ReduceOp.Add, visited, 1, lane)
        dr.scatter_reduce(dr.ReduceOp.Add, wrong, 1, lane, (logged & ~own) |
                          dr.any(entry.weight != mi.Float(lane % 3 + 1) * 0.25))
        dr.scatter_reduce(dr.ReduceOp.Add, slots, 1, lane * MAX_DEPTH + entry.target % 64, logged & own)

    walk_backward(cursor, visit)
    return cursor.n, visited, wrong, slots


def _expected_log() -> tuple[np.ndarray, np.ndarray]:
    """Vertices each lane logs (from its first iteration with a target, at most MAX_DEPTH), and which of its slots
    hold a target: the pattern in NumPy."""
    counts = np.zeros(LANES, dtype=np.int64)
    slots = np.zeros((LANES, MAX_DEPTH), dtype=np.int64)
    for lane in range(LANES):
        n = 0
        for k in range(4 + lane % 9):
            skipped = (lane * 7 + k * 3) % 5 == 0 or k < lane % 4
            if n < MAX_DEPTH and (n > 0 or not skipped):
                slots[lane, n] = not skipped
                n += 1
        counts[lane] = n
    return counts, slots


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
