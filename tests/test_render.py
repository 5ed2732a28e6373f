"""The progressive renderer: budgets, per-pass statistics, no recompilation across passes, snapshots, and the
variance estimate and combination of iteration images."""

import json

import numpy as np
import pytest

from guiding.errors import GuidingError
from guiding.imageio import read_exr
from guiding.render.integrator import GuidedPathIntegrator
from guiding.render.driver import pass_seed
from guiding.render.iterations import combine_iterations, extrapolated_variance, iteration_variance
from guiding.render.progressive import Budget, is_snapshot_spp, render


def test_spp_budget_is_exact(cornell):
    result = render(cornell, GuidedPathIntegrator(), Budget(spp=21, pass_spp=8))
    assert [p.spp for p in result.passes] == [8, 8, 5]
    assert result.spp == 21
    assert np.isfinite(result.image).all() and result.image.shape[2] == 3


def test_seconds_budget_stops_within_one_pass(cornell):
    budget = Budget(seconds=1.0, pass_spp=4)
    result = render(cornell, GuidedPathIntegrator(), budget)
    counted = result.counted_seconds()
    last = result.passes[-1].counted_seconds
    assert counted >= budget.seconds
    assert counted - last < budget.seconds  # the last pass started before the budget was spent


def test_excluded_passes_are_not_counted(cornell):
    result = render(cornell, GuidedPathIntegrator(), Budget(seconds=0.3, pass_spp=2, exclude_passes=3))
    assert len(result.passes) > 3
    counted = sum(p.counted_seconds for p in result.passes[3:])
    assert result.counted_seconds() == pytest.approx(counted)
    assert counted < result.seconds - sum(p.seconds for p in result.passes[:3]) + 1e-9


def test_kernel_count_does_not_grow_with_passes(cornell):
    result = render(cornell, GuidedPathIntegrator(), Budget(spp=12 * 4, pass_spp=4))
    launched = {p.kernels_launched for p in result.passes}
    assert len(launched) == 1, launched
    assert all(p.kernels_compiled == 0 for p in result.passes[1:]), [p.kernels_compiled for p in result.passes]


def test_passes_use_distinct_seeds():
    seeds = {pass_seed(s, i) for s in range(3) for i in range(200)}
    assert len(seeds) == 600


def test_hit_rate_is_a_fraction(cornell):
    result = render(cornell, GuidedPathIntegrator(), Budget(spp=8))
    assert 0 < result.hit_rate < 1


@pytest.mark.parametrize("kwargs", [dict(spp=0), dict(seconds=-1.0), dict(), dict(spp=4, seconds=1.0),
                                    dict(spp=4, pass_spp=0)])
def test_bad_budgets_are_rejected(kwargs):
    with pytest.raises(GuidingError):
        Budget(**kwargs)


# ------------------------------------------------------------------------------------------- snapshots

def test_snapshot_spp_are_pass_spp_times_powers_of_two():
    assert [s for s in range(1, 130) if is_snapshot_spp(s, 8)] == [8, 16, 32, 64, 128]
    assert [s for s in range(1, 20) if is_snapshot_spp(s, 3)] == [3, 6, 12]


class FakeClock:
    """Stands in for the renderer's clock (while the test's ``monkeypatch`` lasts): a pass of ``s`` spp takes
    exactly ``cost_per_spp · s`` seconds, anything else only the time a test adds to :attr:`now`, and compilation
    none (the kernel counts stay real)."""

    def __init__(self, monkeypatch, cost_per_spp: float):
        import types

        import guiding.render.driver as driver_module

        self.now = 0.0
        real_pass, real_costs = driver_module.render_pass, driver_module.KernelCosts.from_history

        def timed_pass(scene, integrator, sensor, seed, spp):
            image = real_pass(scene, integrator, sensor, seed, spp)
            self.now += cost_per_spp * spp
            return image

        def costs_without_compilation(history):
            costs = real_costs(history)
            costs.compile_seconds = 0.0
            return costs

        monkeypatch.setattr(driver_module, "render_pass", timed_pass)
        monkeypatch.setattr(driver_module, "time", types.SimpleNamespace(perf_counter=lambda: self.now))
        monkeypatch.setattr(driver_module.KernelCosts, "from_history", staticmethod(costs_without_compilation))


