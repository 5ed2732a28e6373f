"""The benchmark's cost breakdown and throughput limit on a tiny run (one timed pass, a 16x16 image), and the
parsing of its kernel-size and profile parts."""

import pandas as pd
import pytest

from guiding.bench.benchmark import (GRID_STAGES, OUTSIDE_SEQUENCE, TRACE_ONLY, TREE_STAGES, PassTiming, _guided_per_ray,
                           benchmark, breakdown_variants, interleaved_passes, paired_quartiles, target_table)
from guiding.bench.child import child_failure
from guiding.bench.instruments import HotRowsStage, instrumented_guide
from guiding.bench.cpu_profile import parse_report, profile_table, table_access_share
from guiding.errors import GuidingError
from guiding.bench.kernel_size import kernel_table, parse_disassembly
from guiding.guides.methods import make_guide
from guiding.scenes import load_scene


def test_tree_breakdown_samples_the_methods_own_trees():
    """The trees' ``[no record]`` stage samples the method's trees as they are at each of its passes (not trees of
    its own that stopped learning, coarser than the method's), and records and updates nothing itself."""
    from guiding.render.integrator import GuidedPathIntegrator

    scene = load_scene("cornell-box", 1 / 16)
    method = GuidedPathIntegrator(guide=make_guide("quadtree-grid"))
    [(_, name, view)] = [v for v in breakdown_variants("quadtree-grid", method.guide) if v[2] is not None]
    integrators = {"quadtree-grid": method, name: GuidedPathIntegrator(guide=view)}
    updates, update = [], method.guide.update
    method.guide.update = lambda spp_done: updates.append(spp_done) or update(spp_done)
    interleaved_passes(scene, integrators, passes=2, pass_spp=2, warmup=1)
    assert not view.records() and view._sampling is method.guide._sampling
    # The trees grew after each of the method's own passes (the quadtree grid updates after every pass), and only then.
    assert updates == [2, 4, 6]
    assert method.guide.stats()["dtree_nodes_total"] > 4 * method.guide.stats()["dtree_trees"]


def test_hot_rows_stage_only_where_a_drawn_bin_is_tried_by_rejection():
    """``[hot rows]`` times the rejection samplers' bins proposal with every vertex on the first pair's row, whose
    bins below the vertex's normal bin the in-bin rejection refuses; the inversion samplers would take them (paths
    below the surface, a third shorter), so they have no such stage, and the instrument refuses them."""
    def stages(method):
        return [stage for stage, _, _ in breakdown_variants(method, None)]

    assert all("hot rows" in stages(method) for method in ("ours", "ours-expected", "ours-plus"))
    assert all("hot rows" not in stages(method) for method in ("sarsa-hemi_inv", "sarsa-sphere_inv",
                                                               "ours-uniform-proposals"))
    for method in ("sarsa-hemi_inv", "ours-uniform-proposals"):
        with pytest.raises(ValueError, match="bins proposal"):
            instrumented_guide(method, HotRowsStage)


def _trained_on_two_pairs(guide):
    """``guide`` trained on one cell's random Q with two visited pairs of different normals: two rows of different
    distributions (the same tables for every guide of the same resolution)."""
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    table = guide.record_table
    table.set_bounds(mi.BoundingBox3f(mi.ScalarPoint3f(0), mi.ScalarPoint3f(1)))
    B = table.bins.count
    q = np.zeros(table.cells * B)
    q[:B] = np.random.default_rng(5).uniform(0, 10, B)
    table.acc_sum, table.acc_count = mi.Float64(q), mi.Float64(np.ones_like(q))
    pairs = table.pair(mi.UInt32(0, 0), mi.Vector3f([0, 0], [0, 1], [1, 0]))
    dr.scatter(table.visited, mi.UInt32(1), pairs)
    guide.update(spp_done=150)
    return pairs


