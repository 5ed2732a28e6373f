"""Learning rules record the targets of method.md §3, checked against hand-computed values on a three-vertex path."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from guiding.guides.alias_rows import SLOT_FIELDS
from guiding.guides.grid.guide import GridGuide, GridVertex
from guiding.guides.grid.record import PAIR_FIELDS
from guiding.guides.vertex_log import NO_RECORD

ALBEDO = 0.6


@pytest.fixture(scope="module")
def floor():
    """A diffuse floor (z = 0, normal +z) over [-2, 2]²: three rays straight down give three vertices."""
    return mi.load_dict({"type": "scene", "floor": {
        "type": "rectangle", "to_world": mi.ScalarTransform4f().scale([2, 2, 1]),
        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": ALBEDO}}}})


def _vertex(scene, x, y):
    return scene.ray_intersect(mi.Ray3f(mi.Point3f(x, y, 1), mi.Vector3f(0, 0, -1)))


def _direction(x, y, z):
    bs = dr.zeros(mi.BSDFSample3f, 1)
    bs.wo = dr.normalize(mi.Vector3f(x, y, z))
    return bs


def _run_path(guide, scene, continue_last=False):
    """Vertices v1 → v2 → v3: v1 emits nothing, v2 emits 0.1 (grey), v3 emits (1, 2, 3) and ends the path.

    Returns the (cell, bin) indices of the segments v1→v2 and v2→v3.
    """
    record = guide.record_table
    record.set_bounds(scene.bbox())
    vertices = [_vertex(scene, -1.5, -1.5), _vertex(scene, 0.5, 0.5), _vertex(scene, 1.5, -0.5)]
    directions = [_direction(0.3, 0.2, 0.9), _direction(-0.5, 0.1, 0.8), _direction(0.1, 0.1, 1.0)]
    emitted = [mi.Color3f(0), mi.Color3f(0.1), mi.Color3f(1, 2, 3)]
    weights = [mi.Color3f(0.5), mi.Color3f(0.8, 0.4, 0.6), mi.Color3f(0)]
    continues = [mi.Bool(True), mi.Bool(True), mi.Bool(continue_last)]
    state = guide.new_paths(1, 16)
    for si, bs, le, w, go in zip(vertices, directions, emitted, weights, continues):
        state = guide.record(state, si, le, bs, w, go, mi.Bool(True))
    guide.finish_paths(state)
    indices = [record.index(si.p, si.to_world(bs.wo)) for si, bs in zip(vertices[:2], directions[:2])]
    return [int(i[0]) for i in indices], vertices


def _recorded(guide):
    """{index: (sum, count)} of every (cell, bin) that received a target."""
    record = guide.record_table
    sums, counts = record.totals()
    return {int(i): (sums[i], counts[i]) for i in np.flatnonzero(counts)}


def test_monte_carlo_walks_back_with_the_path_weights(floor):
    guide = GridGuide(spatial_resolution=4, directional_resolution=4, rule="mc", sampler="hemi_rej_plus")
    (first, second), _ = _run_path(guide, floor)
    expected_second = (1 + 2 + 3) / 3                                             # Le(v3)
    expected_first = np.mean(np.array([0.1] * 3) + np.array([0.8, 0.4, 0.6]) * [1, 2, 3])  # Le(v2) + w2·Le(v3)
    recorded = _recorded(guide)
    assert set(recorded) == {first, second}
    assert recorded[second] == pytest.approx((expected_second, 1))
    assert recorded[first] == pytest.approx((expected_first, 1))


def test_sarsa_bootstraps_from_q_at_the_next_vertex(floor):
    guide = GridGuide(spatial_resolution=4, directional_resolution=4, rule="sarsa", sampler="hemi_rej_plus")
    q_next = 2.5
    record = guide.record_table
    record.set_bounds(floor.bbox())
    indexer = GridGuide(spatial_resolution=4, directional_resolution=4, rule="sarsa", sampler="hemi_rej_plus")
    (first, second), _ = _run_path(indexer, floor)  # indices only
    dr.scatter(record.q, q_next, mi.UInt32(second))
    _run_path(guide, floor)
    recorded = _recorded(guide)
    assert set(recorded) == {first, second}
    assert recorded[first] == pytest.approx((0.1 + np.mean([0.8, 0.4, 0.6]) * q_next, 1))
    assert recorded[second] == pytest.approx((2.0, 1))                            # the path ends: Le only


def test_sarsa_bootstraps_where_the_sampler_gave_no_index(floor):
    """The path loop hands ``record`` the record index the sampler took (a GridVertex); at a vertex whose BSDF the
    guide does not guide (glossy, say) the sampler gives none, and the segment that arrived there still bootstraps
    from Q at the direction taken there."""
    guide = GridGuide(spatial_resolution=4, directional_resolution=4, rule="sarsa", sampler="hemi_rej_plus")
    record = guide.record_table
    record.set_bounds(floor.bbox())
    v1, v2 = _vertex(floor, -1.5, -1.5), _vertex(floor, 0.5, 0.5)
    d1, d2 = _direction(0.3, 0.2, 0.9), _direction(-0.5, 0.1, 0.8)
    first, second = record.index(v1.p, v1.to_world(d1.wo)), record.index(v2.p, v2.to_world(d2.wo))
    q_next = 2.5
    dr.scatter(record.q, q_next, second)
    state = guide.new_paths(1, 16)
    state = guide.record(state, v1, mi.Color3f(0), d1, mi.Color3f(0.5), mi.Bool(True), mi.Bool(True),
                         GridVertex(mi.Bool(True), first))
    state = guide.record(state, v2, mi.Color3f(0.1), d2, mi.Color3f(0.8, 0.4, 0.6), mi.Bool(True), mi.Bool(True),
                         GridVertex(mi.Bool(False), mi.UInt32(NO_RECORD)))
    guide.finish_paths(state)
    recorded = _recorded(guide)
    assert set(recorded) == {int(first[0])}
    assert recorded[int(first[0])] == pytest.approx((0.1 + np.mean([0.8, 0.4, 0.6]) * q_next, 1))


def test_expected_sarsa_reads_the_memoised_integral(floor):
    guide = GridGuide(spatial_resolution=4, directional_resolution=4, rule="expected_sarsa", sampler="hemi_rej_plus")
    record = guide.record_table
    record.set_bounds(floor.bbox())
    v2 = _vertex(floor, 0.5, 0.5)
    pair = record.pair(record.cell(v2.p), mi.Vector3f(0, 0, 1))
    integral = 3.0
    dr.scatter(record.value, integral, pair)
    dr.scatter(record.pair_memo, 1.0, PAIR_FIELDS * pair)  # N > 0: marks the memo as computed
    (first, second), _ = _run_path(guide, floor)
    recorded = _recorded(guide)
    assert recorded[first] == pytest.approx((0.1 + ALBEDO / np.pi * integral, 1), rel=1e-5)
    # v3 lies in a pair without a memo and ends the path: the target is its emission.
    assert recorded[second] == pytest.approx((2.0, 1))


@pytest.mark.parametrize("rule", ["mc", "sarsa"])
def test_segment_that_is_not_traced_records_nothing(floor, rule):
    """A guided direction below the surface (weight 0, path ends) leaves its own (cell, bin) untouched."""
    guide = GridGuide(spatial_resolution=4, directional_resolution=4, rule=rule, sampler="hemi_rej_plus")
    record = guide.record_table
    record.set_bounds(floor.bbox())
    si = _vertex(floor, 0.0, 0.0)
    below = _direction(0.2, 0.0, -1.0)
    state = guide.new_paths(1, 16)
    state = guide.record(state, si, mi.Color3f(0), below, mi.Color3f(0), mi.Bool(False), mi.Bool(True))
    guide.finish_paths(state)
    assert _recorded(guide) == {}


def test_running_mean_and_exploration():
    guide = GridGuide(spatial_resolution=1, directional_resolution=1, rule="sarsa", sampler="sphere_inv")
    record = guide.record_table
    record.acc_sum = mi.Float64([6.0, 0.0])
    record.acc_count = mi.Float64([3.0, 0.0])
    guide.update(spp_done=100)                          # ε = 0.1
    q = record.q.numpy()
    assert q == pytest.approx([2.0, 0.0])
    shifted = np.array([2.0, 0.0]) + 1e-6
    expected = 0.9 * shifted / shifted.sum() + 0.1 / 2
    assert record.policy.numpy() == pytest.approx(expected, rel=1e-6)
    density = np.array(record.cell_alias).reshape(-1, SLOT_FIELDS)[:, 2]     # each bin's, as sphere_inv draws it
    assert density * record.bins.solid_angle == pytest.approx(expected, rel=1e-6)


@pytest.mark.parametrize("method", ["sarsa-sphere_inv", "sarsa-hemi_inv", "ours", "ours-no-rejopt", "ours-expected"])
def test_guiding_starts_at_the_second_pass(cornell, method):
    """Pass 0 samples the BSDF only; pass 1 already guides (the hemisphere samplers' memo covers pass 0's pairs)."""
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.guides.methods import make_guide
    from guiding.render.driver import render_pass

    guide = make_guide(method, statistics=True)
    integrator = GuidedPathIntegrator(guide=guide)
    guide.prepare(cornell)
    guided = []
    for index in range(2):
        render_pass(cornell, integrator, 0, index, 4)
        guided.append(guide.update(4 * (index + 1)).stats["guided_samples"])
    assert guided[0] == 0 and guided[1] > 0, guided


def test_statistics_counters_only_when_asked_for(cornell):
    """The per-pass counters (atomics on every bounce) are off by default: the update reports no counter figures,
    and the pass's kernel has no counter atomics; ``statistics=True`` brings them back."""
    from guiding.render.driver import render_pass
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.guides.methods import make_guide

    for statistics in (False, True):
        guide = make_guide("ours", statistics=statistics)
        integrator = GuidedPathIntegrator(guide=guide)
        guide.prepare(cornell)
        for index in range(2):
            render_pass(cornell, integrator, 0, index, 2)
            assert not statistics or guide.counters.arrays
            stats = guide.update(2 * (index + 1)).stats
        counted = {"guided_samples", "invalid_share", "acceptance_rate", "proposals_per_sample"} & set(stats)
        assert counted == (set() if not statistics else {"guided_samples", "invalid_share", "acceptance_rate",
                                                         "proposals_per_sample"}), (statistics, stats)
        assert (guide.counters.arrays == {}) == (not statistics)
        if statistics:
            assert stats["guided_samples"] > 0


