"""The path fallback: a guided render with next-event estimation that hands the rest of its budget to Mitsuba's own
``path`` where guiding does not pay (``path_fallback`` of :class:`~guiding.render.integrator.GuidedPathIntegrator`).

Guiding pays where its lower variance per sample outweighs its cost per sample; on a directly lit scene, or one
whose light a guide cannot learn, ``path`` (the same estimator as BSDF sampling with NEE, at its own cost) wins at
equal time (results/paper/README.md, "Practical"). The check, made once per render:

1. The guide trains and renders as usual until :data:`CHECK_SHARE` of the budget (its seconds counted, or its spp)
   is spent.
2. Two passes of ``path`` follow, each of the last guided pass's spp.
3. For each strategy, the error it would leave after the rest of the budget is predicted from two of its own
   passes (:func:`predicted_mae`): the last two guided passes, the two ``path`` passes. The rest of the budget goes
   to the lower. Under an spp budget both render the spp left; under a seconds budget each renders the seconds left
   at its own measured cost per spp (render and the guide's update, compilation excluded).

Where the guide has nothing to guide in the scene (:meth:`~guiding.guides.base.Guide.guides_any`), every pass is
``path`` already, with or without the fallback (:attr:`~guiding.render.integrator.GuidedPathIntegrator.renders_path`).
Guides with iterations (the SD-tree) are not checked: their final image already weighs their iterations
(:mod:`guiding.render.progressive`).

**Unbiased.** The passes before the decision (the two ``path`` passes included) form one image, the passes after it
another, and the final image weighs them by shares made of the spp and the times alone, never of the images
(:meth:`PathFallback.share_before`): under an spp budget by their spp;
under a seconds budget as if the cheaper strategy per spp rendered the rest. Each part is an unbiased image given
what came before it, so the weighted sum is unbiased. Where the dearer strategy renders the rest, the part before
gets less than its share of the spp; it was rendered by a guide still learning, and in part by the other
strategy, so its samples are worth less than the rest's where the guide wins, and where ``path`` wins the share is
its share of the spp.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass

import mitsuba as mi
import numpy as np

from guiding.metrics import tone_map
from guiding.render.driver import PassDriver

#: Share of the budget the guide renders before the check: enough for the guide to learn (stopping its learning at
#: a quarter of a 10 s budget left the error of ``ours-plus`` with NEE within the seeds' spread on six scenes), and
#: little enough that ``path`` takes over most of the budget where it wins.
CHECK_SHARE = 0.1
#: Passes of each strategy the prediction compares.
COMPARED_PASSES = 2

GUIDE, PATH = "guide", "path"


def predicted_mae(mean: np.ndarray, first: np.ndarray, first_spp: int, second: np.ndarray, second_spp: int,
                  spp: float) -> float:
    """The tone-mapped MAE (:func:`guiding.metrics.mae_tonemapped`) that an image of ``spp`` samples per pixel of
    a strategy is predicted to have around ``mean``, from two independent pass images of the strategy (``first``,
    ``second``, of ``first_spp`` and ``second_spp`` spp).

    The difference of the passes has per pixel the variance ``σ²(1/s₁ + 1/s₂)`` (σ² of one sample), so
    ``(first − second) / sqrt((1/s₁ + 1/s₂)·spp)`` is one draw of the error of an ``spp``-sample image; the mean
    over pixels and channels of ``|T(mean + draw) − T(mean)|`` estimates that image's MAE (the tone map ``T`` taken
    as it is, not linearised, so dark pixels weigh as they do in the MAE)."""
    draw = (first - second) / math.sqrt((1.0 / first_spp + 1.0 / second_spp) * spp)
    return float(np.mean(np.abs(tone_map(mean + draw) - tone_map(mean))))


@dataclass
class PassImage:
    """One pass of a strategy, as the check reads it."""

    image: object              # the pass's image as rendered (a device tensor; read on the host only to decide)
    spp: int
    counted_seconds: float     # render and update, compilation excluded


@dataclass
class FallbackDecision:
    """What the check decided, for ``stats.json`` (:attr:`~guiding.render.progressive.RenderResult.path_fallback`)."""

    chosen: str                            # GUIDE or PATH: what renders the rest of the budget
    reason: str
    spp: int = 0                           # spp and counted seconds when it was decided
    seconds: float = 0.0
    guide_mae: float | None = None         # predicted MAE of each strategy after the rest of the budget
    path_mae: float | None = None
    guide_seconds_per_spp: float | None = None
    path_seconds_per_spp: float | None = None
    share_before: float | None = None      # weight of the image made before the decision

    def summary(self) -> dict:
        return asdict(self)


def nothing_to_guide() -> FallbackDecision:
    """The record of a render whose every pass Mitsuba's ``path`` rendered because the guide had nothing to guide
    (:attr:`~guiding.render.integrator.GuidedPathIntegrator.renders_path`; with or without the check)."""
    return FallbackDecision(PATH, "the guide has nothing to guide in this scene")


def _rgb(image) -> np.ndarray:
    """A pass image on the host, (H, W, 3) float64."""
    return np.asarray(image, dtype=np.float64)[..., :3]


def _seconds_per_spp(passes: list[PassImage]) -> float:
    return sum(p.counted_seconds for p in passes) / sum(p.spp for p in passes)


class PathFallback:
    """The check of one render: which strategy renders the next pass, the passes it compares, its decision.

    Parameters:
      driver: the pass driver of Mitsuba's ``path`` (:meth:`for_render`).
      checked: whether to compare the strategies (False for guides with iterations: every pass is the guide's).
    """

    def __init__(self, driver: PassDriver, checked: bool):
        self.driver = driver
        self.guided: deque[PassImage] = deque(maxlen=COMPARED_PASSES)
        self.path_passes: list[PassImage] = []
        self.decision = None
        self.checked = checked
        self.comparing = False

    @classmethod
    def for_render(cls, scene: mi.Scene, path: mi.SamplingIntegrator, sensor, guide) -> PathFallback:
        """The check of a render of ``scene`` with Mitsuba's ``path`` beside ``guide``."""
        driver = PassDriver(scene, path, sensor)
        driver.prepare()
        return cls(driver, checked=guide.iteration_spp() is None)

    @property
    def renders_path(self) -> bool:
        """Whether the next pass is a ``path`` pass."""
        return self.comparing or (self.decision is not None and self.decision.chosen == PATH)

    @property
    def watches(self) -> bool:
        """Whether the check still reads the passes' images."""
        return self.checked and self.decision is None

    def compare_spp(self) -> int | None:
        """The spp of the next ``path`` pass while comparing (that of the last guided pass), else None."""
        return self.guided[-1].spp if self.comparing else None

    def observe(self, image, spp: int, counted_seconds: float) -> None:
        """A pass rendered while the check watches, by the strategy :attr:`renders_path` said."""
        (self.path_passes if self.comparing else self.guided).append(PassImage(image, spp, counted_seconds))

    def start_due(self, budget_spent: float) -> bool:
        """Whether the ``path`` passes start now: :data:`CHECK_SHARE` of the budget spent, two guided passes seen."""
        return (self.watches and not self.comparing and budget_spent >= CHECK_SHARE
                and len(self.guided) == COMPARED_PASSES)

    def share_before(self, spp_before: int, spp_budget: int | None, seconds_left: float | None) -> float:
        """The weight of the image made up to the decision, from spp and times alone (module docstring):
        ``spp_before`` (the ``path`` passes' spp included) over that plus the most spp the rest of the budget can
        hold (the spp budget's rest, or ``seconds_left`` at the lower seconds per spp of the two strategies)."""
        if spp_budget is not None:
            return min(spp_before / spp_budget, 1.0)
        cheaper = min(_seconds_per_spp(list(self.guided)), _seconds_per_spp(self.path_passes))
        return spp_before / (spp_before + max(seconds_left, 0.0) / cheaper)

    def decide(self, mean: np.ndarray, spp: int, seconds: float, spp_left: int | None,
               seconds_left: float | None, share_before: float) -> FallbackDecision:
        """After the ``path`` passes: the strategy whose predicted MAE after what is left of the budget
        (``spp_left`` spp for both, or ``seconds_left`` at each one's seconds per spp) is lower; ``mean`` is the
        image so far."""
        costs = {GUIDE: _seconds_per_spp(list(self.guided)), PATH: _seconds_per_spp(self.path_passes)}
        errors = {}
        for strategy, (first, second) in ((GUIDE, self.guided), (PATH, self.path_passes)):
            rest = spp_left if spp_left is not None else max(seconds_left, 0.0) / costs[strategy]
            errors[strategy] = predicted_mae(mean, _rgb(first.image), first.spp, _rgb(second.image), second.spp,
                                             max(rest, 1.0))
        chosen = PATH if errors[PATH] < errors[GUIDE] else GUIDE
        reason = (f"{'Mitsuba path' if chosen == PATH else 'the guide'} is predicted the lower error after the rest "
                  "of the budget")
        self.comparing = False
        self.decision = FallbackDecision(chosen, reason, spp, seconds, errors[GUIDE], errors[PATH], costs[GUIDE],
                                         costs[PATH], share_before)
        self.guided.clear()
        self.path_passes.clear()
        return self.decision
