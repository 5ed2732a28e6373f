"""The progressive renderer: passes, each with its own seed, until an spp or a time budget is spent. Passes start at
``pass_spp`` spp and grow where the guide allows (:mod:`guiding.render.pass_schedule`).

**Iterations.** Passes accumulate (in float64) into the image of the current *iteration*. A guide without a schedule
(the grid guide, BSDF sampling) has a single iteration, so the image is the mean over all passes, training passes
included, as in the paper. A guide whose update reports ``iteration_done`` (:class:`~guiding.guides.base.UpdateResult`;
the SD-tree's doubling schedule) closes an iteration there and the next pass starts a new image; the final image is
then (``combine``; by default the guide's own, :attr:`~guiding.guides.base.Guide.combine`: the SD-tree's is
``"inverse-variance"``)

* ``"last"``: the last iteration alone (Müller et al. 2017),
* ``"automatic"``: the last iteration alone, with training stopped by the variance (below), or
* ``"inverse-variance"``: the mean of the last :data:`~guiding.render.iterations.COMBINED_ITERATIONS` iterations
  (the same number as Müller 2019, "Practical Path Guiding in Production"), each weighted by its spp
  (:func:`~guiding.render.iterations.combine_iterations`): the inverse of its image's variance where its samples
  have the variance of the others', a weight fixed before the iteration is rendered. Müller's weights, the inverse
  of a variance estimated from the iteration's own samples, are biased: an iteration that caught a rare, bright
  path is brighter and gets less weight, which pulled the image down where such paths carry the light
  (``glass-lamp``; results/sdtree_combination/). Over the last four iterations the variance per sample changes
  little on most scenes measured, so weighting by spp keeps most of their benefit. The first iteration, rendered
  before the guide has learned anything (BSDF sampling alone), gets no weight.

Every iteration's spp, time, hit rate, variance, weight and the guide's statistics at its end are in
:attr:`RenderResult.iterations`.

**Automatic budget** (``combine="automatic"``, Tom94's default ``sampleCombination``). After iteration ``k``, its
variance is extrapolated to the end of the budget as if its distribution had rendered everything left when it
started: ``E_k = V_k·S_k / R_k`` (:func:`~guiding.render.iterations.extrapolated_variance`; ``V_k`` the variance of its image, ``S_k`` its spp
and ``R_k`` the spp left at its start; under a seconds budget, its counted seconds and the seconds left). Once an
iteration that started after :data:`AUTOMATIC_MIN_SPP` spp has ``E_k > E_{k−1}``, more training no longer pays for
the budget it takes: training stops, and the guide (refined with that iteration's data) renders the rest of the
budget into that iteration's image, as when a seconds budget stops training (below).

**Training under a seconds budget.** At every iteration boundary, the time of the next iteration is estimated as
its spp × the measured seconds per spp of the iteration that just ended (render and update, compilation excluded,
refinement included). If it would not fit in the budget left, the renderer calls the guide's ``stop_training()``
and the frozen guide (refined with the data of the iteration that just ended) renders the rest of the budget into
that iteration's image, which becomes the final iteration: no sample is thrown away (Müller's implementation
likewise extends its current iteration to the end of a time budget). When training stopped (spp and counted
seconds) is in :attr:`RenderResult.training_stopped`, also when the guide's own spp schedule ended it.

**A share of the budget.** A guide whose ``learning_share()`` is below 1 (the grid's ``learning_share``) is told to
``stop_training()`` once that share of the budget (spp, or counted seconds) is spent; it stops recording at once or
at its next update, and renders the rest as it is.

**Snapshots.** ``snapshot`` is called with the image the render would return if it stopped now, after every pass
that completes ``pass_spp · 2^k`` spp and after the last pass (:class:`~guiding.render.progress.SnapshotWriter` writes them to EXR files).

Each pass goes through :class:`guiding.render.driver.PassDriver`: the device is synchronised, the pass is timed, and the
guide updates its distributions.
Pass-varying values (the seed, the pass's size) reach the kernel as parameters, so the same compiled kernel serves
every pass of ``pass_spp·2^k`` spp (a last pass of another size, the rest of an spp budget, compiles one more);
``kernels_compiled`` in the per-pass statistics shows it.

Timing: ``seconds`` of a pass is wall time from launch to synchronisation, compilation included;
``compile_seconds`` is the part Dr.Jit spent generating and compiling code (from its kernel history). A seconds
budget counts pass and update time without compilation (a guide compiles a second kernel once it starts guiding,
which would otherwise eat a short budget), and not the first ``exclude_passes`` passes at all (the paper excluded
its first 80 spp, which contained compilation). The bookkeeping between passes (closing an iteration, snapshots,
``on_pass``) runs outside the timed regions and costs no budget.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import mitsuba as mi
import numpy as np

from guiding.errors import GuidingError
from guiding.guides.parameters import COMBINE_AUTOMATIC, COMBINE_LAST, COMBINE_MODES
from guiding.render import defaults
from guiding.render.driver import PassDriver, pass_seed
from guiding.render.iterations import IterationImages, IterationStats, extrapolated_variance
from guiding.render.pass_schedule import MIN_ITERATION_PASSES, PassSchedule
from guiding.render.path_fallback import COMPARED_PASSES, PATH, PathFallback, nothing_to_guide
from guiding.render.progress import Progress

#: The automatic budget trusts an iteration's variance only if it started after this many spp (Tom94's
#: guided_path.cpp: "we only trust the variance if we drew enough samples for it to be a reliable estimate").
AUTOMATIC_MIN_SPP = 256


@dataclass
class Budget:
    """When to stop: after ``spp`` samples per pixel, or once ``seconds`` have been spent (exactly one is set).

    ``pass_spp``: samples per pixel of the first passes, and the unit of every pass. ``exclude_passes``: leading
    passes not counted against a seconds budget (they keep ``pass_spp``). ``growing_passes``: later passes may
    double up to the guide's next update (:mod:`guiding.render.pass_schedule`); False: every pass has ``pass_spp``.
    """

    spp: int | None = None
    seconds: float | None = None
    pass_spp: int = defaults.PASS_SPP
    exclude_passes: int = 0
    growing_passes: bool = True

    def __post_init__(self):
        if (self.spp is None) == (self.seconds is None):
            raise GuidingError("give exactly one budget: spp or seconds")
        if self.spp is not None and not self.spp > 0:
            raise GuidingError(f"spp budget must be > 0, got {self.spp}")
        if self.seconds is not None and not self.seconds > 0:
            raise GuidingError(f"seconds budget must be > 0, got {self.seconds}")
        if not self.pass_spp > 0:
            raise GuidingError(f"spp per pass must be > 0, got {self.pass_spp}")
        if self.exclude_passes < 0:
            raise GuidingError(f"excluded passes must be >= 0, got {self.exclude_passes}")


@dataclass
class PassStats:
    index: int
    spp: int                 # samples per pixel of this pass
    spp_total: int           # samples per pixel accumulated after this pass
    seconds: float           # wall time of the render kernel(s), device synchronised
    update_seconds: float    # the guide's update after the pass
    compile_seconds: float   # code generation and compilation inside this pass
    kernels_launched: int
    kernels_compiled: int    # kernels new to this process (compiled, or loaded from the disk cache)
    hit_rate: float          # fraction of paths with a non-zero contribution
    guide: dict = field(default_factory=dict)   # the guide's statistics of its update after this pass
    iteration_done: bool = False                # the update ended one of the guide's iterations
    kernel_seconds: float = 0.0                 # execution time of the pass's kernels (part of ``seconds``)

    @property
    def counted_seconds(self) -> float:
        return max(self.seconds - self.compile_seconds, 0.0) + self.update_seconds


@dataclass
class RenderResult:
    image: np.ndarray        # (H, W, 3) float32: the last iteration, or the combination of the last ones
    passes: list[PassStats]
    budget: Budget
    spp_in_image: int        # samples per pixel the image is made of (fewer than `spp` when iterations restart it)
    combine: str = COMBINE_LAST
    iterations: list[IterationStats] = field(default_factory=list)
    training_stopped: dict | None = None   # {"spp", "seconds", "reason", ...} once the guide stopped learning
    path_fallback: dict | None = None      # what Mitsuba's path rendered (FallbackDecision.summary): the path
                                           # fallback's decision, or every pass where nothing is guided

    @property
    def spp(self) -> int:
        return self.passes[-1].spp_total if self.passes else 0

    @property
    def seconds(self) -> float:
        return sum(p.seconds + p.update_seconds for p in self.passes)

    @property
    def compile_seconds(self) -> float:
        return sum(p.compile_seconds for p in self.passes)

    @property
    def hit_rate(self) -> float:
        return _spp_weighted_hit_rate(self.passes)

    def summary(self) -> dict:
        return {"spp": self.spp, "spp_in_image": self.spp_in_image, "seconds": self.seconds,
                "compile_seconds": self.compile_seconds, "budget_seconds_counted": self.counted_seconds(),
                "passes": len(self.passes), "hit_rate": self.hit_rate, "budget": asdict(self.budget),
                "combine": self.combine, "training_stopped": self.training_stopped,
                "path_fallback": self.path_fallback,
                "iterations": [{**asdict(it), "spp": it.spp} for it in self.iterations]}

    def counted_seconds(self) -> float:
        """Time counted against a seconds budget: excluded leading passes and compilation left out."""
        return sum(p.counted_seconds for p in self.passes[self.budget.exclude_passes:])


def _spp_weighted_hit_rate(passes: list[PassStats]) -> float:
    """Over the passes that count their paths (a Mitsuba integrator's, such as the path fallback's, do not)."""
    counted = [p for p in passes if math.isfinite(p.hit_rate)]
    if not counted:
        return math.nan
    return float(np.average([p.hit_rate for p in counted], weights=[p.spp for p in counted]))


def is_snapshot_spp(spp_total: int, pass_spp: int) -> bool:
    """Whether a snapshot is due after a pass that completes ``spp_total`` spp: ``pass_spp · 2^k`` (k ≥ 0)."""
    passes, rest = divmod(spp_total, pass_spp)
    return rest == 0 and passes > 0 and passes & (passes - 1) == 0


def _iteration_record(index: int, passes: list[PassStats]) -> IterationStats:
    """The record of an iteration made of ``passes``; its guide statistics are those of the pass that ended its
    training (with the refinement it triggered), or of its last pass."""
    closing = next((p for p in reversed(passes) if p.iteration_done), passes[-1])
    return IterationStats(index, passes[0].spp_total - passes[0].spp, passes[-1].spp_total, len(passes),
                          sum(p.counted_seconds for p in passes), _spp_weighted_hit_rate(passes),
                          guide=dict(closing.guide))


def _guide_limits(guide, spp_total: int) -> tuple[int | None, int | None]:
    """What the guide allows the next pass (:class:`~guiding.render.pass_schedule.PassSchedule`): the spp up to its next
    update, and a share of its current training iteration (each iteration keeps several passes for its variance)."""
    if guide is None:
        return None, None
    due, iteration = guide.update_due(spp_total), guide.iteration_spp()
    return (None if due is None else due - spp_total,
            None if iteration is None else iteration // MIN_ITERATION_PASSES)


def next_iteration_fits(iteration: IterationStats, next_spp: int, remaining_seconds: float) -> tuple[bool, float]:
    """(fits, estimated seconds): whether an iteration of ``next_spp`` spp, at the seconds per spp measured over
    ``iteration``, fits in ``remaining_seconds``."""
    estimate = next_spp * iteration.seconds / iteration.spp
    return estimate <= remaining_seconds, estimate


def resolve_combine(combine: str | None, integrator: mi.SamplingIntegrator) -> str:
    """The final-image mode of a render: ``combine`` if given, else that of the integrator's guide (``last`` for
    an integrator without one); a GuidingError names an unknown mode."""
    guide = getattr(integrator, "guide", None)
    combine = combine or (guide.combine if guide is not None else COMBINE_LAST)
    if combine not in COMBINE_MODES:
        raise GuidingError(f"unknown combination '{combine}' (known: {', '.join(COMBINE_MODES)})")
    return combine


def render(scene: mi.Scene, integrator: mi.SamplingIntegrator, budget: Budget, seed: int = 0,
           progress: bool | None = None, sensor: int | mi.Sensor = 0, combine: str | None = None,
           snapshot: Callable[[int, np.ndarray, float, int], None] | None = None,
           on_pass: Callable[[PassStats, np.ndarray], None] | None = None) -> RenderResult:
    """Render ``scene`` progressively with ``integrator`` (a ``guided_path`` integrator or any Mitsuba one).

    Parameters:
      scene: the loaded scene.
      integrator: the integrator; when it has a ``guide`` (``guided_path``), the guide is prepared before the
        first pass and updated after each.
      budget: when to stop (:class:`Budget`).
      seed: run seed; pass ``i`` uses ``pass_seed(seed, i)``.
      progress: progress on stderr with an ETA: None (default) a bar on a terminal and a plain line every
        :data:`~guiding.render.progress.PROGRESS_LINE_SECONDS` elsewhere (e.g. a Snakemake log), True the bar,
        False nothing.
      sensor: the sensor to render, or its index.
      combine: the final image of a guide with iterations: ``"last"``, ``"automatic"`` or ``"inverse-variance"``
        (module docstring); None (default): the guide's own (:func:`resolve_combine`).
      snapshot: called as ``snapshot(spp_total, image, counted_seconds, spp_in_image)`` with the image the render
        would return now (float64), after each pass that completes ``pass_spp · 2^k`` spp and after the last
        pass (e.g. a :class:`~guiding.render.progress.SnapshotWriter`).
      on_pass: called as ``on_pass(stats, image)`` after every pass with its statistics and its own image
        ((H, W, 3) float64).
    """
    run = _ProgressiveRender(scene, integrator, budget, resolve_combine(combine, integrator), sensor, snapshot)
    display = Progress(budget, progress)
    try:
        while (spp := run.next_pass_spp()) is not None:
            stats, image = run.render_pass(seed, spp)
            display.show(run.spp_total, run.counted)
            run.after_pass(stats)
            if on_pass is not None:
                on_pass(stats, image.numpy()[..., :3].astype(np.float64))
            if snapshot is not None and is_snapshot_spp(run.spp_total, budget.pass_spp):
                run.take_snapshot()
        run.finish()
    finally:
        display.close()
    return run.result()


class _ProgressiveRender:
    """The state of one :func:`render`: its passes, iterations and images, and the decisions between passes."""

    def __init__(self, scene, integrator, budget: Budget, combine: str, sensor, snapshot):
        self.budget, self.combine, self.snapshot = budget, combine, snapshot
        self.driver = PassDriver(scene, integrator, sensor)
        self.driver.prepare(budget.spp)
        self.guide = self.driver.guide
        # Set by the integrator's prepare (in driver.prepare) where its path_fallback applies.
        path = getattr(integrator, "fallback_integrator", None)
        self.fallback = None if path is None else PathFallback.for_render(scene, path, sensor, self.guide)
        film = (scene.sensors()[sensor] if isinstance(sensor, int) else sensor).film()
        self.schedule = PassSchedule(budget.pass_spp, int(np.prod(film.crop_size())), budget.growing_passes,
                                     budget.exclude_passes)
        self.images = IterationImages(combine)
        self.passes: list[PassStats] = []
        self.iterations: list[IterationStats] = []
        self.training_stopped = None
        self.spp_total, self.counted = 0, 0.0
        self.snapshot_spp = None
        self.last_extrapolated = math.inf     # the automatic budget's E_{k-1}
        self.recorded = False                 # whether the last pass recorded (the guide learned from it)

    # ------------------------------------------------------------------------------ passes
    def next_pass_spp(self) -> int | None:
        """The spp of the next pass, or None once the budget is spent."""
        fallback = self.fallback
        limits = (*_guide_limits(None if self._path_pass() else self.guide, self.spp_total), self._snapshot_limit(),
                  fallback.compare_spp() if fallback is not None else None)
        budget = self.budget
        if budget.spp is not None:
            if self.spp_total >= budget.spp:
                return None
            left = budget.spp - self.spp_total
            return min(self.schedule.next(*limits, left), left)
        if self.counted >= budget.seconds:
            return None
        fitting = None
        last = self.passes[-1] if self.passes else None
        if last is not None and last.counted_seconds > 0:   # at the seconds per spp of the last pass
            fitting = int((budget.seconds - self.counted) * last.spp / last.counted_seconds)
        return self.schedule.next(*limits, fitting)

    def render_pass(self, seed: int, spp: int) -> tuple[PassStats, mi.TensorXf]:
        """Render and update (the timed part): the pass's statistics and its own image."""
        index, path_pass = len(self.passes), self._path_pass()
        self.recorded = self.guide is not None and not path_pass and self.guide.records()
        driver = self.fallback.driver if path_pass else self.driver
        outcome = driver.run(pass_seed(seed, index), spp, accumulate=lambda image: self.images.add_pass(image, spp))
        self.spp_total += spp
        stats = PassStats(index, spp, self.spp_total, outcome.seconds, outcome.update_seconds,
                          outcome.kernels.compile_seconds, outcome.kernels.launched, outcome.kernels.compiled,
                          outcome.hit_rate, outcome.update.stats, outcome.update.iteration_done,
                          outcome.kernels.execution_seconds)
        self.passes.append(stats)
        if index >= self.budget.exclude_passes:
            self.counted += stats.counted_seconds
        if self.fallback is not None and self.fallback.watches:
            self.fallback.observe(outcome.image, spp, stats.counted_seconds)
        return stats, outcome.image

    def _path_pass(self) -> bool:
        """Whether the next pass is Mitsuba's ``path`` (the path fallback's)."""
        return self.fallback is not None and self.fallback.renders_path

    def after_pass(self, stats: PassStats) -> None:
        """Schedule and bookkeeping (not timed): an iteration that ended is closed, or training stops there; training
        stops once the guide's learning share of the budget is spent; the path fallback's check."""
        guide = self.guide
        if self.fallback is not None and self.fallback.watches:
            self._check_fallback()
        if stats.iteration_done:
            ended = self._current_iteration()
            stop = self._seconds_stop(ended)
            # (Also before the schedule's own final iteration: stopping there keeps this iteration's samples.)
            if stop is None and self.combine == COMBINE_AUTOMATIC:
                stop = self._automatic_stop(ended)
            if stop is None:
                self._close_iteration(ended)
            else:
                # The iteration that just ended becomes the final one: the frozen guide (refined with its data)
                # renders the rest of the budget into its image, so no sample is discarded.
                guide.stop_training()
                self.training_stopped = {"spp": self.spp_total, "seconds": self.counted, "iteration": ended.index,
                                         **stop}
        share = guide.learning_share() if guide is not None else 1.0
        if self.recorded and share < 1 and self._budget_spent() >= share:
            guide.stop_training()      # a grid guide stops at its next rebuild
        if self.recorded and not guide.records() and self.training_stopped is None:
            reason = (f"the guide learns from {share:g} of the budget" if share < 1
                      else "the guide's schedule: its final iteration records nothing")
            self.training_stopped = {"spp": self.spp_total, "seconds": self.counted, "reason": reason}

    def _check_fallback(self) -> None:
        """The path fallback's check (:mod:`guiding.render.path_fallback`): its ``path`` passes start once it is
        due; after them, the decision, and the image so far becomes the part before it."""
        fallback, budget = self.fallback, self.budget
        if fallback.comparing and len(fallback.path_passes) == COMPARED_PASSES:
            spp_left = budget.spp - self.spp_total if budget.spp is not None else None
            seconds_left = budget.seconds - self.counted if budget.seconds is not None else None
            share = fallback.share_before(self.spp_total, budget.spp, seconds_left)
            decision = fallback.decide(self.images.image()[0], self.spp_total, self.counted, spp_left, seconds_left,
                                       share)
            self.images.split(share)
            if decision.chosen == PATH:
                self.training_stopped = {"spp": self.spp_total, "seconds": self.counted,
                                         "reason": f"path fallback: {decision.reason}"}
        elif fallback.start_due(self._budget_spent()):
            fallback.comparing = True

    def _budget_spent(self) -> float:
        """The share of the budget spent: of its spp, or of its seconds counted."""
        budget = self.budget
        return self.spp_total / budget.spp if budget.spp is not None else self.counted / budget.seconds

    def finish(self) -> None:
        """After the last pass: the final iteration (the rest of the budget after the last boundary), the last
        snapshot."""
        if self.images.passes:
            self._close_iteration(self._current_iteration())
        if self.snapshot is not None and self.passes and self.snapshot_spp != self.spp_total:
            self.take_snapshot()

    def result(self) -> RenderResult:
        image, spp_in_image, weights = self.images.image()
        for record, weight in weights:
            record.weight = weight
        fallback = self.fallback.decision if self.fallback is not None else None
        if getattr(self.driver.integrator, "renders_path", False):
            fallback = nothing_to_guide()
        return RenderResult(image.astype(np.float32), self.passes, self.budget, spp_in_image, self.combine,
                            self.iterations, self.training_stopped,
                            fallback.summary() if fallback is not None else None)

    # -------------------------------------------------------------------------- iterations
    def _current_iteration(self) -> IterationStats:
        return _iteration_record(len(self.iterations), self.passes[len(self.passes) - self.images.passes:])

    def _close_iteration(self, record: IterationStats) -> None:
        self.images.close(record)
        self.iterations.append(record)

    def _seconds_stop(self, ended: IterationStats) -> dict | None:
        """Why training stops under a seconds budget (the next iteration would not fit), or None."""
        budget, guide = self.budget, self.guide
        if budget.seconds is None or not guide.records() or guide.iteration_spp() is None:
            return None
        next_spp, remaining = guide.iteration_spp(), budget.seconds - self.counted
        fits, estimate = next_iteration_fits(ended, next_spp, remaining)
        if fits:
            return None
        return {"reason": "seconds budget: the next iteration would not fit", "next_iteration_spp": next_spp,
                "next_iteration_seconds_estimate": estimate, "remaining_seconds": remaining}

    def _automatic_stop(self, ended: IterationStats) -> dict | None:
        """Why the automatic budget stops training (the extrapolated variance rose), or None."""
        budget = self.budget
        if budget.spp is not None:
            spent, left = ended.spp, budget.spp - ended.spp_start
        else:
            spent, left = ended.seconds, budget.seconds - (self.counted - ended.seconds)
        extrapolated = extrapolated_variance(self.images.variance(), spent, left)
        previous, self.last_extrapolated = self.last_extrapolated, math.inf if extrapolated is None else extrapolated
        if ended.spp_start > AUTOMATIC_MIN_SPP and extrapolated is not None and extrapolated > previous:
            return {"reason": "automatic budget: the extrapolated variance rose", "extrapolated_variance": extrapolated,
                    "previous_extrapolated_variance": previous}
        return None

    # --------------------------------------------------------------------------- snapshots
    def _snapshot_limit(self) -> int | None:
        """The spp up to the next snapshot (at ``pass_spp·2^k``), so that no pass runs past one."""
        if self.snapshot is None:
            return None
        boundary = self.budget.pass_spp
        while boundary <= self.spp_total:
            boundary *= 2
        return boundary - self.spp_total

    def take_snapshot(self) -> None:
        image, spp_in_image, _ = self.images.image()
        self.snapshot(self.spp_total, image, self.counted, spp_in_image)
        self.snapshot_spp = self.spp_total