def test_rebuild_growth_rebuilds_geometrically_and_keeps_every_target():
    """With ``rebuild_growth`` g the record is rebuilt at the next multiple of the largest power of two ≤ g × the
    spp of its last rebuild; the targets of the passes in between are folded in at the next rebuild, none lost."""
    guide = GridGuide(spatial_resolution=1, directional_resolution=1, rule="sarsa", sampler="sphere_inv",
                      rebuild_growth=0.5)
    record = guide.record_table
    rebuilt = []
    for spp_done in range(8, 89, 8):
        record.accumulate(mi.UInt32(0), mi.Float(spp_done), mi.Bool(True))
        stats = guide.update(spp_done).stats
        rebuilt.append(spp_done) if stats["rebuilt"] else None
        assert stats["memo_pairs"] == 0
    assert rebuilt == [8, 16, 24, 32, 48, 64]
    # Q is the mean of the targets up to the last rebuild (8 … 64); those of 72 … 88 wait in the pass's sums.
    assert record.q.numpy()[0] == pytest.approx(np.mean(np.arange(8, 65, 8)))
    sums, counts = record.totals()
    assert counts[0] == 11 and sums[0] == pytest.approx(np.arange(8, 89, 8).sum())


def test_stopped_training_freezes_the_record_at_its_next_rebuild():
    """Asked to stop between rebuilds, the guide learns on to its next rebuild (the targets recorded since the last
    one are folded in, none lost), then records nothing, rebuilds nothing and sets no more updates due; asked right
    after a rebuild, it stops at once."""
    guide = GridGuide(spatial_resolution=1, directional_resolution=1, rule="sarsa", sampler="sphere_inv",
                      rebuild_growth=0.5)
    record = guide.record_table
    for spp_done in (8, 16, 24, 32, 40):      # rebuilt at 8, 16, 24 and 32; 40 waits for 48
        record.accumulate(mi.UInt32(0), mi.Float(spp_done), mi.Bool(True))
        guide.update(spp_done)
    guide.stop_training()
    assert guide.records() and guide.update_due(40) == 48
    record.accumulate(mi.UInt32(0), mi.Float(48), mi.Bool(True))
    assert guide.update(48).stats["rebuilt"]
    assert not guide.records() and guide.update_due(48) is None
    assert record.q.numpy()[0] == pytest.approx(np.mean(np.arange(8, 49, 8)))
    record.accumulate(mi.UInt32(0), mi.Float(1000), mi.Bool(True))   # what a frozen guide is not asked to record
    assert not guide.update(64).stats["rebuilt"]
    assert record.q.numpy()[0] == pytest.approx(np.mean(np.arange(8, 49, 8)))

    at_rebuild = GridGuide(spatial_resolution=1, directional_resolution=1, rule="sarsa", sampler="sphere_inv")
    at_rebuild.update(8)
    at_rebuild.stop_training()
    assert not at_rebuild.records()


