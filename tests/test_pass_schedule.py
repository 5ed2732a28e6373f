"""Growing passes (:mod:`guiding.render.pass_schedule`): sizes, the limits each guide sets, and one render kernel for
every pass size."""

import drjit as dr
import numpy as np
import pytest

from guiding.render.driver import PassDriver, pass_seed, render_pass
from guiding.guides.grid.guide import GridGuide
from guiding.guides.trees.sdtree import SDTreeGuide
from guiding.render.integrator import GuidedPathIntegrator
from guiding.guides.methods import make_guide
from guiding.render.pass_schedule import MAX_PASS_PATHS, MIN_ITERATION_PASSES, PassSchedule
from guiding.render.progressive import Budget, render


def test_passes_double_up_to_the_tightest_limit_in_powers_of_two():
    schedule = PassSchedule(pass_spp=8, pixels=1000)
    sizes = [schedule.next() for _ in range(12)]
    most = 8 * 2 ** int(np.log2(MAX_PASS_PATHS // 1000 // 8))
    assert sizes[:6] == [8, 16, 32, 64, 128, 256] and max(sizes) == most and sizes[-1] == most
    # Within the tightest limit, down to pass_spp but never below; None is no limit.
    assert [schedule.next(None, 100), schedule.next(3), schedule.next(5000, 40)] == [64, 8, 32]
    # After small passes it may only double the largest so far.
    small = PassSchedule(pass_spp=4, pixels=1)
    assert [small.next(4), small.next(4), small.next()] == [4, 4, 8]


def test_fixed_and_leading_passes_keep_pass_spp():
    assert [PassSchedule(8, 100, growing=False).next() for _ in range(3)] == [8, 8, 8]
    leading = PassSchedule(8, 100, fixed_passes=3)
    assert [leading.next() for _ in range(5)] == [8, 8, 8, 16, 32]


def test_brdf_passes_grow_to_the_budget_with_one_kernel(cornell):
    result = render(cornell, GuidedPathIntegrator(), Budget(spp=120, pass_spp=8), progress=False)
    assert [p.spp for p in result.passes] == [8, 16, 32, 64] and result.spp == 120
    assert all(p.kernels_compiled == 0 for p in result.passes[1:])


@pytest.mark.parametrize("growth, ends", [
    # The paper's rule (ours): an update after every pass, so every pass keeps pass_spp.
    (0.0, list(range(8, 161, 8))),
    # Rebuilt at 2^k·(1, 5/4, 3/2, 7/4): the passes in between merged into one.
    (0.25, [8, 16, 24, 32, 40, 48, 56, 64, 80, 96, 112, 128, 160]),
])
def test_grid_passes_end_at_the_rebuilds_and_keep_one_kernel(cornell, growth, ends):
    """Every pass ends with a rebuild, so no pass samples with tables older than the fixed-pass render would."""
    guide = GridGuide(rule="sarsa", sampler="hemi_rej_plus", rebuild_growth=growth)
    result = render(cornell, GuidedPathIntegrator(guide=guide), Budget(spp=160, pass_spp=8), progress=False)
    assert [p.spp_total for p in result.passes] == ends
    assert all(p.guide["rebuilt"] for p in result.passes)


@pytest.mark.parametrize("method", ["ours-plus", "mc-hemi_inv", "sdtree"])
def test_one_render_kernel_serves_every_pass_size(cornell, method):
    """The kernels of a guided pass are the same whatever its size (the grid guide's RGB means once had the pass's
    width as a constant: a new kernel, 2 s of compilation, for every size). Compared by hash, so that Dr.Jit's disk
    cache cannot hide a new kernel."""
    integrator = GuidedPathIntegrator(guide=make_guide(method))
    driver = PassDriver(cornell, integrator)
    driver.prepare()
    for index in range(2):                 # pass 0 samples the BSDF, pass 1 guides
        driver.run(pass_seed(0, index), 8)

    def kernels(spp: int) -> set[str]:
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            image = render_pass(cornell, integrator, 0, pass_seed(1, spp), spp)
            dr.eval(image)
            dr.sync_thread()
            return {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}

    assert kernels(8) == kernels(16) == kernels(64)


def test_sdtree_iterations_end_on_pass_boundaries_with_several_passes(cornell):
    guide = SDTreeGuide(base_spp=8)
    result = render(cornell, GuidedPathIntegrator(guide=guide), Budget(spp=248, pass_spp=8), seed=4,
                    progress=False)
    # Iterations (0, 8), (8, 24), (24, 56), (56, 120) train; the final one (120, 248) records nothing.
    assert [p.spp_total for p in result.passes if p.iteration_done] == [8, 24, 56, 120]
    assert [(it.spp_start, it.spp_end) for it in result.iterations] == [(0, 8), (8, 24), (24, 56), (56, 120),
                                                                       (120, 248)]
    for it in result.iterations:
        assert it.passes >= min(MIN_ITERATION_PASSES, it.spp // 8), it
    assert max(p.spp for p in result.passes) > 8      # the final iteration's passes grew
    assert result.iterations[-1].variance is not None and np.isfinite(result.image).all()


def test_a_second_render_of_a_trained_grid_guide_rebuilds_from_its_own_spp(cornell):
    """The spp of a render count from 0: a guide trained by an earlier render rebuilds after the new render's first
    pass (not at the old render's next rebuild), and its passes grow from there."""
    integrator = GuidedPathIntegrator(guide=GridGuide(rebuild_growth=0.25))
    render(cornell, integrator, Budget(spp=64, pass_spp=8), progress=False)
    again = render(cornell, integrator, Budget(spp=64, pass_spp=8), progress=False)
    assert [p.spp_total for p in again.passes] == [8, 16, 24, 32, 40, 48, 56, 64]
    assert all(p.guide["rebuilt"] for p in again.passes)
