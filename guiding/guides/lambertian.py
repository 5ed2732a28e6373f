"""Lambertian BSDFs evaluated and sampled in the path loop itself, not through Mitsuba's BSDF call.

A guided vertex needs the BSDF's value and density at the guide's direction and a BSDF sample (the two strategies
of the one-sample mixture). Mitsuba's ``BSDF.eval_pdf_sample`` does both in one call, but for most BSDFs (``diffuse``
and ``twosided`` among them) as two calls in one, each evaluating the reflectance texture and, for ``twosided``,
choosing the side. Where the BSDF is Mitsuba's ``diffuse``, one-sided or wrapped two-sided in ``twosided``, all
of that is ``ρ·cos/π`` and a cosine-weighted direction: :class:`LambertianBsdfs` computes them inline from one
call of ``eval_diffuse_reflectance`` (the texture read once), the same values as Mitsuba's own (same warps, same
random numbers, the same lanes zero). Other BSDFs, and ``diffuse`` under any other wrapper (a bump or normal map
changes the frame, ``roughdiffuse`` is not Lambertian), keep Mitsuba's call.
"""

from __future__ import annotations

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


class LambertianBsdfs:
    """Which of a scene's BSDFs are Lambertian (:func:`lambertian_sides`), by their Dr.Jit registry id, and their
    value, density and samples computed inline.

    Parameters:
      scene: the scene whose shapes' BSDFs are looked at (None: no BSDF is known, every lane takes Mitsuba's call).
    """

    def __init__(self, scene: mi.Scene | None = None):
        sides = {}
        for shape in scene.shapes() if scene is not None else []:
            bsdf = shape.bsdf()
            if bsdf is not None:
                sides[int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(bsdf))[0])] = lambertian_sides(bsdf)
        table = [NOT_LAMBERTIAN] * (max(sides, default=0) + 1)
        for registry_id, side in sides.items():
            table[registry_id] = side
        self.any = any(side != NOT_LAMBERTIAN for side in table)
        self._sides = mi.UInt32(table)

    def sides(self, bsdf: mi.BSDFPtr, active: mi.Bool) -> mi.UInt32:
        """:data:`NOT_LAMBERTIAN`, :data:`FRONT_SIDE` or :data:`BOTH_SIDES` per lane (a BSDF the table does not know
        is not Lambertian)."""
        registry_id = dr.reinterpret_array(mi.UInt32, bsdf)
        known = active & (registry_id < dr.width(self._sides))
        return dr.gather(mi.UInt32, self._sides, registry_id, known)

    def eval_pdf_sample(self, bsdf: mi.BSDFPtr, bsdf_ctx: mi.BSDFContext, si: mi.SurfaceInteraction3f,
                        wo: mi.Vector3f, sample1: mi.Float, sample2: mi.Point2f, active: mi.Bool):
        """What ``bsdf.eval_pdf_sample`` returns (value and density at local direction ``wo``, a BSDF sample and its
        weight), inline at Lambertian lanes, through Mitsuba's call at the others. Inline lanes ignore ``bsdf_ctx``
        (the path loop's is the default context, every lobe enabled)."""
        if not self.any:
            return bsdf.eval_pdf_sample(bsdf_ctx, si, wo, sample1, sample2, active)
        sides = self.sides(bsdf, active)
        inline = active & (sides != NOT_LAMBERTIAN)
        value, pdf, bs, weight = bsdf.eval_pdf_sample(bsdf_ctx, si, wo, sample1, sample2, active & ~inline)

        # Mitsuba's twosided turns a back-side query into a front-side one of its back BSDF (wi and wo mirrored);
        # diffuse alone is black from behind.
        cos_i = mi.Frame3f.cos_theta(si.wi)
        mirrored = (cos_i < 0) & (sides == BOTH_SIDES)
        lit = inline & ((cos_i > 0) | mirrored)
        flip = dr.select(mirrored, -1.0, 1.0)
        albedo = bsdf.eval_diffuse_reflectance(si, lit)

        cos_o = flip * mi.Frame3f.cos_theta(wo)
        facing = lit & (cos_o > 0)
        value = dr.select(inline, dr.select(facing, albedo * (cos_o * dr.inv_pi), 0), value)
        pdf = dr.select(inline, dr.select(facing, cos_o * dr.inv_pi, 0), pdf)

        local = mi.warp.square_to_cosine_hemisphere(sample2)
        sample_pdf = mi.warp.square_to_cosine_hemisphere_pdf(local)
        bs.wo = dr.select(inline, mi.Vector3f(local.x, local.y, flip * local.z), bs.wo)
        bs.pdf = dr.select(inline, sample_pdf, bs.pdf)
        bs.eta = dr.select(inline, 1.0, bs.eta)
        bs.sampled_type = dr.select(inline, mi.UInt32(+mi.BSDFFlags.DiffuseReflection), bs.sampled_type)
        bs.sampled_component = dr.select(inline, mi.UInt32(0), bs.sampled_component)
        weight = dr.select(inline, dr.select(lit & (sample_pdf > 0), albedo, 0), weight)
        return value, pdf, bs, weight
