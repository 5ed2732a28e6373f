"""The benchmark's cost breakdown and throughput limit on a tiny run (one timed pass, a 16x16 image)."""

import pytest

from guiding.bench import GRID_STAGES, OUTSIDE_SEQUENCE, TRACE_ONLY, TREE_STAGES, benchmark, target_table


def test_breakdown_table_shape():
    frame, breakdown = benchmark([("glossy-box", 1 / 16)], ["ours", "sdtree"], passes=1, pass_spp=1, max_depth=4)
    assert list(frame["method"]) == ["path", TRACE_ONLY, "brdf", "ours", "sdtree"]
    assert frame.set_index("method").loc[TRACE_ONLY, "share_of_trace_limit"] == pytest.approx(1)
    assert (frame.set_index("method").loc[["brdf", "ours", "sdtree"], "share_of_trace_limit"] > 0).all()
    stages = [stage for stage, _, _ in GRID_STAGES] + [stage for stage, _, _ in TREE_STAGES]
    assert list(breakdown["stage"]) == stages
    assert list(breakdown["method"]) == ["ours"] * len(GRID_STAGES) + ["sdtree"] * len(TREE_STAGES)
    full = breakdown.set_index("integrator").loc["ours"]
    assert full["ratio_to_brdf"] == frame.set_index("method").loc["ours", "ratio_to_brdf"]
    # The increments of the sequence add up to each method's last stage (the first is counted from brdf); a stage
    # outside it is counted from the method itself.
    for method, rows in breakdown.groupby("method"):
        sequence = rows[~rows["stage"].isin(OUTSIDE_SEQUENCE)]
        assert abs(1 + sequence["increment_ratio"].sum() - sequence["ratio_to_brdf"].iloc[-1]) < 1e-9
        for _, row in rows[rows["stage"].isin(OUTSIDE_SEQUENCE)].iterrows():
            own = rows.set_index("integrator").loc[method, "ratio_to_brdf"]
            assert abs(own + row["increment_ratio"] - row["ratio_to_brdf"]) < 1e-9
    # The statistics variant supplies the guided share (zero: glossy-box has no guidable surface).
    assert frame.set_index("method").loc["ours", "guided_per_ray"] == 0
    # glossy-box is a scene with nothing to guide for ours (purely diffuse surfaces only), not for the SD-tree;
    # mirror-box (delta lobes only) for both.
    targets = target_table(frame, "cpu")
    nothing = targets[targets["target"].str.startswith("nothing to guide")]
    assert list(nothing["target"]) == ["nothing to guide: `ours` ≤ 1.05× `brdf`"]
    frame["scene"] = "mirror-box"
    nothing = target_table(frame, "cpu").query("target.str.startswith('nothing to guide')", engine="python")
    assert set(nothing["target"]) == {"nothing to guide: `ours` ≤ 1.05× `brdf`",
                                      "nothing to guide: `sdtree` ≤ 1.05× `brdf`"}
