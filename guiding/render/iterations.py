"""The images of a render's iterations and the final image made of them (``combine``, see
:mod:`guiding.render.progressive`): each iteration's running sums on the device, its variance estimated from the
spread of its pass images (for the ``automatic`` stopping rule and the statistics), and the combination of the last
ones, weighted by their spp."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from guiding.guides.parameters import COMBINE_INVERSE_VARIANCE

#: Iterations the ``inverse-variance`` combination weighs: the last four, as in Müller's implementation.
COMBINED_ITERATIONS = 4


@dataclass
class IterationStats:
    """One iteration: the passes after one of the guide's ``iteration_done`` up to the next (all passes for other
    guides); the final one also holds the passes rendered with the frozen guide once training stopped."""

    index: int
    spp_start: int           # spp rendered before its first pass
    spp_end: int             # spp rendered after its last pass
    passes: int
    seconds: float           # render + update seconds of its passes, compilation excluded (refinement included)
    hit_rate: float          # spp-weighted mean of its passes' hit rates
    variance: float | None = None   # estimated variance of its image, mean over pixels and channels (None: 1 pass)
    weight: float = 0.0      # its weight in the final image
    guide: dict = field(default_factory=dict)   # the guide's statistics at its end (see _iteration_record)

    @property
    def spp(self) -> int:
        return self.spp_end - self.spp_start


def iteration_variance(first: np.ndarray, second: np.ndarray, spp: int, passes: int) -> float | None:
    """Estimated variance of an iteration's image from the spread of its pass images; None for fewer than 2 passes.

    ``first`` = Σ s_j X_j and ``second`` = Σ s_j X_j² over its passes (pass image X_j of s_j spp, S = Σ s_j =
    ``spp``). Since Var(X_j) = σ²/s_j, ``σ̂² = Σ s_j (X_j − X̄)² / (n − 1) = (second − first²/S) / (n − 1)`` is an
    unbiased estimate of the per-sample variance σ² of each pixel and channel, and ``σ̂²/S`` of the variance of
    the iteration's image ``X̄ = first / S``. Returns its mean over pixels and channels.
    """
    if passes < 2:
        return None
    per_sample = np.maximum(second - first * first / spp, 0.0) / (passes - 1)   # rounding can go below 0
    return float(np.mean(per_sample / spp))


def extrapolated_variance(variance: float | None, spent: float, left: float) -> float | None:
    """The variance of the final image if the distribution of an iteration whose image has ``variance`` after
    ``spent`` spp (or seconds) had rendered the ``left`` spp (seconds) left when it started: ``variance·spent /
    left`` (the variance of a mean falls as 1/samples). None without a variance estimate, or with a zero one: it
    comes from an iteration in which no pass found light, not from an exact estimate, and a rise from it would stop
    training as soon as the guide finds the light."""
    return variance * spent / left if variance else None


def combine_iterations(images: list[np.ndarray], spps: list[int],
                       learned: list[bool]) -> tuple[np.ndarray, list[float]]:
    """``(Σ w_k I_k, [w_k])``: iteration images weighted by their spp, ``w_k = S_k / Σ S``, over the images whose
    iteration was rendered with a guide that had learned (``learned``; the others get weight 0); when none was, the
    last image alone (weight 1).

    Unbiased: every iteration's image is an unbiased estimate given what the iterations before it taught the guide,
    and its weight is fixed before it is rendered (by the guide's schedule, or under a seconds budget by the times
    measured, never by the images), so ``E[Σ w_k I_k] = Σ E[w_k] μ = μ``. These are the inverse-variance weights
    where the iterations' samples have equal variance; weights estimated from the images' own samples are not
    unbiased: an iteration that caught a rare, bright path is brighter and gets less weight
    (results/sdtree_combination/)."""
    weights = np.array([s if trained else 0.0 for s, trained in zip(spps, learned)], dtype=np.float64)
    if not weights.any():
        weights[-1] = 1.0
    weights /= weights.sum()
    image = sum(w * img for w, img in zip(weights, images) if w > 0)
    return image, [float(w) for w in weights]


class IterationImages:
    """The current iteration's running sums on the device (float64): ``Σ s_j X_j`` and ``Σ s_j X_j²`` over its
    passes; and, on the host (float64), the finished iterations that the final image may still need."""

    def __init__(self, combine: str):
        self.combine = combine
        self.kept: deque = deque(maxlen=COMBINED_ITERATIONS if combine == COMBINE_INVERSE_VARIANCE else 1)
        self.first = self.second = None
        self.spp = self.passes = 0
        self.summed_spp = 0           # spp in the running sums (those after the split, once split)
        self.before: tuple[np.ndarray, float] | None = None   # (image, share) of the running iteration's split

    def add_pass(self, image, spp: int) -> None:
        """Add a pass image (a device tensor) of ``spp`` samples per pixel (inside the pass's timed region)."""
        x = mi.TensorXd(image)
        if self.summed_spp == 0:
            # A new iteration starts from evaluated zeros (not literals), so that every pass runs the same
            # accumulation kernel: a different first pass would be compiled in the second pass of a render.
            self.first, self.second = dr.zeros(mi.TensorXd, x.shape), dr.zeros(mi.TensorXd, x.shape)
            dr.make_opaque(self.first, self.second)
        weighted = x * spp
        self.first, self.second = self.first + weighted, self.second + weighted * x
        dr.eval(self.first, self.second)
        self.spp += spp
        self.summed_spp += spp
        self.passes += 1

    def split(self, share: float) -> None:
        """From here on the running iteration's image is ``share`` × its image so far + (1 − ``share``) × the mean
        of the passes after (:mod:`guiding.render.path_fallback`: unbiased for a share not made of the images)."""
        self.before = (self._current_image(), share)
        self.summed_spp = 0

    def _current_image(self) -> np.ndarray:
        after = self.first.numpy()[..., :3].astype(np.float64) / self.summed_spp if self.summed_spp else None
        if self.before is None:
            return after
        before, share = self.before
        return before if after is None else share * before + (1.0 - share) * after

    def variance(self) -> float | None:
        """The estimated variance of the current iteration's image (:func:`iteration_variance`); None once split."""
        if self.before is not None:
            return None
        first = self.first.numpy()[..., :3].astype(np.float64)
        second = self.second.numpy()[..., :3].astype(np.float64)
        return iteration_variance(first, second, self.spp, self.passes)

    def close(self, record: IterationStats) -> None:
        """End the current iteration: keep its image, fill in its variance; the next pass starts a new one."""
        record.variance = self.variance()
        self.kept.append((record, self._current_image()))
        self.spp = self.passes = self.summed_spp = 0
        self.before = None

    def image(self) -> tuple[np.ndarray, int, list[tuple[IterationStats | None, float]]]:
        """What the render shows now: (image (H, W, 3) float64, spp it is made of, [(iteration, weight)]), with
        the running iteration (record None) as the newest one."""
        items = [(record, image, record.spp, record.index > 0) for record, image in self.kept]
        if self.passes:
            # The running iteration learned from the guide's training if any iteration closed before it.
            items.append((None, self._current_image(), self.spp, bool(self.kept)))
        if self.combine != COMBINE_INVERSE_VARIANCE:
            record, image, spp, _ = items[-1]
            return image, spp, [(record, 1.0)]
        items = items[-COMBINED_ITERATIONS:]
        image, weights = combine_iterations([i[1] for i in items], [i[2] for i in items], [i[3] for i in items])
        spp = sum(i[2] for i, w in zip(items, weights) if w > 0)
        return image, spp, [(i[0], w) for i, w in zip(items, weights)]
