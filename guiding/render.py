"""The progressive renderer: passes of a few spp, each with its own seed, until an spp or a time budget is spent.

Every pass is accumulated into the final image (training passes included, as in the paper), except for guides
whose update reports ``iteration_done`` (the SD-tree's doubling schedule): the image then restarts, so it holds
the last iteration alone, as Müller et al. do. After each pass the
device is synchronised, the pass is timed, and the guide updates its distributions. Pass-varying values (the seed)
reach the kernel as parameters, so the same compiled kernel serves every pass; ``kernels_compiled`` in the per-pass
statistics shows it.

Timing: ``seconds`` of a pass is wall time from launch to synchronisation, compilation included;
``compile_seconds`` is the part Dr.Jit spent generating and compiling code (from its kernel history). A seconds
budget counts pass and update time without compilation (a guide compiles a second kernel once it starts guiding,
which would otherwise eat a short budget), and not the first ``exclude_passes`` passes at all (the paper excluded
its first 80 spp, which contained compilation).
"""

from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .errors import GuidingError


@dataclass
class Budget:
    """When to stop: after ``spp`` samples per pixel, or once ``seconds`` have been spent (exactly one is set).

    ``pass_spp``: samples per pixel of each pass. ``exclude_passes``: leading passes not counted against a
    seconds budget.
    """

    spp: int | None = None
    seconds: float | None = None
    pass_spp: int = 8
    exclude_passes: int = 0

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
    guide: dict = field(default_factory=dict)

    @property
    def counted_seconds(self) -> float:
        return max(self.seconds - self.compile_seconds, 0.0) + self.update_seconds


@dataclass
class RenderResult:
    image: np.ndarray        # (H, W, 3) float32, the mean over all passes
    passes: list[PassStats]
    budget: Budget
    spp_in_image: int        # samples per pixel the image averages (fewer than `spp` when iterations restart it)

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
        return float(np.average([p.hit_rate for p in self.passes], weights=[p.spp for p in self.passes]))

    def summary(self) -> dict:
        return {"spp": self.spp, "spp_in_image": self.spp_in_image, "seconds": self.seconds, "compile_seconds": self.compile_seconds,
                "budget_seconds_counted": self.counted_seconds(), "passes": len(self.passes),
                "hit_rate": self.hit_rate, "budget": asdict(self.budget)}

    def counted_seconds(self) -> float:
        """Time counted against a seconds budget: excluded leading passes and compilation left out."""
        return sum(p.counted_seconds for p in self.passes[self.budget.exclude_passes:])


def pass_seed(seed: int, index: int) -> int:
    """A distinct 32-bit sampler seed for every (run seed, pass) pair."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


class _Progress:
    """A one-line progress display on stderr for interactive runs (silent when stderr is not a terminal)."""

    def __init__(self, budget: Budget, enabled: bool | None):
        self.budget = budget
        self.enabled = sys.stderr.isatty() if enabled is None else enabled

    def show(self, spp: int, counted: float) -> None:
        if not self.enabled:
            return
        if self.budget.spp is not None:
            done = f"{spp}/{self.budget.spp} spp"
            fraction = spp / self.budget.spp
        else:
            done = f"{counted:.1f}/{self.budget.seconds:g} s, {spp} spp"
            fraction = min(counted / self.budget.seconds, 1.0)
        bar = "#" * int(30 * fraction)
        sys.stderr.write(f"\r[{bar:<30}] {done}")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")


def _kernel_costs(history: list[dict]) -> tuple[float, int, int]:
    """(compile seconds, launched JIT kernels, compiled JIT kernels) of one pass's kernel history."""
    jit = [k for k in history if k.get("type") == dr.KernelType.JIT]
    compile_ms = sum(k.get("codegen_time", 0.0) + k.get("backend_time", 0.0) for k in jit)
    compiled = sum(1 for k in jit if not k.get("cache_hit", False))
    return compile_ms / 1000.0, len(jit), compiled


def render(scene: mi.Scene, integrator: mi.SamplingIntegrator, budget: Budget, seed: int = 0,
           progress: bool | None = None, sensor: int = 0) -> RenderResult:
    """Render ``scene`` progressively with ``integrator`` (a ``guided_path`` integrator or any Mitsuba one).

    Parameters:
      scene: the loaded scene.
      integrator: the integrator; when it has a ``guide`` (``guided_path``), the guide is prepared before the
        first pass and updated after each.
      budget: when to stop (:class:`Budget`).
      seed: run seed; pass ``i`` uses ``pass_seed(seed, i)``.
      progress: show a progress line on stderr (default: when stderr is a terminal).
      sensor: index of the sensor to render.
    """
    guide = getattr(integrator, "guide", None)
    if guide is not None:
        guide.prepare(scene)
        if hasattr(guide, "set_budget"):
            guide.set_budget(budget.spp)
    counters = hasattr(integrator, "reset_counters")

    accumulated = None
    passes: list[PassStats] = []
    display = _Progress(budget, progress)
    spp_total, counted = 0, 0.0
    spp_in_image = 0
    try:
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()  # discard what ran before this render
            while True:
                if budget.spp is not None:
                    if spp_total >= budget.spp:
                        break
                    spp = min(budget.pass_spp, budget.spp - spp_total)
                else:
                    if counted >= budget.seconds:
                        break
                    spp = budget.pass_spp
                index = len(passes)

                # ------------------------------ Render one pass ------------------------------
                if counters:
                    integrator.reset_counters()
                start = time.perf_counter()
                image = mi.render(scene, integrator=integrator, spp=spp, seed=pass_seed(seed, index),
                                  sensor=sensor)
                weighted = mi.TensorXd(image) * spp
                accumulated = weighted if accumulated is None or spp_in_image == 0 else accumulated + weighted
                spp_in_image += spp
                dr.eval(accumulated)
                dr.sync_thread()
                seconds = time.perf_counter() - start
                compile_seconds, launched, compiled = _kernel_costs(dr.kernel_history())

                # ------------------------------- Guide update -------------------------------
                start = time.perf_counter()
                guide_stats = guide.update(spp_total + spp) if guide is not None else {}
                dr.sync_thread()
                update_seconds = time.perf_counter() - start
                dr.kernel_history()  # update kernels are timed above, not counted as render kernels

                hit_rate = (integrator.hit_count[0] / max(integrator.path_count[0], 1)) if counters else float("nan")
                spp_total += spp
                passes.append(PassStats(index, spp, spp_total, seconds, update_seconds, compile_seconds, launched,
                                        compiled, float(hit_rate), guide_stats))
                if index >= budget.exclude_passes:
                    counted += passes[-1].counted_seconds
                display.show(spp_total, counted)
                if guide_stats.get("iteration_done") and not (budget.spp is not None and spp_total >= budget.spp):
                    spp_in_image = 0  # the next iteration starts the image afresh
    finally:
        display.close()

    image = (accumulated / spp_in_image).numpy().astype(np.float32)[..., :3]
    return RenderResult(image, passes, budget, spp_in_image)
