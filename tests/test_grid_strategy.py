"""The grid guide's names become classes in one place (`grid_strategy`): each rule, sampler and proposal, the tables
they need, and the combinations refused."""

import pytest

from guiding.guides import PROPOSALS, RULES, SAMPLERS
from guiding.guides.grid.strategy import grid_strategy
from guiding.guides.parameters import GridParameters


def expected_tables(rule: str, sampler: str, proposal: str | None) -> dict[str, bool]:
    """The tables of method.md §4 for each configuration: the cells' alias tables for sphere_inv, the memo tables for
    the hemisphere samplers, the pairs' alias rows for hemi_inv and for the rejection samplers' bins proposal (with
    the in-bin tables), V for Expected SARSA."""
    rejection = sampler in ("hemi_rej", "hemi_rej_plus")
    in_bin = rejection and proposal == "bins"
    return {"needs_cell_alias": sampler == "sphere_inv", "needs_memo": sampler != "sphere_inv",
            "needs_hemi_alias": sampler == "hemi_inv" or in_bin, "needs_in_bin": in_bin,
            "needs_value": rule == "expected_sarsa"}


@pytest.mark.parametrize("rule", RULES)
@pytest.mark.parametrize("sampler", SAMPLERS)
@pytest.mark.parametrize("proposal", (None, *PROPOSALS))
def test_every_configuration_needs_its_tables(rule, sampler, proposal):
    strategy = grid_strategy(GridParameters(rule=rule, sampler=sampler, proposal=proposal))
    rejection = sampler in ("hemi_rej", "hemi_rej_plus")
    default = "bins" if sampler == "hemi_rej_plus" else "uniform"
    resolved = (proposal or default) if rejection else None
    assert strategy.proposal_name == resolved
    assert strategy.table_needs() == expected_tables(rule, sampler, resolved)
    assert strategy.draws_bins_by_rejection == (resolved == "bins")


def test_refined_bins_only_with_the_bins_proposal():
    assert grid_strategy(GridParameters(sampler="hemi_rej", proposal="bins", sub_resolution=2)).draws_bins_by_rejection
    for sampler, proposal in (("hemi_inv", None), ("sphere_inv", "bins"), ("hemi_rej", None),
                              ("hemi_rej_plus", "uniform")):
        with pytest.raises(ValueError, match="refines the bins proposal"):
            grid_strategy(GridParameters(sampler=sampler, proposal=proposal, sub_resolution=2))