def test_hot_rows_instrument_draws_and_looks_up_in_the_first_row():
    """With ``hot_rows``, a vertex whose pair has another row draws its bin from the first pair's row and reads the
    density of any bin there (the two reads the stage times); the guide itself reads its pair's own row. Two pairs of
    one cell with different normals: two rows of different distributions."""
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    from guiding.guides.grid.guide import GridGuide
    from guiding.guides.grid.vertex import SamplerVertex

    parameters = dict(spatial_resolution=2, directional_resolution=4, rule="sarsa", sampler="hemi_rej_plus",
                      proposal="bins")
    guides = {stage: kind(**parameters) for stage, kind in ((None, GridGuide), ("hot_rows", HotRowsStage))}
    pairs = {stage: _trained_on_two_pairs(guide) for stage, guide in guides.items()}
    table = guides[None].record_table
    np.testing.assert_array_equal(table.hemi_alias, guides["hot_rows"].record_table.hemi_alias)

    lanes = 4096
    second = int(np.argmax(np.array(table.memo(pairs[None], True).row)))      # the pair whose row is not the first
    pair = dr.gather(mi.UInt32, pairs[None], dr.full(mi.UInt32, second, lanes))
    memo = table.memo(pair, True)
    assert np.all(np.array(memo.row) == 1)
    k = dr.arange(mi.UInt32, lanes) % table.bins.count
    drawn = {}
    for stage, guide in guides.items():
        row = mi.UInt32(0) if stage else memo.row
        vertex = SamplerVertex(guided=mi.Bool(True), cell=mi.UInt32(0), side=mi.Float(1), pair=pair, memo=memo,
                               centre=table.normal_centre(pair))
        vertex.row = guide._pair_row(vertex)
        np.testing.assert_array_equal(guide.sampler.bin_density(vertex, k, True),
                                      table.hemi_density(pair, row, k, True))
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(1, lanes)
        draw = guide.sampler.proposal.draw(sampler, vertex, mi.Bool(True))
        np.testing.assert_array_equal(draw.density, table.hemi_density(pair, row, draw.bin, True))
        drawn[stage] = np.array(draw.bin)
    assert not np.array_equal(table.hemi_density(pair, 0, k, True), table.hemi_density(pair, 1, k, True))
    assert not np.array_equal(drawn[None], drawn["hot_rows"])


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
    # Zero: glossy-box has nothing ours guides, so its passes run without the guide (and its counters).
    assert frame.set_index("method").loc["ours", "guided_per_ray"] == 0
    # glossy-box has nothing to guide for ours (purely diffuse surfaces only), but glossy lobes for the SD-tree.
    assert frame.set_index("method")["nothing_to_guide"].to_dict() == {
        "path": False, TRACE_ONLY: False, "brdf": False, "ours": True, "sdtree": False}
    assert frame.set_index("method").loc["brdf", ["ratio_q25", "ratio_q75"]].tolist() == [1.0, 1.0]
    targets = target_table(frame, "cpu")
    nothing = targets[targets["target"].str.startswith("nothing to guide")]
    assert (nothing["pass_q25"] <= nothing["pass_q75"]).all()
    assert list(nothing["target"]) == ["nothing to guide: `ours` ≤ 1.05× `brdf`"]
    assert "`sdtree` ≤ 1.3× `brdf` per spp" in set(targets["target"])


def test_paired_quartiles_divide_each_pass_by_the_baselines_pass_of_the_same_index():
    """The spread of a ratio comes from passes paired by index (run seconds apart), not from the two methods'
    times sorted apart: a machine that slows both alike leaves every paired ratio at 2."""
    def passes(kernels):
        return [PassTiming(wall=k, kernel=k, compile=0.0, update=0.0, refine=0.0) for k in kernels]

    baseline = passes([1.0, 3.0, 2.0, 5.0, 4.0])
    assert paired_quartiles(passes([2.0, 6.0, 4.0, 10.0, 8.0]), baseline) == {"ratio_q25": 2.0, "ratio_q75": 2.0}
    # Paired ratios 5, 2, 1, 0.5, 0.2; sorted apart, the same times would give 1 five times.
    steady = passes([1.0, 2.0, 3.0, 4.0, 5.0])
    assert paired_quartiles(passes([5.0, 4.0, 3.0, 2.0, 1.0]), steady) == {"ratio_q25": 0.5, "ratio_q75": 2.0}


def test_guided_per_ray_sums_the_counted_passes():
    passes = [PassTiming(wall=1, kernel=1, compile=0, update=0, refine=0, rays=rays, guided=guided)
              for rays, guided in ((100, 30), (300, 10))]
    assert _guided_per_ray(passes, nothing_to_guide=False) == pytest.approx(40 / 400)
    assert _guided_per_ray(passes, nothing_to_guide=True) == 0
    assert _guided_per_ray([PassTiming(wall=1, kernel=1, compile=0, update=0, refine=0)], False) is None


@pytest.mark.parametrize("scene_name, guided", [("mirror-box", set()), ("glossy-box", {"ours-plus", "sdtree",
                                                                                       "quadtree-grid"}),
                                                ("cornell", {"ours", "ours-plus", "sarsa-sphere_inv", "sdtree",
                                                             "quadtree-grid"})])
def test_nothing_to_guide_comes_from_the_scenes_bsdfs(scene_name, guided):
    """Which methods have something to guide in a scene follows from the guides' own test of its BSDFs: nothing
    in the box of delta lobes, only glossy lobes (guided by the smooth guides) in glossy-box."""
    scene = load_scene(scene_name, 1 / 16)
    methods = ["ours", "ours-plus", "sarsa-sphere_inv", "sdtree", "quadtree-grid"]
    assert {m for m in methods if make_guide(m).guides_any(scene)} == guided


