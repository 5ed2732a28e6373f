"""Determinism: run-to-run differences of the same seed, on one thread and on the suite's thread count.

On one thread every method is bit-identical from run to run. On two threads the guides' sums are float64, added
without atomics into a copy per thread (``ReduceMode.Expand``) and folded after the pass, so only the order in which
the copies' float32 terms were added differs; that has so far given identical images for every method (the tree
guides splatted float32 energies with atomics before, which could change images in the last bits). The figures give
the largest difference.
"""

import drjit as dr
import numpy as np
import pytest

from guiding.render.integrator import GuidedPathIntegrator
from guiding.guides.methods import make_guide
from guiding.render.progressive import Budget, render
from guiding.scenes import load_scene

#: Methods whose determinism is measured: the baseline (no learning), grid guides (SARSA with rejection sampling, MC
#: with hemi_inv) and the tree guides.
DETERMINISM_METHODS = ("brdf", "ours", "mc-hemi_inv", "sdtree", "quadtree-grid")
DETERMINISM_SCALE, DETERMINISM_SPP = 32 / 256, 32


def render_cornell(method: str, seed: int) -> np.ndarray:
    scene = load_scene("cornell", scale=DETERMINISM_SCALE)
    return render(scene, GuidedPathIntegrator(guide=make_guide(method)), Budget(spp=DETERMINISM_SPP, pass_spp=8),
                  seed=seed, progress=False).image


@pytest.fixture
def thread_count():
    """The suite's Dr.Jit thread count, restored after the test (which may change it)."""
    threads = dr.thread_count()
    yield threads
    dr.set_thread_count(threads)


@pytest.mark.parametrize("method", DETERMINISM_METHODS)
def test_same_seed_same_image(method, thread_count, figures):
    """The same seed gives the same image: bit-identical for every method on one thread and for brdf on two; where
    guides learn on two threads (per-thread sums, folded in an order that may vary), the largest difference is
    measured and must stay below 1e-3 of the difference between two seeds."""
    for count in (1, thread_count):
        dr.set_thread_count(count)
        first, second = render_cornell(method, seed=5), render_cornell(method, seed=5)
        difference = float(np.abs(first - second).max())
        label = f"{count} thread{'s' if count > 1 else ''}"
        figures[label] = {"max_abs_difference": difference,
                          "pixels_differing": int(np.count_nonzero((first != second).any(axis=-1)))}
        if count == 1 or method == "brdf":
            assert difference == 0, f"{label}: the same seed differs by up to {difference:.3g}"
        else:
            noise = float(np.abs(first - render_cornell(method, seed=6)).max())
            figures[label]["max_abs_difference_between_seeds"] = noise
            assert difference <= 1e-3 * noise, \
                f"{label}: the same seed differs by up to {difference:.3g}, two seeds by {noise:.3g}"