def test_snapshots_show_the_running_mean_and_cost_no_budget(cornell, monkeypatch):
    clock = FakeClock(monkeypatch, cost_per_spp=1e-3)
    pass_images, snapshots = [], []

    def snapshot(spp, image, seconds, spp_in_image):
        snapshots.append((spp, image, seconds, spp_in_image))
        clock.now += 1.0   # a slow disk: must show in no pass and cost no budget

    result = render(cornell, GuidedPathIntegrator(), Budget(spp=44, pass_spp=4), snapshot=snapshot,
                    on_pass=lambda stats, image: pass_images.append((stats.spp, image)))
    assert [s[0] for s in snapshots] == [4, 8, 16, 32, 44]       # pass_spp·2^k, and the last pass
    assert [p.spp for p in result.passes] == [4, 4, 8, 16, 8, 4]   # passes grow, but none runs past a snapshot
    for spp, image, seconds, spp_in_image in snapshots:
        done = pass_images[:sum(p.spp_total <= spp for p in result.passes)]
        expected = sum(s * img for s, img in done) / sum(s for s, _ in done)
        np.testing.assert_allclose(image, expected, rtol=1e-9, atol=1e-12)
        assert spp_in_image == spp and seconds == pytest.approx(1e-3 * spp)
    np.testing.assert_allclose(result.image, snapshots[-1][1].astype(np.float32))
    assert [p.seconds for p in result.passes] == pytest.approx([1e-3 * p.spp for p in result.passes])
    assert all(p.update_seconds == 0 for p in result.passes) and result.counted_seconds() == pytest.approx(0.044)
    # Nor does the bookkeeping launch a kernel that a pass would count.
    assert len({p.kernels_launched for p in result.passes}) == 1
    assert all(p.kernels_compiled == 0 for p in result.passes[1:])


def test_render_command_writes_snapshots_listed_in_stats(tmp_path):
    from guiding.cli import main

    out = tmp_path / "run"
    assert main(["render", "--scene", "cornell", "--scale", "0.125", "--method", "sdtree", "--spp", "40",
                 "--snapshots", "--combine", "inverse-variance", "--variant", "llvm_ad_rgb", "--quiet",
                 "--out", str(out)]) == 0
    stats = json.loads((out / "stats.json").read_text())
    assert [(s["spp"], s["file"]) for s in stats["snapshots"]] == [
        (8, "image_snap00008.exr"), (16, "image_snap00016.exr"), (32, "image_snap00032.exr"),
        (40, "image_snap00040.exr")]
    assert sorted(p.name for p in out.glob("image_snap*")) == [s["file"] for s in stats["snapshots"]]
    for path in out.iterdir():
        assert path.stat().st_mode & 0o777 == 0o644, path   # not mkstemp's 0600
    np.testing.assert_array_equal(read_exr(out / "image_snap00040.exr"), read_exr(out / "image.exr"))
    assert stats["combine"] == "inverse-variance" and stats["snapshots"][-1]["seconds"] == pytest.approx(
        stats["budget_seconds_counted"])
    assert [(it["spp_start"], it["spp_end"]) for it in stats["iterations"]] == [(0, 8), (8, 40)]


def test_unknown_combination_is_rejected(cornell):
    with pytest.raises(GuidingError, match="unknown combination"):
        render(cornell, GuidedPathIntegrator(), Budget(spp=4), combine="median")


# ---------------------------------------------------------------------------------- iteration variance

def test_iteration_variance_estimates_the_variance_of_the_iteration_image():
    """Passes of unequal spp (the last pass of an spp budget is shorter): over many simulated iterations, the
    estimate averages to the true variance of the spp-weighted mean, σ²/S, pixel by pixel."""
    rng = np.random.default_rng(3)
    sigma2 = rng.uniform(0.5, 2.0, size=(4, 5, 3))     # per-sample variance of each pixel and channel
    spps = np.array([8, 8, 8, 3])
    estimates, means = [], []
    for _ in range(4000):
        passes = [1.0 + rng.normal(0, np.sqrt(sigma2 / s)) for s in spps]
        first = sum(s * x for s, x in zip(spps, passes))
        second = sum(s * x * x for s, x in zip(spps, passes))
        estimates.append(iteration_variance(first, second, spps.sum(), len(spps)))
        means.append((first / spps.sum()).mean())
    true = float(np.mean(sigma2 / spps.sum()))
    spread = np.std(estimates) / np.sqrt(len(estimates))
    assert abs(np.mean(estimates) - true) < 4 * spread and spread < 0.02 * true
    assert iteration_variance(first, second, spps.sum(), 1) is None     # one pass: no estimate


def test_inverse_variance_combination_weights():
    """Weights ∝ spp over the iterations rendered by a guide that had learned, whatever their images hold."""
    images = [np.full((2, 2, 3), v) for v in (1.0, 2.0, 4.0)]
    image, weights = combine_iterations(images, [8, 16, 48], [False, True, True])
    assert weights == pytest.approx([0.0, 0.25, 0.75])
    np.testing.assert_allclose(image, 0.5 + 3.0)
    image, weights = combine_iterations(images, [8, 16, 48], [False, False, False])   # none learned: the last alone
    assert weights == [0.0, 0.0, 1.0] and (image == 4.0).all()
    # An iteration whose passes found no light keeps its weight: its black image is what its estimate drew.
    images = [np.zeros((2, 2, 3)), np.full((2, 2, 3), 2.0), np.full((2, 2, 3), 4.0)]
    image, weights = combine_iterations(images, [16, 16, 32], [True, True, True])
    assert weights == pytest.approx([0.25, 0.25, 0.5])
    np.testing.assert_allclose(image, 0.5 + 2.0)
    # A zero variance is no estimate for the automatic budget: a rise from 0 would stop training when the guide finds
    # light.
    assert extrapolated_variance(0.0, 64, 512) is None and extrapolated_variance(None, 64, 512) is None
    assert extrapolated_variance(0.5, 64, 512) == pytest.approx(0.0625)


