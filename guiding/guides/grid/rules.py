"""The grid guide's learning rules (method.md §3): each a class with its target in one place, the target recorded for
the segment x → x′ that left x in direction ω:

  :class:`MonteCarlo`     ``mc``: the radiance the path actually brought back (backward walk, Russian roulette
                          included);
  :class:`Sarsa`          ``sarsa``: ``Le(x′) + (f·cos/p)(ω′)·Q(x′, ω′)`` with ω′ the direction sampled at x′;
  :class:`ExpectedSarsa`  ``expected_sarsa``: ``Le(x′) + ρ̄/π·∫_H Q(x′, ω) cos dω``, read from the memo table (O(1)
                          per bounce).

Only segments that leave a surface the guide guides are recorded (Q is read nowhere else); a segment whose guided
direction went below the surface is never traced, so it records nothing. The guide adds each target to the record's
pass sums (:meth:`~guiding.guides.grid.record.RadianceRecord.accumulate`).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from guiding.guides.base import rgb_mean
from guiding.guides.grid.record import RadianceRecord
from guiding.guides.grid.vertex import GridVertex, arrival_side, guidable
from guiding.guides.vertex_log import NO_RECORD, VertexLog, known_or_found, walk_backward


class LearningRule:
    """How a grid guide learns Q from its paths: the per-path state, what a vertex records, what runs after the
    path loop (the device side of :class:`~guiding.guides.base.Guide`'s ``new_paths``, ``record`` and
    ``finish_paths``).

    Parameters:
      table: the guide's radiance record.
    """

    #: The record tables the rule reads (``needs_*`` arguments of :class:`RadianceRecord`).
    tables: frozenset[str] = frozenset()
    #: Whether ``record`` reads the albedo of the Lambertian BSDFs that ``GridGuide.locate`` reads for it
    #: (:attr:`GridVertex.lambertian`).
    reads_albedo = False

    def __init__(self, table: RadianceRecord):
        self.table = table

    def new_paths(self, size: int, max_depth: int):
        """The per-path state of ``size`` paths of at most ``max_depth`` vertices."""
        raise NotImplementedError

    def record(self, state, si: mi.SurfaceInteraction3f, emitted: mi.Spectrum, bs: mi.BSDFSample3f,
               weight: mi.Spectrum, continues: mi.Bool, active: mi.Bool, leaves: mi.Bool,
               index: mi.UInt32 | None = None, vertex: GridVertex | None = None):
        """Learn from vertex ``si`` (arguments as :meth:`Guide.record`'s); ``leaves``: the lanes whose segment
        leaving ``si`` is recorded; ``index``: the record index of the direction sampling took (None: not handed
        over); ``vertex``: what ``locate`` found. Returns the state."""
        raise NotImplementedError

    def finish_paths(self, state) -> None:
        """Called once after the path loop with the final per-path state."""

    def _record_index(self, si, bs, index, needed) -> mi.UInt32:
        """The record index of the direction sampled at ``si``, in the lanes ``needed``: the sampler's (``index``),
        looked up where it gave none (None; NO_RECORD at a vertex whose BSDF it does not guide, where a segment that
        arrives still reads Q)."""
        return known_or_found(index, needed, lambda lanes: self.table.index(si.p, si.to_world(bs.wo)))


class MonteCarlo(LearningRule):
    """``mc``: the radiance each segment brought back, walked backwards as soon as the paths end; the per-path
    state is the paths' vertex log (:class:`~guiding.guides.vertex_log.VertexLog`)."""

    def __init__(self, table: RadianceRecord):
        super().__init__(table)
        self._log: VertexLog | None = None      # the pass's vertices

    def new_paths(self, size: int, max_depth: int):
        self._log = VertexLog(max_depth)
        return self._log.new_paths(size)

    def record(self, state, si, emitted, bs, weight, continues, active, leaves, index=None, vertex=None):
        here = dr.select(leaves, self._record_index(si, bs, index, leaves), NO_RECORD)
        return self._log.append(state, emitted, weight, continues, here, active)

    def finish_paths(self, state) -> None:
        walk_backward(state, lambda entry, L: self.table.accumulate(entry.target, rgb_mean(L),
                                                                    entry.target != NO_RECORD))


class Sarsa(LearningRule):
    """``sarsa``: at x′, the target of the segment that led there, ``Le(x′)`` plus the bootstrap from x′
    (:meth:`_bootstrap`: ``(f·cos/p)(ω′)·Q(x′, ω′)``). The per-path state is the record index of the segment that
    led to the current vertex (NO_RECORD: none)."""

    def new_paths(self, size: int, max_depth: int) -> mi.UInt32:
        return dr.full(mi.UInt32, NO_RECORD, size)

    @dr.syntax
    def record(self, previous, si, emitted, bs, weight, continues, active, leaves, index=None,
               vertex=None) -> mi.UInt32:
        """The target of the segment that led here (``previous``), and the entry of the segment that leaves
        (returned). A branch: packets with neither (unguided surfaces) skip it."""
        table = self.table
        pending = active & (previous != NO_RECORD)
        if pending | leaves:
            here = self._record_index(si, bs, index, pending | leaves)
            target = rgb_mean(emitted)
            onward = rgb_mean(weight) * dr.gather(mi.Float, table.q, table.entry(here), pending & continues)  # ∫ f·Q·cos
            onward, known = self._bootstrap(si, pending, onward, vertex)
            target += dr.select(continues | known, onward, 0)
            table.accumulate(previous, target, pending)
            previous = dr.select(leaves, here, NO_RECORD)
        return previous

    def _bootstrap(self, si, pending: mi.Bool, sampled: mi.Float, vertex) -> tuple[mi.Float, mi.Bool]:
        """What the path brings back from x′ on, given ``sampled``, the weight of the direction sampled there times
        its Q (counted where the path continues): (the estimate, the lanes where it holds even though the path ends
        at x′). SARSA's is ``sampled``."""
        return sampled, mi.Bool(False)


class ExpectedSarsa(Sarsa):
    """``expected_sarsa``: SARSA with the bootstrap ``ρ̄/π·V(x′)``, ``V = ∫_H Q(x′, ω) cos dω`` read from the memo
    table, where x′'s BSDF is diffuse and its pair memoised (whether or not the path goes on from x′)."""

    tables = frozenset({"needs_value"})
    reads_albedo = True

    def _bootstrap(self, si, pending, sampled, vertex):
        table = self.table
        bsdf = si.bsdf()
        pair = table.pair(table.cell(si.p), si.sh_frame.n * arrival_side(si))
        known = pending & si.is_valid() & guidable(bsdf) & (table.memo(pair, pending).norm > 0)
        albedo = self._albedo(si, bsdf, known, vertex)
        return dr.select(known, albedo / dr.pi * dr.gather(mi.Float, table.value, pair, known), sampled), known

    @dr.syntax
    def _albedo(self, si, bsdf, known, vertex) -> mi.Float:
        """The mean albedo ρ of the BSDF at the lanes ``known``: what ``locate`` read at the vertex's guidable
        lanes, the BSDF's call at the others (a branch: most packets have none)."""
        if dr.hint(vertex is None or vertex.lambertian is None, mode="scalar"):
            albedo = rgb_mean(bsdf.eval_diffuse_reflectance(si, known))
        else:
            albedo = rgb_mean(vertex.lambertian.albedo)
            missing = known & ~vertex.guidable
            if missing:
                albedo = dr.select(missing, rgb_mean(bsdf.eval_diffuse_reflectance(si, missing)), albedo)
        return albedo
