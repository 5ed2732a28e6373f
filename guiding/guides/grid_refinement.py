"""Finer directions where a cell's light is concentrated: sub-bins of the radiance record's brightest bins.

A bin of the record (2·D² equal-area bins, each ~9° wide at D = 16) cannot concentrate on a source a fraction of a
degree wide: a sun of 1e-3 sr covers 4 % of one. Once a (cell, bin) entry holds at least ``share`` of its cell's
policy, the bin's square is cut into ``R × R`` equal-area sub-bins (the bins' map is equal-area, so each sub-bin is a
direction cone of solid angle A/R²), whose distribution within the bin is learned from the same targets as Q:
``π_j = (1 − ε)·(Q_j + δ)/Σ(Q_j + δ) + ε/R²``, with ``Q_j`` the mean target of sub-bin j shrunk towards the bin's Q
(``(Σ targets + n₀·Q)/(visits + n₀)``, n₀ = :data:`PRIOR_VISITS`) and the exploration share ε = :data:`SUB_EXPLORATION`, so that no direction of the bin loses its density.

The coarse record is unchanged (Q, the policy, the memo tables): a sampler that drew a refined bin draws its sub-bin
from π and a uniform direction in it, with density ``π_j·R²/A`` within the bin. Refinement only grows, a slot per
entry, up to ``capacity`` entries; a record index with refinement is ``entry·R² + j`` (j the sub-bin of the
direction), so that the learning rules hand it on like any entry.

Life cycle: :meth:`BinRefinement.accumulate` in the path loop (beside the record's own sums), :meth:`update` after
the record's policy is rebuilt; :meth:`lookup` and :meth:`sample` / :meth:`density` in the samplers.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .cdf_rows import cut_count, cut_points, normalised_cdf, sample_rows
from .pass_sums import add_target, entry_sums, pass_sums

#: Slot of an entry that is not refined.
UNREFINED = 0xFFFFFFFF
#: Exploration share of the sub-bin distributions: every sub-bin keeps at least SUB_EXPLORATION/R² of its bin.
SUB_EXPLORATION = 0.1
#: Added to the sub-bins' Q before normalising (as the record's Q_OFFSET), relative to the bin's Q.
SUB_OFFSET = 1e-6
#: Visits of the bin's own Q that each sub-bin's mean starts from: a sub-bin seen a few times stays near its bin's Q,
#: so that noise in few targets does not become noise in the sampling density.
PRIOR_VISITS = 8.0


class BinRefinement:
    """Sub-bins of the record entries that hold a large share of their cell's policy.

    Parameters:
      bins: the record's :class:`~guiding.directions.SphereBins`.
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
        # One bit per entry (a cell's 2·D² bins in one cache line at D = 16): the test at every vertex reads this
        # small table, and only refined entries read their slot.
        self.mask = dr.zeros(mi.UInt32, (entries + 31) // 32)
        self.entry_of = dr.zeros(mi.UInt32, capacity)
        self.acc_sum = dr.zeros(mi.Float64, size)
        self.acc_count = dr.zeros(mi.Float64, size)
        self.pass_targets = pass_sums(size)
        self.probability = dr.full(mi.Float, 1 / self.sub, size)
        self.cdf = normalised_cdf(self.probability, self.sub)
        self.cuts = cut_points(self.cdf, self.sub)
        dr.eval(self.slot, self.cdf, self.cuts)

    @staticmethod
    def planned_bytes(entries: int, resolution: int, capacity: int) -> int:
        """Bytes of the tables of a refinement built with these arguments (all allocated up front)."""
        sub = resolution * resolution
        return (4 * entries + 4 * ((entries + 31) // 32) + 4 * capacity
                + capacity * (sub * (8 + 8 + 16 + 4 + 4) + 4 * (cut_count(sub) + 1)))

    def memory_bytes(self) -> int:
        arrays = [self.slot, self.mask, self.entry_of, self.acc_sum, self.acc_count, self.pass_targets, self.probability,
                  self.cdf, self.cuts]
        return sum(dr.width(a) * (8 if isinstance(a, mi.Float64) else 4) for a in arrays)

    # ------------------------------------------------------------------ device side
    def lookup(self, entry: mi.UInt32, active: mi.Bool) -> tuple[mi.UInt32, mi.Bool]:
        """(slot, refined) of each (cell, bin) ``entry`` among the ``active`` lanes; the slot is read only where the
        entry is refined."""
        word = dr.gather(mi.UInt32, self.mask, entry >> 5, active)
        refined = active & (((word >> (entry & 31)) & 1) != 0)
        return dr.gather(mi.UInt32, self.slot, entry, refined), refined

    def accumulate(self, entry: mi.UInt32, sub: mi.UInt32, target: mi.Float, active: mi.Bool) -> None:
        """Add ``target`` to sub-bin ``sub`` of the refined ``entry`` lanes (as :meth:`RadianceRecord.accumulate`)."""
        slot, refined = self.lookup(entry, active)
        add_target(self.pass_targets, slot * self.sub + sub, target, refined)

    def sample(self, k: mi.UInt32, slot: mi.UInt32, sampler: mi.Sampler, active: mi.Bool) -> tuple[mi.Vector3f,
                                                                                                  mi.UInt32]:
        """A sub-bin of refined bin ``k`` (its ``slot``) drawn from π, and a uniform direction in it: (world
        direction, sub-bin)."""
        j = sample_rows(self.cdf, self.cuts, slot, self.sub, sampler.next_1d(active), active)
        return self.bins.sample_sub(k, j, self.R, sampler.next_2d(active)), j

    def density(self, slot: mi.UInt32, sub: mi.UInt32, active: mi.Bool) -> mi.Float:
        """Density (solid angle) within a refined bin of its sub-bin ``sub``: ``π_j·R²/A``."""
        return dr.gather(mi.Float, self.probability, slot * self.sub + sub, active) * (self.sub / self.bins.solid_angle)

    # -------------------------------------------------------------------- host side
    def update(self, policy: mi.Float, q: mi.Float) -> dict:
        """Fold the pass's targets in, refine the entries whose ``policy`` reached the share (while slots last),
        and rebuild π for every refined entry from its sub-bins' means (the bin's ``q`` where unvisited)."""
        self._fold_pass()
        candidates = dr.compress((policy >= self.share) & (self.slot == UNREFINED))
        wanted = dr.width(candidates)
        added = min(wanted, self.capacity - self.used)
        if added > 0:
            chosen = dr.gather(mi.UInt32, candidates, dr.arange(mi.UInt32, added))
            slots = dr.arange(mi.UInt32, added) + self.used
            dr.scatter(self.slot, slots, chosen)
            dr.scatter(self.entry_of, chosen, slots)
            dr.scatter_reduce(dr.ReduceOp.Or, self.mask, mi.UInt32(1) << (chosen & 31), chosen >> 5)
            self.used += added
        if self.used > 0:
            self._rebuild(q)
        return {"refined_bins": self.used, "refinements_refused": wanted - added}

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
        cdf = normalised_cdf(probability, self.sub)
        dr.scatter(self.cdf, cdf, flat)
        cuts = cut_points(cdf, self.sub)
        G = cut_count(self.sub) + 1
        dr.scatter(self.cuts, cuts, dr.arange(mi.UInt32, self.used * G))
        dr.eval(self.probability, self.cdf, self.cuts)
