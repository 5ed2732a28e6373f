"""Rows of discrete distributions on the device, sampled by Walker's alias method: one packet read per sample.

A table of ``rows × size`` weights becomes ``rows × size`` slots of four floats, read together (:func:`sample`):
slot j of a row holds its threshold ``t_j``, its alias ``a_j`` (the bits of a uint32), and the densities of bins j
and ``a_j``. A sample ``(u, v)`` takes slot ``j = ⌊u·size⌋`` and bin ``k = j if v < t_j else a_j``, and its
density comes with it: one gather per sample, none dependent on another.

Densities are exact for the finished table: bin k's probability is ``(t_k + Σ_{j: a_j = k} (1 − t_j))/size``,
summed in float64 (by the sweep, as it hands the slots out) from the float32 thresholds the sampler compares
against, times the caller's per-bin ``scale`` (a bin's solid angle, say). A bin of zero weight (or below :data:`NEGLIGIBLE`) has threshold 0 and is nobody's
alias: it is never drawn.

Built by Vose's method as a sweep (one lane per row, a loop of at most ``size`` steps): the bins of probability
below the mean are handed, in order, to the current bin above it, whose excess pays for their slots; when its
excess runs out, it becomes a small bin itself, aliased to the next large one.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: Largest float32 below one: what is left of a sample stays in [0, 1).
ONE_MINUS_EPS = 1 - 2 ** -24
#: Floats per slot: threshold, alias bits, density of the slot's bin, density of its alias.
SLOT_FIELDS = 4
#: Bytes per bin of a table.
SLOT_BYTES = 4 * SLOT_FIELDS
#: Bytes per bin of the temporaries of a table's construction (the weights and their float64 copy for the row sums,
#: the small-bin flags, the lists of bins beside their weights, thresholds and aliases, the float64 sums the sweep
#: writes, densities).
BUILD_BYTES = 52
#: Thresholds below this are set to 0: such a bin (probability < 2⁻⁶⁴/size) is never drawn, so that no drawn bin
#: has a density that underflows float32.
NEGLIGIBLE = 2.0 ** -64


def build(weight: mi.Float, size: int, scale: mi.Float | float = 1.0) -> mi.Float:
    """The slots of consecutive rows of ``size`` weights (finite, non-negative, a positive sum per row: the callers'
    policies are at least ε/B and their weights sanitised; a row of zeros, whose every bin is its maximum, comes out
    uniform); a bin's density field is its probability times ``scale`` (per bin, or one value)."""
    rows = dr.width(weight) // size
    flat = dr.arange(mi.UInt32, rows * size)
    row_of, k = flat // size, flat % size
    w = mi.Float(weight)
    dr.eval(w)     # the callers' weights are expressions of gathers: computed once, not in every reduction below
    row_sum = dr.block_reduce(dr.ReduceOp.Add, mi.Float64(w), size)
    large = ((_probability(w, dr.gather(mi.Float64, row_sum, row_of), size) >= 1)
             | (w == dr.gather(mi.Float, block_max(w, size), row_of)))
    small = mi.UInt32(~large)
    dr.eval(small)
    entries, small_count = _lists(small, row_of, k, w, size)
    threshold = dr.select(small == 0, mi.Float(1), 0)
    alias = dr.select(small == 0, k, 0)    # its own variable: the sweep writes in place (a scatter into k copies k)
    received = dr.zeros(mi.Float64, rows * size)
    dr.make_opaque(received)       # zeroed here, once (a literal scattered into in the sweep's loop is zeroed twice)
    dr.eval(threshold, alias, entries)
    _sweep(row_sum, threshold, alias, received, entries, small_count, size)

    first = row_of * size
    density = mi.Float((mi.Float64(threshold) + received) / size) * scale
    # Every slot is written, whole, by one packet scatter: no zeroing pass, one pass over the table.
    slots = dr.empty(mi.Float, SLOT_FIELDS * rows * size)
    dr.scatter(slots, mi.Vector4f(threshold, dr.reinterpret_array(mi.Float, alias), density,
                                  dr.gather(mi.Float, density, first + alias)), flat)
    dr.eval(slots)
    return slots


