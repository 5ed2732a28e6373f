"""Memory: grid tables over the memory limit are refused before anything is allocated.

A grid method whose tables would exceed the limit (default 8 GiB, `--memory-limit`, `$GUIDING_MEMORY_LIMIT`) is
refused by `methods.check_method` before anything is allocated; `ours-S64-D64` used to start allocating 57 GiB.
The SD-tree's tables grow while it learns and are not checked up front.
"""

import time

import drjit as dr
import mitsuba as mi
import pytest

from guiding.errors import GuidingError
from guiding.guides import PROPOSALS, RULES, SAMPLERS
from guiding.guides.alias_rows import SLOT_BYTES
from guiding.guides.grid.guide import GridGuide
from guiding.guides.grid.record import RadianceRecord
from guiding.guides.grid.strategy import grid_strategy
from guiding.guides.grid.refinement import REFINE_VISITS
from guiding.guides.methods import MEMORY_LIMIT_VARIABLE, check_method, format_size, make_guide, table_bytes
from arrays import few
from command_line import one_error_line, run_cli

#: A table far beyond any memory limit: 64³ cells × 2·64² bins (the issue's example).
OVERSIZED_METHOD = "ours-S64-D64"


@pytest.mark.parametrize("rule", RULES)
def test_planned_table_size_is_what_built_tables_report(rule, figures):
    """The size planned before allocation (`RadianceRecord.planned_bytes`, the fixed tables) bounds what a built
    record reports, and once every (cell, normal bin) pair has been visited the record holds one alias row of
    `row_length` slots per pair in place of its placeholder row, for every sampler and proposal (the per-pair alias
    tables hold rows for visited pairs only). D = 4: a row holds 30 of the 32 bins (hemi_inv, the uniform proposal)
    or 24 (the bins proposal: those above the horizon of the normal bin's centre)."""
    for sampler in SAMPLERS:
        for proposal in PROPOSALS:
            guide = GridGuide(spatial_resolution=2, directional_resolution=4, rule=rule, sampler=sampler,
                              proposal=proposal)
            record = guide.record_table
            planned = RadianceRecord.planned_bytes(2, 4, **grid_strategy(guide.parameters).table_needs())
            fresh = record.memory_bytes()
            assert fresh <= planned, f"{sampler} ({proposal}): planned {planned} bytes, built {fresh}"
            if record.needs_pairs:
                record.visited = record.visited + 1
            record.update(spp_done=8)
            visited = record.memory_bytes()
            # every pair's row of row_length slots, in place of the placeholder row of B slots a fresh record holds
            pairs = record.cells * record.normal_bins.count
            assert not record.needs_pairs or record.row_length < record.bins.count
            rows = (pairs * record.row_length - record.bins.count) * SLOT_BYTES if record.needs_hemi_alias else 0
            assert fresh + rows == visited, f"{sampler} ({proposal}): fresh {fresh} + rows {rows} bytes, " \
                                            f"all pairs visited {visited}"
    figures["configurations"] = len(SAMPLERS) * len(PROPOSALS)


def test_refined_bins_are_planned_and_bounded():
    """ours-plus's refined bins (`BinRefinement`) are allocated up front: `table_bytes` plans them, the built
    record reports them, and no update grows them however many entries ask to be refined (at S = 2, D = 3 every
    bin holds 1/18 of its cell's policy, over the 5 % share: all 144 entries ask, once visited often enough)."""
    name = "ours-plus-S2-D3"
    record = make_guide(name, refine_capacity=5).record_table
    record.acc_count = dr.full(mi.Float64, REFINE_VISITS * record.fine, dr.width(record.acc_count))
    fresh = record.memory_bytes()
    assert fresh <= table_bytes(name)
    stats = []
    for spp_done in (8, 16):
        record.visited = record.visited + 1
        record.update(spp_done=spp_done)
        stats.append(record.refined_stats)
    assert stats[-1]["refined_bins"] == 5 and stats[-1]["refinements_refused"] == 139
    rows = (record.cells * record.normal_bins.count * record.row_length - record.bins.count) * SLOT_BYTES
    assert record.memory_bytes() == fresh + rows     # the visited pairs' rows only: the refinement did not grow


def test_visited_pairs_rows_over_the_limit_are_refused():
    """The per-pair alias rows grow with the visits: an update that would build more than the memory limit leaves
    for them stops with one line naming the pairs and the bytes, rather than exhausting the machine."""
    guide = make_guide("ours-S2-D3", memory_limit=table_bytes("ours-S2-D3") + 100)
    record = guide.record_table
    assert record.row_memory_limit == 100
    record.visited = record.visited + 1
    with pytest.raises(GuidingError, match=r"visited 1200 \(cell, normal bin\) pairs: their alias rows need"):
        record.update(spp_done=8)


def test_table_over_the_limit_is_refused(figures):
    """A table over the memory limit (ours-S64-D64) is refused with one line giving the size it needs,
    by `check_method` and by `make_guide`; a table exactly at the limit, or under a raised one, is allowed."""
    size = table_bytes(OVERSIZED_METHOD)
    figures.update(oversized_table=format_size(size), ours_table=format_size(table_bytes("ours")))
    with pytest.raises(GuidingError) as refusal:
        check_method(OVERSIZED_METHOD)
    message = str(refusal.value)
    assert "\n" not in message and format_size(size) in message, f"refusal message: {message!r}"
    with pytest.raises(GuidingError):
        make_guide(OVERSIZED_METHOD)
    with pytest.raises(GuidingError):
        check_method("ours", table_bytes("ours") - 1)
    check_method("ours", table_bytes("ours"))
    check_method(OVERSIZED_METHOD, 2 * size)


def test_memory_limit_from_the_environment(monkeypatch, figures):
    """`$GUIDING_MEMORY_LIMIT` sets the limit: 1M refuses `ours`."""
    monkeypatch.setenv(MEMORY_LIMIT_VARIABLE, "1M")
    figures["ours_table"] = format_size(table_bytes("ours"))
    with pytest.raises(GuidingError):
        check_method("ours")


def test_command_line_refuses_a_table_over_the_limit(tmp_path, figures):
    """The command line refuses a table over the limit with exit 2 and one line giving the size it needs, before
    it creates the output folder; `--memory-limit 1M` refuses `ours`."""
    out = tmp_path / "out"
    start = time.perf_counter()
    run = run_cli(["render", "--scene", "cornell", "--method", OVERSIZED_METHOD, "--spp", "1", "--out", str(out)])
    figures["cli_refusal_seconds"] = round(time.perf_counter() - start, 3)
    problems = one_error_line(run, f"needs {format_size(table_bytes(OVERSIZED_METHOD))}")
    assert not problems, few(problems)
    assert not out.exists(), "the output folder was created"
    run = run_cli(["render", "--scene", "cornell", "--method", "ours", "--spp", "1", "--out", str(out),
                   "--memory-limit", "1M"])
    assert not one_error_line(run, "over the memory limit of 1.0 MiB"), f"--memory-limit 1M: {run.errors}"
