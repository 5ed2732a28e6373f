"""Grid path guiding learned online (Kim & Kim 2021): a :class:`RadianceRecord`, a learning rule and a sampler.

:class:`GridGuide` composes one learning rule (:mod:`~guiding.guides.grid.rules`) and one sampler
(:mod:`~guiding.guides.grid.samplers`), chosen by their names in :class:`~guiding.guides.parameters.GridParameters`
(:func:`~guiding.guides.grid.strategy.grid_strategy`). The guide finds the vertex in the record, leaves the lanes it
does not guide to BSDF sampling, and mixes the sampler's direction with one BSDF sample (one BSDF call gives both
the sample and the BSDF's value and density at the guide's direction); the sampler decides which of the lanes it
guides, draws, and reports the mixture's density; the rule records what the paths see.

Pass 0 samples the BSDF only (the tables are empty); it marks the (cell, normal bin) pairs it visits, so the
hemisphere samplers guide from pass 1.

The bounce's steps are protected methods (:meth:`GridGuide._guided_sample`, :meth:`~GridGuide._draw_both`,
:meth:`~GridGuide._weigh`, :meth:`~GridGuide._pair_row`), so that the benchmark's instruments
(:mod:`guiding.bench.instruments`) can switch parts of it off by overriding them.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from guiding.guides.base import Guide, UpdateResult
from guiding.guides.grid.counters import PassCounters
from guiding.guides.grid.lambertian import LambertianBsdfs
from guiding.guides.grid.record import RadianceRecord
from guiding.guides.grid.samplers import GuideDraw
from guiding.guides.grid.strategy import grid_strategy
from guiding.guides.grid.vertex import GridVertex, SamplerVertex, arrival_side, guidable
from guiding.guides.vertex_log import NO_RECORD
from guiding.guides.parameters import GridParameters, with_overrides


@dataclass
class MixtureSample:
    """Both strategies' samples at the guided lanes of a vertex (:meth:`GridGuide._draw_both`), and then the
    mixture's density and weight at the direction each lane takes (:meth:`GridGuide._weigh`)."""

    guide: GuideDraw               # the guide's direction, and the lanes that take it
    guide_wo: mi.Vector3f          # the guide's direction in the local frame
    guide_value: mi.Spectrum       # the BSDF's f·cos at it
    guide_bsdf_pdf: mi.Float       # the BSDF's density at it
    bs: mi.BSDFSample3f            # the BSDF's own sample
    bsdf_weight: mi.Spectrum       # and its weight
    world: mi.Vector3f = None      # the direction taken (world)
    chosen_bin: mi.UInt32 = None   # its bin, where the sampler draws bins
    pdf: mi.Float = None           # the mixture's density at it
    weight: mi.Spectrum = None     # f·cos/pdf


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
        self.strategy = grid_strategy(p)
        self.name = name or f"{p.rule}-{p.sampler}"
        self.smooth = p.guided_bsdfs == "smooth"
        self.smooth_bsdf_share = p.smooth_bsdf_share
        self.rebuild_growth = p.rebuild_growth
        self._rebuilt_at = 0           # spp done at the record's last rebuild
        self._updated_at = 0           # spp done at the last update
        self._table_stats = {}         # memo pairs and refinement figures of the last rebuild
        self._bsdfs = LambertianBsdfs()   # the scene's Lambertian BSDFs (none known until prepare)
        self.record_table = RadianceRecord(
            p.spatial_resolution, p.directional_resolution, p.normal_resolution, **self.strategy.table_needs(),
            min_exploration=p.min_exploration, sub_resolution=p.sub_resolution, refine_share=p.refine_share,
            refine_capacity=p.refine_capacity)
        self.counters = PassCounters(p.statistics)
        self.rule, self.sampler = self.strategy.build(self.record_table, p, self.counters)
        self.trained = False
        self.learning = True           # False once training stopped (see stop_training)
        self._stopping = False         # the renderer stopped its training (learning_share)

    # ================================================================ host side
    def prepare(self, scene: mi.Scene) -> None:
        self.record_table.set_bounds(scene.bbox())
        self._bsdfs = LambertianBsdfs(scene, guided=lambda bsdf: bool(self.guides(mi.BSDFPtr(bsdf), True)[0]))
        self._rebuilt_at = 0      # a render that continues a trained guide counts its spp from 0: rebuild after a pass
        self._updated_at = 0
        self.learning, self._stopping = True, False     # and learns again

    def update(self, spp_done: int) -> UpdateResult:
        stats = self.counters.figures()
        if not self.learning or (self.trained and self.rebuild_growth > 0 and spp_done < self._next_rebuild()):
            stats.update(self._table_stats, rebuilt=False)     # the tables of the last rebuild, still in use
        else:
            table = self.record_table
            self._table_stats = {"memo_pairs": table.update(spp_done), **table.refined_stats}
            self._rebuilt_at = spp_done
            # With the entries the rebuild dropped or clamped (grid_record's sanitising).
            stats.update(self._table_stats, **table.sanitised, rebuilt=True)
            self.learning = not self._stopping
        self.trained, self._updated_at = True, spp_done
        self.counters.reset()
        return UpdateResult(stats)

    def update_due(self, spp_done: int) -> int | None:
        """After every pass while untrained or without ``rebuild_growth``, else at the next rebuild
        (:meth:`_next_rebuild`); never once training stopped."""
        if not self.learning:
            return None
        return self._next_rebuild() if self.trained and self.rebuild_growth > 0 else spp_done

    def _next_rebuild(self) -> int:
        """The spp of the next rebuild, from the last one alone: the next multiple of ``step``, the largest power of
        two ≤ ``rebuild_growth`` g × the spp of the last rebuild (g = 1/4: at 2^k·(1, 5/4, 3/2, 7/4)), so that the
        passes in between can be one pass of a power-of-two size."""
        step = 1 << max(int(self.rebuild_growth * self._rebuilt_at).bit_length() - 1, 0)
        return (self._rebuilt_at // step + 1) * step

    def records(self) -> bool:
        return self.learning

    def learning_share(self) -> float:
        return self.parameters.learning_share

    def stop_training(self) -> None:
        """Freeze the record now if the last update rebuilt it, else at its next rebuild: it then holds every target
        recorded (with ``rebuild_growth``, the passes since the last rebuild recorded targets not yet folded in)."""
        self._stopping = True
        if self.trained and self._rebuilt_at == self._updated_at:
            self.learning = False

    def trace_key(self) -> tuple:
        # learning as well as records(): the benchmark's stage guides stop recording without stopping learning
        return self.trained, self.records(), self.learning

    def stats(self) -> dict:
        table, p = self.record_table, self.parameters
        return {"rule": p.rule, "sampler": p.sampler, "proposal": self.strategy.proposal_name,
                "bsdf_fraction": p.bsdf_fraction, "min_bsdf_share": p.min_bsdf_share,
                "S": table.S, "D": table.bins.resolution,
                "bins": table.bins.count, "normal_bins": table.normal_bins.count,
                "sub_resolution": table.sub_resolution,
                "memory_bytes": table.memory_bytes()}

    # ============================================================== device side
    # ---------------------------------------------------------------- sampling
    def locate(self, si, bsdf, active) -> GridVertex:
        guidable_lanes = self.guides(bsdf, active)
        lambertian = None
        if self.trained and self.rule.reads_albedo:
            # Read here, before sampling's branches, so that the record reads it too: one BSDF call, not two.
            lambertian = self._bsdfs.vertex(bsdf, si, guidable_lanes)
        return GridVertex(guidable_lanes, lambertian=lambertian)

    def sample_and_eval(self, scene, sampler, si, bsdf, bsdf_ctx, active, wo, wo_active, vertex=None):
        """Where every BSDF next-event estimation evaluates is Lambertian and computed inline, its value towards the
        emitter comes from the albedo the guided sample reads too (one BSDF call per vertex, not two); elsewhere the
        BSDF is evaluated, then sampled."""
        if vertex is None or not (self.trained and self._bsdfs.inline_emitter_eval):
            return super().sample_and_eval(scene, sampler, si, bsdf, bsdf_ctx, active, wo, wo_active, vertex)
        if vertex.lambertian is None:
            # Emitter samples are drawn only at smooth BSDFs, and inline_emitter_eval means each is a guided one.
            vertex.lambertian = self._bsdfs.vertex(bsdf, si, vertex.guidable)
        value, bsdf_pdf = self._bsdfs.eval_pdf(vertex.lambertian, wo, wo_active)
        bs, weight = self.sample(scene, sampler, si, bsdf, bsdf_ctx, active, vertex)
        return value, bsdf_pdf, bs, weight

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
        """The guide where the sampler guides the vertex (its pair has a memo, say), one BSDF sample elsewhere."""
        vertex = self._vertex(si, bsdf, active, mark_visited=self.learning)   # for the next rebuild
        if vertex.guided:
            bs, weight, index = self._guided_sample(sampler, si, bsdf, bsdf_ctx, vertex, lambertian)
        else:
            bs, weight, index = self._unguided_sample(sampler, si, bsdf, bsdf_ctx, active & ~vertex.guided)
        return bs, weight, index

    def _unguided_sample(self, sampler, si, bsdf, bsdf_ctx, active):
        """One BSDF sample at a guidable vertex whose pair has no memo yet (its first visits), and its record index."""
        bs, weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(active), sampler.next_2d(active), active)
        return bs, weight, self._index_taken(si, si.to_world(bs.wo))

    def _guided_sample(self, sampler, si, bsdf, bsdf_ctx, vertex: SamplerVertex,
                       lambertian=None) -> tuple[mi.BSDFSample3f, mi.Spectrum, mi.UInt32]:
        """The one-sample mixture of BSDF sampling and the guide at the guided lanes: both samples
        (:meth:`_draw_both`), the mixture's density and weight at the direction taken (:meth:`_weigh`), and that
        direction as the bounce's sample. Returns the sample, its weight and its record index."""
        mixture = self._draw_both(sampler, si, bsdf, bsdf_ctx, vertex, lambertian)
        self._weigh(si, vertex, mixture)
        bs, taken = mixture.bs, mixture.guide.taken
        bs.wo = dr.select(taken, mixture.guide_wo, bs.wo)
        bs.pdf = mixture.pdf
        bs.sampled_type = dr.select(taken, mi.UInt32(mi.BSDFFlags.DiffuseReflection), bs.sampled_type)
        bs.eta = dr.select(taken, 1.0, bs.eta)
        return bs, mixture.weight, self._index_taken(si, mixture.world, vertex.cell, mixture.chosen_bin)

    def _draw_both(self, sampler, si, bsdf, bsdf_ctx, vertex: SamplerVertex, lambertian=None) -> MixtureSample:
        """The sampler's direction, and one BSDF call for the BSDF's sample and its value and density at the
        guide's direction (computed inline where the BSDF is Lambertian, :mod:`~guiding.guides.grid.lambertian`)."""
        guided = vertex.guided
        draw = self.sampler.draw(sampler, vertex)
        guide_wo = si.to_local(draw.world)
        guide_value, guide_bsdf_pdf, bs, bsdf_weight = self._bsdfs.eval_pdf_sample(
            bsdf, bsdf_ctx, si, guide_wo, sampler.next_1d(guided), sampler.next_2d(guided), guided, lambertian)
        return MixtureSample(draw, guide_wo, guide_value, guide_bsdf_pdf, bs, bsdf_weight)

    def _weigh(self, si, vertex: SamplerVertex, mixture: MixtureSample) -> None:
        """The direction each lane takes, its bin (where the sampler draws bins), the mixture's density there and
        the weight ``f·cos/pdf``, into ``mixture``; counted where ``statistics`` is on."""
        draw, bs, guided = mixture.guide, mixture.bs, vertex.guided
        value = dr.select(draw.taken, mixture.guide_value, mixture.bsdf_weight * bs.pdf)
        bsdf_pdf = dr.select(draw.taken, mixture.guide_bsdf_pdf, bs.pdf)
        mixture.world = dr.select(draw.taken, draw.world, si.to_world(bs.wo))
        bin_density = None
        if draw.bin is not None:
            bsdf_lanes = guided & ~draw.taken
            mixture.chosen_bin = dr.select(draw.taken, draw.bin, self.record_table.fine_bin(mixture.world))
            bin_density = dr.select(draw.taken, draw.density,
                                    self.sampler.bin_density(vertex, mixture.chosen_bin, bsdf_lanes))
        mixture.pdf = self.sampler.pdf(vertex, mixture.world, bsdf_pdf, mixture.chosen_bin, bin_density)
        mixture.weight = dr.select(mixture.pdf > 0, value / mixture.pdf, 0)
        self.counters.add("guided", 1, guided)
        self.counters.add("invalid", 1, guided & dr.all(mixture.weight == 0))

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

    def pdf(self, si, bsdf, bsdf_ctx, wo, active, bsdf_pdf=None, vertex=None) -> mi.Float:
        """Density (solid angle) with which :meth:`sample` draws local direction ``wo`` at ``si``. The sampler's
        vertex (cell, pair, memo) is looked up here again: ``locate``'s :class:`GridVertex` holds only the guided mask
        and the albedo."""
        bsdf_pdf = bsdf.pdf(bsdf_ctx, si, wo, active) if bsdf_pdf is None else bsdf_pdf
        if not self.trained:
            return bsdf_pdf
        vertex = self._vertex(si, bsdf, active, mark_visited=False)
        return dr.select(vertex.guided, self.sampler.pdf(vertex, si.to_world(wo), bsdf_pdf), bsdf_pdf)

    def _locate(self, si, bsdf, active, mark_visited=True) -> SamplerVertex:
        """The vertex's cell, arrival side, (cell, normal bin) pair and its memo; marks a pair without memo visited
        (the memoised ones stay marked: written at every vertex, the flags cost the cores' caches a line each)."""
        table = self.record_table
        vertex = SamplerVertex(guided=active & guidable(bsdf, self.smooth), cell=table.cell(si.p),
                               side=arrival_side(si))
        if table.needs_pairs:
            vertex.pair = table.pair(vertex.cell, si.sh_frame.n * vertex.side)
            vertex.memo = table.memo(vertex.pair, vertex.guided)
            if mark_visited:
                table.mark_visited(vertex.pair, vertex.guided & (vertex.memo.norm == 0))
        return vertex

    def _vertex(self, si, bsdf, active, mark_visited=True) -> SamplerVertex:
        """What the sampler reads at a vertex; decides which lanes are guided (the sampler's, and at a BSDF that is
        not purely diffuse, a BSDF share of at least ``smooth_bsdf_share``)."""
        vertex = self._locate(si, bsdf, active, mark_visited)
        if vertex.memo is not None:
            vertex.row = self._pair_row(vertex)
        self.sampler.classify(vertex)
        if self.smooth:
            glossy = ~guidable(bsdf)
            vertex.bsdf_share = dr.select(glossy, dr.maximum(vertex.bsdf_share, self.smooth_bsdf_share),
                                          vertex.bsdf_share)
        return vertex

    def _pair_row(self, vertex: SamplerVertex) -> mi.UInt32:
        """The row of ``hemi_alias`` the vertex draws from and reads densities in: its pair's."""
        return vertex.memo.row

    # ---------------------------------------------------------------- learning
    def new_paths(self, size: int, max_depth: int):
        return self.rule.new_paths(size, max_depth)

    def record(self, state, si, emitted, bs, weight, continues, active, vertex=None):
        # Only segments that leave a guidable surface are recorded: Q is read nowhere else.
        leaves = continues & (guidable(si.bsdf(), self.smooth) if vertex is None else vertex.guidable)
        index = vertex.index if vertex is not None else None
        return self.rule.record(state, si, emitted, bs, weight, continues, active, leaves, index, vertex)

    def finish_paths(self, state) -> None:
        self.rule.finish_paths(state)
