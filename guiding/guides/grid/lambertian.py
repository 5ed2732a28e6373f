"""Lambertian BSDFs evaluated and sampled in the path loop itself, not through Mitsuba's BSDF calls.

A guided vertex needs the BSDF's value and density at the guide's direction and a BSDF sample (the two strategies
of the one-sample mixture). Mitsuba's ``BSDF.eval_pdf_sample`` does both in one call, but for most BSDFs (``diffuse``
and ``twosided`` among them) as two calls in one, each evaluating the reflectance texture and, for ``twosided``,
choosing the side. Where the BSDF is Mitsuba's ``diffuse``, one-sided or wrapped two-sided in ``twosided``, all of
that is ``ρ·cos/π`` and a cosine-weighted direction: :class:`LambertianBsdfs` computes them inline from one call of
``eval_diffuse_reflectance`` (the texture read once), the same values as Mitsuba's own (same warps, same random
numbers, the same lanes zero), where every BSDF a guide guides in the scene is such a BSDF. Any other BSDF,
``diffuse`` under another wrapper included (a bump or normal map changes the frame, a blend may mix in other lobes),
keeps Mitsuba's calls for the whole scene.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

#: Sides of a BSDF in the table: not Lambertian (Mitsuba's call), ``diffuse`` (front side only), ``twosided`` of
#: ``diffuse`` on both sides.
NOT_LAMBERTIAN, FRONT_SIDE, BOTH_SIDES = 0, 1, 2


def lambertian_sides(bsdf: mi.BSDF) -> int:
    """:data:`FRONT_SIDE` for Mitsuba's ``diffuse``, :data:`BOTH_SIDES` for ``twosided`` with ``diffuse`` on both
    sides, :data:`NOT_LAMBERTIAN` for any other BSDF."""
    name = bsdf.class_name()
    if name == "SmoothDiffuse":
        return FRONT_SIDE
    if name == "TwoSidedBRDF":
        children = _children(bsdf)
        if children and all(child.class_name() == "SmoothDiffuse" for child in children):
            return BOTH_SIDES
    return NOT_LAMBERTIAN


def _children(bsdf: mi.BSDF) -> list:
    """The BSDFs a BSDF holds (``twosided``: its two sides)."""

    class Children(mi.TraversalCallback):
        def __init__(self):
            super().__init__()
            self.found = []

        def put(self, name, value, flags):
            if isinstance(value, mi.BSDF):
                self.found.append(value)

    callback = Children()
    bsdf.traverse(callback)
    return callback.found


@dataclass
class LambertianVertex:
    """What the inline evaluation and sampling share at a vertex (:meth:`LambertianBsdfs.vertex`)."""

    lit: mi.Bool          # a side the BSDF reflects on (front, or either for twosided)
    flip: mi.Float        # −1 where twosided mirrors a back-side query to its front, else 1
    albedo: mi.Spectrum   # ρ, from the BSDF's one call (what ``eval_diffuse_reflectance`` gives, either side)


class LambertianBsdfs:
    """Whether every BSDF a guide guides in a scene is Lambertian (:func:`lambertian_sides`), and then their value,
    density and samples computed inline; else Mitsuba's calls, unchanged. All or nothing per scene: with a BSDF of
    another kind, its lanes would need Mitsuba's call beside the inline one, and a call costs the passing of its
    arguments even in packets with no lane to run (a mixed kernel is slower than Mitsuba's call alone). A scene with instances keeps Mitsuba's calls: ``scene.shapes()`` lists an instance, not
    the shapes (and BSDFs) of its shape group, which its rays hit.

    Parameters:
      scene: the scene whose shapes' BSDFs are looked at (None: nothing inline).
      guided: which of them the guide asks about (by default all).
    """

    def __init__(self, scene: mi.Scene | None = None, guided: Callable[[mi.BSDF], bool] = lambda bsdf: True):
        shapes = scene.shapes() if scene is not None else []
        bsdfs = {}
        for shape in shapes:
            bsdf = shape.bsdf()
            if bsdf is not None:
                bsdfs[int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(bsdf))[0])] = bsdf
        sides = {registry_id: lambertian_sides(bsdf) for registry_id, bsdf in bsdfs.items()}
        asked = [sides[registry_id] for registry_id, bsdf in bsdfs.items() if guided(bsdf)]
        table = [NOT_LAMBERTIAN] * (max(sides, default=0) + 1)
        for registry_id, side in sides.items():
            table[registry_id] = side
        instanced = any(shape.class_name() == "Instance" for shape in shapes)
        #: Whether the asked BSDFs are computed inline (there is one, every one is Lambertian, and no instance).
        self.inline = bool(asked) and NOT_LAMBERTIAN not in asked and not instanced
        smooth = [bsdf for bsdf in bsdfs.values() if mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)]
        #: Whether every BSDF next-event estimation evaluates (those with a smooth lobe) is computed inline.
        self.inline_emitter_eval = self.inline and all(lambertian_sides(bsdf) != NOT_LAMBERTIAN and guided(bsdf)
                                                       for bsdf in smooth)
        self._sides = mi.UInt32(table)

    def sides(self, bsdf: mi.BSDFPtr, active: mi.Bool) -> mi.UInt32:
        """:data:`NOT_LAMBERTIAN`, :data:`FRONT_SIDE` or :data:`BOTH_SIDES` per lane (:data:`NOT_LAMBERTIAN` for a
        BSDF of no shape of the scene)."""
        registry_id = dr.reinterpret_array(mi.UInt32, bsdf)
        known = active & (registry_id < dr.width(self._sides))
        return dr.gather(mi.UInt32, self._sides, registry_id, known)

    def vertex(self, bsdf: mi.BSDFPtr, si: mi.SurfaceInteraction3f, active: mi.Bool) -> LambertianVertex | None:
        """The BSDF's side and albedo at the ``active`` lanes (whose BSDFs must be ones the table was asked about,
        ``guided``: it treats every other as one-sided diffuse); None where the scene's BSDFs are not computed
        inline. Mitsuba's twosided turns a back-side query into a front-side one of its back BSDF (wi and wo
        mirrored); diffuse alone is black from behind."""
        if not self.inline:
            return None
        cos_i = mi.Frame3f.cos_theta(si.wi)
        mirrored = (cos_i < 0) & (self.sides(bsdf, active) == BOTH_SIDES)
        lit = active & ((cos_i > 0) | mirrored)
        return LambertianVertex(lit=lit, flip=dr.select(mirrored, -1.0, 1.0),
                                albedo=bsdf.eval_diffuse_reflectance(si, active))

    @staticmethod
    def eval_pdf(vertex: LambertianVertex, wo: mi.Vector3f, active: mi.Bool) -> tuple[mi.Spectrum, mi.Float]:
        """What ``bsdf.eval_pdf`` returns at local direction ``wo``: ``ρ·cos/π`` and ``cos/π`` on the side the BSDF
        reflects on, from ``vertex`` (read at lanes including ``active``)."""
        cos_o = vertex.flip * mi.Frame3f.cos_theta(wo)
        facing = active & vertex.lit & (cos_o > 0)
        # Mitsuba's order of operations, so that the values are its own to the bit.
        value = dr.select(facing, vertex.albedo * dr.inv_pi * cos_o, 0)
        pdf = dr.select(facing, dr.inv_pi * cos_o, 0)
        return value, pdf

    def eval_pdf_sample(self, bsdf: mi.BSDFPtr, bsdf_ctx: mi.BSDFContext, si: mi.SurfaceInteraction3f,
                        wo: mi.Vector3f, sample1: mi.Float, sample2: mi.Point2f, active: mi.Bool,
                        vertex: LambertianVertex | None = None):
        """What ``bsdf.eval_pdf_sample`` returns: the value and density at local direction ``wo``, and a BSDF sample
        with its weight. Inline from ``vertex`` (read here if None, else read at lanes including ``active``), with
        the default context (every lobe enabled: the path loop's) and without ``sample1`` (one lobe); Mitsuba's
        single call where the scene is not inline."""
        vertex = self.vertex(bsdf, si, active) if vertex is None else vertex
        if vertex is None:
            return bsdf.eval_pdf_sample(bsdf_ctx, si, wo, sample1, sample2, active)
        value, pdf = self.eval_pdf(vertex, wo, active)
        local = mi.warp.square_to_cosine_hemisphere(sample2)
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = mi.Vector3f(local.x, local.y, vertex.flip * local.z)
        bs.pdf = mi.warp.square_to_cosine_hemisphere_pdf(local)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
        weight = dr.select(active & vertex.lit & (bs.pdf > 0), vertex.albedo, 0)
        return value, pdf, bs, weight
