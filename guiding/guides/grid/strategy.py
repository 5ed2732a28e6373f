"""Which learning rule and which sampler a grid guide runs: the one place where the names of
:class:`~guiding.guides.parameters.GridParameters` (``rule``, ``sampler``, ``proposal``) become classes
(:mod:`~guiding.guides.grid.rules`, :mod:`~guiding.guides.grid.samplers`). Needs no Mitsuba variant: the tables a
configuration needs are known before anything is built (:func:`guiding.guides.methods.table_bytes`).
"""

from __future__ import annotations

from dataclasses import dataclass

from guiding.guides.grid.rules import ExpectedSarsa, LearningRule, MonteCarlo, Sarsa
from guiding.guides.grid.samplers import (BinsProposal, GridSampler, HemisphereInversion, HemisphereRejection,
                                          RejectionPlus, SphereInversion, UniformProposal)

#: The ``needs_*`` arguments of :class:`~guiding.guides.grid.record.RadianceRecord`.
TABLES = ("needs_cell_alias", "needs_memo", "needs_hemi_alias", "needs_in_bin", "needs_value")


@dataclass(frozen=True)
class GridStrategy:
    """The classes of a grid guide's learning rule, sampler and (for the rejection samplers) proposal."""

    rule: type[LearningRule]
    sampler: type[GridSampler]
    proposal: type | None

    def table_needs(self) -> dict[str, bool]:
        """The tables the rule and the sampler read (the ``needs_*`` arguments of ``RadianceRecord``)."""
        needed = self.rule.tables | self.sampler.tables | (self.proposal.tables if self.proposal else frozenset())
        return {name: name in needed for name in TABLES}

    @property
    def draws_bins_by_rejection(self) -> bool:
        """Whether the sampler draws a bin from its pair's alias row, then a direction in it by rejection (the
        rejection samplers' ``bins`` proposal): the samplers with in-bin tables and refined bins."""
        return self.proposal is not None and self.proposal.draws_bins

    @property
    def proposal_name(self) -> str | None:
        return self.proposal.name if self.proposal else None

    def build(self, table, parameters, counters) -> tuple[LearningRule, GridSampler]:
        """The rule and the sampler over radiance record ``table`` (the guide's ``parameters`` and pass
        ``counters``)."""
        proposal = self.proposal(table, parameters, counters) if self.proposal else None
        return self.rule(table), self.sampler(table, parameters, counters, proposal)


def grid_strategy(parameters) -> GridStrategy:
    """The strategy ``parameters`` name: its rule, its sampler, and a rejection sampler's proposal (the sampler's
    own unless ``parameters.proposal`` names one; the inversion samplers take none). A ValueError for refined bins
    (``sub_resolution`` > 1) with a sampler that does not draw bins by rejection."""
    rule = {"mc": MonteCarlo, "sarsa": Sarsa, "expected_sarsa": ExpectedSarsa}[parameters.rule]
    sampler = {"sphere_inv": SphereInversion, "hemi_inv": HemisphereInversion, "hemi_rej": HemisphereRejection,
               "hemi_rej_plus": RejectionPlus}[parameters.sampler]
    proposal = None
    if sampler.proposes:
        proposal = ({"bins": BinsProposal, "uniform": UniformProposal}[parameters.proposal]
                    if parameters.proposal is not None else sampler.default_proposal)
    strategy = GridStrategy(rule, sampler, proposal)
    if parameters.sub_resolution > 1 and not strategy.draws_bins_by_rejection:
        raise ValueError(f"sub_resolution > 1 refines the bins proposal of the rejection samplers, not "
                         f"{parameters.sampler} ({strategy.proposal_name or 'no proposal'})")
    return strategy
