"""Rows of discrete distributions on the device: inclusive CDFs, and the cut points that sample them in a few
gathers (Chen & Asau's guide table).

A table of ``rows × size`` weights becomes ``rows × size`` inclusive CDFs (:func:`normalised_cdf`), each ending at
exactly 1, and ``rows × G`` cut points (:func:`cut_points`), G the power of two at least ``size``: ``cut[g]`` is
the first bin whose CDF exceeds ``g/G`` (``cut[G]``: the first that reaches 1). A sample ``u`` with
``g = ⌊u·G⌋`` lies between bins ``cut[g]`` and ``cut[g + 1]``, usually the same bin or neighbours, so
:func:`sample_rows` reads one packed entry (the interval's first bin and its width, :func:`pack_interval`) and a
window of ``WINDOW`` CDF entries, and runs the full binary search (log₂ size gathers) only for the lanes whose
interval is wider. Both give the same bin: the first with CDF > u. A power of two G keeps ``u·G`` and ``g/G``
exact in float32, so the cut points agree with every sample's comparisons.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: CDF entries read after the cut points: wider intervals (rare: most hold one or two bins) take the full search.
WINDOW = 2
#: A packed interval: its first bin in the low bits (rows of up to 2·256² = 2^17 bins), its width above them,
#: clamped to WINDOW + 1 (wider ones are searched in full whatever their width).
LOW_BITS = 17


def cut_count(size: int) -> int:
    """G: the power of two at least ``size``."""
    return 1 << max(size - 1, 0).bit_length()


def normalised_cdf(weight: mi.Float, size: int) -> mi.Float:
    """Inclusive CDFs of consecutive rows of ``size`` weights, each divided by its own last entry.

    Every row then ends at exactly 1.0 (x/x is exact), as do the trailing zero-weight bins, so a search for any
    u < 1 stops at a bin with positive weight. Dividing by a separately reduced total instead (summed in another
    order) left rows ending at 1 − 1e-7: u above that picked the last bin even when its weight was 0, a direction
    with density 0.
    """
    running = dr.block_prefix_sum(weight, size, exclusive=False)
    row_end = (dr.arange(mi.UInt32, dr.width(weight)) // size + 1) * size - 1
    return running / dr.gather(mi.Float, running, row_end)


def cut_points(cdf: mi.Float, size: int) -> mi.UInt32:
    """The ``G`` packed intervals of each row of ``cdf`` (rows of ``size`` inclusive CDFs ending at 1): entry g
    packs ``cut[g]`` and ``cut[g + 1]`` (:func:`pack_interval`), one gather for :func:`sample_rows`.

    ``cut[g] = #{k : cdf[k] ≤ g/G} = #{k : ⌈cdf[k]·G⌉ ≤ g}`` for g < G, a prefix sum of the histogram of
    ``⌈cdf[k]·G⌉`` (exact integers); ``cut[G] = #{k : cdf[k] < 1}``, the row's last bin of positive weight."""
    if size > 1 << LOW_BITS:
        raise ValueError(f"rows of at most {1 << LOW_BITS} bins, got {size}")
    G = cut_count(size)
    rows = dr.width(cdf) // size
    flat = dr.arange(mi.UInt32, rows * size)
    row = flat // size
    level = mi.UInt32(dr.ceil(cdf * G))
    histogram = dr.zeros(mi.UInt32, rows * (G + 1))
    dr.scatter_reduce(dr.ReduceOp.Add, histogram, mi.UInt32(1), row * (G + 1) + level)
    cut = dr.block_prefix_sum(histogram, G + 1, exclusive=False)
    below_one = dr.block_reduce(dr.ReduceOp.Add, dr.select(cdf < 1, mi.UInt32(1), 0), size)
    dr.scatter(cut, below_one, dr.arange(mi.UInt32, rows) * (G + 1) + G)
    g = dr.arange(mi.UInt32, rows * G)
    first = g + g // G       # cut[g] of row g // G in the rows of G + 1
    return pack_interval(dr.gather(mi.UInt32, cut, first), dr.gather(mi.UInt32, cut, first + 1), size)


def pack_interval(low: mi.UInt32, high: mi.UInt32, size: int) -> mi.UInt32:
    """One uint32 for the bins ``low … min(high, size − 1)`` a sample can land in: ``low`` and the width."""
    width = dr.minimum(dr.minimum(high, size - 1) - low, WINDOW + 1)
    return low | (width << LOW_BITS)


def full_search(cdf: mi.Float, row: mi.UInt32, size: int, u: mi.Float, active: mi.Bool) -> mi.UInt32:
    """The first k in [0, size) with ``cdf[row + k] > u`` (binary search over one row of inclusive CDFs)."""
    return mi.UInt32(dr.binary_search(0, size - 1, lambda i: dr.gather(mi.Float, cdf, row + i, active) <= u))


@dr.syntax
def sample_rows(cdf: mi.Float, cut: mi.UInt32, row_id: mi.UInt32, size: int, u: mi.Float,
                active: mi.Bool) -> mi.UInt32:
    """The first k in [0, size) with ``cdf[row_id·size + k] > u``, for u ∈ [0, 1): what :func:`full_search` gives,
    from the row's cut points and a window of the CDF."""
    G = cut_count(size)
    row = row_id * size
    interval = dr.gather(mi.UInt32, cut, row_id * G + dr.minimum(mi.UInt32(u * G), G - 1), active)
    low, width = interval & ((1 << LOW_BITS) - 1), interval >> LOW_BITS
    k = mi.UInt32(low)
    for i in range(WINDOW):
        inside = active & (width > i)
        k += dr.select(inside & (dr.gather(mi.Float, cdf, row + low + i, inside) <= u), 1, 0)
    wide = active & (width > WINDOW)
    if wide:
        k = full_search(cdf, row, size, u, wide)
    return k
