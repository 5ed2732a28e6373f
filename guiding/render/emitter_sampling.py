"""Next-event estimation for the guided path loop: one emitter sample per vertex, combined with the directions the
guide samples by multiple importance sampling (the power heuristic, as Mitsuba's ``path``).

Both strategies' weights use the densities the loop really samples with: the emitter sample's ``ds.pdf`` and the
guide's one-sample mixture of BSDF and guide (:meth:`guiding.guides.base.Guide.pdf`, equal to the ``bs.pdf`` its
``sample`` reports), not the BSDF's density alone. Delta emitters (point, directional) are reached only by emitter
sampling (weight 1); delta BSDF lobes only by the guide's sample (weight 1 on the emission they hit).

Emitters it cannot sample are refused before a render (:func:`unsampleable_emitters`).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


#: Emitters (by Mitsuba class name, with their plugin's name) whose directions Mitsuba cannot sample inside a traced
#: call: its own ``path`` integrator fails on them, and Dr.Jit aborts the process where the scene has other emitters
#: too (tests/test_nee.py checks that this is still so).
UNSAMPLED_IN_TRACED_CALLS = {"TimedSunskyEmitter": "timed_sunsky"}


def unsampleable_emitters(scene: mi.Scene) -> list[str]:
    """The emitters of ``scene`` that next-event estimation cannot sample, each named by its plugin with why:
    those of :data:`UNSAMPLED_IN_TRACED_CALLS`, and surfaces that emit in one direction only (``directionalarea``),
    whose light no emitter sample from a point can reach (Mitsuba renders them only with its particle tracer)."""
    found = []
    for emitter in scene.emitters():
        flags = emitter.flags()
        if emitter.class_name() in UNSAMPLED_IN_TRACED_CALLS:
            found.append(f"'{UNSAMPLED_IN_TRACED_CALLS[emitter.class_name()]}' (Mitsuba {mi.__version__} cannot "
                         "sample its directions in a traced call)")
        elif mi.has_flag(flags, mi.EmitterFlags.Surface) and mi.has_flag(flags, mi.EmitterFlags.DeltaDirection):
            found.append("'directionalarea' (it emits in one direction only: only a particle tracer renders it)")
    return found


def mis_weight(pdf_a: mi.Float, pdf_b: mi.Float) -> mi.Float:
    """The power heuristic's weight of strategy a against b (0 where both densities are 0 or a's is infinite)."""
    a2, b2 = dr.square(pdf_a), dr.square(pdf_b)
    return dr.detach(dr.select(dr.isfinite(a2) & (a2 + b2 > 0), a2 / (a2 + b2), 0))


@dataclass
class PreviousVertex:
    """What the weight of emission found by a sampled direction needs of the vertex the direction left: the
    interaction, the density the direction was sampled with, and whether it was a delta lobe's (or the camera's)."""

    si: mi.Interaction3f = None
    pdf: mi.Float = None
    delta: mi.Bool = None
    DRJIT_STRUCT = {"si": mi.Interaction3f, "pdf": mi.Float, "delta": mi.Bool}

    @staticmethod
    def camera(size: int) -> "PreviousVertex":
        """Before the first bounce: emitters seen directly take weight 1."""
        return PreviousVertex(dr.zeros(mi.Interaction3f, size), dr.zeros(mi.Float, size), dr.full(mi.Bool, True, size))


def hit_weight(scene: mi.Scene, si: mi.SurfaceInteraction3f, previous: PreviousVertex, active: mi.Bool) -> mi.Float:
    """MIS weight of the emission at ``si`` (or of the environment, where the ray escaped), found by the direction
    sampled at ``previous``: against the density with which emitter sampling at ``previous`` finds the same point."""
    ds = mi.DirectionSample3f(scene, si=si, ref=previous.si)
    emitter_pdf = scene.pdf_emitter_direction(previous.si, ds, active & ~previous.delta & (ds.emitter != None))
    return dr.select(previous.delta, 1.0, mis_weight(previous.pdf, emitter_pdf))


@dataclass
class EmitterDirection:
    """One emitter sample at a vertex, before the BSDF is evaluated there: the direction sample, the emitter's weight
    ``Le/p_e`` (visibility tested), the direction in the local frame, and the lanes that have a sample."""

    ds: mi.DirectionSample3f
    emitter_weight: mi.Spectrum
    wo: mi.Vector3f
    active: mi.Bool


@dataclass
class EmitterSample:
    """One next-event sample at a vertex: its contribution before the path weight β (``f·cos·Le/p_e`` times its MIS
    weight), its direction (local) and the two densities of the MIS weight."""

    contribution: mi.Spectrum
    wo: mi.Vector3f
    emitter_pdf: mi.Float
    guide_pdf: mi.Float
    weight: mi.Float


def sample_emitter_direction(scene: mi.Scene, sampler: mi.Sampler, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr,
                             active: mi.Bool) -> EmitterDirection:
    """Next-event estimation's emitter sample at ``si``, for the lanes ``active`` whose BSDF has a smooth component
    (visibility tested). The BSDF's value there comes from the guide's
    :meth:`~guiding.guides.base.Guide.sample_and_eval`, in the call that samples the next direction."""
    active = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
    ds, emitter_weight = scene.sample_emitter_direction(si, sampler.next_2d(active), True, active)
    active &= ds.pdf != 0
    return EmitterDirection(ds, emitter_weight, si.to_local(ds.d), active)


def weigh_emitter_sample(light: EmitterDirection, value: mi.Spectrum, bsdf_pdf: mi.Float, guide,
                         si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, bsdf_ctx: mi.BSDFContext,
                         vertex=None) -> EmitterSample:
    """The emitter sample ``light`` with the BSDF's ``value`` (``f·cos``) and density ``bsdf_pdf`` in its direction:
    its MIS weight against ``guide.pdf``, the loop's own density there (``vertex``: what ``guide.locate`` found at
    ``si``, None: the guide finds it itself), and its contribution."""
    ds = light.ds
    guide_pdf = guide.pdf(si, bsdf, bsdf_ctx, light.wo, light.active, bsdf_pdf, vertex)
    weight = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, guide_pdf))
    contribution = dr.select(light.active, weight * value * light.emitter_weight, 0)
    return EmitterSample(contribution, light.wo, ds.pdf, guide_pdf, weight)
