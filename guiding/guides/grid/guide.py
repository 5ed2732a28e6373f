"""Grid path guiding learned online (Kim & Kim 2021): learning rules and samplers over a :class:`RadianceRecord`.

Rules (method.md §3), the target recorded for the segment x → x′ that left x in direction ω:
  ``mc``              the radiance the path actually brought back (backward walk, Russian roulette included);
  ``sarsa``           ``Le(x′) + (f·cos/p)(ω′)·Q(x′, ω′)`` with ω′ the direction sampled at x′;
  ``expected_sarsa``  ``Le(x′) + ρ̄/π·∫_H Q(x′, ω) cos dω``, read from the memo table (O(1) per bounce).
A segment whose guided direction went below the surface is never traced, so it records nothing.

Samplers (method.md §5), used only at surfaces whose BSDF is purely diffuse; others are BSDF-sampled:
  ``sphere_inv``     bin from the cell's distribution over the sphere, uniform in the bin;
  ``hemi_inv``       bin from the memoised distribution of P·∫cos per (cell, normal bin), uniform in the bin;
  ``hemi_rej``       the target ``P(ω)·cos⁺(ω, n_c)/N`` by rejection;
  ``hemi_rej_plus``  the same with the share ε_r = max((1−2c)/(2−2c), 0), c = ū/M, drawn apart (the paper's Rej+).
Every sampler is a one-sample mixture with BSDF sampling, ``p = α·p_bsdf + (1 − α)·p_guide``, and reports that
density exactly. The BSDF share α bounds the weight ``f·cos/p`` of a diffuse vertex by ρ/α and gives every direction
with f·cos > 0 a positive density. For the inversion samplers α = ``bsdf_fraction`` (0.5; 0 is the paper's pure
sampler, whose weight reached 97·ρ at door-ajar vertices: a few paths carried most of the image). For the rejection
samplers α = 1 − (1 − u)·(1 − r): u = max(ε_r, ``min_bsdf_share``), where the paper mixes ε_r of a uniform density
into the target instead (ours draws it from the BSDF: a weight bound of 2ρ rather than 4ρ at ε_r = ½), and r, the
share of loops that exhaust ``max_proposals`` and fall back to the BSDF's direction.

The rejection target uses the normal bin's centre ``n_c``: the memoised ``N = ∫ P·cos⁺(ω, n_c)`` is exact for it
at every true normal, so the samplers are exact by construction (with N taken at n_c but the cosine at the true
normal, each bounce was off by N(n_c)/N(n): ``ours`` was +1.25 ± 0.29 % off ``path`` on the tilted Cornell box).
Target directions below the true surface have f = 0 and weight 0. The target is drawn with one of the proposals:
  ``bins``     without a loop: a bin k from the pair's alias table of ``P_k·∫_k cos⁺``, then a direction of the bin
               ∝ ``cos(ω, n_c)``, the first of ``IN_BIN_PROPOSALS`` uniform proposals in the bin accepted against
               the bin's bound (most bins accept ~90 % of proposals, bins across the horizon less); r, the chance
               that all are rejected, is memoised per pair (``in_bin_miss``);
  ``uniform``  the paper's loop: uniform directions on the hemisphere of n_c, accepted if ``ξ·M < P·cos(ω, n_c)``;
               acceptance ``a = N/(2π·M)``, a few percent once P is peaked; ``r = (1 − a)^max_proposals``.
With ``sub_resolution`` R > 1 (``ours-plus``), a bin drawn by the ``bins`` proposal that the record has refined
(:mod:`~guiding.guides.grid.refinement`) gives its direction without rejection: a sub-bin from its learned
distribution π, a uniform direction in it, density within the bin ``π_j·R²/A`` (A the bin's solid angle) in place of the in-bin rejection's; such bins add no
miss share.
Pass 0 samples the BSDF only (the tables are empty); it marks the (cell, normal bin) pairs it visits, so the
hemisphere samplers guide from pass 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from guiding.guides.base import Guide, UpdateResult, rgb_mean
from guiding.guides import alias_rows
from guiding.guides.grid.lambertian import LambertianBsdfs, LambertianVertex
from guiding.guides.grid.record import IN_BIN_PROPOSALS, PairMemo, RadianceRecord, table_needs
from guiding.guides.parameters import (PROFILE_BSDF_PATHS, PROFILE_HOT_ROWS, PROFILE_STAGES, PROFILE_TRAINING_PASSES, GridParameters,
                         with_overrides)
from guiding.guides.vertex_log import NO_RECORD, VertexLog, known_or_found, walk_backward


@dataclass
class SarsaState:
    """The (cell, bin) of the segment that led to the current vertex, or NO_RECORD."""

    previous: mi.UInt32 = None
    DRJIT_STRUCT = {"previous": mi.UInt32}


@dataclass
class GridVertex:
    """What the path loop hands from :meth:`GridGuide.locate` to ``sample`` and ``record`` at a vertex: the lanes
    the guide may guide (the BSDF flags), and the record index of the direction ``sample`` took (left None by an
    untrained guide and by refined bins, whose record index ``record`` computes: the sampler's bin of a refined
    entry's unrefined neighbour does not say the sub-bin), and, for Expected SARSA's record, the albedo of
    Lambertian BSDFs read at the ``guidable`` lanes (sampling computes their BSDF from it; None: not read here)."""

    guidable: mi.Bool
    index: mi.UInt32 = None
    lambertian: LambertianVertex = None


@dataclass
class _Vertex:
    """Per-lane facts about a vertex that the samplers share (filled by ``GridGuide._vertex``)."""

    guided: mi.Bool
    cell: mi.UInt32
    side: mi.Float
    pair: mi.UInt32 = None
    memo: PairMemo = None          # the pair's N, alias row, M and in-bin miss share
    centre: mi.Vector3f = None     # n_c, the normal bin's centre on the arrival side (world)
    bsdf_share: mi.Float = None    # u: bsdf_fraction, or max(ε_r, min_bsdf_share); ≥ smooth_bsdf_share if not diffuse


def _first_accepted(sampler, searching, propose, accepts, count: int) -> tuple[mi.Vector3f, mi.Bool, mi.UInt32]:
    """``count`` proposals side by side, without a loop: (the first accepted, whether one was, the proposals made
    until then). Where most lanes accept the first proposal, a symbolic loop cost more than the proposals it saved
    (it keeps the sampler and the candidates as loop state)."""
    wo = mi.Vector3f(0, 0, 1)
    accepted = mi.Bool(False)
    proposals = mi.UInt32(0)
    for _ in range(count):
        candidate = propose(sampler, searching)
        proposals += dr.select(searching & ~accepted, 1, 0)
        take = searching & ~accepted & accepts(sampler, candidate, searching)
        wo = dr.select(take, candidate, wo)
        accepted |= take
    return wo, accepted, proposals


def _arrival_side(si: mi.SurfaceInteraction3f) -> mi.Float:
    """+1 or −1: the side of the surface the path arrived on, where guided directions must leave."""
    return dr.select(si.wi.z < 0, -1.0, 1.0)


def guidable(bsdf: mi.BSDFPtr, smooth: bool = False) -> mi.Bool:
    """Purely diffuse reflection: the BSDFs the paper guides (glossy, delta and transmissive lobes are not). With
    ``smooth``, every reflecting BSDF without a delta, null or transmissive lobe (rough plastic and conductors too)."""
    flags, F = bsdf.flags(), mi.BSDFFlags
    reflects = F.DiffuseReflection | (F.GlossyReflection if smooth else 0)
    excluded = F.Delta | F.DiffuseTransmission | F.GlossyTransmission | (F.Null if smooth else F.Glossy)
    return ((flags & int(reflects)) != 0) & ((flags & int(excluded)) == 0)


class GridGuide(Guide):
    """Kim & Kim's guide: a ``S³ × 2·D²`` radiance record, a learning rule and a sampler.

    Parameters:
      parameters: the guide's :class:`~guiding.guides.parameters.GridParameters` (resolution, rule, sampler,
        mixture shares; each documented there), default ``GridParameters()``.
      name: the method name shown in tables (default ``{rule}-{sampler}``).
      overrides: parameters changed from ``parameters`` (``GridGuide(rule="mc", spatial_resolution=4)``).
    """

    def __init__(self, parameters: GridParameters | None = None, name: str | None = None, **overrides):
        self.parameters = p = with_overrides(parameters or GridParameters(), overrides)
        self.rule, self.sampler, self.proposal = p.rule, p.sampler, p.proposal
        self.name = name or f"{p.rule}-{p.sampler}"
        self.bsdf_fraction = p.bsdf_fraction
        self.max_proposals = p.max_proposals
        self.min_bsdf_share = p.min_bsdf_share
        self.smooth = p.guided_bsdfs == "smooth"
        self.smooth_bsdf_share = p.smooth_bsdf_share
        self.statistics = p.statistics
        #: Benchmark instrument: how far the bounce goes (index into PROFILE_STAGES; len = the whole guide).
        self._stage = PROFILE_STAGES.index(p.profile_stage) if p.profile_stage in PROFILE_STAGES else len(PROFILE_STAGES)
        self._bsdf_paths = p.profile_stage == PROFILE_BSDF_PATHS
        self._hot_rows = p.profile_stage == PROFILE_HOT_ROWS
        self._updates = 0
        self.rebuild_growth = p.rebuild_growth
        self._rebuilt_at = 0           # spp done at the record's last rebuild
        self._table_stats = {}         # memo pairs and refinement figures of the last rebuild
        self._bsdfs = LambertianBsdfs()   # the scene's Lambertian BSDFs (none known until prepare)
        self.record_table = RadianceRecord(
            p.spatial_resolution, p.directional_resolution, p.normal_resolution,
            **table_needs(p.rule, p.sampler, p.proposal), min_exploration=p.min_exploration,
            sub_resolution=p.sub_resolution, refine_share=p.refine_share, refine_capacity=p.refine_capacity)
        self.trained = False
        self._mc_log: VertexLog | None = None      # the pass's vertices (rule mc)
        self._reset_counters()

    # ================================================================ host side
    def prepare(self, scene: mi.Scene) -> None:
        self.record_table.set_bounds(scene.bbox())
        self._bsdfs = LambertianBsdfs(scene, guided=lambda bsdf: bool(self.guides(mi.BSDFPtr(bsdf), True)[0]))
        self._rebuilt_at = 0      # a render that continues a trained guide counts its spp from 0: rebuild after a pass

    def update(self, spp_done: int) -> UpdateResult:
        stats = self._read_counters() if self.statistics else {}
        if self.trained and self.rebuild_growth > 0 and spp_done < self._next_rebuild():
            stats.update(self._table_stats, rebuilt=False)     # the tables of the last rebuild, still in use
        else:
            table = self.record_table
            self._table_stats = {"memo_pairs": table.update(spp_done), **table.refined_stats}
            self._rebuilt_at = spp_done
            # With the entries the rebuild dropped or clamped (grid_record's sanitising).
            stats.update(self._table_stats, **table.sanitised, rebuilt=True)
        self.trained = True
        self._updates += 1
        self._reset_counters()
        return UpdateResult(stats)

    def update_due(self, spp_done: int) -> int:
        """After every pass while untrained or without ``rebuild_growth``, else at the next rebuild
        (:meth:`_next_rebuild`)."""
        return self._next_rebuild() if self.trained and self.rebuild_growth > 0 else spp_done

    def _next_rebuild(self) -> int:
        """The spp of the next rebuild, from the last one alone: the next multiple of ``step``, the largest power of
        two ≤ ``rebuild_growth`` g × the spp of the last rebuild (g = 1/4: at 2^k·(1, 5/4, 3/2, 7/4)), so that the
        passes in between can be one pass of a power-of-two size."""
        step = 1 << max(int(self.rebuild_growth * self._rebuilt_at).bit_length() - 1, 0)
        return (self._rebuilt_at // step + 1) * step

    def records(self) -> bool:
        # A profiled stage (benchmark instrument) learns its tables in the warm-up passes, then records nothing.
        return self._stage == len(PROFILE_STAGES) or self._updates < PROFILE_TRAINING_PASSES

    def trace_key(self) -> tuple:
        return self.trained, self.records()

    def stats(self) -> dict:
        table = self.record_table
        return {"rule": self.rule, "sampler": self.sampler, "proposal": self.proposal,
                "bsdf_fraction": self.bsdf_fraction, "min_bsdf_share": self.min_bsdf_share,
                "S": table.S, "D": table.bins.resolution,
                "bins": table.bins.count, "normal_bins": table.normal_bins.count,
                "sub_resolution": table.sub_resolution,
                "memory_bytes": table.memory_bytes()}

    def _reset_counters(self) -> None:
        if not self.statistics:
            self.counters = {}
            return
        self.counters = {key: mi.UInt32(0) for key in ("guided", "invalid", "proposals", "rejection_samples",
                                                        "accepted")}

    def _read_counters(self) -> dict:
        c = {key: int(value[0]) for key, value in self.counters.items()}
        return {"guided_samples": c["guided"],
                "invalid_share": c["invalid"] / c["guided"] if c["guided"] else 0.0,
                "acceptance_rate": c["accepted"] / c["proposals"] if c["proposals"] else None,
                "proposals_per_sample": c["proposals"] / c["rejection_samples"] if c["rejection_samples"] else None}

    def _count(self, key: str, value, active: mi.Bool) -> None:
        """One atomic add into a pass counter; nothing is traced unless ``statistics`` is on."""
        if not self.statistics:
            return
        dr.scatter_reduce(dr.ReduceOp.Add, self.counters[key], mi.UInt32(value), mi.UInt32(0), active)

    # ============================================================== device side
    # ---------------------------------------------------------------- sampling
    def locate(self, si, bsdf, active) -> GridVertex:
        guidable_lanes = self.guides(bsdf, active)
        lambertian = None
        if self.trained and self.rule == "expected_sarsa":
            # Read here, before sampling's branches, so that the record reads it too: one BSDF call, not two.
            lambertian = self._bsdfs.vertex(bsdf, si, guidable_lanes)
        return GridVertex(guidable_lanes, lambertian=lambertian)

    def sample(self, scene, sampler, si, bsdf, bsdf_ctx, active, vertex=None):
        if not self.trained:
            if self.record_table.needs_pairs:
                self._locate(si, bsdf, active)     # marks the pairs this pass visits: memoised for the next pass
            return bsdf.sample(bsdf_ctx, si, sampler.next_1d(active), sampler.next_2d(active), active)
        guidable_lanes = self.guides(bsdf, active) if vertex is None else vertex.guidable
        lambertian = None if vertex is None else vertex.lambertian
        bs, weight, index = self._sample_vertex(sampler, si, bsdf, bsdf_ctx, active, guidable_lanes, lambertian)
        if vertex is not None and not self.record_table.refinement:
            vertex.index = index
        return bs, weight

    @dr.syntax
    def _sample_vertex(self, sampler, si, bsdf, bsdf_ctx, active, guidable_lanes, lambertian=None):
        """The guide where the BSDF is one it guides, one BSDF sample elsewhere: a branch, not a select, so that
        packets of lanes with nothing to guide (delta and, unless ``guided_bsdfs`` is smooth, glossy BSDFs; emitters;
        escaped paths) pay only the BSDF flags test, not even the vertex's cell. Returns the sample, its weight and
        the record index of its direction (NO_RECORD where the BSDF is not guided: ``record`` looks it up there if a
        recorded segment arrived). ``lambertian``: the Lambertian BSDF's side and albedo, if :meth:`locate` read
        them."""
        if guidable_lanes:
            bs, weight, index = self._sample_guidable(sampler, si, bsdf, bsdf_ctx, guidable_lanes, lambertian)
        else:
            others = active & ~guidable_lanes
            bs, weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(others), sampler.next_2d(others), others)
            index = mi.UInt32(NO_RECORD)
        return bs, weight, index

    @dr.syntax
    def _sample_guidable(self, sampler, si, bsdf, bsdf_ctx, active, lambertian=None):
        """The guide where the vertex's (cell, normal bin) pair has its memo, one BSDF sample elsewhere."""
        vertex = self._vertex(si, bsdf, active)
        if vertex.guided:
            bs, weight, index = self._guided_sample(sampler, si, bsdf, bsdf_ctx, vertex, lambertian)
        else:
            bs, weight, index = self._unguided_sample(sampler, si, bsdf, bsdf_ctx, active & ~vertex.guided)
        return bs, weight, index

    def _unguided_sample(self, sampler, si, bsdf, bsdf_ctx, active):
        """One BSDF sample at a guidable vertex whose pair has no memo yet (its first visits), and its record index."""
        bs, weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(active), sampler.next_2d(active), active)
        return bs, weight, self._index_taken(si, si.to_world(bs.wo))

    def _guided_sample(self, sampler, si, bsdf, bsdf_ctx, vertex,
                       lambertian=None) -> tuple[mi.BSDFSample3f, mi.Spectrum, mi.UInt32]:
        """The one-sample mixture of BSDF sampling and the guide at the guided lanes: one BSDF call gives its sample,
        and its value and density at the guide's direction (computed inline where the BSDF is Lambertian,
        :mod:`~guiding.guides.grid.lambertian`). Returns the sample, its weight and its record index."""
        guided = vertex.guided
        table = self.record_table
        if self._stage == 0:      # profile stage "classify": the mask is computed (and used), the BSDF samples
            bs, weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(guided), sampler.next_2d(guided), guided)
            return bs, weight * 0.5, self._index_taken(si, si.to_world(bs.wo))
        if self.sampler.endswith("_inv"):
            use_guide = guided & (sampler.next_1d(guided) >= vertex.bsdf_share)
            guide_world, guide_bin, guide_density = self._sample_inversion(sampler, vertex, use_guide)
        else:
            searching = guided & (sampler.next_1d(guided) >= vertex.bsdf_share)
            guide_world, guide_bin, guide_density, use_guide = self._sample_rejection(sampler, vertex, searching)
        guide_wo = si.to_local(guide_world)
        guide_value, guide_bsdf_pdf, bs, bsdf_weight = self._bsdfs.eval_pdf_sample(
            bsdf, bsdf_ctx, si, guide_wo, sampler.next_1d(guided), sampler.next_2d(guided), guided, lambertian)
        if self._stage == 1:      # profile stage "sample": guided directions, the BSDF's weights
            bs.wo = dr.select(use_guide, guide_wo, bs.wo)
            return bs, bsdf_weight, self._index_taken(si, si.to_world(bs.wo))
        value = dr.select(use_guide, guide_value, bsdf_weight * bs.pdf)
        bsdf_pdf = dr.select(use_guide, guide_bsdf_pdf, bs.pdf)
        world = dr.select(use_guide, guide_world, si.to_world(bs.wo))
        chosen_bin = bin_density = None
        if guide_bin is not None:
            bsdf_lanes = guided & ~use_guide
            chosen_bin = dr.select(use_guide, guide_bin, table.fine_bin(world))
            bin_density = dr.select(use_guide, guide_density, self._bin_density(vertex, chosen_bin, bsdf_lanes))
        pdf = self._mixture_pdf(vertex, world, bsdf_pdf, chosen_bin, bin_density)

        weight = dr.select(pdf > 0, value / pdf, 0)
        self._count("guided", 1, guided)
        self._count("invalid", 1, guided & dr.all(weight == 0))
        if self._bsdf_paths:      # everything above is kept alive by an opaque zero, the path follows the BSDF
            keep = dr.opaque(mi.Float, 0) * (weight + mi.Float(guide_wo.x))
            return bs, bsdf_weight + keep, self._index_taken(si, si.to_world(bs.wo))
        bs.wo = dr.select(use_guide, guide_wo, bs.wo)
        bs.pdf = pdf
        bs.sampled_type = dr.select(use_guide, mi.UInt32(mi.BSDFFlags.DiffuseReflection), bs.sampled_type)
        bs.eta = dr.select(use_guide, 1.0, bs.eta)
        return bs, weight, self._index_taken(si, world, vertex.cell, chosen_bin)

    def _index_taken(self, si, world: mi.Vector3f, cell: mi.UInt32 = None, chosen_bin: mi.UInt32 = None) -> mi.UInt32:
        """The record index of direction ``world`` taken at ``si``, for ``record`` (from the vertex's cell and the bin
        the direction was drawn or looked up in, where the sampler has them); NO_RECORD with refined bins, whose
        index ``record`` looks up (see :class:`GridVertex`)."""
        table = self.record_table
        if table.refinement:
            return mi.UInt32(NO_RECORD)
        if chosen_bin is not None:
            return cell * table.bins.count + chosen_bin
        return table.index(si.p, world)

    def guides(self, bsdf, active) -> mi.Bool:
        return active & guidable(bsdf, self.smooth)

    def pdf(self, si, bsdf, bsdf_ctx, wo, active) -> mi.Float:
        """Density (solid angle) with which :meth:`sample` draws local direction ``wo`` at ``si``."""
        bsdf_pdf = bsdf.pdf(bsdf_ctx, si, wo, active)
        if not self.trained:
            return bsdf_pdf
        vertex = self._vertex(si, bsdf, active, mark_visited=False)
        return dr.select(vertex.guided, self._mixture_pdf(vertex, si.to_world(wo), bsdf_pdf), bsdf_pdf)

    def _locate(self, si, bsdf, active, mark_visited=True) -> "_Vertex":
        """The vertex's cell, arrival side, (cell, normal bin) pair and its memo; marks a pair without memo visited
        (the memoised ones stay marked: written at every vertex, the flags cost the cores' caches a line each)."""
        table = self.record_table
        vertex = _Vertex(guided=active & guidable(bsdf, self.smooth), cell=table.cell(si.p), side=_arrival_side(si))
        if table.needs_pairs:
            vertex.pair = table.pair(vertex.cell, si.sh_frame.n * vertex.side)
            vertex.memo = table.memo(vertex.pair, vertex.guided)
            if mark_visited:
                table.mark_visited(vertex.pair, vertex.guided & (vertex.memo.norm == 0))
        return vertex

    def _vertex(self, si, bsdf, active, mark_visited=True) -> "_Vertex":
        """What every sampler needs to know about a vertex; decides which lanes are guided."""
        table = self.record_table
        vertex = self._locate(si, bsdf, active, mark_visited)
        if self.sampler.startswith("hemi"):
            # A pair seen for the first time has no memo yet: its vertices keep BSDF sampling this pass.
            vertex.guided &= vertex.memo.norm > 0
        vertex.bsdf_share = mi.Float(self.bsdf_fraction)
        if self.sampler.startswith("hemi_rej"):
            vertex.centre = table.normal_centre(vertex.pair, vertex.guided)
            share = mi.Float(0)
            if self.sampler == "hemi_rej_plus":
                c = vertex.memo.norm / (2 * dr.pi * vertex.memo.bound)     # ū/M, the mean of P·cos over its maximum
                share = dr.maximum((1 - 2 * c) / (2 - 2 * c), 0)
            vertex.bsdf_share = dr.maximum(share, self.min_bsdf_share)
        if self.smooth:
            glossy = ~guidable(bsdf)
            vertex.bsdf_share = dr.select(glossy, dr.maximum(vertex.bsdf_share, self.smooth_bsdf_share),
                                          vertex.bsdf_share)
        return vertex

    def _bin_density(self, vertex, fine_bin: mi.UInt32, active: mi.Bool) -> mi.Float:
        """The alias table's density of bin ``fine_bin`` (with refinement ``bin·R² + sub-bin``; the bin's) in the
        vertex's row: the cell's for ``sphere_inv``, the pair's for the hemisphere samplers."""
        table = self.record_table
        k = fine_bin // table.fine if table.refinement else fine_bin
        if self.sampler == "sphere_inv":
            return table.cell_density(vertex.cell, k, active)
        return table.hemi_density(vertex.pair, self._pair_row(vertex), k, active)

    def _pair_row(self, vertex) -> mi.UInt32:
        """The row of ``hemi_alias`` the vertex draws from and reads densities in: its pair's, or with the benchmark
        instrument ``hot_rows`` the first pair's (:data:`~.parameters.PROFILE_HOT_ROWS`)."""
        return mi.UInt32(0) if self._hot_rows else vertex.memo.row

    def _mixture_pdf(self, vertex, world: mi.Vector3f, bsdf_pdf: mi.Float, chosen_bin=None,
                     bin_density=None) -> mi.Float:
        """Density of the mixture ``α·p_bsdf + (1 − α)·p_guide`` at world direction ``world``, given ``p_bsdf``.

        ``chosen_bin``: the bin ``world`` was drawn in (or looked up in; with refinement ``bin·R² + sub-bin``),
        whose density is reported, and ``bin_density`` its density in the alias table where known (from the draw).
        Looking the direction up again can give a neighbour when it lies within rounding of a bin boundary, and a
        neighbour of negligible weight would report density 0 for a direction the guide drew."""
        table = self.record_table
        refinement = table.refinement
        k = table.fine_bin(world) if chosen_bin is None else chosen_bin
        if bin_density is None and (self.sampler.endswith("_inv") or self.proposal == "bins"):
            bin_density = self._bin_density(vertex, k, vertex.guided)
        if refinement:
            k, sub = k // table.fine, k % table.fine
        if self.sampler.endswith("_inv"):
            share = vertex.bsdf_share
            return share * bsdf_pdf + (1 - share) * bin_density
        if self.proposal == "bins":
            miss_all = vertex.memo.in_bin_miss
            cosine = dr.maximum(dr.dot(world, vertex.centre), 0)
            guide_density = bin_density * cosine
            if refinement:
                entry = vertex.cell * table.bins.count + k
                refined = refinement.sampled(entry, vertex.guided)
                guide_density = dr.select(refined, bin_density * refinement.density(entry, sub, refined),
                                          guide_density)
        else:
            acceptance = vertex.memo.norm / (2 * dr.pi * vertex.memo.bound)
            miss_all = dr.power(1 - dr.minimum(acceptance, 1), self.max_proposals)
            cosine = dr.maximum(dr.dot(world, vertex.centre), 0)
            target = dr.gather(mi.Float, table.policy, vertex.cell * table.bins.count + k, vertex.guided)
            guide_density = (1 - miss_all) * target * cosine / vertex.memo.norm
        # The rejected share r falls back to the BSDF: α = 1 − (1 − u)·(1 − r).
        share = 1 - (1 - vertex.bsdf_share) * (1 - miss_all)
        return share * bsdf_pdf + (1 - vertex.bsdf_share) * guide_density

    def _sample_inversion(self, sampler, vertex, active) -> tuple[mi.Vector3f, mi.UInt32, mi.Float]:
        """A world direction drawn from the sampler's alias row (the cell's, or the pair's), its bin and the bin's
        density."""
        table = self.record_table
        u = sampler.next_2d(active)
        if self.sampler == "sphere_inv":
            k, density = alias_rows.sample(table.cell_alias, vertex.cell, table.bins.count, u, active)
        else:
            k, density = table.hemi_sample(vertex.pair, self._pair_row(vertex), u, active)
        return table.bins.sample(k, sampler.next_2d(active)), k, density

    def _sample_rejection(self, sampler, vertex, searching) -> tuple[mi.Vector3f, mi.UInt32 | None, mi.Float | None,
                                                                     mi.Bool]:
        """A world direction from the target ``P·cos⁺(ω, n_c)/N``: (direction, the bin it was drawn in and the bin's
        density, or None, whether it was accepted; the lanes that were not fall back to the BSDF's direction)."""
        table = self.record_table
        centre = vertex.centre
        k = density = None
        if self.proposal == "bins":
            k, density = table.hemi_sample(vertex.pair, self._pair_row(vertex), sampler.next_2d(searching), searching)
            if table.refinement:
                entry = vertex.cell * table.bins.count + k
                refined = table.refinement.sampled(entry, searching)
                searching &= ~refined
            bound = dr.gather(mi.Float, table.in_bin_bound, table.normal_bin_flat(vertex.pair, k), searching)

            def propose(sampler, active):
                return table.bins.sample(k, sampler.next_2d(active))

            def accepts(sampler, candidate, active):
                return sampler.next_1d(active) * bound < dr.dot(candidate, centre)
        else:
            frame = mi.Frame3f(centre)

            def propose(sampler, active):
                return frame.to_world(mi.warp.square_to_uniform_hemisphere(sampler.next_2d(active)))

            def accepts(sampler, candidate, active):   # ξ·M < P·cos(ω, n_c)
                target = table.policy_at(vertex.cell, candidate, active) * dr.dot(candidate, centre)
                return sampler.next_1d(active) * vertex.memo.bound < target

        self._count("rejection_samples", 1, searching)
        if self.proposal == "bins":
            wo, accepted, proposals = _first_accepted(sampler, searching, propose, accepts, IN_BIN_PROPOSALS)
        else:
            wo, accepted, proposals = self._rejection_loop(sampler, mi.Bool(searching), propose, accepts,
                                                           self.max_proposals)
        self._count("proposals", proposals, searching)
        self._count("accepted", 1, accepted)
        if self.proposal == "bins" and table.refinement:
            # A refined bin: its sub-bin from π, a uniform direction in it, nothing rejected.
            sub_wo, sub = table.refinement.sample(k, entry, sampler.next_2d(refined), sampler.next_2d(refined), refined)
            wo = dr.select(refined, sub_wo, wo)
            accepted |= refined
            k = k * table.fine + dr.select(refined, sub, 0)
        return wo, k, density, accepted

    @dr.syntax
    def _rejection_loop(self, sampler, searching, propose, accepts, cap: int) -> tuple[mi.Vector3f, mi.Bool, mi.UInt32]:
        """Proposals until one ``accepts`` or ``cap`` are spent: (the last proposal, accepted, proposals).

        ``sampler`` is named in the loop body (not only in the closures) so that its state is a loop variable."""
        wo = mi.Vector3f(0, 0, 1)
        proposals = mi.UInt32(0)
        accepted = mi.Bool(False)
        while dr.hint(searching, label="Rejection sampling", max_iterations=-1):
            wo = propose(sampler, searching)
            proposals += 1
            accepted = accepts(sampler, wo, searching)
            searching &= ~accepted & (proposals < cap)
        return wo, accepted, proposals

    # ---------------------------------------------------------------- learning
    def new_paths(self, size: int, max_depth: int):
        if self.rule == "mc":
            self._mc_log = VertexLog(max_depth)
            return self._mc_log.new_paths(size)
        return SarsaState(dr.full(mi.UInt32, NO_RECORD, size))

    def record(self, state, si, emitted, bs, weight, continues, active, vertex=None):
        # Only segments that leave a guidable surface are recorded: Q is read nowhere else.
        leaves = continues & (guidable(si.bsdf(), self.smooth) if vertex is None else vertex.guidable)
        index = vertex.index if vertex is not None else None
        if self.rule == "mc":
            here = dr.select(leaves, self._record_index(si, bs, index, leaves), NO_RECORD)
            return self._mc_log.append(state, emitted, weight, continues, here, active)
        state.previous = self._record_td(state.previous, si, emitted, bs, weight, continues, leaves, active, index,
                                         vertex)
        return state

    def _record_index(self, si, bs, index, needed) -> mi.UInt32:
        """The record index of the direction sampled at ``si``, in the lanes ``needed``: the sampler's (``index``),
        looked up where it gave none (None; NO_RECORD at a vertex whose BSDF it does not guide, where a segment that
        arrives still reads Q)."""
        return known_or_found(index, needed, lambda lanes: self.record_table.index(si.p, si.to_world(bs.wo)))

    @dr.syntax
    def _record_td(self, previous, si, emitted, bs, weight, continues, leaves, active, index=None,
                   vertex=None) -> mi.UInt32:
        """SARSA / Expected SARSA: the target of the segment that led here (``previous``), and the entry of the
        segment that leaves (returned); ``index`` and ``vertex`` (:class:`GridVertex`) as sampling handed them over.
        A branch: packets with neither (unguided surfaces) skip it."""
        table = self.record_table
        pending = active & (previous != NO_RECORD)
        if pending | leaves:
            here = self._record_index(si, bs, index, pending | leaves)
            target = rgb_mean(emitted)
            onward = rgb_mean(weight) * dr.gather(mi.Float, table.q, table.entry(here), pending & continues)  # ∫ f·Q·cos
            known = mi.Bool(False)
            if dr.hint(self.rule == "expected_sarsa", mode="scalar"):
                bsdf = si.bsdf()
                pair = table.pair(table.cell(si.p), si.sh_frame.n * _arrival_side(si))
                known = pending & si.is_valid() & guidable(bsdf) & (table.memo(pair, pending).norm > 0)
                albedo = self._albedo(si, bsdf, known, vertex)
                onward = dr.select(known, albedo / dr.pi * dr.gather(mi.Float, table.value, pair, known), onward)
            target += dr.select(continues | known, onward, 0)
            table.accumulate(previous, target, pending)
            previous = dr.select(leaves, here, NO_RECORD)
        return previous

    @dr.syntax
    def _albedo(self, si, bsdf, known, vertex) -> mi.Float:
        """The mean albedo ρ of the BSDF at the lanes ``known``: what :meth:`locate` read at the vertex's guidable
        lanes, the BSDF's call at the others (a branch: most packets have none)."""
        if dr.hint(vertex is None or vertex.lambertian is None, mode="scalar"):
            albedo = rgb_mean(bsdf.eval_diffuse_reflectance(si, known))
        else:
            albedo = rgb_mean(vertex.lambertian.albedo)
            missing = known & ~vertex.guidable
            if missing:
                albedo = dr.select(missing, rgb_mean(bsdf.eval_diffuse_reflectance(si, missing)), albedo)
        return albedo

    def finish_paths(self, state) -> None:
        if self.rule == "mc":
            # Monte Carlo targets: the radiance each segment brought back, walked as soon as the paths end.
            walk_backward(state, lambda entry, L: self.record_table.accumulate(entry.target, rgb_mean(L),
                                                                               entry.target != NO_RECORD))
