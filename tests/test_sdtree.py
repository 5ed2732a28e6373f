"""The SD-tree (Müller et al. 2017) and the quadtree grid in renders: guided images converge to Mitsuba's `path`
integrator, what the trees record, and the SD-tree's iterations, budgets and final-image combination."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from guiding.guides.trees.quadtree_grid import QuadtreeGridGuide
from guiding.guides.trees.sdtree import SDTreeGuide
from guiding.render.integrator import GuidedPathIntegrator
from guiding.experiments.validation import Z_LIMIT, pass_means, z_scores
from test_render import FakeClock
from tree_helpers import doubling_schedule


# ============================================================================================ rendering
@pytest.fixture(scope="module")
def door():
    from guiding.scenes import load_scene

    return load_scene("door-ajar", scale=0.1)


GUIDES = {"sdtree": lambda: SDTreeGuide(base_spp=16), "quadtree-grid": QuadtreeGridGuide}
#: door-ajar's light comes through a gap: a pass that finds it through a rare path is worth several others, bounded
#: (BSDF share 0.5) but seen. Over 72 seeds the SD-tree's standard error over 56 passes exceeded a tenth of the mean
#: in 3 (descents from the root) and 1 (from the cell tables); over 112 passes in none of 24 each (at most 0.071).
DOOR_PASSES, CORNELL_PASSES, SPP = 112, 24, 32


@pytest.fixture(scope="module")
def door_reference(door):
    return pass_means(door, mi.load_dict({"type": "path", "max_depth": 16}), passes=DOOR_PASSES, spp=SPP, seed=2)


@pytest.fixture(scope="module")
def cornell_reference(cornell):
    return pass_means(cornell, mi.load_dict({"type": "path", "max_depth": 16}), passes=CORNELL_PASSES, spp=SPP,
                      seed=2)


@pytest.mark.parametrize("method", GUIDES)
def test_guided_renders_match_mitsuba_path_on_door_ajar(door, door_reference, method):
    guide = GUIDES[method]()
    passes = DOOR_PASSES
    ours = pass_means(door, GuidedPathIntegrator(guide=guide), passes=passes, spp=SPP, seed=1)
    reference = door_reference
    z = z_scores(ours, reference)
    assert (z < Z_LIMIT).all(), f"z-scores {z}, means {ours.mean(0)} vs {reference.mean(0)}"
    # Able to fail: the standard error is a small part of the signal (fireflies make this scene noisy).
    se = ours.std(axis=0, ddof=1) / passes ** 0.5
    assert (se < 0.1 * reference.mean(axis=0)).all(), se / reference.mean(axis=0)
    stats = guide.stats()
    assert stats["dtree_nodes_max"] > 85       # the trees were refined from what the passes recorded
    if method == "sdtree":
        assert stats["iteration"] >= 3 and stats["stree_leaves"] > 1


VARIANTS = {"sdtree-learned": {"learn_bsdf_fraction": True}, "sdtree, stochastic filter": {"spatial_filter": "stochastic"}}


@pytest.mark.parametrize("method", [*GUIDES, *VARIANTS])
def test_guided_renders_match_mitsuba_path_on_cornell(cornell, cornell_reference, method):
    """A scene where guided passes are not firefly-ridden: a tighter check (standard error < 1 % of the mean)."""
    guide = GUIDES[method]() if method in GUIDES else SDTreeGuide(base_spp=16, **VARIANTS[method])
    ours = pass_means(cornell, GuidedPathIntegrator(guide=guide), passes=CORNELL_PASSES, spp=SPP, seed=1)
    reference = cornell_reference
    z = z_scores(ours, reference)
    assert (z < Z_LIMIT).all(), f"z-scores {z}, means {ours.mean(0)} vs {reference.mean(0)}"
    assert (ours.std(axis=0, ddof=1) / len(ours) ** 0.5 < 0.01 * reference.mean(axis=0)).all()


@pytest.mark.parametrize("method", GUIDES)
def test_trained_dtrees_point_at_the_light(cornell, method):
    """After a few passes, the D-trees of floor points send most samples towards the ceiling light: recording
    put the energy where the light comes from (directions, S-tree leaves and the backward walk agree)."""
    guide = GUIDES[method]()
    pass_means(cornell, GuidedPathIntegrator(guide=guide), passes=8, spp=16, seed=4)
    floor = np.array([[-0.7, 0.01, 0.6], [0.75, 0.01, -0.5], [-0.3, 0.01, 0.55], [0.3, 0.01, -0.5]])
    to_light = np.array([0, 1.98, 0]) - floor
    to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
    trees = guide._locate(mi.Point3f(*[mi.Float(floor[:, i].astype(np.float32)) for i in range(3)]), True).numpy()
    n = 20_000
    sample = mi.Point2f(np.random.default_rng(0).random((2, n)).astype(np.float32))
    cos30 = np.cos(np.radians(30))
    near = []
    for tree, axis in zip(trees, to_light):
        d, _ = guide._sampling.sample_dir(dr.full(mi.UInt32, int(tree), n), sample)
        near.append(((d.x.numpy() * axis[0] + d.y.numpy() * axis[1] + d.z.numpy() * axis[2]) > cos30).mean())
    # A uniform density puts 6.7 % of its samples within 30° of the light (the trees are noisy after 128 spp
    # of 32 x 32 pixels: one point may fall short, the mean may not).
    assert np.mean(near) > 0.35 and np.min(near) > 0.067, near


def test_dtree_vertex_counts_are_their_leaves_counts(cornell):
    """The vertex count of each D-tree (what splits the S-tree) is the sum of the counts its leaves recorded: read
    through each leaf's own tree (Forest.leaf_table), every vertex of the pass lands in a leaf, and no count is given
    to another tree."""
    guide = SDTreeGuide(base_spp=8)
    integrator = GuidedPathIntegrator(guide=guide)
    integrator.prepare(cornell)
    for spp_done in (8, 16, 24):       # iterations (0, 8) and (8, 24) refine the S-tree; no budget: it goes on
        integrator.render_pass(cornell, cornell.sensors()[0], seed=spp_done, spp=8)
        guide.update(spp_done)
    integrator.render_pass(cornell, cornell.sensors()[0], seed=7, spp=4)
    host = guide._recording_host
    assert host.n_trees > 8
    _, visits = guide.recorded_sums()
    tree, slot = host.leaf_table()[:2]
    assert visits.sum() > 1000 and visits[slot].sum() == visits.sum()
    _, counts = guide._pull()
    np.testing.assert_array_equal(counts, np.bincount(tree, weights=visits[slot], minlength=host.n_trees))


def test_quadtree_grid_records_the_leaf_its_descent_found(cornell):
    """The quadtree grid's sampling and recording D-trees are one, so a guided vertex records the leaf its mixture's
    descent found: the same pass recorded through a lookup of the recording tree (the SD-tree's way) fills the same
    leaves with the same energy (but for directions within rounding of a leaf's edge)."""
    import copy

    from guiding.experiments.testing import train

    guide = train(cornell, QuadtreeGridGuide(spatial_resolution=4), spp=16)
    # The same tree, but not the same object: the recording leaf is looked up.
    _assert_same_leaves_recorded(GuidedPathIntegrator(guide=guide), cornell, "_recording",
                                 (guide._sampling, copy.copy(guide._sampling)))


def test_sdtree_records_through_the_overlay_what_a_lookup_records(cornell):
    """The SD-tree finds a vertex's recording leaf from the sampling leaf its mixture's descent found
    (`Forest.overlay`): a pass records the same leaves with the same energy as the same pass recorded through a
    lookup of the recording tree (but for directions within rounding of a leaf's edge)."""
    guide = SDTreeGuide(base_spp=8)
    integrator = GuidedPathIntegrator(guide=guide)
    integrator.prepare(cornell)
    sensor = cornell.sensors()[0]
    for spp_done in (8, 16, 24):       # iterations (0, 8) and (8, 24); no budget: it goes on recording
        integrator.render_pass(cornell, sensor, seed=spp_done, spp=8)
        guide.update(spp_done)
    assert guide.records() and guide._recording_host.n_nodes != guide._sampling_host.n_nodes
    # Frozen passes (the integrator was prepared): without the overlay, the guide's arrays differ, and Dr.Jit
    # records the pass anew rather than replaying the overlay's kernel.
    _assert_same_leaves_recorded(integrator, cornell, "_overlay", (guide._overlay, None))


def _assert_same_leaves_recorded(integrator, scene, attribute: str, values: tuple):
    """One pass recorded with the attribute ``attribute`` of the integrator's guide set to each of ``values`` fills
    the same leaves with the same energy (but for directions within rounding of a leaf's edge)."""
    guide = integrator.guide
    recorded = []
    for value in values:
        setattr(guide, attribute, value)
        guide._reset_accumulators()
        integrator.render_pass(scene, scene.sensors()[0], seed=5, spp=4)
        recorded.append(guide.recorded_sums())
    (energy, counts), (other_energy, other_counts) = recorded
    assert counts.sum() > 1000 and counts.sum() == other_counts.sum()
    assert np.count_nonzero(counts != other_counts) <= 1e-3 * np.count_nonzero(counts)
    assert np.count_nonzero(energy != other_energy) <= 1e-3 * np.count_nonzero(energy)
    assert energy.sum() == pytest.approx(other_energy.sum(), rel=1e-4)


def test_progressive_render_statistics_and_one_kernel(cornell):
    from guiding.render.progressive import Budget, render

    guide = SDTreeGuide(base_spp=8)
    result = render(cornell, GuidedPathIntegrator(guide=guide), Budget(spp=128, pass_spp=8, growing_passes=False),
                    seed=3, combine="last")
    stats = [p.guide for p in result.passes]
    # The renderer hands the guide its 128-spp budget: iterations (0, 8), (8, 24), (24, 56) and a final (56, 128).
    assert [p.iteration_done for p in result.passes] == [True, False, True, False, False, False, True] + [False] * 9
    assert result.spp == 128 and result.spp_in_image == 72    # the image is the final iteration alone
    for key in ("stree_leaves", "dtree_nodes_mean", "dtree_nodes_max", "memory_bytes", "refine_seconds"):
        assert all(key in s for s in stats), key
    assert stats[-1]["stree_leaves"] > 1 and stats[-1]["dtree_nodes_max"] > 85
    # Refinement never recompiles the render; only the final iteration, which records nothing, has a kernel of its
    # own (pass 7, the first after 56 spp: compiled there unless Dr.Jit's disk cache already holds it).
    assert [p.kernels_compiled for p in result.passes[1:] if p.index != 7] == [0] * 14
    assert np.isfinite(result.image).all()


def test_budget_makes_the_last_iteration_run_to_the_end_without_learning(cornell):
    from guiding.render.progressive import Budget, render

    guide = SDTreeGuide(base_spp=8, budget_spp=64)
    assert doubling_schedule(guide.base_spp, guide.budget_spp) == [(0, 8), (8, 24), (24, 64)]
    result = render(cornell, GuidedPathIntegrator(guide=guide), Budget(spp=64, pass_spp=8, growing_passes=False),
                    seed=3)
    stats = [p.guide for p in result.passes]
    assert [p.iteration_done for p in result.passes] == [True, False, True] + [False] * 5
    assert [s["final_iteration"] for s in stats] == [False] * 2 + [True] * 6
    # The final iteration (passes after 24 spp: what a renderer keeps for Müller's final image) records nothing.
    assert guide.iteration_start_spp == 24 and guide.iteration_end_spp == 64 and not guide.records()
    # Its render kernels have no recording code: the accumulators, cleared by the refinement at 24 spp, stay empty.
    assert not any(sums.any() for sums in guide.recorded_sums())


def test_iterations_in_the_render_result(cornell):
    """Per-iteration statistics (stats.json's `iterations`): the schedule's spp ranges, the hit rate of their
    passes, and the structure of the trees each training iteration built."""
    from guiding.render.progressive import Budget, render

    guide = SDTreeGuide(base_spp=8)
    result = render(cornell, GuidedPathIntegrator(guide=guide), Budget(spp=128, pass_spp=8, growing_passes=False),
                    seed=3, combine="last")
    its = result.iterations
    assert [(it.spp_start, it.spp_end, it.passes) for it in its] == [(0, 8, 1), (8, 24, 2), (24, 56, 4), (56, 128, 9)]
    for it in its:
        mine = [p for p in result.passes if it.spp_start < p.spp_total <= it.spp_end]
        assert it.hit_rate == pytest.approx(sum(p.hit_rate * p.spp for p in mine) / it.spp)
        assert it.seconds == pytest.approx(sum(p.counted_seconds for p in mine))
        assert (it.variance is None) == (it.passes < 2)
    for it, end in zip(its[:3], (8, 24, 56)):   # training iterations: the refinement they ended with
        closing = next(p for p in result.passes if p.spp_total == end)
        assert closing.iteration_done and it.guide == closing.guide
        assert it.guide["refine_seconds"] > 0 and it.guide["iteration_start_spp"] == end
        for key in ("stree_leaves", "stree_max_depth", "dtree_nodes_total", "dtree_nodes_mean", "dtree_nodes_max",
                    "memory_bytes", "vertices_recorded"):
            assert key in it.guide, key
    assert its[2].guide["stree_leaves"] > its[0].guide["stree_leaves"]
    assert its[2].guide["dtree_nodes_max"] > its[0].guide["dtree_nodes_max"]
    assert [it.weight for it in its] == [0, 0, 0, 1]     # combine="last": the final iteration alone
    assert result.training_stopped["spp"] == 56      # the final iteration (the guide's schedule) records nothing
    summary = result.summary()
    assert [it["spp"] for it in summary["iterations"]] == [8, 16, 32, 72] and summary["combine"] == "last"


# ===================================================================================== seconds budgets
@pytest.mark.parametrize("seconds, stop_spp, final_spp", [
    # 1 ms per spp, iterations of 8, 16, 32, ... spp. With 0.5 s: after 248 spp (0.248 s) the next iteration
    # (256 spp, 0.256 s) would not fit in the 0.252 s left; passes of 8 spp go on until 0.504 s.
    (0.5, 248, 504),
    # With 0.6 s, it fits (0.256 <= 0.352); after 504 spp the next (512 spp) would not fit in 0.096 s.
    (0.6, 504, 600),
])
def test_seconds_budget_stops_training_when_the_next_iteration_would_not_fit(cornell, monkeypatch, seconds,
                                                                              stop_spp, final_spp):
    from guiding.render.progressive import Budget, render

    FakeClock(monkeypatch, cost_per_spp=1e-3)   # 1 ms per spp, and compilation free
    guide = SDTreeGuide(base_spp=8)
    result = render(cornell, GuidedPathIntegrator(guide=guide),
                    Budget(seconds=seconds, pass_spp=8, growing_passes=False), seed=1,
                    combine="last")
    assert result.training_stopped["spp"] == stop_spp
    assert result.training_stopped["seconds"] == pytest.approx(stop_spp * 1e-3)
    assert result.training_stopped["next_iteration_spp"] == stop_spp + 8
    assert result.spp == final_spp and not guide.records()
    # The iteration that ended at the stop runs to the end with the frozen guide: one image, nothing discarded.
    last = result.iterations[-1]
    assert (last.spp_start, last.spp_end) == ((stop_spp - 8) // 2, final_spp)
    assert result.spp_in_image == last.spp and last.weight == 1
    frozen = [p for p in result.passes if p.spp_total > stop_spp]
    assert frozen and not any(p.iteration_done for p in frozen)
    # Nothing recorded after the stop: the accumulators, cleared by the refinement there, stay empty.
    assert not any(sums.any() for sums in guide.recorded_sums())
    assert {p.guide["stree_leaves"] for p in frozen} == {result.passes[stop_spp // 8 - 1].guide["stree_leaves"]}


def test_seconds_budget_training_decisions_match_the_measured_times(cornell):
    """Real timings: every iteration boundary's decision, recomputed from the per-pass record (seconds per spp of
    the iteration that ended × the next iteration's base_spp·2^(k+1) spp, against the budget left)."""
    from guiding.render.progressive import Budget, render

    budget = Budget(seconds=1.5, pass_spp=8)
    guide = SDTreeGuide(base_spp=8)
    result = render(cornell, GuidedPathIntegrator(guide=guide), budget, seed=2, combine="last")
    counted, start, stop = 0.0, 0, None
    for i, p in enumerate(result.passes):
        counted += p.counted_seconds
        if p.iteration_done:
            ended = result.passes[start:i + 1]
            per_spp = sum(q.counted_seconds for q in ended) / sum(q.spp for q in ended)
            next_spp = 8 * 2 ** (p.guide["iteration"] + 1)
            if next_spp * per_spp > budget.seconds - counted:
                stop = i
                break
            start = i + 1
    if stop is None:   # every iteration was let start; the budget then ran out inside the last one
        assert result.training_stopped is None and guide.records()
    else:              # the iteration that ended there ran to the end with the frozen guide
        assert result.training_stopped["spp"] == result.passes[stop].spp_total and not guide.records()
        assert all(not p.iteration_done for p in result.passes[stop + 1:])
    first = result.passes[start]
    assert result.iterations[-1].spp_start == first.spp_total - first.spp
    assert result.spp_in_image == result.spp - result.iterations[-1].spp_start
    assert result.counted_seconds() >= budget.seconds > result.counted_seconds() - result.passes[-1].counted_seconds


# ============================================================================ inverse-variance combination
def test_inverse_variance_image_is_the_spp_weighted_mean_of_the_last_four_iterations(cornell):
    from guiding.experiments.sdtree_combination import iteration_images
    from guiding.render.progressive import Budget, render

    records = []
    guide = SDTreeGuide(base_spp=4)
    # Iterations of 4, 8, 16, 32, 64 and (to the end) 128 spp: passes 1, 2, 4, 8, 16, 32.
    result = render(cornell, GuidedPathIntegrator(guide=guide), Budget(spp=252, pass_spp=4), seed=6,
                    combine="inverse-variance",
                    on_pass=lambda stats, image: records.append((stats.spp, stats.guide["iteration"], image)))
    iterations = iteration_images(records)
    assert [it.spp for it in iterations] == [4, 8, 16, 32, 64, 128]
    weights = np.array([16, 32, 64, 128]) / 240
    expected = sum(w * it.image for w, it in zip(weights, iterations[-4:]))
    np.testing.assert_allclose(result.image, expected, rtol=1e-5, atol=1e-7)
    assert [it.weight for it in result.iterations] == pytest.approx([0, 0, *weights], rel=1e-12)
    assert [it.variance for it in result.iterations[1:]] == pytest.approx([it.variance for it in iterations[1:]],
                                                                          rel=1e-6)
    assert result.spp_in_image == 16 + 32 + 64 + 128
    # Able to fail: the combination is far from the last iteration alone.
    assert np.abs(result.image - iterations[-1].image).mean() > 100 * 1e-5 * np.abs(expected).mean()
    # The same render with combine="last" (the same passes) shows the last iteration alone.
    last = render(cornell, GuidedPathIntegrator(guide=SDTreeGuide(base_spp=4)), Budget(spp=252, pass_spp=4), seed=6,
                  combine="last")
    np.testing.assert_allclose(last.image, iterations[-1].image, rtol=1e-5, atol=1e-7)


def test_inverse_variance_weights_depend_on_the_schedule_alone(cornell):
    """Weights fixed before the images are drawn: renders of other seeds (other images, other variances) get the
    same weights, ∝ spp; the first iteration (BSDF sampling before the guide learned) gets none; and every snapshot
    weighs the running iteration by its spp so far."""
    from guiding.render.progressive import Budget, render

    renders = []
    for seed in (2, 3):
        snapshots = []
        result = render(cornell, GuidedPathIntegrator(guide=SDTreeGuide(base_spp=8)), Budget(spp=120, pass_spp=8),
                        seed=seed, snapshot=lambda spp, image, seconds, in_image: snapshots.append((spp, in_image)))
        renders.append((result, snapshots))
    (first, first_snapshots), (second, second_snapshots) = renders
    # Iterations of 8, 16, 32 and (to the end) 64 spp.
    expected = [(8, 0.0), (16, 16 / 112), (32, 32 / 112), (64, 64 / 112)]
    for result in (first, second):
        assert [(it.spp, it.weight) for it in result.iterations] == pytest.approx(expected, rel=1e-12)
    assert [it.variance for it in first.iterations[1:]] != [it.variance for it in second.iterations[1:]]
    # After 8 spp the first iteration is the image; later the learned ones so far, the running one included.
    assert first_snapshots == second_snapshots == [(8, 8), (16, 8), (32, 24), (64, 56), (120, 112)]


def test_inverse_variance_combination_matches_mitsuba_path(cornell, cornell_reference):
    """The image means of independent renders agree with Mitsuba's `path` integrator (glass-lamp and door-ajar, with
    every combination: tests/test_sdtree_combination.py)."""
    from guiding.render.progressive import Budget, render

    renders = 24
    means = []
    for seed in range(renders):
        result = render(cornell, GuidedPathIntegrator(guide=SDTreeGuide(base_spp=4)),
                        Budget(spp=60, pass_spp=4), seed=100 + seed, combine="inverse-variance")
        assert sum(it.weight > 0 for it in result.iterations) == 3   # iterations of 8, 16 and 32 spp
        means.append(result.image.astype(np.float64).mean(axis=(0, 1)))
    means = np.array(means)
    z = z_scores(means, cornell_reference)
    assert (z < Z_LIMIT).all(), f"z-scores {z}, means {means.mean(0)} vs {cornell_reference.mean(0)}"
    assert (means.std(axis=0, ddof=1) / renders ** 0.5 < 0.01 * cornell_reference.mean(axis=0)).all()


def test_sdtree_combines_by_inverse_variance_unless_told(cornell):
    """Müller 2019's combination is the `sdtree` method's final image; `sdtree-last` (and combine="last") is the
    2017 paper's; a guide without iterations has one image whatever the mode."""
    from guiding.guides.methods import make_guide
    from guiding.render.progressive import Budget, render

    budget = Budget(spp=56, pass_spp=8)
    result = render(cornell, GuidedPathIntegrator(guide=make_guide("sdtree")), budget, seed=5)
    assert result.combine == "inverse-variance" and result.summary()["combine"] == "inverse-variance"
    # iterations of 8, 16 and 32 spp: the first, rendered before the guide learned, has no weight
    assert [it.weight > 0 for it in result.iterations] == [False, True, True]
    last = render(cornell, GuidedPathIntegrator(guide=make_guide("sdtree-last")), budget, seed=5)
    assert last.combine == "last" and [it.weight for it in last.iterations] == [0, 0, 1]
    assert render(cornell, GuidedPathIntegrator(), Budget(spp=8)).combine == "last"


# ===================================================================================== automatic budget
def _constant_sample_variance(first, second, spp, passes):
    """An iteration variance as if every sample had variance 1: 1/spp (None for one pass, as the estimate)."""
    return None if passes < 2 else 1.0 / spp


@pytest.mark.parametrize("kind", ["spp", "seconds"])
def test_automatic_budget_stops_training_once_the_extrapolated_variance_rises(cornell, monkeypatch, kind):
    """With a variance per sample that does not fall, each iteration's extrapolated variance (∝ 1/(spp or seconds
    left)) rises: training stops after the first iteration whose predecessor had an estimate and that started
    after AUTOMATIC_MIN_SPP (lowered to 0 here). Iterations of 8, 16, 32 spp: the first has one pass, no
    estimate; the second sets E ∝ 1/248 (1/0.248 s); the third's 1/232 is larger: stop at 56 spp, and the rest
    of the budget goes into the third iteration's image."""
    import guiding.render.iterations as iterations_module
    import guiding.render.progressive as render_module
    from guiding.render.progressive import Budget, render

    monkeypatch.setattr(render_module, "AUTOMATIC_MIN_SPP", 0)
    monkeypatch.setattr(iterations_module, "iteration_variance", _constant_sample_variance)
    if kind == "spp":
        budget = Budget(spp=256, pass_spp=8)
    else:
        FakeClock(monkeypatch, cost_per_spp=1e-3)
        budget = Budget(seconds=0.256, pass_spp=8)
    guide = SDTreeGuide(base_spp=8)
    result = render(cornell, GuidedPathIntegrator(guide=guide), budget, seed=1, combine="automatic")
    stopped = result.training_stopped
    assert stopped["spp"] == 56 and stopped["reason"] == "automatic budget: the extrapolated variance rose"
    # E = V·spent/left with V = 1/spp: 1/(spp left), or (1 ms per spp) 1e-3/(seconds left)
    cost, left = {"spp": (1.0, (248, 232)), "seconds": (1e-3, (0.248, 0.232))}[kind]
    assert stopped["previous_extrapolated_variance"] == pytest.approx(cost / left[0], rel=1e-6)
    assert stopped["extrapolated_variance"] == pytest.approx(cost / left[1], rel=1e-6)
    assert not guide.records() and result.spp == 256
    assert [(it.spp_start, it.spp_end) for it in result.iterations] == [(0, 8), (8, 24), (24, 256)]
    assert result.spp_in_image == 232 and result.iterations[-1].weight == 1


def test_automatic_budget_waits_for_a_reliable_variance(cornell, monkeypatch):
    """Tom94's guard: iterations that started before AUTOMATIC_MIN_SPP (256) spp never stop training, however
    their variance goes; the guide's own schedule ends it."""
    import guiding.render.iterations as iterations_module
    from guiding.render.progressive import Budget, render

    monkeypatch.setattr(iterations_module, "iteration_variance", _constant_sample_variance)
    result = render(cornell, GuidedPathIntegrator(guide=SDTreeGuide(base_spp=8)), Budget(spp=256, pass_spp=8),
                    seed=1, combine="automatic")
    assert result.training_stopped["reason"] == "the guide's schedule: its final iteration records nothing"
    assert [(it.spp_start, it.spp_end) for it in result.iterations][-1] == (120, 256)


def test_automatic_budget_decisions_match_the_measured_variances(cornell, monkeypatch):
    """Real variances: every iteration boundary's decision, recomputed from the iterations' records (E_k =
    V_k·S_k / spp left at its start, against E_{k-1})."""
    import guiding.render.progressive as render_module
    from guiding.render.iterations import extrapolated_variance
    from guiding.render.progressive import Budget, render

    monkeypatch.setattr(render_module, "AUTOMATIC_MIN_SPP", 0)
    budget = Budget(spp=504, pass_spp=8)
    result = render(cornell, GuidedPathIntegrator(guide=SDTreeGuide(base_spp=8)), budget, seed=4,
                    combine="automatic")
    stopped = result.training_stopped
    previous = np.inf
    for it in result.iterations[:-1]:     # every closed training iteration let training go on
        e = extrapolated_variance(it.variance, it.spp, budget.spp - it.spp_start)
        assert e is None or e <= previous
        previous = np.inf if e is None else e
    if stopped["reason"].startswith("automatic"):
        assert stopped["extrapolated_variance"] > previous == pytest.approx(stopped["previous_extrapolated_variance"])
        assert stopped["spp"] < result.iterations[-1].spp_end == budget.spp