def test_disassembly_log_is_split_into_kernel_modules():
    log = "\n".join(["jit_var_new(): r1", "jit_llvm_disasm(): ========== 0 ==========",
                     "jit_llvm_disasm(): 0x00000000   push\trbp",
                     "jit_llvm_disasm(): 0x00000001   vpgatherdd\tzmm2 {k2}, zmmword ptr [rax + 4*zmm0]",
                     "jit_llvm_disasm(): 0x00000002   ret",
                     "jit_llvm_disasm(): ========== 1 ==========", "jit_llvm_disasm(): 0x00000000   ret",
                     "jit_llvm_disasm(): ...", "jit_llvm_disasm(): ========== 0 ==========",
                     "jit_llvm_disasm(): 0x00000000   ret"])
    assert parse_disassembly(log) == [[(3, 1), (1, 0)], [(1, 0)]]


PERF_REPORT = """\
# Samples: 10K of event 'cpu-clock'
# Overhead        Period  Shared Object
# ........  ............  ...........................................
#
    65.27%    1686500000  [JIT] tid 5751
    27.95%     722250000  libembree3.so
     4.08%     105500000  libpython3.11.so.1.0
     0.95%      24500000  libdrjit-core.so
     0.73%      19000000  [kernel.kallsyms]
     0.37%       9500000  _drjit_ext.cpython-311-x86_64-linux-gnu.so
     0.01%        250000  libgfortran-040039e1-0352e75f.so.5.0.0
"""


def test_perf_report_is_grouped_by_code():
    """``bench --part profile`` groups perf's shared objects: Dr.Jit's compiled kernels, Embree, the Dr.Jit runtime
    (its Python bindings included), Python, the operating system, and the rest; periods are nanoseconds."""
    seconds = parse_report(PERF_REPORT)
    assert seconds == pytest.approx({"jit_kernels": 1.6865, "embree": 0.72225, "llvm_compile": 0.0,
                                     "drjit_runtime": 0.034, "python": 0.1055, "os": 0.019, "other": 0.00025})


OBJDUMP = """\
    1000:\t62 d2 7d 49 92 24 88 \tvgatherdps (%rax,%zmm1,4),%zmm4{%k1}
    1007:\t62 b1 44 48 5f cf    \tvmaxps %zmm23,%zmm7,%zmm1
    100d:\t62 f1 7c 48 28 44 24 \tvmovaps 0x700(%rsp),%zmm8
    1014:\t1c 
    1015:\t62 f1 7c 48 59 c1    \tvmulps %zmm1,%zmm0,%zmm0
    101b:\tc5 79 29 28          \tvmovapd %xmm13,(%rax)
    101f:\t4c 8d a4 24 00 2d 00 \tlea    (%rax,%rbx,4),%r12
    1026:\t62 f1 7c 48 58 c1    \tvaddps %zmm1,%zmm0,%zmm0
"""


def test_kernel_samples_at_table_accesses():
    """A sample counts as a table access at a gather, a load or store through a computed address, or the instruction
    after one (where a timer sample waiting on it lands); not at stack spills, ``lea`` or arithmetic."""
    samples = {0x1000: 1, 0x1007: 10, 0x100d: 100, 0x1015: 1000, 0x101b: 10000, 0x101f: 100000, 0x1026: 1000000,
               0x1014: 7}      # not an instruction's address: not counted
    assert table_access_share(samples, OBJDUMP) == (1 + 10 + 10000 + 100000, 1111111)


def test_fixed_passes_split_into_kernels_updates_and_the_rest():
    """`bench --part pass-schedule` splits a render's counted seconds (compilation left out) into the kernels'
    execution, the updates, and the rest of the passes; the three add up to the counted seconds."""
    from guiding.bench.benchmark import _pass_parts
    from guiding.render.progressive import PassStats

    passes = [PassStats(0, 8, 8, seconds=0.05, update_seconds=0.02, compile_seconds=0.01, kernels_launched=2,
                        kernels_compiled=1, hit_rate=0.5, kernel_seconds=0.03),
              PassStats(1, 8, 16, seconds=0.04, update_seconds=0.015, compile_seconds=0.004, kernels_launched=2,
                        kernels_compiled=0, hit_rate=0.5, kernel_seconds=0.03)]
    parts = _pass_parts(passes)
    assert parts == pytest.approx({"kernel": 0.06, "update": 0.035, "rest": 0.016})
    assert sum(parts.values()) == pytest.approx(sum(p.counted_seconds for p in passes))


def test_a_failed_child_is_told_in_one_line():
    """A benchmark child's failure reaches the user as its last line (the exception), not its whole log."""
    log = "Traceback (most recent call last):\n  File \"x.py\", line 1\nValueError: bad scale\n\n"
    error = child_failure("profile run of 'ours' on cornell-box", log)
    assert str(error) == "profile run of 'ours' on cornell-box failed: ValueError: bad scale"
    assert str(child_failure("kernel-size run", "")) == "kernel-size run failed: no message"


