"""A pass's sums of learning targets: float64 (sum, count) neighbours per entry, added in the path loop and folded
into the totals between passes. Shared by the radiance record (:mod:`~guiding.guides.grid.record`) and its refined
sub-bins (:mod:`~guiding.guides.grid.refinement`).

The sum and count of an entry are neighbours in one array (one cache line for both), added without atomics where
the CPU backend can give each thread a copy (``ReduceMode.Expand``, while the copies fit in :data:`EXPAND_BYTES`;
float64 atomic adds are compare-and-swap loops on the CPU). Float64 sums of float32 targets come out the
same in any order while an entry's sum holds every bit of its targets (their count times their range below 2^29),
so the learned tables, and the images, do not depend on the thread count or the mode (float32 sums did).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


def pass_sums(entries: int) -> mi.Float64:
    """Empty sums and counts of ``entries`` entries (in memory, not a literal: a frozen pass takes them as the
    same kind of input every time)."""
    sums = dr.zeros(mi.Float64, 2 * entries)
    dr.make_opaque(sums)
    return sums


def add_target(sums: mi.Float64, index: mi.UInt32, target: mi.Float, active: mi.Bool) -> None:
    """Add ``target`` to entry ``index`` of ``sums``, and one to its count: one packet scatter of the pair (two
    scatters cost twice the cache misses, and on the CPU two loops over the lanes)."""
    dr.scatter_reduce(dr.ReduceOp.Add, sums, _pair_type(sums)(mi.Float64(target), 1), index, active,
                      mode=copied_per_thread(sums))


#: Most bytes the per-thread copies of one table of sums may take together. Dr.Jit's own limit
#: (``dr.expand_threshold()``, 10⁶ entries whatever their size and the thread count) sent the SD-tree's recorded sums
#: to atomics once its recording trees passed 2^17 nodes, which on a long render they do.
EXPAND_BYTES = 64 << 20


def copied_per_thread(sums) -> dr.ReduceMode:
    """How a kernel adds into ``sums``: ``Expand`` (a copy per CPU thread, added into without atomics, and a
    scatter of adjacent values is one packet write) while the copies take at most :data:`EXPAND_BYTES` together, or
    the table has at most ``dr.expand_threshold()`` entries; beyond, ``Local`` (on the CPU a loop over the packet's
    lanes with an atomic per lane and per value). Expand compiles the kernel for the size of the copies: a table
    that grows recompiles it at each new size. Other backends treat Expand as Auto."""
    expands = _expands(dr.width(sums), dr.itemsize_v(sums), copies(sums))
    return dr.ReduceMode.Expand if expands else dr.ReduceMode.Local


def _expands(width: int, itemsize: int, copies: int) -> bool:
    return itemsize * width * copies <= EXPAND_BYTES or width <= dr.expand_threshold()


def copies(sums) -> int:
    """The copies of ``sums`` that Expand keeps: one per CPU thread (one on other backends)."""
    return dr.thread_count() if dr.backend_v(sums) == dr.JitBackend.LLVM else 1


def footprint(sums) -> int:
    """Bytes that ``sums`` takes while kernels add into it, its per-thread copies included."""
    expanded = copied_per_thread(sums) == dr.ReduceMode.Expand
    return dr.itemsize_v(sums) * dr.width(sums) * (copies(sums) if expanded else 1)


def planned_footprint(entries: int) -> int:
    """:func:`footprint` of the sums of ``entries`` entries, before they exist (on the CPU backend with its present
    thread count; other backends keep no copies, and take less)."""
    width, threads = 2 * entries, dr.thread_count()
    return 8 * width * (threads if _expands(width, 8, threads) else 1)


def entry_sums(sums: mi.Float64, index: mi.UInt32) -> tuple[mi.Float64, mi.Float64]:
    """The sum and the count of entries ``index``."""
    pair = dr.gather(_pair_type(sums), sums, index)
    return pair.x, pair.y


def _pair_type(sums: mi.Float64) -> type:
    """The (sum, count) pair of float64 on the backend of ``sums`` (Mitsuba has no two-component float64 type)."""
    return dr.cuda.ad.Array2f64 if dr.backend_v(sums) == dr.JitBackend.CUDA else dr.llvm.ad.Array2f64
