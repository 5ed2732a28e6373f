"""How many samples per pixel the next pass of a progressive render takes (:func:`guiding.render.progressive.render`).

Passes start at the budget's ``pass_spp`` and grow, at most to twice the largest pass so far (so that the time of
a pass is foreseen from one of at least half its size), as far as every limit allows: the guide's next update
(:meth:`~guiding.guides.base.Guide.update_due`: a guide that learns after every pass, such as the paper's ``ours``,
keeps passes of ``pass_spp``; BSDF sampling and a frozen guide have no such limit), an eighth of the guide's
current iteration (each iteration's variance, which the ``automatic`` rule stops training on and the statistics
report, is estimated from its passes), the next snapshot, the spp or seconds left in the budget, and
:data:`MAX_PASS_PATHS` paths per launch.

Why: every pass pays for tracing the path loop in Python, launching its kernel and the guide's update, a large
share of a pass at the small sizes of ``config/paper.yaml``, and a launch that small keeps the threads unevenly busy
(the measurements: results/pass_schedule/README.md).

Sizes are ``pass_spp·2^k`` only: the render kernel is compiled once for every spp that is a power of two times
another (Mitsuba's sampler and film take the spp as a kernel constant where it is not a power of two).
"""

from __future__ import annotations

from dataclasses import dataclass

#: Most paths a growing pass launches (pixels × spp), about those of one 8-spp pass at 1280 × 720 (7.4 M), so that
#: a pass grows only where the default pass of a full-size image would fit (a ``pass_spp`` pass is never cut).
MAX_PASS_PATHS = 1 << 23
#: Least passes of an iteration (SD-tree): its variance, which decides when the ``automatic`` rule stops training and
#: the statistics report, is estimated from its pass images (7 degrees of freedom per pixel; fixed passes had 2^k − 1).
MIN_ITERATION_PASSES = 8


@dataclass
class PassSchedule:
    """The spp of each pass of one render.

    Parameters:
      pass_spp: the first passes' spp, and the unit of every pass.
      pixels: the image's pixel count (for :data:`MAX_PASS_PATHS`).
      growing: whether passes may grow at all (False: every pass has ``pass_spp``).
      fixed_passes: leading passes that keep ``pass_spp`` (those not counted against a seconds budget).
    """

    pass_spp: int
    pixels: int
    growing: bool = True
    fixed_passes: int = 0
    _largest: int = 0
    _passes: int = 0

    def next(self, *limits: int | None) -> int:
        """The spp of the next pass: the largest ``pass_spp·2^k`` at most twice the largest pass so far and within
        every limit given (None: no limit), never below ``pass_spp``."""
        spp = self.pass_spp
        if self.growing and self._passes >= self.fixed_passes:
            most = min([2 * self._largest, MAX_PASS_PATHS // max(self.pixels, 1)]
                       + [limit for limit in limits if limit is not None])
            while 2 * spp <= most:
                spp *= 2
        self._largest = max(self._largest, spp)
        self._passes += 1
        return spp