def test_profile_without_perf_is_one_line(monkeypatch):
    monkeypatch.setattr("shutil.which", lambda name: None)
    with pytest.raises(GuidingError, match="needs Linux perf on the PATH"):
        profile_table([("cornell-box", 0.0625)], ["ours"], passes=1)


def test_a_guided_kernel_holds_more_instructions_than_brdfs():
    """The count comes from the disassembly of kernels compiled in a fresh process; the grid guide's bounce adds its
    lookup, sampler and recording to the BSDF sampling it still does."""
    frame = kernel_table([("cornell-box", 1 / 16)], ["sarsa-sphere_inv"]).set_index("method")
    assert frame.loc["brdf", "instructions"] > 1000
    assert frame.loc["sarsa-sphere_inv", "ratio_to_brdf"] > 1.2


def test_a_missed_target_names_the_part_of_the_bounce_its_time_goes_to():
    """The Targets table names, for a missed cost ratio, the stages of the same run's breakdown up to the method
    itself (not the instruments after it) and the largest of them, and what the method saves with one alias row
    for all its vertices; for the update share, the update's time."""
    frame = pd.DataFrame([
        {"scene": "box", "method": "brdf", "ratio_to_brdf": 1.0, "nothing_to_guide": False, "update_share": 0.0,
         "share_of_trace_limit": 0.7, "ratio_to_path": 0.9, "refine_share": 0.0},
        {"scene": "box", "method": "ours", "ratio_to_brdf": 1.5, "ratio_q25": 1.4, "ratio_q75": 1.7,
         "nothing_to_guide": False, "update_share": 0.05,
         "update_ms": 12.5, "memo_pairs": 400, "kernel_ms_per_spp": 30.0, "share_of_trace_limit": 0.5,
         "ratio_to_path": 1.3, "refine_share": 0.0}])
    stages = [("classify", 1.1, 0.1), ("+sample", 1.3, 0.2), ("+pdf", 1.35, 0.05), ("+record", 1.5, 0.15),
              ("+statistics", 2.4, 0.9), ("bsdf paths", 2.45, 0.95), ("hot rows", 1.375, -0.125)]
    breakdown = pd.DataFrame([{"scene": "box", "method": "ours", "stage": stage,
                               "integrator": "ours" if stage == "+record" else f"ours[{stage}]",
                               "ratio_to_brdf": ratio, "increment_ratio": increment,
                               "rays_per_path": 5.5 if stage == "hot rows" else 5.0}
                              for stage, ratio, increment in stages])
    targets = target_table(frame, "cpu", breakdown).set_index("target")
    ratio = targets.loc["`ours` ≤ 1.2× `brdf` per spp (CPU)"]
    assert not ratio["met"]
    assert ratio["bottleneck"] == ("the bounce's parts, × brdf's time: classify +0.10, +sample +0.20, +pdf +0.05, "
                                   "+record +0.15; largest: +sample; with one alias row for all (ours[hot rows]): "
                                   "-0.12, -17% per ray")
    assert ratio[["pass_q25", "pass_q75"]].tolist() == [1.4, 1.7]
    update = targets.loc["grid update ≤ 2 % of pass time (`ours`)"]
    assert "12.5 ms per pass (400 visited pairs)" in update["bottleneck"]
    assert update[["pass_q25", "pass_q75"]].isna().all()     # quartiles belong to ratios to brdf only
    assert targets.loc["`brdf` ≤ 1.0× Mitsuba `path` per spp", "bottleneck"] == ""


def test_gathers_part_times_both_builds_of_every_method(monkeypatch):
    """``bench --part gathers``: each method (after ``path`` and ``brdf``) in both builds, the build chosen before
    each of its passes, and the target as it was restored afterwards."""
    from guiding import llvm_gathers
    from guiding.bench import gathers as gather_bench

    before = llvm_gathers.gathers_in_use()
    choices = []
    monkeypatch.setattr(gather_bench, "use_hardware_gathers",
                        lambda enable=None: choices.append(enable) or llvm_gathers.use_hardware_gathers(enable))
    frame = gather_bench.gathers_table([("cornell", 0.0625)], ["ours"], passes=1, pass_spp=1)
    # Three passes (two warm-up) of six builds, alternating; the target as it was afterwards.
    assert choices == [True, False] * 9
    assert list(frame["method"]) == ["path", "brdf", "ours"]
    assert (frame[["gather_ms_per_spp", "scalar_loads_ms_per_spp", "speed_up"]] > 0).all().all()
    assert frame.loc[frame["method"] == "brdf", "ratio_to_brdf_gathers"].item() == 1.0
    assert llvm_gathers.gathers_in_use() == before