def test_progress_lines_off_a_terminal_and_a_bar_with_eta_on_request(cornell, capsys, monkeypatch):
    """Not on a terminal (a Snakemake log) the default is plain lines with an ETA, at most one per
    PROGRESS_LINE_SECONDS and one at the end; progress=True is tqdm's bar; False shows nothing."""
    import guiding.render.progress as progress_module

    integrator = GuidedPathIntegrator()
    monkeypatch.setattr(progress_module, "PROGRESS_LINE_SECONDS", 1e9)   # a slow machine must not add lines
    render(cornell, integrator, Budget(spp=24, pass_spp=8))          # stderr is pytest's capture: no terminal
    lines = capsys.readouterr().err.splitlines()   # the first pass, then (none due in between) the last
    assert [line.split(",")[0] for line in lines] == ["render: 8/24 spp (33%)", "render: 24/24 spp (100%)"]
    assert all("elapsed, ETA" in line for line in lines)
    monkeypatch.setattr(progress_module, "PROGRESS_LINE_SECONDS", 0.0)
    render(cornell, integrator, Budget(seconds=0.3, pass_spp=8))
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) >= 3 and all(" s counted (" in line and "ETA" in line and " spp" in line for line in lines)
    render(cornell, integrator, Budget(spp=16, pass_spp=8), progress=True)
    bar = capsys.readouterr().err
    assert "\r" in bar and "16/16 spp" in bar and "100%|" in bar and "<00:00" in bar   # [elapsed<remaining]
    render(cornell, integrator, Budget(spp=16, pass_spp=8), progress=False)
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("method", ["ours", "sdtree"])
def test_a_scene_with_nothing_to_guide_renders_the_bsdf_path_loop(method, monkeypatch):
    """In mirror-box (delta BSDFs only) a guided method traces BSDF sampling without the guide's code (its
    ``sample`` and ``record`` are never traced): its passes are `brdf`'s, sample for sample (same seeds), while its
    guide still updates between them. In cornell-box the guide is traced."""
    from guiding.render.driver import PassDriver
    from guiding.guides.methods import make_guide
    from guiding.scenes import load_scene

    traced = []
    guide = make_guide(method)
    for name in ("sample", "record"):
        original = getattr(guide, name)
        monkeypatch.setattr(guide, name, lambda *args, _original=original, _name=name, **kwargs:
                            traced.append(_name) or _original(*args, **kwargs))
    scene = load_scene("mirror-box", 1 / 16)
    drivers = [PassDriver(scene, GuidedPathIntegrator(guide=g)) for g in (make_guide("brdf"), guide)]
    for driver in drivers:
        driver.prepare()
    for seed in range(3):
        plain, guided = (np.array(driver.run(seed, 4).image) for driver in drivers)
        assert np.array_equal(plain, guided) and np.any(plain > 0)
    assert traced == [] and drivers[1].spp_done == 12
    cornell = PassDriver(load_scene("cornell", 1 / 16), GuidedPathIntegrator(guide=guide))
    cornell.prepare()
    cornell.run(0, 1)
    assert "sample" in traced


def test_a_scene_with_instances_counts_as_guided():
    """The BSDFs of instanced shapes are not listed by the scene: such a scene is assumed to have something to
    guide."""
    import mitsuba as mi

    from guiding.guides.methods import make_guide

    scene = mi.load_dict({"type": "scene", "group": {"type": "shapegroup", "ball": {"type": "sphere",
                                                                                  "bsdf": {"type": "conductor"}}},
                          "copy": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"}}})
    assert make_guide("ours").guides_any(scene)


def test_a_scene_with_nothing_to_guide_never_updates_the_guide():
    """mirror-box holds delta lobes only: the passes are BSDF sampling, the guide is never updated (it would rebuild
    empty tables after every pass), and the passes grow as a guide-less render's do."""
    from guiding.guides.methods import make_guide
    from guiding.scenes import load_scene

    integrator = GuidedPathIntegrator(guide=make_guide("ours"))
    result = render(load_scene("mirror-box", 1 / 16), integrator, Budget(spp=64, pass_spp=8), seed=0)
    assert not integrator.guide.trained
    assert [p.spp for p in result.passes] == [8, 16, 32, 8]
    assert all(not p.guide for p in result.passes)
