"""The grid guide's samplers (method.md §5): each a class with its draw and its density side by side, the record
tables it reads (``tables``: the ``needs_*`` arguments of :class:`~guiding.guides.grid.record.RadianceRecord`) and
the BSDF share of its mixture. They are used only at surfaces whose BSDF the guide guides; others are BSDF-sampled.

  :class:`SphereInversion`      ``sphere_inv``: a bin from the cell's distribution over the sphere, uniform in the bin;
  :class:`HemisphereInversion`  ``hemi_inv``: a bin from the memoised distribution of P·∫cos per (cell, normal bin),
                                uniform in the bin;
  :class:`HemisphereRejection`  ``hemi_rej``: the target ``P(ω)·cos⁺(ω, n_c)/N`` by rejection, with a proposal
                                (:class:`BinsProposal` or the paper's :class:`UniformProposal`);
  :class:`RejectionPlus`        ``hemi_rej_plus``, the paper's Rej+: the same with the share
                                ε_r = max((1−2c)/(2−2c), 0), c = ū/M, drawn apart.

Every sampler is a one-sample mixture with BSDF sampling, ``p = α·p_bsdf + (1 − α)·p_guide``, and reports that
density exactly. The BSDF share α bounds the weight ``f·cos/p`` of a diffuse vertex by ρ/α and gives every direction
with f·cos > 0 a positive density. For the inversion samplers α = ``bsdf_fraction`` (0.5; 0 is the paper's pure
sampler, whose weights are heavy-tailed: a few paths carried most of the image, results/bounce_weights.md). For the
rejection samplers α = 1 − (1 − u)·(1 − r): u = max(ε_r, ``min_bsdf_share``), where the paper mixes ε_r of a uniform
density into the target instead (ours draws it from the BSDF: a weight bound of 2ρ rather than 4ρ at ε_r = ½), and
r, the share of draws whose proposals were all rejected and that fall back to the BSDF's direction.

The rejection target uses the normal bin's centre ``n_c``: the memoised ``N = ∫ P·cos⁺(ω, n_c)`` is exact for it
at every true normal, so the samplers are exact by construction (with N taken at n_c but the cosine at the true
normal, each bounce was off by N(n_c)/N(n), a bias seen on the tilted Cornell box: README).
Target directions below the true surface have f = 0 and weight 0. The proposals:
  ``bins``     without a loop: a bin k from the pair's alias table of ``P_k·∫_k cos⁺``, then a direction of the bin
               ∝ ``cos(ω, n_c)``, the first of ``IN_BIN_PROPOSALS`` uniform proposals in the bin accepted against
               the bin's bound (most bins accept ~90 % of proposals, bins across the horizon less); r, the chance
               that all are rejected, is memoised per pair (``in_bin_miss``);
  ``uniform``  the paper's loop: uniform directions on the hemisphere of n_c, accepted if ``ξ·M < P·cos(ω, n_c)``;
               acceptance ``a = N/(2π·M)``, a few percent once P is peaked; ``r = (1 − a)^max_proposals``.
With ``sub_resolution`` R > 1 (``ours-plus``), a bin drawn by the ``bins`` proposal that the record has refined
(:mod:`~guiding.guides.grid.refinement`) gives its direction without rejection: a sub-bin from its learned
distribution π, a uniform direction in it, density within the bin ``π_j·R²/A`` (A the bin's solid angle) in place
of the in-bin rejection's; such bins add no miss share.

A sampler draws from the row of its vertex (``SamplerVertex.row``), which the guide chooses
(:meth:`~guiding.guides.grid.guide.GridGuide._pair_row`).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from guiding.guides import alias_rows
from guiding.guides.grid.counters import PassCounters
from guiding.guides.grid.record import IN_BIN_PROPOSALS, RadianceRecord
from guiding.guides.grid.vertex import SamplerVertex


@dataclass
class GuideDraw:
    """The guide's direction at a vertex (world), the lanes that take it (they chose the guide and, for the
    rejection samplers, had a proposal accepted), and, where the sampler drew a bin of its alias rows, the bin (with
    refinement ``bin·R² + sub-bin``) and the bin's density in the row (None otherwise)."""

    world: mi.Vector3f
    taken: mi.Bool
    bin: mi.UInt32 | None = None
    density: mi.Float | None = None


