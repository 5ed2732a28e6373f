"""Drift: float32 accumulation over a long progressive render.

The renderer accumulates passes in float64; the figures show what a float32 accumulator would have cost over the
long run, compared with the 1e-4 threshold.
"""

import numpy as np

from guiding.render.integrator import GuidedPathIntegrator
from guiding.render.progressive import Budget, render
from guiding.scenes import load_scene
from arrays import EPS32

#: The long run: 1250 passes of 8 spp (the renderer's default pass) = 10 000 spp.
DRIFT_PASSES, DRIFT_PASS_SPP = 1250, 8
#: Relative error above which float32 accumulation would need fixing (the issue's threshold).
DRIFT_LIMIT = 1e-4


def test_accumulation_drift(figures):
    """A 10 000 spp run (1250 passes of 8 spp, cornell at 16x16): the renderer's image equals the float64 sum of
    its passes to float32 rounding, and the drift a float32 accumulator would have had is measured against it."""
    scene = load_scene("cornell", scale=16 / 256)
    sum64 = sum32 = None

    def accumulate(stats, image) -> None:
        nonlocal sum64, sum32
        weighted64 = image * stats.spp                                   # what the renderer adds (float64)
        weighted32 = image.astype(np.float32) * np.float32(stats.spp)    # what a float32 accumulator would add
        sum64 = weighted64 if sum64 is None else sum64 + weighted64
        sum32 = weighted32 if sum32 is None else sum32 + weighted32

    result = render(scene, GuidedPathIntegrator(), Budget(spp=DRIFT_PASSES * DRIFT_PASS_SPP,
                                                          pass_spp=DRIFT_PASS_SPP, growing_passes=False),
                    progress=False, on_pass=accumulate)
    spp = result.spp_in_image
    assert spp == DRIFT_PASSES * DRIFT_PASS_SPP and len(result.passes) == DRIFT_PASSES, \
        f"{len(result.passes)} passes, {spp} spp in the image"
    mean64, mean32 = sum64 / spp, sum32 / np.float32(spp)
    lit = mean64 > 0
    renderer_error = np.abs(result.image - mean64)[lit] / mean64[lit]
    float32_drift = np.abs(mean32 - mean64)[lit] / mean64[lit]
    figures.update(spp=spp, passes=DRIFT_PASSES, renderer_max_relative_error=float(renderer_error.max()),
                   float32_max_relative_drift=float(float32_drift.max()),
                   float32_mean_relative_drift=float(float32_drift.mean()),
                   float32_would_need_a_fix=bool(float32_drift.max() > DRIFT_LIMIT))
    assert renderer_error.max() <= EPS32, \
        f"the renderer's image differs from the float64 sum of its passes by {renderer_error.max():.3g} (relative)"
