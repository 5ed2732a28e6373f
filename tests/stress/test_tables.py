"""Tables: updates of both guides' tables from all-zero, huge, denormal, NaN and infinite accumulators.

A NaN, ±Inf or negative accumulator entry made a whole cell's policy NaN for the rest of the run (the grid's
accumulators are never cleared) and an SD-tree's probabilities NaN; an infinite vertex count would have split the
S-tree to depth 60. `RadianceRecord.update` (via `_fold_pass_into_q`) now drops such entries and clamps Q to 1e30
(`Q_LIMIT`), the SD-tree's `_pull` zeroes bad energies and counts; both report `dropped_entries` (and the grid
`clamped_entries`) in each pass's statistics.
"""

import numpy as np
import pytest

from guiding.guides.grid.record import RadianceRecord
from arrays import few
from hostile import HOSTILE_ENTRIES, hostile_grid, record_arrays, record_violations
from sdtree_parts import TREE_METHODS, forest_violations, hostile_tree

#: The grid guides whose tables cover every array an update builds: the cells' alias tables (sphere_inv), the
#: per-pair N, M and alias tables (hemi_inv's, and the bins proposal's with its fallback share), and Expected SARSA's V.
TABLE_METHODS = ("expected_sarsa-sphere_inv", "expected_sarsa-hemi_inv", "expected_sarsa-hemi_rej_plus",
                 "sarsa-hemi_rej")

#: Largest relative error allowed in the memo tables' cosine integrals. A rejection sampler reports the density
#: P·cos/N, so N's relative error is its relative bias: 1e-3 keeps that an order of magnitude below the ~1 %
#: standard errors of the unbiasedness checks (results/grid_unbiasedness.md), which could not see it.
COSINE_INTEGRAL_TOLERANCE = 1e-3


@pytest.mark.parametrize("min_exploration", [None, 0.0], ids=["default-floor", "paper-schedule"])
@pytest.mark.parametrize("method", TABLE_METHODS)
def test_grid_table_updates(method, min_exploration, figures):
    """Grid record: an update from all-zero, 1e30, 1e39, denormal, NaN, ±Inf or negative accumulators gives finite
    tables (policy > 0 summing to 1, alias tables with a density > 0 for every bin they draw, N > 0, M ≥ ū),
    counts what it dropped or clamped, and equals the update of the sanitised table (nothing propagates); with the
    default exploration floor, and with the paper's schedule (ε → 1e-10)."""
    updates = 0
    for kind, spec in HOSTILE_ENTRIES.items():
        hostile, expected = hostile_grid(method, kind, min_exploration)
        for spp_done in (8, 1000):       # first update, and a late one with a small ε
            where = f"{kind}, {spp_done} spp"
            stats = hostile.update(spp_done).stats
            expected.update(spp_done)
            problems = record_violations(hostile.record_table)
            assert not problems, f"{where}: {few(problems)}"
            want = {"dropped_entries": int(bool(spec.get("dropped"))) if spp_done == 8 else 0,
                    "clamped_entries": int(bool(spec.get("clamped")))}
            got = {key: stats.get(key) for key in want}
            assert got == want, f"{where}: counted {got}, expected {want}"
            for name, array in record_arrays(hostile.record_table).items():
                differ = np.count_nonzero(array != record_arrays(expected.record_table)[name])
                assert differ == 0, f"{where}: {name} differs from the sanitised table's in {differ} entries"
            updates += 1
    figures.update(kinds=list(HOSTILE_ENTRIES), updates_checked=updates)


@pytest.mark.parametrize("resolution", [1, 2, 3, 4, 8, 16, 32, 64])
def test_memo_cosine_integrals(resolution, figures):
    """Memo tables: for every normal bin and D = 1 … 64, the cosine integrals of all bins sum to ∫_H cos dω = π
    within 1e-3 (N's relative error is the rejection samplers' relative bias)."""
    record = RadianceRecord(1, resolution, needs_memo=True)
    integrals = np.array(record.cos_integral, dtype=np.float64).reshape(record.normal_bins.count, -1)
    error = np.abs(integrals.sum(axis=1) / np.pi - 1)
    worst = int(np.argmax(error))
    figures["max_relative_error"] = float(error.max())
    assert error[worst] <= COSINE_INTEGRAL_TOLERANCE, (
        f"D = {resolution}: the cosine integrals of normal bin {worst} sum to {integrals[worst].sum():.6g} instead "
        f"of π (relative error {error[worst]:.3g})")


@pytest.mark.parametrize("method", TREE_METHODS)
def test_sdtree_table_updates(method, figures):
    """SD-tree and quadtree grid: an update from all-zero, huge, denormal, NaN, ±Inf or negative energies and
    vertex counts gives finite D-tree probabilities (summing to 1 per node), counts what it dropped, keeps the
    S-tree bounded, and equals the update of the sanitised input."""
    checked = 0
    for kind, spec in HOSTILE_ENTRIES.items():
        hostile, expected, dropped = hostile_tree(method, kind)
        spp_done = getattr(hostile, "iteration_end_spp", 8)    # the SD-tree refines at an iteration's end
        stats = hostile.update(spp_done).stats
        expected.update(spp_done)
        problems = forest_violations(hostile._sampling)
        assert not problems, f"{kind}: {few(problems)}"
        assert stats.get("dropped_entries") == dropped, \
            f"{kind}: counted {stats.get('dropped_entries')} dropped entries, expected {dropped}"
        same = np.array_equal(np.array(hostile._sampling.prob), np.array(expected._sampling.prob))
        assert same, f"{kind}: the D-trees differ from those of the sanitised input"
        if hasattr(hostile, "stree"):
            assert hostile.stree.n_nodes == expected.stree.n_nodes, \
                f"{kind}: S-tree of {hostile.stree.n_nodes} nodes, {expected.stree.n_nodes} expected"
        if not spec:
            assert not np.array(hostile._sampling.has_energy).any(), f"{kind}: a tree without energy is guided"
        checked += 1
    figures.update(kinds=list(HOSTILE_ENTRIES), updates_checked=checked)


def test_bound_covers_every_bin_the_normal_bin_reaches():
    """M, the memo's bound, is the largest P·max_cos over every bin some normal of the normal bin reaches, also where
    the rejection samplers' alias rows hold fewer bins (those above the horizon of the normal bin's centre): a policy
    peaked on a bin only the normal bin's edge reaches sets M."""
    import drjit as dr
    import mitsuba as mi

    record = RadianceRecord(1, 4, 5, needs_memo=True, needs_hemi_alias=True, needs_in_bin=True)
    B, NB = record.bins.count, record.normal_bins.count
    max_cos = np.array(record.max_cos).reshape(NB, B)
    cos_integral = np.array(record.cos_integral).reshape(NB, B)
    edge_only = (max_cos > 0) & (cos_integral == 0)
    nb = int(np.flatnonzero(edge_only.any(axis=1))[0])
    k = int(np.flatnonzero(edge_only[nb])[0])
    policy = np.full(B, 1e-3, dtype=np.float32)
    policy[k] = 1
    record.policy = mi.Float(policy)
    dr.scatter(record.visited, mi.UInt32(1), mi.UInt32(nb))     # the pair of the only cell and normal bin nb
    record._update_memo()
    reached = policy * max_cos[nb]
    assert reached[k] > reached[cos_integral[nb] > 0].max()      # the edge bin, not one the rows hold, is the largest
    assert record.memo_columns()["bound"][nb] == pytest.approx(reached.max(), rel=1e-6)
