"""The pass driver: what every progressive loop (:func:`guiding.render.progressive.render`, the benchmark, the statistical
checks) does for one pass, defined once.

Life cycle: ``PassDriver(scene, integrator)``, ``prepare(spp_budget)`` once, then ``run(seed, spp)`` per pass:
render the pass, synchronise the device, read the pass's kernel history, and let the guide update from what the
pass recorded. A guide-less integrator (any Mitsuba integrator) goes through the same steps with nothing to update.

Times: ``seconds`` is wall time from launch to synchronisation (Python tracing and compilation included);
``kernels`` splits the pass's kernel history into execution and compilation (:class:`KernelCosts`, the only
definition of compile time in the package); the guide's update is timed apart, and the kernels it launches are not
counted as the pass's.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from guiding.guides import UpdateResult


@dataclass
class KernelCosts:
    """The kernels of one pass, from Dr.Jit's kernel history."""

    execution_seconds: float   # time the kernels ran
    compile_seconds: float     # code generation and backend compilation of the JIT kernels
    launched: int              # JIT kernels launched
    compiled: int              # JIT kernels new to this process (compiled, or loaded from the disk cache)

    @classmethod
    def from_history(cls, history: list[dict]) -> KernelCosts:
        jit = [k for k in history if k.get("type") == dr.KernelType.JIT]
        return cls(execution_seconds=sum(k.get("execution_time", 0.0) for k in history) / 1e3,
                   compile_seconds=sum(k.get("codegen_time", 0.0) + k.get("backend_time", 0.0) for k in jit) / 1e3,
                   launched=len(jit), compiled=sum(1 for k in jit if not k.get("cache_hit", False)))


@dataclass
class PassOutcome:
    """One pass: its image, its times and what the integrator counted (zero for one whose ``counts_paths`` is not
    true, such as any Mitsuba integrator)."""

    image: mi.TensorXf
    seconds: float             # launch to synchronisation
    kernels: KernelCosts
    update_seconds: float      # the guide's update after the pass
    update: UpdateResult
    paths: int = 0             # paths traced, and those with a non-zero contribution
    hits: int = 0
    rays: int = 0
    counted: bool = False      # whether the integrator counts paths (``guided_path`` does)

    @property
    def hit_rate(self) -> float:
        return self.hits / max(self.paths, 1) if self.counted else float("nan")


def pass_seed(seed: int, index: int) -> int:
    """A distinct 32-bit sampler seed for every (run seed, pass) pair."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


def render_pass(scene: mi.Scene, integrator: mi.SamplingIntegrator, sensor: int | mi.Sensor, seed: int,
                spp: int) -> mi.TensorXf:
    """One pass: an integrator with a ``render_pass`` of its own (``guided_path``, whose ``render`` is the progressive
    loop) renders it that way, any other integrator by ``mi.render``."""
    if hasattr(integrator, "render_pass"):
        return integrator.render_pass(scene, scene.sensors()[sensor] if isinstance(sensor, int) else sensor, seed,
                                      spp)
    return mi.render(scene, integrator=integrator, spp=spp, seed=seed, sensor=sensor)


class PassDriver:
    """Runs the passes of one render of ``scene`` with ``integrator`` (its ``guide``, if any, learns in between).

    Parameters:
      scene: the loaded scene.
      integrator: a ``guided_path`` integrator or any Mitsuba sampling integrator.
      sensor: the sensor to render, or its index.
    """

    def __init__(self, scene: mi.Scene, integrator: mi.SamplingIntegrator, sensor: int | mi.Sensor = 0):
        self.scene, self.integrator, self.sensor = scene, integrator, sensor
        self.guide = getattr(integrator, "guide", None)
        self.spp_done = 0

    def prepare(self, spp_budget: int | None = None) -> None:
        """Before the first pass: the integrator and its guide prepare for the scene (``prepare``), and the guide
        learns the spp budget (None: a time budget). In a scene with nothing to guide (``Guide.guides_any``) the
        driver drops the guide: its passes are BSDF sampling, and nothing updates between them."""
        guide = getattr(self.integrator, "guide", None)
        if guide is not None:
            self.integrator.prepare(self.scene)
            guide.set_budget(spp_budget)
            # Nothing in the scene to guide: the passes trace BSDF sampling and record nothing, so the guide's
            # update would only rebuild empty tables after every pass (and keep passes from growing).
            self.guide = guide if self.integrator.guides_scene else None
        self.spp_done = 0

    def run(self, seed: int, spp: int, accumulate: Callable[[mi.TensorXf], None] | None = None) -> PassOutcome:
        """Render one pass of ``spp`` samples per pixel with sampler seed ``seed``, then update the guide.

        ``accumulate(image)`` runs inside the timed region, before synchronisation (the progressive renderer adds
        the pass to its running sums there, so that its kernel is timed with the pass)."""
        integrator, counts = self.integrator, getattr(self.integrator, "counts_paths", False)
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()   # discard what ran before this pass
            if counts:
                integrator.reset_counters()

            # ------------------------------ Render one pass ------------------------------
            start = time.perf_counter()
            image = render_pass(self.scene, integrator, self.sensor, seed, spp)
            if accumulate is not None:
                accumulate(image)
            dr.eval(image)
            dr.sync_thread()
            seconds = time.perf_counter() - start
            kernels = KernelCosts.from_history(dr.kernel_history())
            outcome = PassOutcome(image, seconds, kernels, 0.0, UpdateResult(), counted=counts)
            if counts:
                outcome.paths, outcome.hits = int(integrator.path_count[0]), int(integrator.hit_count[0])
                outcome.rays = int(integrator.ray_count[0])

            # ------------------------------- Guide update -------------------------------
            self.spp_done += spp
            if self.guide is not None:
                start = time.perf_counter()
                outcome.update = self.guide.update(self.spp_done)
                dr.sync_thread()
                outcome.update_seconds = time.perf_counter() - start
            dr.kernel_history()   # the update's kernels are timed above, not counted as the pass's
        return outcome