def block_max(values: mi.Float, size: int) -> mi.Float:
    """The largest of each block of ``size`` non-negative floats, from their bits: such floats order as their bit
    patterns (the sign bit cleared, for −0), and a block maximum over integers took a sixth of the time of one over
    floats (CPU)."""
    bits = dr.reinterpret_array(mi.UInt32, values) & 0x7FFFFFFF
    return dr.reinterpret_array(mi.Float, dr.block_reduce(dr.ReduceOp.Max, bits, size))


def _probability(w: mi.Float, row_sum: mi.Float64, size: int) -> mi.Float64:
    """Weights ``w`` of rows summing to ``row_sum`` as probabilities of mean 1 per row, in float64: one expression
    for the large/small split and for the sweep, so that both see the very same values."""
    return mi.Float64(w) * size / row_sum


def _lists(small: mi.UInt32, row_of: mi.UInt32, k: mi.UInt32, w: mi.Float,
           size: int) -> tuple[mi.Float, mi.UInt32]:
    """Each row's bins (bin ``k`` of row ``row_of`` per slot, 1 in ``small`` where it is small, weight ``w``) in one
    stretch of ``size`` entries: its small bins in order, then its large ones in order, each entry the bin's bits beside
    its weight (a step of the sweep reads both in one packet gather, not the weight through a second, dependent one);
    and the number of small bins per row (where the large ones start)."""
    position = dr.block_prefix_sum(small, size, exclusive=True)
    last = dr.arange(mi.UInt32, dr.width(k) // size) * size + size - 1
    small_count = dr.gather(mi.UInt32, position, last) + dr.gather(mi.UInt32, small, last)
    # A large bin's place: after the row's small bins, behind the large bins before it (k − the small ones before it).
    place = dr.select(small != 0, position, dr.gather(mi.UInt32, small_count, row_of) + k - position)
    entries = dr.empty(mi.Float, 2 * dr.width(k))
    dr.scatter(entries, mi.Vector2f(dr.reinterpret_array(mi.Float, k), w), row_of * size + place)
    return entries, small_count


def _as_sampled(threshold):
    """A threshold as :func:`sample` compares against it: float32, and 0 below :data:`NEGLIGIBLE`."""
    return mi.Float(dr.select(threshold < NEGLIGIBLE, 0, threshold))


@dr.syntax
def _sweep(row_sum, threshold, alias, received_by, entries, small_count, size: int) -> None:
    """Vose's pairing, one lane per row (the rows' weight sums ``row_sum``): writes the small bins' thresholds
    and aliases, and those of the large bins whose excess ran out (the others keep threshold 1), thresholds as
    sampled (:func:`_as_sampled`). Writes to ``received_by`` what each bin receives from the slots that alias it,
    ``Σ (1 − t_j)``, summed as the sweep hands the slots out (a large bin is the alias of the slots handed to it while
    it is the current one), not by an atomic add per slot.

    ``entries``: each row's small bins, then its large ones, each beside its weight (:func:`_lists`). A step either
    hands the next small bin to the current large bin (give) or, once the current one's excess is below 1, turns it
    small, aliased to the next large bin (turn): never both, so a step reads one list entry (its bin and weight, in
    one packet gather) and writes one slot."""
    first = dr.arange(mi.UInt32, dr.width(small_count)) * size
    large_count = size - small_count
    taken, converted = mi.UInt32(0), mi.UInt32(0)        # small bins handed out; large bins turned small
    entry = dr.gather(mi.Vector2f, entries, first + small_count)
    current = dr.reinterpret_array(mi.UInt32, entry.x)
    # The current large bin's probability not yet in a slot.
    excess = _probability(entry.y, row_sum, size)
    received = mi.Float64(0)                             # what the current large bin's aliasing slots add to it
    going = mi.Bool(True)
    while going:
        turn = (excess < 1) & (converted + 1 < large_count)
        give = ~turn & (taken < small_count)
        going = turn | give
        entry = dr.gather(mi.Vector2f, entries, first + dr.select(turn, small_count + converted + 1, taken), going)
        following = dr.reinterpret_array(mi.UInt32, entry.x)
        mass = _probability(entry.y, row_sum, size)
        # turn: the current bin's slot keeps its excess and is aliased to the following large bin; give: the
        # following small bin's slot keeps its probability and is aliased to the current bin.
        slot = first + dr.select(turn, current, following)
        kept = _as_sampled(dr.select(turn, excess, mass))
        dr.scatter(threshold, kept, slot, going)
        dr.scatter(alias, dr.select(turn, following, current), slot, going)
        received = dr.select(turn, 0, received) + dr.select(going, 1 - mi.Float64(kept), 0)
        excess = dr.select(turn, mass - (1 - excess), dr.select(give, excess - (1 - mass), excess))
        current = dr.select(turn, following, current)
        converted += dr.select(turn, 1, 0)
        taken += dr.select(give, 1, 0)
        # The current bin's running sum, written at every step: final when the sweep moves on from the bin (a turn
        # adds nothing to it first) or ends, and nothing of the loop's state is read after it (that would trace the
        # loop into a second kernel).
        dr.scatter(received_by, received, first + current)


def sample(slots: mi.Float, row: mi.UInt32, size: int, u: mi.Point2f,
           active: mi.Bool) -> tuple[mi.UInt32, mi.Float]:
    """A bin of row ``row`` drawn with ``u`` ∈ [0, 1)², and its density field: one packet gather."""
    k, density, _ = pick(slots, row, size, dr.minimum(mi.UInt32(u.x * size), size - 1), u.y, active)
    return k, density


def pick(slots: mi.Float, row: mi.UInt32, size: int, j: mi.UInt32, v: mi.Float,
         active: mi.Bool) -> tuple[mi.UInt32, mi.Float, mi.Float]:
    """The bin of row ``row`` that slot ``j`` (uniform over the row's slots) gives for ``v`` ∈ [0, 1) (its own
    below the slot's threshold, its alias above), its density field, and what is left of ``v``: uniform on [0, 1)
    and independent of the bin (``v``'s place within its side of the threshold), for a draw that goes on inside it."""
    slot = dr.gather(mi.Vector4f, slots, row * size + j, active)
    own = v < slot.x
    rest = dr.select(own, v / slot.x, (v - slot.x) / (1 - slot.x))
    return (dr.select(own, j, dr.reinterpret_array(mi.UInt32, slot.y)), dr.select(own, slot.z, slot.w),
            dr.clip(rest, 0, ONE_MINUS_EPS))


def density(slots: mi.Float, row: mi.UInt32, size: int, k: mi.UInt32, active: mi.Bool) -> mi.Float:
    """The density field of bin ``k`` of row ``row``."""
    return dr.gather(mi.Float, slots, SLOT_FIELDS * (row * size + k) + 2, active)


def drawn_probability(slots, size: int):
    """On the host, for checks: each bin's probability under :func:`sample` (rows × ``size``, float64), from the
    thresholds and aliases alone: its own slot below the threshold, and the slots that alias it above theirs."""
    import numpy as np

    table = np.asarray(slots, dtype=np.float32).reshape(-1, size, SLOT_FIELDS)
    threshold = table[..., 0].astype(np.float64)
    alias = table[..., 1].view(np.uint32).astype(np.int64)
    rows = np.repeat(np.arange(table.shape[0]), size)
    others = (alias != np.arange(size)).ravel()
    probability = threshold.copy()
    np.add.at(probability, (rows[others], alias.ravel()[others]), 1 - threshold.ravel()[others])
    return probability / size
