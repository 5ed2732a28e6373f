"""Targets: learning targets from extreme radiance, zero or tiny densities, and paths ending at every depth.

Emission above ~1.1e38 overflows float32 in `dr.mean` over RGB and reaches the grid's accumulators as Inf; such
entries are now dropped and counted (see `dropped_entries` in the figures), never propagated. The SD-tree already
skipped non-finite L/pdf values when splatting.
"""

import numpy as np
import pytest

from guiding.guides.directions import SphereBins
from arrays import few, vectors
from hostile import SyntheticPaths, floor_scene, grid_guide, record_violations
from sdtree_parts import TREE_METHODS, forest_violations, tree_guide


@pytest.mark.parametrize("rule", ["mc", "sarsa", "expected_sarsa"])
def test_grid_learning_targets(rule, figures):
    """Learning targets of MC, SARSA and Expected SARSA for paths ending at every depth 1-16: benign paths record
    exactly the hand-computed targets and counts; paths with emission up to 3e38 and pdfs down to 2e-38 (weights to
    2.5e37) record the right number of targets and the update leaves every table finite."""
    guide = grid_guide(f"{rule}-hemi_rej_plus", S=2, D=4)
    record = guide.record_table
    record.set_bounds(floor_scene().bbox())
    benign, hostile = SyntheticPaths.benign(), SyntheticPaths.hostile()
    benign.run(guide)
    hostile.run(guide)
    sums, counts = record.totals()
    B = record.bins.count
    cell = {name: int(np.array(record.cell(vectors(np.array([[*paths.position, 0.0]]))))[0])
            for name, paths in (("benign", benign), ("hostile", hostile))}
    assert cell["benign"] != cell["hostile"], "the benign and hostile paths share a grid cell"
    bins = np.array(SphereBins(4).index(SphereBins(4).centres()))
    for depth, (total, count) in benign.expected_grid_targets(rule).items():
        entry = cell["benign"] * B + bins[depth]
        assert counts[entry] == count and abs(sums[entry] - total) <= 1e-6 * total, \
            f"depth {depth + 1}: recorded (sum {sums[entry]}, count {counts[entry]}), expected ({total}, {count})"
    recorded = counts.reshape(-1, B)[cell["hostile"]].sum()
    assert recorded == hostile.records(), f"hostile paths recorded {recorded} targets, expected {hostile.records()}"
    stats = guide.update(spp_done=8).stats
    figures.update(dropped_entries=stats["dropped_entries"], clamped_entries=stats["clamped_entries"])
    problems = record_violations(record)
    assert not problems, few(problems)


@pytest.mark.parametrize("method", TREE_METHODS)
def test_sdtree_learning_targets(method, figures):
    """SD-tree recording (L/pdf into the leaves) for paths ending at every depth 1-16 with emission up to 3e38 and
    pdfs down to 2e-38 or 0: the vertex counts are exact and the D-trees built from them are finite."""
    guide = tree_guide(method)
    paths = SyntheticPaths.hostile()
    paths.run(guide)      # the backward walk splats as the paths finish
    counts = guide.recorded_sums()[1]
    recorded_vertices = paths.records()     # every vertex that continues has pdf > 0
    assert counts.sum() == recorded_vertices, f"{counts.sum()} vertices recorded, expected {recorded_vertices}"
    stats = guide.update(getattr(guide, "iteration_end_spp", 8)).stats
    figures["dropped_entries"] = stats.get("dropped_entries")
    problems = forest_violations(guide._sampling)
    assert not problems, few(problems)
