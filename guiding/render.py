"""The progressive renderer: passes, each with its own seed, until an spp or a time budget is spent. Passes start at
``pass_spp`` spp and grow where the guide allows (:mod:`guiding.pass_schedule`).

**Iterations.** Passes accumulate (in float64) into the image of the current *iteration*. A guide without a schedule
(the grid guide, BSDF sampling) has a single iteration, so the image is the mean over all passes, training passes
included, as in the paper. A guide whose update reports ``iteration_done`` (:class:`~guiding.guides.base.UpdateResult`;
the SD-tree's doubling schedule) closes an iteration there and the next pass starts a new image; the final image is
then (``combine``; by default the guide's own, :attr:`~guiding.guides.base.Guide.combine`: the SD-tree's is
``"inverse-variance"``)

* ``"last"``: the last iteration alone (Müller et al. 2017),
* ``"automatic"``: the last iteration alone, with training stopped by the variance (below), or
* ``"inverse-variance"``: the mean of the last :data:`COMBINED_ITERATIONS` iterations (the same number as Müller
  2019, "Practical Path Guiding in Production"), each weighted by its spp (:func:`combine_iterations`): the
  inverse of its image's variance where its samples have the variance of the others', a weight fixed before the
  iteration is rendered. Müller's weights, the inverse of a variance estimated from the iteration's own samples,
  are biased: an iteration that caught a rare, bright path is brighter and gets less weight, which pulled the
  image down where such paths carry the light (``glass-lamp``; results/sdtree_combination/).
  Over the last four iterations the variance per sample changes little on most scenes measured, so weighting by
  spp keeps most of their benefit. The first iteration, rendered before the guide has learned anything (BSDF
  sampling alone), gets no weight.

Every iteration's spp, time, hit rate, variance, weight and the guide's statistics at its end are in
:attr:`RenderResult.iterations`.

**Automatic budget** (``combine="automatic"``, Tom94's default ``sampleCombination``). After iteration ``k``, its
variance is extrapolated to the end of the budget as if its distribution had rendered everything left when it
started: ``E_k = V_k·S_k / R_k`` (:func:`extrapolated_variance`; ``V_k`` the variance of its image, ``S_k`` its spp
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

**Snapshots.** ``snapshot`` is called with the image the render would return if it stopped now, after every pass
that completes ``pass_spp · 2^k`` spp and after the last pass (:class:`SnapshotWriter` writes them to EXR files).

Each pass goes through :class:`guiding.driver.PassDriver`: the device is synchronised, the pass is timed, and the
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
import sys
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
from tqdm import tqdm

from .driver import PassDriver, pass_seed
from .errors import GuidingError
from .guides.parameters import COMBINE_AUTOMATIC, COMBINE_INVERSE_VARIANCE, COMBINE_LAST, COMBINE_MODES
from .pass_schedule import MIN_ITERATION_PASSES, PassSchedule

#: Iterations an inverse-variance combination weighs: the last four, as in Müller's implementation.
COMBINED_ITERATIONS = 4
#: The automatic budget trusts an iteration's variance only if it started after this many spp (Tom94's
#: guided_path.cpp: "we only trust the variance if we drew enough samples for it to be a reliable estimate").
AUTOMATIC_MIN_SPP = 256


@dataclass
class Budget:
    """When to stop: after ``spp`` samples per pixel, or once ``seconds`` have been spent (exactly one is set).

    ``pass_spp``: samples per pixel of the first passes, and the unit of every pass. ``exclude_passes``: leading
    passes not counted against a seconds budget (they keep ``pass_spp``). ``growing_passes``: later passes may
    double up to the guide's next update (:mod:`guiding.pass_schedule`); False: every pass has ``pass_spp``.
    """

    spp: int | None = None
    seconds: float | None = None
    pass_spp: int = 8
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


@dataclass
class RenderResult:
    image: np.ndarray        # (H, W, 3) float32: the last iteration, or the combination of the last ones
    passes: list[PassStats]
    budget: Budget
    spp_in_image: int        # samples per pixel the image is made of (fewer than `spp` when iterations restart it)
    combine: str = COMBINE_LAST
    iterations: list[IterationStats] = field(default_factory=list)
    training_stopped: dict | None = None   # {"spp", "seconds", "reason", ...} once the guide stopped learning

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
                "iterations": [{**asdict(it), "spp": it.spp} for it in self.iterations]}

    def counted_seconds(self) -> float:
        """Time counted against a seconds budget: excluded leading passes and compilation left out."""
        return sum(p.counted_seconds for p in self.passes[self.budget.exclude_passes:])


def _spp_weighted_hit_rate(passes: list[PassStats]) -> float:
    return float(np.average([p.hit_rate for p in passes], weights=[p.spp for p in passes]))


def is_snapshot_spp(spp_total: int, pass_spp: int) -> bool:
    """Whether a snapshot is due after a pass that completes ``spp_total`` spp: ``pass_spp · 2^k`` (k ≥ 0)."""
    passes, rest = divmod(spp_total, pass_spp)
    return rest == 0 and passes > 0 and passes & (passes - 1) == 0


# ------------------------------------------------------------------------------------ iteration images

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
    left`` (the variance of a mean falls as 1/samples). None without a variance estimate, or with a zero one (no
    pass found light: :func:`combine_iterations`), which would stop training as soon as the guide finds the light."""
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
    unbiased (module docstring)."""
    weights = np.array([s if trained else 0.0 for s, trained in zip(spps, learned)], dtype=np.float64)
    if not weights.any():
        weights[-1] = 1.0
    weights /= weights.sum()
    image = sum(w * img for w, img in zip(weights, images) if w > 0)
    return image, [float(w) for w in weights]


class _IterationImages:
    """The current iteration's running sums on the device (float64): ``Σ s_j X_j`` and ``Σ s_j X_j²`` over its
    passes; and, on the host (float64), the finished iterations that the final image may still need."""

    def __init__(self, combine: str):
        self.combine = combine
        self.kept: deque = deque(maxlen=COMBINED_ITERATIONS if combine == COMBINE_INVERSE_VARIANCE else 1)
        self.first = self.second = None
        self.spp = self.passes = 0
        self.closed = 0       # iterations closed so far: the first, rendered before the guide learned, is number 0

    def add_pass(self, image, spp: int) -> None:
        """Add a pass image (a device tensor) of ``spp`` samples per pixel (inside the pass's timed region)."""
        x = mi.TensorXd(image)
        if self.passes == 0:
            # A new iteration starts from evaluated zeros (not literals), so that every pass runs the same
            # accumulation kernel: a different first pass would be compiled in the second pass of a render.
            self.first, self.second = dr.zeros(mi.TensorXd, x.shape), dr.zeros(mi.TensorXd, x.shape)
            dr.make_opaque(self.first, self.second)
        weighted = x * spp
        self.first, self.second = self.first + weighted, self.second + weighted * x
        dr.eval(self.first, self.second)
        self.spp += spp
        self.passes += 1

    def _current(self) -> tuple[np.ndarray, int, float | None]:
        first = self.first.numpy()[..., :3].astype(np.float64)
        second = self.second.numpy()[..., :3].astype(np.float64)
        return first / self.spp, self.spp, iteration_variance(first, second, self.spp, self.passes)

    def variance(self) -> float | None:
        """The estimated variance of the current iteration's image (:func:`iteration_variance`)."""
        return self._current()[2]

    def close(self, record: IterationStats) -> None:
        """End the current iteration: keep its image, fill in its variance; the next pass starts a new one."""
        image, _, record.variance = self._current()
        self.kept.append((record, image))
        self.spp = self.passes = 0
        self.closed += 1

    def image(self) -> tuple[np.ndarray, int, list[tuple[IterationStats | None, float]]]:
        """What the render shows now: (image (H, W, 3) float64, spp it is made of, [(iteration, weight)]), with
        the running iteration (record None) as the newest one."""
        items = [(record, image, record.spp, record.index > 0) for record, image in self.kept]
        if self.passes:
            items.append((None, *self._current()[:2], self.closed > 0))
        if self.combine != COMBINE_INVERSE_VARIANCE:
            record, image, spp, _ = items[-1]
            return image, spp, [(record, 1.0)]
        items = items[-COMBINED_ITERATIONS:]
        image, weights = combine_iterations([i[1] for i in items], [i[2] for i in items], [i[3] for i in items])
        spp = sum(i[2] for i, w in zip(items, weights) if w > 0)
        return image, spp, [(i[0], w) for i, w in zip(items, weights)]


class SnapshotWriter:
    """A ``snapshot`` callback for :func:`render` that writes ``image_snapNNNNN.exr`` (spp zero-padded to five
    digits, atomically) into ``folder`` and lists them in :attr:`entries` (for ``stats.json``). ``metadata``: the
    EXR header attributes every snapshot carries (:func:`guiding.imageio.write_exr`), its spp added."""

    def __init__(self, folder: str | Path, metadata: dict | None = None):
        self.folder = Path(folder)
        self.metadata = metadata or {}
        self.entries: list[dict] = []

    def __call__(self, spp: int, image: np.ndarray, seconds: float, spp_in_image: int) -> None:
        from .imageio import write_exr

        name = f"image_snap{spp:05d}.exr"
        # Listed before it is written: a Ctrl-C that lands between the file's rename and its listing (Mitsuba
        # delivers it late) must still find the file to remove; stats.json, written last, never lists a failed one.
        self.entries.append({"spp": spp, "file": name, "seconds": seconds, "spp_in_image": spp_in_image})
        write_exr(self.folder / name, image, {**self.metadata, "spp": spp, "spp_in_image": spp_in_image})


#: Seconds between two progress lines when stderr is not a terminal (a Snakemake job's log, a pipe): often enough to
#: show that a long reference is alive, rarely enough to keep its log short.
PROGRESS_LINE_SECONDS = 10.0


class _Progress:
    """Progress of a render on stderr, with its ETA: a tqdm bar on a terminal; elsewhere (a Snakemake job's log, a
    pipe), where a redrawn bar would be one endless line, a plain line of tqdm's meter every
    :data:`PROGRESS_LINE_SECONDS` and one when the budget is spent.

    ``budget``: the render's budget (spp, or counted seconds, are the progress). ``enabled``: None: the bar on a
    terminal, lines elsewhere; True: the bar; False: nothing.
    """

    def __init__(self, budget: Budget, enabled: bool | None):
        self.by_spp = budget.spp is not None
        self.total = budget.spp if self.by_spp else budget.seconds
        amount = "{n:g}/{total:g} spp" if self.by_spp else "{n:.1f}/{total:g} s counted"
        self.lines = enabled is None and not sys.stderr.isatty()
        self.started = time.monotonic()
        self.last_line = -math.inf
        self.bar = None
        if enabled or (enabled is None and not self.lines):
            meter = "{desc}: {percentage:3.0f}%|{bar}| " + amount + " [{elapsed}<{remaining}{postfix}]"
            self.bar = tqdm(total=self.total, desc="render", file=sys.stderr, bar_format=meter)
        self.line_format = "{desc}: " + amount + " ({percentage:.0f}%), {elapsed} elapsed, ETA {remaining}{postfix}"

    def _done(self, spp: int, counted: float) -> float:
        return spp if self.by_spp else min(counted, self.total)

    def show(self, spp: int, counted: float) -> None:
        """After a pass: ``spp`` samples per pixel rendered, ``counted`` seconds counted against the budget."""
        done = self._done(spp, counted)
        postfix = None if self.by_spp else f"{spp} spp"
        if self.bar is not None:
            self.bar.set_postfix_str(postfix or "", refresh=False)
            self.bar.update(done - self.bar.n)
            return
        now = time.monotonic()
        if self.lines and (now - self.last_line >= PROGRESS_LINE_SECONDS or done >= self.total):
            self.last_line = now
            print(tqdm.format_meter(done, self.total, now - self.started, prefix="render", postfix=postfix,
                                    bar_format=self.line_format), file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _iteration_record(index: int, passes: list[PassStats]) -> IterationStats:
    """The record of an iteration made of ``passes``; its guide statistics are those of the pass that ended its
    training (with the refinement it triggered), or of its last pass."""
    closing = next((p for p in reversed(passes) if p.iteration_done), passes[-1])
    return IterationStats(index, passes[0].spp_total - passes[0].spp, passes[-1].spp_total, len(passes),
                          sum(p.counted_seconds for p in passes), _spp_weighted_hit_rate(passes),
                          guide=dict(closing.guide))


def _guide_limits(guide, spp_total: int) -> tuple[int | None, int | None]:
    """What the guide allows the next pass (:class:`~guiding.pass_schedule.PassSchedule`): the spp up to its next
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
        :data:`PROGRESS_LINE_SECONDS` elsewhere (e.g. a Snakemake log), True the bar, False nothing.
      sensor: the sensor to render, or its index.
      combine: the final image of a guide with iterations: ``"last"``, ``"automatic"`` or ``"inverse-variance"``
        (module docstring); None (default): the guide's own (:func:`resolve_combine`).
      snapshot: called as ``snapshot(spp_total, image, counted_seconds, spp_in_image)`` with the image the render
        would return now (float64), after each pass that completes ``pass_spp · 2^k`` spp and after the last
        pass (e.g. a :class:`SnapshotWriter`).
      on_pass: called as ``on_pass(stats, image)`` after every pass with its statistics and its own image
        ((H, W, 3) float64).
    """
    combine = resolve_combine(combine, integrator)
    driver = PassDriver(scene, integrator, sensor)
    driver.prepare(budget.spp)
    guide = driver.guide

    film = (scene.sensors()[sensor] if isinstance(sensor, int) else sensor).film()
    schedule = PassSchedule(budget.pass_spp, int(np.prod(film.crop_size())), budget.growing_passes,
                            budget.exclude_passes)
    images = _IterationImages(combine)
    passes: list[PassStats] = []
    iterations: list[IterationStats] = []
    training_stopped = None
    display = _Progress(budget, progress)
    spp_total, counted = 0, 0.0
    snapshot_spp = None
    last_extrapolated = math.inf     # the automatic budget's E_{k-1}

    def current_iteration() -> IterationStats:
        return _iteration_record(len(iterations), passes[len(passes) - images.passes:])

    def close_iteration(record: IterationStats) -> None:
        images.close(record)
        iterations.append(record)

    def snapshot_limit() -> int | None:
        """The spp up to the next snapshot (at ``pass_spp·2^k``), so that no pass runs past one."""
        if snapshot is None:
            return None
        boundary = budget.pass_spp
        while boundary <= spp_total:
            boundary *= 2
        return boundary - spp_total

    def take_snapshot() -> None:
        nonlocal snapshot_spp
        image, spp_in_image, _ = images.image()
        snapshot(spp_total, image, counted, spp_in_image)
        snapshot_spp = spp_total

    try:
        while True:
            if budget.spp is not None:
                if spp_total >= budget.spp:
                    break
                left = budget.spp - spp_total
                spp = min(schedule.next(*_guide_limits(guide, spp_total), snapshot_limit(), left), left)
            else:
                if counted >= budget.seconds:
                    break
                fitting = None
                if passes and passes[-1].counted_seconds > 0:   # at the seconds per spp of the last pass
                    fitting = int((budget.seconds - counted) * passes[-1].spp / passes[-1].counted_seconds)
                spp = schedule.next(*_guide_limits(guide, spp_total), snapshot_limit(), fitting)
            index = len(passes)

            # ------------------------------ Render and update ------------------------------
            recorded = guide is not None and guide.records()
            outcome = driver.run(pass_seed(seed, index), spp, accumulate=lambda image: images.add_pass(image, spp))
            spp_total += spp
            passes.append(PassStats(index, spp, spp_total, outcome.seconds, outcome.update_seconds,
                                    outcome.kernels.compile_seconds, outcome.kernels.launched,
                                    outcome.kernels.compiled, outcome.hit_rate, outcome.update.stats,
                                    outcome.update.iteration_done, outcome.kernels.execution_seconds))
            if index >= budget.exclude_passes:
                counted += passes[-1].counted_seconds
            display.show(spp_total, counted)

            # --------------------- Schedule and bookkeeping (not timed) ----------------------
            if outcome.update.iteration_done:
                ended = current_iteration()
                stop = None
                if budget.seconds is not None and guide.records() and guide.iteration_spp() is not None:
                    next_spp, remaining = guide.iteration_spp(), budget.seconds - counted
                    fits, estimate = next_iteration_fits(ended, next_spp, remaining)
                    if not fits:
                        stop = {"reason": "seconds budget: the next iteration would not fit",
                                "next_iteration_spp": next_spp, "next_iteration_seconds_estimate": estimate,
                                "remaining_seconds": remaining}
                # (Also before the schedule's own final iteration: stopping there keeps this iteration's samples.)
                if stop is None and combine == COMBINE_AUTOMATIC:
                    if budget.spp is not None:
                        spent, left = ended.spp, budget.spp - ended.spp_start
                    else:
                        spent, left = ended.seconds, budget.seconds - (counted - ended.seconds)
                    extrapolated = extrapolated_variance(images.variance(), spent, left)
                    if ended.spp_start > AUTOMATIC_MIN_SPP and extrapolated is not None \
                            and extrapolated > last_extrapolated:
                        stop = {"reason": "automatic budget: the extrapolated variance rose",
                                "extrapolated_variance": extrapolated,
                                "previous_extrapolated_variance": last_extrapolated}
                    last_extrapolated = math.inf if extrapolated is None else extrapolated
                if stop is None:
                    close_iteration(ended)
                else:
                    # The iteration that just ended becomes the final one: the frozen guide (refined with its
                    # data) renders the rest of the budget into its image, so no sample is discarded.
                    guide.stop_training()
                    training_stopped = {"spp": spp_total, "seconds": counted, "iteration": ended.index, **stop}
            if recorded and not guide.records() and training_stopped is None:
                training_stopped = {"spp": spp_total, "seconds": counted,
                                    "reason": "the guide's schedule: its final iteration records nothing"}
            if on_pass is not None:
                on_pass(passes[-1], outcome.image.numpy()[..., :3].astype(np.float64))
            if snapshot is not None and is_snapshot_spp(spp_total, budget.pass_spp):
                take_snapshot()
        if images.passes:
            close_iteration(current_iteration())   # the final iteration: the rest of the budget after the last boundary
        if snapshot is not None and passes and snapshot_spp != spp_total:
            take_snapshot()
    finally:
        display.close()

    image, spp_in_image, weights = images.image()
    for record, weight in weights:
        record.weight = weight
    return RenderResult(image.astype(np.float32), passes, budget, spp_in_image, combine, iterations,
                        training_stopped)