class GridSampler:
    """A way to draw the guide's directions at a vertex, mixed with BSDF sampling, and its exact density.

    Parameters:
      table: the guide's radiance record.
      parameters: the guide's :class:`~guiding.guides.parameters.GridParameters` (the mixture's shares, the cap of
        the rejection loop).
      counters: the guide's pass counters.
      proposal: how a rejection sampler draws its target (None for the others).
    """

    #: The record tables the sampler reads (``needs_*`` arguments of :class:`RadianceRecord`).
    tables: frozenset[str] = frozenset()
    #: Whether it draws its target through a proposal (the rejection samplers), and the one it takes by default.
    proposes = False
    default_proposal: type | None = None
    #: Whether its draws come from a bin of its alias rows (:class:`GuideDraw` has the bin and its density), whose
    #: density :meth:`bin_density` reads.
    draws_bins = False

    def __init__(self, table: RadianceRecord, parameters, counters: PassCounters, proposal=None):
        self.table = table
        self.parameters = parameters
        self.counters = counters
        self.proposal = proposal

    def classify(self, vertex: SamplerVertex) -> None:
        """Narrow ``vertex.guided`` to the lanes the sampler can guide, and set the BSDF share α of its mixture
        there (and what else its draw and density read)."""
        raise NotImplementedError

    def draw(self, sampler: mi.Sampler, vertex: SamplerVertex) -> GuideDraw:
        """The guide's direction in the guided lanes that choose the guide (``ξ ≥ α``; the others take the BSDF's)."""
        chosen = vertex.guided & (sampler.next_1d(vertex.guided) >= vertex.bsdf_share)
        return self._draw(sampler, vertex, chosen)

    def _draw(self, sampler: mi.Sampler, vertex: SamplerVertex, chosen: mi.Bool) -> GuideDraw:
        raise NotImplementedError

    def bin_density(self, vertex: SamplerVertex, fine_bin: mi.UInt32, active: mi.Bool) -> mi.Float:
        """The density of bin ``fine_bin`` (with refinement ``bin·R² + sub-bin``: the bin's) in the vertex's alias
        row (samplers that :attr:`draws_bins`)."""
        raise NotImplementedError

    def pdf(self, vertex: SamplerVertex, world: mi.Vector3f, bsdf_pdf: mi.Float, chosen_bin: mi.UInt32 = None,
            bin_density: mi.Float = None) -> mi.Float:
        """Density of the mixture ``α·p_bsdf + (1 − α)·p_guide`` at world direction ``world``, given ``p_bsdf``.

        ``chosen_bin``: the bin ``world`` was drawn in (or looked up in; with refinement ``bin·R² + sub-bin``),
        whose density is reported, and ``bin_density`` its density in the alias table where known (from the draw).
        Looking the direction up again can give a neighbour when it lies within rounding of a bin boundary, and a
        neighbour of negligible weight would report density 0 for a direction the guide drew."""
        raise NotImplementedError

    def _chosen_bin_density(self, vertex, world, chosen_bin, bin_density) -> tuple[mi.UInt32, mi.Float]:
        """The bin of ``world`` (``chosen_bin`` where given) and its density (``bin_density`` where given)."""
        k = self.table.fine_bin(world) if chosen_bin is None else chosen_bin
        if bin_density is None:
            bin_density = self.bin_density(vertex, k, vertex.guided)
        return k, bin_density


# ==================================================================== inversion
class _Inversion(GridSampler):
    """A bin drawn from an alias row, a uniform direction in it; BSDF share ``bsdf_fraction``."""

    draws_bins = True

    def classify(self, vertex: SamplerVertex) -> None:
        vertex.bsdf_share = mi.Float(self.parameters.bsdf_fraction)

    def _draw(self, sampler, vertex, chosen) -> GuideDraw:
        k, density = self._draw_bin(vertex, sampler.next_2d(chosen), chosen)
        return GuideDraw(self.table.bins.sample(k, sampler.next_2d(chosen)), chosen, k, density)

    def _draw_bin(self, vertex: SamplerVertex, u: mi.Point2f, active: mi.Bool) -> tuple[mi.UInt32, mi.Float]:
        """A bin drawn with ``u`` from the vertex's alias row, and its density there."""
        raise NotImplementedError

    def pdf(self, vertex, world, bsdf_pdf, chosen_bin=None, bin_density=None) -> mi.Float:
        _, bin_density = self._chosen_bin_density(vertex, world, chosen_bin, bin_density)
        share = vertex.bsdf_share
        return share * bsdf_pdf + (1 - share) * bin_density