def test_learning_share_stops_training_and_lets_the_passes_grow(cornell):
    """With ``learning_share`` ½ of a 128-spp budget, the guide learns from the 8-spp passes up to 64 spp (``ours``
    rebuilds after every pass, so it stops there at once); the passes after that record nothing, rebuild nothing
    and grow."""
    from guiding.guides.methods import make_guide
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.render.progressive import Budget, render

    guide = make_guide("ours", learning_share=0.5)
    result = render(cornell, GuidedPathIntegrator(guide=guide), Budget(spp=128), seed=0, progress=False)
    assert result.training_stopped["spp"] == 64
    assert result.training_stopped["reason"] == "the guide learns from 0.5 of the budget"
    passes = [p.spp for p in result.passes]
    assert passes[:8] == [8] * 8 and max(passes[8:]) > 8 and sum(passes) == 128
    assert all(p.guide["rebuilt"] for p in result.passes[:8]) and not any(p.guide["rebuilt"] for p in result.passes[8:])
    assert not guide.records()
    with pytest.raises(ValueError, match="learning_share"):
        make_guide("ours", learning_share=0)


def test_learning_share_crossed_between_rebuilds_stops_at_the_next(cornell):
    """``ours-plus`` rebuilds at 64, 80, 96, … spp (``rebuild_growth`` ¼): with 8-spp passes and a share of 0.42 of
    200 spp (84), the share is crossed after the pass at 88 spp, between rebuilds; the guide learns on to the
    rebuild at 96, which folds in the passes since 80, and stops there."""
    from guiding.guides.methods import make_guide
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.render.progressive import Budget, render

    guide = make_guide("ours-plus", learning_share=0.42)
    budget = Budget(spp=200, growing_passes=False)
    result = render(cornell, GuidedPathIntegrator(guide=guide), budget, seed=0, progress=False)
    rebuilt = [p.spp_total for p in result.passes if p.guide["rebuilt"]]
    assert rebuilt[-3:] == [64, 80, 96]
    assert result.training_stopped["spp"] == 96 and not guide.records()


