"""Finer directions where a cell's light is concentrated: sub-bins of the radiance record's brightest bins.

A bin of the record (2·D² equal-area bins, each ~9° wide at D = 16) cannot concentrate on a source a fraction of a
degree wide: a sun of 1e-3 sr covers 4 % of one. Once a (cell, bin) entry holds at least ``share`` of its cell's
policy, the bin's square is cut into ``R × R`` equal-area sub-bins (the bins' map is equal-area, so each sub-bin is a
direction cone of solid angle A/R²), whose distribution within the bin is learned from the same targets as Q:
``π_j = (1 − ε)·(Q_j + δ)/Σ(Q_j + δ) + ε/R²``, with ``Q_j`` the mean target of sub-bin j shrunk towards the bin's Q
(``(Σ targets + n₀·Q)/(visits + n₀)``, n₀ = :data:`PRIOR_VISITS`) and the exploration share ε = :data:`SUB_EXPLORATION`, so that no direction of the bin loses its density.

An entry is refined once it holds ``share`` of its cell's policy and has been visited :data:`REFINE_VISITS` times per
sub-bin (fewer visits teach its sub-bins nothing, and a noisy Q reaches the share by chance). Its sub-bins are
*sampled* only while they pay: while ``1 + χ² = R²·Σ π_j²`` (the factor by which drawing ∝ π rather than uniformly
lowers the second moment of an integrand ∝ π in the bin) is at least :data:`SAMPLING_GAIN`. An entry that is still
below it after :data:`SETTLED_VISITS` visits per sub-bin stops learning: light that fills its bin evenly (a window,
a large lamp) gains nothing from sub-bins and would cost a lookup at every visit. Sampled and learning entries each
have a bit mask, read at every vertex; everything else (slot, sub-bin tables) only in a branch that packets without
a refined lane skip.

The coarse record is unchanged (Q, the policy, the memo tables): a sampler that drew a sampled refined bin draws its
sub-bin from π and a uniform direction in it, with density ``π_j·R²/A`` within the bin. Refinement only grows, a slot per
entry, up to ``capacity`` entries; a record index with refinement is ``entry·R² + j`` (j the sub-bin of the
direction), so that the learning rules hand it on like any entry.

Life cycle: :meth:`BinRefinement.accumulate` in the path loop (beside the record's own sums), :meth:`update` after
the record's policy is rebuilt; :meth:`sampled` and :meth:`sample` / :meth:`density` in the samplers.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from guiding.guides import alias_rows
from guiding.guides.pass_sums import add_target, entry_sums, footprint, pass_sums, planned_footprint

#: Slot of an entry that is not refined.
UNREFINED = 0xFFFFFFFF
#: Exploration share of the sub-bin distributions: every sub-bin keeps at least SUB_EXPLORATION/R² of its bin.
SUB_EXPLORATION = 0.1
#: Added to the sub-bins' Q before normalising (as the record's Q_OFFSET), relative to the bin's Q.
SUB_OFFSET = 1e-6
#: Visits of the bin's own Q that each sub-bin's mean starts from: a sub-bin seen a few times stays near its bin's Q,
#: so that noise in few targets does not become noise in the sampling density.
PRIOR_VISITS = 8.0
#: Visits per sub-bin an entry must have had (in the record) before it is refined.
REFINE_VISITS = 4
#: Least ``1 + χ²`` of a refined entry's π against the uniform distribution for its sub-bins to be sampled.
SAMPLING_GAIN = 1.2
#: Visits per sub-bin (since refinement) after which an entry whose π stays below SAMPLING_GAIN stops learning.
SETTLED_VISITS = 16


class BinRefinement:
    """Sub-bins of the record entries that hold a large share of their cell's policy.

    Parameters:
      bins: the record's :class:`~guiding.guides.directions.SphereBins`.
      entries: the record's (cell, bin) entries, ``S³·2·D²``.
      resolution: R, sub-bins per side of a refined bin (R² per bin).
      share: least policy share of an entry that is refined.
      capacity: most entries refined (their tables are allocated up front).
    """

    def __init__(self, bins, entries: int, resolution: int, share: float, capacity: int):
        if resolution < 2:
            raise ValueError(f"sub-bin resolution must be >= 2, got {resolution}")
        if capacity < 1:
            raise ValueError(f"refinement capacity must be >= 1, got {capacity}")
        if entries * resolution * resolution >= UNREFINED:
            raise ValueError(f"{entries} entries × {resolution}² sub-bins do not fit a 32-bit record index")
        self.bins, self.R, self.share, self.capacity = bins, resolution, share, capacity
        self.sub = resolution * resolution
        self.used = 0
        size = capacity * self.sub
        self.slot = dr.full(mi.UInt32, UNREFINED, entries)
        # One bit per entry (a cell's 2·D² bins in one cache line at D = 16), so that the test at every vertex reads
        # a small table: the entries whose sub-bins are sampled, and those whose sub-bins still learn.
        self.words = (entries + 31) // 32
        self.sampling_mask = dr.zeros(mi.UInt32, self.words)
        self.learning_mask = dr.zeros(mi.UInt32, self.words)
        self.sampled_count = self.settled_count = 0
        self.entry_of = dr.zeros(mi.UInt32, capacity)
        self.acc_sum = dr.zeros(mi.Float64, size)
        self.acc_count = dr.zeros(mi.Float64, size)
        self.pass_targets = pass_sums(size)
        self.probability = dr.full(mi.Float, 1 / self.sub, size)
        self.alias = alias_rows.build(self.probability, self.sub, self._density_scale())
        # In memory, not literals: a frozen pass takes them as the same kind of input before and after the first
        # refinement (guiding.render.frozen_pass).
        dr.make_opaque(self.slot, self.sampling_mask, self.learning_mask, self.entry_of, self.acc_sum,
                       self.acc_count, self.probability)

    @staticmethod
    def planned_bytes(entries: int, resolution: int, capacity: int) -> int:
        """Bytes of the tables of a refinement built with these arguments (all allocated up front)."""
        sub = resolution * resolution
        return (4 * entries + 2 * 4 * ((entries + 31) // 32) + 4 * capacity
                + capacity * sub * (8 + 8 + 4 + alias_rows.SLOT_BYTES) + planned_footprint(capacity * sub))

    def memory_bytes(self) -> int:
        arrays = [self.slot, self.sampling_mask, self.learning_mask, self.entry_of, self.acc_sum, self.acc_count,
                  self.probability, self.alias]
        return footprint(self.pass_targets) + sum(dr.width(a) * (8 if isinstance(a, mi.Float64) else 4)
                                                  for a in arrays)

    # ------------------------------------------------------------------ device side
    @staticmethod
    def _bit(mask: mi.UInt32, entry: mi.UInt32, active: mi.Bool) -> mi.Bool:
        word = dr.gather(mi.UInt32, mask, entry >> 5, active)
        return active & (((word >> (entry & 31)) & 1) != 0)

    def sampled(self, entry: mi.UInt32, active: mi.Bool) -> mi.Bool:
        """Whether each (cell, bin) ``entry`` among the ``active`` lanes is drawn from its sub-bins."""
        return self._bit(self.sampling_mask, entry, active)

    @dr.syntax
    def accumulate(self, entry: mi.UInt32, sub: mi.UInt32, target: mi.Float, active: mi.Bool) -> None:
        """Add ``target`` to sub-bin ``sub`` of the learning ``entry`` lanes (as :meth:`RadianceRecord.accumulate`)."""
        learning = self._bit(self.learning_mask, entry, active)
        if learning:
            slot = dr.gather(mi.UInt32, self.slot, entry, learning)
            add_target(self.pass_targets, slot * self.sub + sub, target, learning)

    @dr.syntax
    def sample(self, k: mi.UInt32, entry: mi.UInt32, u: mi.Point2f, square: mi.Point2f,
               active: mi.Bool) -> tuple[mi.Vector3f, mi.UInt32]:
        """For the sampled ``entry`` lanes (bin ``k`` of their cell): a sub-bin drawn from π with ``u``, and a uniform
        direction in it from ``square``: (world direction, sub-bin)."""
        direction = mi.Vector3f(0, 0, 1)
        j = mi.UInt32(0)
        if active:
            slot = dr.gather(mi.UInt32, self.slot, entry, active)
            j, _ = alias_rows.sample(self.alias, slot, self.sub, u, active)
            direction = self.bins.sample_sub(k, j, self.R, square)
        return direction, j

    @dr.syntax
    def density(self, entry: mi.UInt32, sub: mi.UInt32, active: mi.Bool) -> mi.Float:
        """Density (solid angle) within a sampled refined bin of its sub-bin ``sub``: ``π_j·R²/A``, with π_j as
        :meth:`sample` draws it."""
        value = mi.Float(0)
        if active:
            slot = dr.gather(mi.UInt32, self.slot, entry, active)
            value = alias_rows.density(self.alias, slot, self.sub, sub, active)
        return value

    def _density_scale(self) -> float:
        """From a sub-bin's probability to its density within the bin (solid angle): R²/A."""
        return self.sub / self.bins.solid_angle

    # -------------------------------------------------------------------- host side
    def update(self, policy: mi.Float, q: mi.Float, visits: mi.Float64) -> dict:
        """Fold the pass's targets in, refine the entries whose ``policy`` reached the share after enough ``visits``
        (while slots last), rebuild π for every refined entry from its sub-bins' means (the bin's ``q`` where
        unvisited), and decide which are sampled and which still learn."""
        self._fold_pass()
        candidates = dr.compress((policy >= self.share) & (visits >= REFINE_VISITS * self.sub)
                                 & (self.slot == UNREFINED))
        wanted = dr.width(candidates)
        added = min(wanted, self.capacity - self.used)
        if added > 0:
            chosen = dr.gather(mi.UInt32, candidates, dr.arange(mi.UInt32, added))
            slots = dr.arange(mi.UInt32, added) + self.used
            dr.scatter(self.slot, slots, chosen)
            dr.scatter(self.entry_of, chosen, slots)
            self.learning_mask |= self._mask(chosen, True)     # a new entry learns
            self.used += added
        if self.used > 0:
            self._rebuild(q)
            self._classify()
        return {"refined_bins": self.used, "refinements_refused": wanted - added,
                "sampled_refined_bins": self.sampled_count, "settled_refined_bins": self.settled_count}

    def _classify(self) -> None:
        """The masks: entries sampled from their sub-bins (gain ≥ SAMPLING_GAIN), entries still learning (sampled,
        or below SETTLED_VISITS); an entry that settles below the gain stays settled."""
        flat = dr.arange(mi.UInt32, self.used * self.sub)
        squares = dr.square(dr.gather(mi.Float, self.probability, flat))
        gain = dr.block_reduce(dr.ReduceOp.Add, squares, self.sub) * self.sub
        visits = dr.block_reduce(dr.ReduceOp.Add, dr.gather(mi.Float64, self.acc_count, flat), self.sub)
        entries = dr.gather(mi.UInt32, self.entry_of, dr.arange(mi.UInt32, self.used))
        sampled = gain >= SAMPLING_GAIN
        learning = self._bit(self.learning_mask, entries, True) & (sampled | (visits < SETTLED_VISITS * self.sub))
        self.sampling_mask, self.learning_mask = self._mask(entries, sampled), self._mask(entries, learning)
        dr.eval(self.sampling_mask, self.learning_mask)
        self.sampled_count = int(dr.count(sampled)[0])
        self.settled_count = self.used - int(dr.count(learning)[0])

    def _mask(self, entries: mi.UInt32, members: mi.Bool) -> mi.UInt32:
        """The bit mask of the ``entries`` that are ``members``."""
        mask = dr.zeros(mi.UInt32, self.words)
        dr.scatter_reduce(dr.ReduceOp.Or, mask, mi.UInt32(1) << (entries & 31), entries >> 5, members)
        return mask

    def _fold_pass(self) -> None:
        """Add the pass's sums of the refined entries' sub-bins (the first ``used`` slots) to the totals, dropping
        non-finite or negative ones, and clear them."""
        if self.used == 0:
            return
        index = dr.arange(mi.UInt32, self.used * self.sub)
        added, visits = entry_sums(self.pass_targets, index)
        total = dr.gather(mi.Float64, self.acc_sum, index) + added
        count = dr.gather(mi.Float64, self.acc_count, index) + visits
        bad = ~(dr.isfinite(total) & (total >= 0))
        dr.scatter(self.acc_sum, dr.select(bad, 0, total), index)
        dr.scatter(self.acc_count, dr.select(bad, 0, count), index)
        dr.scatter(self.pass_targets, mi.Float64(0), dr.arange(mi.UInt32, 2 * self.used * self.sub))
        dr.eval(self.acc_sum, self.acc_count, self.pass_targets)

    def _rebuild(self, q: mi.Float) -> None:
        flat = dr.arange(mi.UInt32, self.used * self.sub)
        bin_q = dr.gather(mi.Float, q, dr.gather(mi.UInt32, self.entry_of, flat // self.sub))
        count = dr.gather(mi.Float64, self.acc_count, flat)
        total_target = dr.gather(mi.Float64, self.acc_sum, flat)
        mean = mi.Float((total_target + PRIOR_VISITS * mi.Float64(bin_q)) / (count + PRIOR_VISITS))
        shifted = dr.minimum(mean, dr.largest(mi.Float) / (4 * self.sub)) + SUB_OFFSET * dr.maximum(bin_q, 1e-30)
        total = dr.gather(mi.Float, dr.block_reduce(dr.ReduceOp.Add, shifted, self.sub), flat // self.sub)
        probability = (1 - SUB_EXPLORATION) * shifted / total + SUB_EXPLORATION / self.sub
        dr.scatter(self.probability, probability, flat)
        slots = alias_rows.build(probability, self.sub, self._density_scale())
        dr.scatter(self.alias, slots, dr.arange(mi.UInt32, dr.width(slots)))
        dr.eval(self.probability, self.alias)