class SphereInversion(_Inversion):
    """``sphere_inv``: a bin from the cell's alias row over the sphere (``cell_alias``), uniform in the bin."""

    tables = frozenset({"needs_cell_alias"})

    def _draw_bin(self, vertex, u, active):
        table = self.table
        return alias_rows.sample(table.cell_alias, vertex.cell, table.bins.count, u, active)

    def bin_density(self, vertex, fine_bin, active) -> mi.Float:
        return self.table.cell_density(vertex.cell, fine_bin, active)


class HemisphereInversion(_Inversion):
    """``hemi_inv``: a bin from the pair's alias row of ``P·∫cos`` (``hemi_alias``), uniform in the bin."""

    tables = frozenset({"needs_memo", "needs_hemi_alias"})

    def classify(self, vertex: SamplerVertex) -> None:
        _guide_memoised_pairs(vertex)
        super().classify(vertex)

    def _draw_bin(self, vertex, u, active):
        return self.table.hemi_sample(vertex.pair, vertex.row, u, active)

    def bin_density(self, vertex, fine_bin, active) -> mi.Float:
        return self.table.hemi_density(vertex.pair, vertex.row, fine_bin, active)


# ==================================================================== rejection
class BinsProposal:
    """The rejection target drawn without a loop: a bin from the pair's alias row of ``P_k·∫_k cos⁺``, then a
    direction of the bin ∝ ``cos(ω, n_c)`` by in-bin rejection (a refined bin: from its sub-bins, no rejection)."""

    name = "bins"
    tables = frozenset({"needs_hemi_alias", "needs_in_bin"})
    draws_bins = True

    def __init__(self, table: RadianceRecord, parameters, counters: PassCounters):
        self.table = table
        self.counters = counters

    def draw(self, sampler, vertex: SamplerVertex, searching: mi.Bool) -> GuideDraw:
        table = self.table
        refinement = table.refinement
        centre = vertex.centre
        k, density = table.hemi_sample(vertex.pair, vertex.row, sampler.next_2d(searching), searching)
        if refinement:
            entry = vertex.cell * table.bins.count + k
            refined = refinement.sampled(entry, searching)
            searching &= ~refined
        bound = dr.gather(mi.Float, table.in_bin_bound, table.normal_bin_flat(vertex.pair, k), searching)

        def propose(sampler, active):
            return table.bins.sample(k, sampler.next_2d(active))

        def accepts(sampler, candidate, active):
            return sampler.next_1d(active) * bound < dr.dot(candidate, centre)

        wo, accepted, proposals = _first_accepted(sampler, searching, propose, accepts, IN_BIN_PROPOSALS)
        self.counters.add_rejection(searching, proposals, accepted)
        if refinement:
            # A refined bin: its sub-bin from π, a uniform direction in it, nothing rejected.
            sub_wo, sub = refinement.sample(k, entry, sampler.next_2d(refined), sampler.next_2d(refined), refined)
            wo = dr.select(refined, sub_wo, wo)
            accepted |= refined
            k = k * table.fine + dr.select(refined, sub, 0)
        return GuideDraw(wo, accepted, k, density)

    def bin_density(self, vertex: SamplerVertex, fine_bin: mi.UInt32, active: mi.Bool) -> mi.Float:
        table = self.table
        k = fine_bin // table.fine if table.refinement else fine_bin
        return table.hemi_density(vertex.pair, vertex.row, k, active)

    def density(self, vertex: SamplerVertex, world: mi.Vector3f, k: mi.UInt32,
                bin_density: mi.Float) -> tuple[mi.Float, mi.Float]:
        """(r, the share of draws whose proposals were all rejected; the density of the accepted directions) at
        ``world``, drawn in (or looked up in) bin ``k`` of density ``bin_density``."""
        table = self.table
        refinement = table.refinement
        cosine = dr.maximum(dr.dot(world, vertex.centre), 0)
        guide_density = bin_density * cosine
        if refinement:
            k, sub = k // table.fine, k % table.fine
            entry = vertex.cell * table.bins.count + k
            refined = refinement.sampled(entry, vertex.guided)
            guide_density = dr.select(refined, bin_density * refinement.density(entry, sub, refined), guide_density)
        return vertex.memo.in_bin_miss, guide_density


