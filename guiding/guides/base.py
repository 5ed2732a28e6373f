"""The Guide interface: one path loop (:mod:`guiding.render.integrator`), many ways to choose directions."""

from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from guiding.guides.parameters import COMBINE_LAST


def rgb_mean(spectrum: mi.Spectrum) -> mi.Float:
    """The mean of an RGB value's three channels, per lane. Not ``dr.mean``, whose per-lane mean is traced as a
    sum times the array's width over three times its width: the width is a literal of the kernel, and every pass
    of another size was a new render kernel, compiled again."""
    return (spectrum.x + spectrum.y + spectrum.z) * (1.0 / 3.0)


@dataclass
class NoPathState:
    """Per-path learning state of a guide that learns nothing (an empty Dr.Jit PyTree)."""

    DRJIT_STRUCT = {}


@dataclass
class UpdateResult:
    """What :meth:`Guide.update` reports about the pass it learned from."""

    #: Per-pass statistics for ``stats.json`` and the benchmark (counters, timings, table sizes).
    stats: dict = field(default_factory=dict)
    #: The pass ended one of the guide's iterations: the distributions change now, and a renderer that keeps only
    #: the last iteration starts a new image.
    iteration_done: bool = False


class Guide:
    """Base class of all guides; the defaults describe plain BSDF sampling that learns nothing.

    Host side, in this order:
      ``prepare(scene)`` once before the first pass; ``update(spp_done)`` after each pass, once the pass's
      kernel has run (an :class:`UpdateResult`); ``stats()`` at any time; ``records()`` and ``trace_key()`` before
      each pass.
    Device side, traced into the path loop:
      ``new_paths(size, max_depth)`` builds the per-path state carried through the loop;
      ``guides(bsdf, active)`` the lanes whose BSDF it may guide (the others are BSDF-sampled);
      ``locate(si, bsdf, active)`` finds the vertex in the guide's structure once, for ``sample`` and ``record``;
      ``sample(...)`` draws the next direction; with next-event estimation ``sample_and_eval(...)`` draws it and
      evaluates the BSDF towards the emitter sample (one BSDF call where it can: BSDF sampling, and the grid
      guides in scenes of Lambertian BSDFs);
      ``record(...)`` hands the guide what the path saw at a vertex (learning rules live here);
      ``finish_paths(state)`` runs once after the loop (e.g. the backward walk of Monte Carlo learning).
    """

    #: Short method name, as used on the command line and in tables.
    name = "guide"
    #: The final image a renderer makes of this guide's iterations unless told otherwise (``combine`` of
    #: :func:`guiding.render.progressive.render`; one of :data:`~guiding.guides.parameters.COMBINE_MODES`). A guide without
    #: iterations has one, which every mode returns.
    combine = COMBINE_LAST

    # ---------------------------------------------------------------- host side
    def prepare(self, scene: mi.Scene) -> None:
        """Allocate tables for ``scene`` before the first pass."""

    def update(self, spp_done: int) -> UpdateResult:
        """Rebuild the sampling distributions from what the last pass recorded (``spp_done`` spp so far)."""
        return UpdateResult()

    def update_due(self, spp_done: int) -> int | None:
        """The spp total at which the distributions next change, asked after the update that followed
        ``spp_done`` spp: a renderer may render up to there in one pass. ``spp_done`` (the default): after every
        pass; None: never (the guide learns nothing, or has stopped)."""
        return spp_done

    def records(self) -> bool:
        """Whether the next pass records what its paths see (``record`` / ``finish_paths``); the path loop is
        traced without them otherwise. A scheduled guide stops recording in its final iteration."""
        return False

    def stats(self) -> dict:
        """Memory and configuration figures for ``stats.json``."""
        return {}

    def trace_key(self) -> tuple:
        """The host-side values that shape the traced path loop (Python branches, literals): a pass whose key is
        new traces it, the others replay a recording (:mod:`guiding.render.frozen_pass`). Tables are not part of it: every
        Dr.Jit array of the guide is an input of the replay."""
        return (self.records(),)

    # ----------------------------------------------------------- schedule (host side)
    # A guide whose learning runs in iterations (the SD-tree) ends one by setting ``UpdateResult.iteration_done``;
    # the renderer then asks ``iteration_spp`` whether the next fits a seconds budget and
    # calls ``stop_training`` when it does not. Guides without iterations keep these defaults and are never asked
    # about iterations; a guide whose ``learning_share`` is below 1 (the grid's parameter) is stopped after it.
    def set_budget(self, spp: int | None) -> None:
        """The render's spp budget (None under a seconds budget), told once before the first pass."""

    def iteration_spp(self) -> int | None:
        """Length in spp of the iteration the next pass belongs to; None for a guide without iterations (or when
        it is unknown)."""
        return None

    def learning_share(self) -> float:
        """The share of the render's budget (spp, or counted seconds) after which the renderer calls
        :meth:`stop_training`; 1: the guide learns to the end of the budget (the default)."""
        return 1.0

    def stop_training(self) -> None:
        """Freeze the distributions, at once or at the guide's next update (the grid's next rebuild): the passes after
        that record nothing and run to the end of the budget."""

    # -------------------------------------------------------------- device side
    def new_paths(self, size: int, max_depth: int):
        """Per-path state for ``size`` paths of at most ``max_depth`` vertices (a Dr.Jit PyTree)."""
        return NoPathState()

    def locate(self, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, active: mi.Bool):
        """Where vertex ``si`` lies in the guide's structure (the SD-tree's S-tree leaf, say), found once for
        ``pdf``, ``sample`` and ``record`` (the path loop hands it to all three); None for a guide that finds
        nothing ahead."""
        return None

    def sample(self, scene: mi.Scene, sampler: mi.Sampler, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr,
               bsdf_ctx: mi.BSDFContext, active: mi.Bool, vertex=None) -> tuple[mi.BSDFSample3f, mi.Spectrum]:
        """Sample the direction leaving ``si``; returns the BSDF sample (``wo`` in the local frame, ``pdf`` the
        density actually used) and the weight ``f·cos/pdf``, exactly like ``BSDF.sample``. ``vertex``: what
        :meth:`locate` found at ``si`` (None: the guide finds it itself)."""
        return bsdf.sample(bsdf_ctx, si, sampler.next_1d(active), sampler.next_2d(active), active)

    def sample_and_eval(self, scene: mi.Scene, sampler: mi.Sampler, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr,
                        bsdf_ctx: mi.BSDFContext, active: mi.Bool, wo: mi.Vector3f, wo_active: mi.Bool,
                        vertex=None) -> tuple[mi.Spectrum, mi.Float, mi.BSDFSample3f, mi.Spectrum]:
        """The BSDF's value (``f·cos``) and density at local direction ``wo`` for the lanes ``wo_active`` (next-event
        estimation's emitter direction), then :meth:`sample` for the lanes ``active``: what ``bsdf.eval_pdf_sample``
        returns (at lanes outside ``wo_active`` the value and density are not asked for, whatever they are). A guide
        that samples other directions than the BSDF's evaluates, then samples: two BSDF calls."""
        value, bsdf_pdf = bsdf.eval_pdf(bsdf_ctx, si, wo, wo_active)
        bs, weight = self.sample(scene, sampler, si, bsdf, bsdf_ctx, active, vertex)
        return value, bsdf_pdf, bs, weight

    def record(self, state, si: mi.SurfaceInteraction3f, emitted: mi.Spectrum, bs: mi.BSDFSample3f,
               weight: mi.Spectrum, continues: mi.Bool, active: mi.Bool, vertex=None):
        """Learn from vertex ``si`` of the active paths.

        ``emitted`` is the radiance emitted at ``si`` towards the previous vertex; ``bs``/``weight`` the direction
        sampled at ``si`` and its weight including the Russian-roulette factor; ``continues`` whether the path goes
        on from ``si`` (false at escapes, absorption, maximum depth and Russian-roulette termination); ``vertex``
        what :meth:`locate` found at ``si`` (None: the guide finds it itself).
        """
        return state

    def finish_paths(self, state) -> None:
        """Called once after the path loop with the final per-path state."""

    def guides(self, bsdf: mi.BSDFPtr, active: mi.Bool) -> mi.Bool:
        """The lanes whose BSDF this guide may guide, from its flags alone (elsewhere it samples the BSDF and pays
        nothing else); BSDF sampling guides none."""
        return active & False

    def guides_any(self, scene: mi.Scene) -> bool:
        """Whether some BSDF of ``scene`` is one this guide guides (:meth:`guides`; host side). A scene with
        instances counts as guided: the BSDFs of instanced shapes are not listed."""
        if any(shape.class_name() == "Instance" for shape in scene.shapes()):
            return True
        bsdfs = scene.shapes_dr().bsdf()
        return bool(dr.any(self.guides(bsdfs, dr.full(mi.Bool, True, dr.width(bsdfs))))[0])

    def pdf(self, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, bsdf_ctx: mi.BSDFContext, wo: mi.Vector3f,
            active: mi.Bool, bsdf_pdf: mi.Float | None = None, vertex=None) -> mi.Float:
        """Density (solid angle) with which :meth:`sample` draws local direction ``wo`` at ``si`` (the chi-square
        tests compare it with the samples); BSDF sampling's by default. ``bsdf_pdf``: the BSDF's own density of
        ``wo``, where the caller has it already (next-event estimation reads it with the BSDF's value); ``vertex``: what
        :meth:`locate` found at ``si`` (None: the guide finds it itself)."""
        return bsdf.pdf(bsdf_ctx, si, wo, active) if bsdf_pdf is None else bsdf_pdf