def test_ours_plus_rebuilds_less_often_than_the_paper():
    from guiding.guides.methods import make_guide

    assert make_guide("ours").rebuild_growth == 0
    assert make_guide("ours-plus").rebuild_growth > 0


def test_pair_memo_reads_back_every_visited_pairs_row():
    """The memo packs each visited pair's alias row number with N, M and the miss share (one packet gather): every pair
    reads back its own row, in the order the rows were built, and N > 0."""
    record = GridGuide(spatial_resolution=3, directional_resolution=3, rule="sarsa",
                       sampler="hemi_rej_plus").record_table
    visited = dr.arange(mi.UInt32, 0, dr.width(record.visited), 3)       # every third pair
    dr.scatter(record.visited, 1, visited)
    record.update(spp_done=8)
    memo = record.memo(visited, True)
    assert np.array_equal(np.array(memo.row), np.arange(dr.width(visited)))
    assert (np.array(memo.norm) > 0).all()


def test_a_guide_that_stops_learning_renders_paths_estimator_with_nee(cornell):
    """``ours-plus`` with next-event estimation learning from a quarter of each 128-spp render, then rendering the
    rest frozen (no recording, no rebuilds): the mean of its images is Mitsuba ``path``'s."""
    from guiding.experiments.validation import assert_means_agree, path_render_means
    from guiding.guides.methods import make_guide
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.render.progressive import Budget, render

    renders = 16
    means = []
    for seed in range(renders):
        props = mi.Properties()
        props["nee"] = True
        integrator = GuidedPathIntegrator(props, guide=make_guide("ours-plus", learning_share=0.25))
        result = render(cornell, integrator, Budget(spp=128), seed=seed, progress=False)
        assert result.training_stopped is not None and result.training_stopped["spp"] < 128
        means.append(result.image.mean(axis=(0, 1)))
    assert_means_agree(np.array(means), path_render_means(cornell, renders, 128))