class UniformProposal:
    """The paper's loop: uniform directions on the hemisphere of n_c, accepted if ``ξ·M < P·cos(ω, n_c)``, at most
    ``max_proposals``."""

    name = "uniform"
    tables = frozenset()
    draws_bins = False

    def __init__(self, table: RadianceRecord, parameters, counters: PassCounters):
        self.table = table
        self.counters = counters
        self.max_proposals = parameters.max_proposals

    def draw(self, sampler, vertex: SamplerVertex, searching: mi.Bool) -> GuideDraw:
        table = self.table
        centre = vertex.centre
        frame = mi.Frame3f(centre)

        def propose(sampler, active):
            return frame.to_world(mi.warp.square_to_uniform_hemisphere(sampler.next_2d(active)))

        def accepts(sampler, candidate, active):   # ξ·M < P·cos(ω, n_c)
            target = table.policy_at(vertex.cell, candidate, active) * dr.dot(candidate, centre)
            return sampler.next_1d(active) * vertex.memo.bound < target

        wo, accepted, proposals = _rejection_loop(sampler, mi.Bool(searching), propose, accepts, self.max_proposals)
        self.counters.add_rejection(searching, proposals, accepted)
        return GuideDraw(wo, accepted)

    def density(self, vertex: SamplerVertex, world: mi.Vector3f, k: mi.UInt32,
                bin_density: mi.Float | None) -> tuple[mi.Float, mi.Float]:
        """As :meth:`BinsProposal.density` (``bin_density`` is not used: the target reads the policy)."""
        table = self.table
        acceptance = vertex.memo.norm / (2 * dr.pi * vertex.memo.bound)
        miss_all = dr.power(1 - dr.minimum(acceptance, 1), self.max_proposals)
        cosine = dr.maximum(dr.dot(world, vertex.centre), 0)
        target = dr.gather(mi.Float, table.policy, vertex.cell * table.bins.count + k, vertex.guided)
        return miss_all, (1 - miss_all) * target * cosine / vertex.memo.norm


class HemisphereRejection(GridSampler):
    """``hemi_rej``: the target ``P(ω)·cos⁺(ω, n_c)/N`` drawn by its proposal (default: the paper's uniform
    proposals); BSDF share ``u = max(ε, min_bsdf_share)`` (ε = 0 here, the Rej+ share for :class:`RejectionPlus`),
    and the draws whose proposals were all rejected fall back to the BSDF."""

    tables = frozenset({"needs_memo"})
    proposes = True
    default_proposal = UniformProposal

    def classify(self, vertex: SamplerVertex) -> None:
        _guide_memoised_pairs(vertex)
        vertex.centre = self.table.normal_centre(vertex.pair, vertex.guided)
        vertex.bsdf_share = dr.maximum(self._target_share(vertex), self.parameters.min_bsdf_share)

    def _target_share(self, vertex: SamplerVertex) -> mi.Float:
        """The share of the target drawn apart, from the BSDF (none for hemi_rej)."""
        return mi.Float(0)

    @property
    def draws_bins(self) -> bool:
        return self.proposal.draws_bins

    def _draw(self, sampler, vertex, chosen) -> GuideDraw:
        return self.proposal.draw(sampler, vertex, chosen)

    def bin_density(self, vertex, fine_bin, active) -> mi.Float:
        return self.proposal.bin_density(vertex, fine_bin, active)

    def pdf(self, vertex, world, bsdf_pdf, chosen_bin=None, bin_density=None) -> mi.Float:
        if self.draws_bins:
            chosen_bin, bin_density = self._chosen_bin_density(vertex, world, chosen_bin, bin_density)
        else:
            chosen_bin = self.table.fine_bin(world)
        miss_all, guide_density = self.proposal.density(vertex, world, chosen_bin, bin_density)
        # The rejected share r falls back to the BSDF: α = 1 − (1 − u)·(1 − r).
        share = 1 - (1 - vertex.bsdf_share) * (1 - miss_all)
        return share * bsdf_pdf + (1 - vertex.bsdf_share) * guide_density


class RejectionPlus(HemisphereRejection):
    """``hemi_rej_plus``, the paper's Rej+: :class:`HemisphereRejection` with the share
    ε_r = max((1−2c)/(2−2c), 0), c = ū/M the mean of P·cos over its maximum, drawn apart (default: the ``bins``
    proposal)."""

    default_proposal = BinsProposal

    def _target_share(self, vertex: SamplerVertex) -> mi.Float:
        c = vertex.memo.norm / (2 * dr.pi * vertex.memo.bound)     # ū/M, the mean of P·cos over its maximum
        return dr.maximum((1 - 2 * c) / (2 - 2 * c), 0)


def _guide_memoised_pairs(vertex: SamplerVertex) -> None:
    """Leave the lanes whose pair has no memo yet (seen for the first time) to BSDF sampling for this pass."""
    vertex.guided &= vertex.memo.norm > 0


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


@dr.syntax
def _rejection_loop(sampler, searching, propose, accepts, cap: int) -> tuple[mi.Vector3f, mi.Bool, mi.UInt32]:
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
