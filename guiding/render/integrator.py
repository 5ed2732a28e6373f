"""The guided unidirectional path tracer (the paper's protocol, next-event estimation optional), registered as the
Mitsuba integrator ``guided_path``.

One Dr.Jit path loop serves every method: it asks a :class:`~guiding.guides.base.Guide` for each direction and
tells it what each vertex saw. Following Kim & Kim (2021), emitters are found by default only by the sampled
directions (no next-event estimation), paths stop at ``max_depth``, and Russian roulette starts at ``rr_depth`` with
the continuation probability ``q = max(max_rgb(β), rr_min)``. With ``nee``, every vertex the path continues from
with a smooth BSDF also samples an emitter, combined with the sampled directions by MIS as in Mitsuba's ``path``;
Russian roulette then starts at depth 5, as there, and weighs β by η² (η the relative index of refraction along the
path), as there, but keeps the paper's floor ``rr_min`` (where ``path`` caps ``q`` at 0.95 instead). Where a guide
that learns has nothing to guide in a scene, BSDF sampling with next-event estimation is ``path``'s estimator, so
Mitsuba's ``path`` renders those passes, at its own cost.

Usable from XML (``<integrator type="guided_path"><string name="method" value="ours"/></integrator>``), from
``mi.load_dict({'type': 'guided_path', ...})``, or built in Python with an explicit guide object. ``mi.render``
trains the guide: it runs the progressive passes of :func:`guiding.render.progressive.render` (``pass_spp`` and growing, the
guide updated in between) and returns their image.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from guiding.errors import GuidingError
from guiding.guides import BSDFGuide, Guide, NoPathState
from guiding.guides.methods import BadSetting, make_guide
from guiding.render import defaults
from guiding.render.emitter_sampling import (PreviousVertex, hit_weight, sample_emitter_direction,
                                             unsampleable_emitters, weigh_emitter_sample)
from guiding.render.frozen_pass import FrozenPasses, recordable
from guiding.render.progressive import Budget, render


class GuidedPathIntegrator(mi.SamplingIntegrator):
    r"""Unidirectional path tracer whose directions come from a guide.

    Parameters (XML / ``load_dict``):
      ``max_depth`` (int, 16): longest path, in vertices after the camera; 1 shows only directly visible
        emitters (Mitsuba's convention, so images compare with its ``path`` integrator).
      ``rr_depth`` (int, 8; 5 with ``nee``, as Mitsuba's ``path``): depth from which Russian roulette may end a path.
      ``rr_min`` (float, 0.05): lower bound of the continuation probability ``q = max(max_rgb(β), rr_min)`` (with
        ``nee``, ``q = max(max_rgb(β)·η², rr_min)``).
      ``method`` (str, "brdf"): a method name of :mod:`guiding.guides.methods`; ignored when a guide is passed.
      ``pass_spp`` (int, 8): samples per pixel of the first passes of ``mi.render``; the guide updates between
        passes, and later passes grow to ``pass_spp·2^k`` up to its next update (:mod:`guiding.render.pass_schedule`).
      ``growing_passes`` (bool, true): false keeps every pass at ``pass_spp``.
      ``seconds`` (float, 0): when positive, ``mi.render`` renders for this many seconds instead of ``spp``.
      ``freeze`` (bool, true): passes after the first of each configuration replay the path loop's recorded
        kernels instead of tracing it again (:mod:`guiding.render.frozen_pass`); false traces every pass.
      ``nee`` (bool, false): next-event estimation: at every vertex the path continues from (below ``max_depth``) with
        a smooth BSDF component, one emitter sample, weighted against the guide's own density by the power heuristic
        (as Mitsuba's ``path``; :mod:`guiding.render.emitter_sampling`); Russian roulette then starts at depth 5, as
        there. In a scene where the guide has nothing to guide, Mitsuba's ``path`` renders the passes (``brdf``, the
        loop's own reference, excepted). False is the paper's protocol (emitters found only by sampled directions).
      ``learn_nee_light`` (bool, true): with ``nee``, the guide learns the full incident radiance its sampled
        directions bring back, light that emitter sampling also finds included; false: only the share of emission
        that next-event estimation leaves to sampled directions (their MIS weight).
      ``path_fallback`` (bool, false): with ``nee``: after a tenth of the budget, two passes of Mitsuba's ``path`` are
        compared with the guide's last two and the rest of the budget goes to the one predicted the lower error
        (:mod:`guiding.render.path_fallback`; not for guides with iterations, the SD-tree). ``mi.render`` then
        returns an unbiased mix.
      Any other property is a parameter of the method's guide, as ``--set`` gives it on the command line: a field of
        its parameters (:mod:`guiding.guides.parameters`) with a value of the field's type, for example
        ``learning_share`` (float), ``spatial_resolution`` (int), or ``statistics`` (bool, grid methods: count
        guided vertices, proposals and acceptances per pass; they cost atomics on every bounce). A property the
        method does not take is refused (BadSetting, naming it).

    Attributes read by the progressive renderer and the benchmark after each pass: ``path_count``,
    ``hit_count`` (paths with a non-zero contribution) and ``ray_count`` (rays traced), reset by
    :meth:`reset_counters` (passes of Mitsuba's ``path`` count nothing: :attr:`counts_paths`). After ``mi.render``,
    ``last_result`` holds the :class:`~guiding.render.progressive.RenderResult` (per-pass statistics, iterations,
    when training stopped).
    """

    def __init__(self, props: mi.Properties = None, guide: Guide | None = None):
        props = props if props is not None else mi.Properties()
        super().__init__(props)
        self.max_depth = props.get("max_depth", defaults.MAX_DEPTH)
        self.rr_min = props.get("rr_min", defaults.RR_MIN)
        self.pass_spp = props.get("pass_spp", defaults.PASS_SPP)
        self.seconds = props.get("seconds", 0.0)
        self.growing_passes = props.get("growing_passes", True)
        self.nee = props.get("nee", False)
        self.rr_depth = props.get("rr_depth", defaults.RR_DEPTH_NEE if self.nee else defaults.RR_DEPTH)
        self.learn_nee_light = props.get("learn_nee_light", True)
        self.path_fallback = props.get("path_fallback", False)
        if self.path_fallback and not self.nee:
            raise ValueError("path_fallback hands passes to Mitsuba's path, which samples emitters: set nee too")
        if self.max_depth < 1:
            raise ValueError(f"max_depth must be >= 1, got {self.max_depth}")
        if self.pass_spp < 1:
            raise ValueError(f"pass_spp must be >= 1, got {self.pass_spp}")
        self.freeze = props.get("freeze", True)
        if guide is None:
            guide = _guide_of(props)
        self.guide = guide
        self.path_guide = guide      # what the path loop asks (see prepare)
        self.frozen_passes = None     # the FrozenPasses of the scene last prepared (None: traced passes)
        self.path_integrator = None   # Mitsuba's path, for the scene last prepared where nee and the guide learn
        self.last_result = None
        self.reset_counters()

    def render(self, scene: mi.Scene, sensor: int | mi.Sensor = 0, seed: int = 0, spp: int = 0,
               develop: bool = True, evaluate: bool = True) -> mi.TensorXf:
        """What ``mi.render`` calls: progressive passes with the guide's updates in between; the final RGB image.

        ``spp`` 0 takes the sensor's sample count; a positive ``seconds`` parameter replaces it by a time budget."""
        if not develop:
            raise ValueError("guided_path renders progressive passes and returns their image: develop=False is "
                             "not supported")
        sensor = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        if self.seconds > 0:
            budget = Budget(seconds=self.seconds, pass_spp=self.pass_spp, growing_passes=self.growing_passes)
        else:
            budget = Budget(spp=spp or sensor.sampler().sample_count(), pass_spp=self.pass_spp,
                            growing_passes=self.growing_passes)
        self.last_result = render(scene, self, budget, seed=seed, sensor=sensor)
        return mi.TensorXf(self.last_result.image)

    def render_pass(self, scene: mi.Scene, sensor: mi.Sensor, seed: int, spp: int) -> mi.TensorXf:
        """One pass of ``spp`` samples per pixel with the guide as it is (Mitsuba's own ``render``; frozen, see
        ``freeze``, once :meth:`prepare` has seen the scene), or Mitsuba's ``path`` where it renders the passes
        (:attr:`renders_path`)."""
        if self.renders_path:
            return mi.render(scene, integrator=self.path_integrator, sensor=sensor, seed=seed, spp=spp)
        if self.freeze and self.frozen_passes is not None and self.frozen_passes.scene_id == id(scene):
            return self.frozen_passes.render(scene, sensor, seed, spp)
        return mi.render(scene, integrator=_PassRenderer(self), sensor=sensor, seed=seed, spp=spp)

    def prepare(self, scene: mi.Scene) -> None:
        """Before the first pass on ``scene``: the guide allocates its tables; and where no BSDF of the scene is one
        the guide guides, the passes trace plain BSDF sampling, without the guide's code (masked off at every
        vertex, it would still cost every bounce), or with ``nee`` are Mitsuba's ``path`` (:attr:`renders_path`).
        The passes on ``scene`` are frozen from here on (``freeze``).
        With ``nee`` and a guide that learns, Mitsuba's ``path`` is made ready (for those passes and the path
        fallback, :mod:`guiding.render.path_fallback`).
        With ``nee``, a scene without emitters, or with one that emitter sampling cannot sample
        (:func:`~guiding.render.emitter_sampling.unsampleable_emitters`), is refused (GuidingError, one line)."""
        if self.nee and not scene.emitters():
            raise GuidingError("nee samples emitters, and this scene has none: render it without nee")
        unsampleable = unsampleable_emitters(scene) if self.nee else []
        if unsampleable:
            raise GuidingError(f"nee cannot sample the emitter {'; '.join(unsampleable)}: render it without nee")
        self.guide.prepare(scene)
        self.path_guide = self.guide if self.guide.guides_any(scene) else _BSDF_SAMPLING
        # BSDF sampling with NEE is path's estimator: brdf (a guide that learns nothing) keeps the loop, as its
        # reference; a guide with nothing to guide hands its passes to path, which renders them at path's cost.
        self.path_integrator = (mi.load_dict({"type": "path", "max_depth": self.max_depth, "rr_depth": self.rr_depth})
                                if self.nee and self.guide.records() else None)
        traced = self.freeze and recordable(scene) and not self.renders_path
        self.frozen_passes = FrozenPasses(self, scene, _PassRenderer) if traced else None

    @property
    def renders_path(self) -> bool:
        """Whether Mitsuba's ``path`` renders the passes on the scene last prepared: with ``nee``, where a guide that
        learns has nothing to guide."""
        return self.path_integrator is not None and not self.guides_scene

    @property
    def fallback_integrator(self) -> mi.SamplingIntegrator | None:
        """Mitsuba's ``path`` where the path fallback applies to the scene last prepared (``path_fallback``, and the
        guide guides something there), else None."""
        return self.path_integrator if self.path_fallback and self.guides_scene else None

    @property
    def counts_paths(self) -> bool:
        """Whether the passes count paths, hits and rays (Mitsuba's ``path`` does not)."""
        return not self.renders_path

    @property
    def guides_scene(self) -> bool:
        """Whether the passes on the scene last prepared use the guide (False where it has nothing to guide, and
        for ``brdf``, whose guide guides nothing): the pass driver updates the guide only then."""
        return self.path_guide is self.guide

    def reset_counters(self) -> None:
        self.path_count = mi.UInt32(0)
        self.hit_count = mi.UInt32(0)
        self.ray_count = mi.UInt32(0)

    @dr.syntax
    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f, medium: mi.Medium = None,
               active: mi.Bool = True) -> tuple[mi.Spectrum, mi.Bool, list]:
        guide = self.path_guide
        records = guide.records()
        bsdf_ctx = mi.BSDFContext()

        # --------------------------- Configure loop state ---------------------------
        ray = mi.Ray3f(ray)
        β = mi.Spectrum(1)            # Path throughput weight
        L = mi.Spectrum(0)            # Radiance accumulator
        depth = mi.UInt32(0)          # Number of surface vertices so far
        rays = mi.UInt32(0)           # Rays traced by this path
        active = dr.full(mi.Bool, True, dr.width(ray.o)) & active
        started = mi.Bool(active)     # The lanes that trace a path (for the hit rate)
        path_state = guide.new_paths(dr.width(ray.o), self.max_depth)
        previous = PreviousVertex.camera(dr.width(ray.o)) if self.nee else NoPathState()   # empty loop state
        η = mi.Float(1) if self.nee else NoPathState()   # Relative index of refraction (Russian roulette with nee)

        while dr.hint(active, max_iterations=self.max_depth, label="Guided path tracer"):
            si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=(depth == 0), active=active)
            rays += 1

            # ----------------------------- Emission -----------------------------
            emitted = si.emitter(scene).eval(si, active)
            if dr.hint(self.nee, mode="scalar"):
                # Emission found by a sampled direction shares its weight with the emitter sample that could find it.
                shared = hit_weight(scene, si, previous, active)
                L += β * shared * emitted
                if dr.hint(not self.learn_nee_light, mode="scalar"):
                    emitted = shared * emitted    # the guide learns only what next-event estimation leaves to it
            else:
                L += β * emitted

            # ------------------------ Stopping criterion ------------------------
            depth[si.is_valid()] += 1
            continues = active & si.is_valid() & (depth < self.max_depth)

            # The vertex in the guide's structure, found once for the emitter sample's density, the sample, the record
            bsdf = si.bsdf(ray)
            vertex = guide.locate(si, bsdf, continues)

            # ------- Emitter sampling (next-event estimation) and direction sampling (the guide) -------
            if dr.hint(self.nee, mode="scalar"):
                light = sample_emitter_direction(scene, sampler, si, bsdf, continues)
                # The BSDF's value towards the emitter and the next direction: one BSDF call where the guide can.
                value, bsdf_pdf, bs, weight = guide.sample_and_eval(scene, sampler, si, bsdf, bsdf_ctx, continues,
                                                                    light.wo, light.active, vertex)
                L += β * weigh_emitter_sample(light, value, bsdf_pdf, guide, si, bsdf, bsdf_ctx, vertex).contribution
            else:
                bs, weight = guide.sample(scene, sampler, si, bsdf, bsdf_ctx, continues, vertex)
            weight = dr.select(continues, weight, 0)

            # -------------------------- Russian roulette --------------------------
            if dr.hint(self.nee, mode="scalar"):
                η *= bs.eta
            q = continuation_probability(β * weight, η if self.nee else None, self.rr_min)
            roulette = continues & (depth >= self.rr_depth)
            survives = ~roulette | (sampler.next_1d(roulette) < q)
            weight = dr.select(survives, dr.select(roulette, weight / q, weight), 0)
            continues &= survives & dr.any(weight != 0)

            # ----------------------------- Learning -----------------------------
            if dr.hint(records, mode="scalar"):
                path_state = guide.record(path_state, si, emitted, bs, weight, continues, active, vertex)

            # --------------------------- Next segment ---------------------------
            if dr.hint(self.nee, mode="scalar"):
                previous = PreviousVertex(mi.Interaction3f(si), bs.pdf,
                                          mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta))
            β *= weight
            ray = si.spawn_ray(si.to_world(bs.wo))
            active = continues

        if dr.hint(records, mode="scalar"):
            guide.finish_paths(path_state)

        hit = dr.any(L != 0)
        dr.scatter_reduce(dr.ReduceOp.Add, self.path_count, mi.UInt32(1), mi.UInt32(0), started)
        dr.scatter_reduce(dr.ReduceOp.Add, self.hit_count, mi.UInt32(1), mi.UInt32(0), started & hit)
        dr.scatter_reduce(dr.ReduceOp.Add, self.ray_count, rays, mi.UInt32(0), started)
        return L, mi.Bool(True), []

    def to_string(self) -> str:
        return (f"GuidedPathIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"pass_spp={self.pass_spp}, growing_passes={self.growing_passes}, nee={self.nee}, "
                f"path_fallback={self.path_fallback}, "
                f"guide={self.guide.name}]")


def continuation_probability(throughput: mi.Spectrum, η: mi.Float | None, rr_min: float) -> mi.Float:
    """Russian roulette's continuation probability ``q = min(max(max_rgb(throughput)·η², rr_min), 1)`` (the paper's
    without ``η``, the relative index of refraction along the path, which next-event estimation adds).

    η² as Mitsuba's ``path``: each refraction into glass scales β by 1/η², which must not end the path there. The
    floor ``rr_min`` where ``path`` caps ``q`` at 0.95 instead: a guided path keeps β near its value, and the floor
    bounds the weight ``1/q`` of a path that survives (results/nee_cost/README.md, "Which roulette")."""
    largest = dr.max(throughput)
    if η is not None:
        largest *= dr.square(η)
    return dr.minimum(dr.maximum(largest, rr_min), 1)


class _PassRenderer(mi.SamplingIntegrator):
    """Mitsuba's own ``render`` of one pass, tracing the paths with ``integrator.sample``.

    A separate object because Mitsuba's trampoline sends a call of the base ``render`` on a GuidedPathIntegrator back
    to its Python ``render`` (the progressive loop) unless that is running, and reaching the base from there nests
    two bindings whose Ctrl-C handlers swallow the signal. Made for each traced pass (each recording of a frozen one),
    and not kept by the integrator: ``mi.render`` traverses the integrator's attributes, and a reference cycle would
    never end."""

    def __init__(self, integrator: GuidedPathIntegrator):
        super().__init__(mi.Properties())
        self.integrator = integrator

    def sample(self, scene, sampler, ray, medium=None, active=True):
        return self.integrator.sample(scene, sampler, ray, medium, active)


def _guide_of(props: mi.Properties) -> Guide:
    """A fresh guide of the method ``props`` names, with the properties the integrator has not read (Mitsuba marks
    them unqueried) as its parameters, typed as in XML."""
    method = props.get("method", "brdf")
    try:
        return make_guide(method, **{name: props[name] for name in props.unqueried()})
    except BadSetting as error:
        # Nor is it one of the integrator's own, which it read before (their list: the class docstring, the README).
        raise BadSetting(f"guided_path: {error}; nor is it a property of guided_path itself") from None


#: The path loop's guide in a scene with nothing to guide.
_BSDF_SAMPLING = BSDFGuide()

_registered = set()


def register() -> None:
    """Register ``guided_path`` for the current variant (idempotent)."""
    variant = mi.variant()
    if variant not in _registered:
        mi.register_integrator("guided_path", lambda props: GuidedPathIntegrator(props))
        _registered.add(variant)


def integrator_for(method, max_depth: int = defaults.MAX_DEPTH, nee: bool = False,
                   memory_limit: int | str | None = None, path_fallback: bool = False) -> mi.SamplingIntegrator:
    """The integrator that renders ``method`` (a :class:`~guiding.guides.methods.Method`): the Mitsuba integrator it
    names (``path``, which always does next-event estimation), else ``guided_path`` with a fresh guide of the method,
    ``nee`` and ``path_fallback`` (refused, GuidingError, if the guide's tables would exceed ``memory_limit``)."""
    if method.mitsuba_integrator is not None:
        return mi.load_dict({"type": method.mitsuba_integrator, "max_depth": max_depth})
    props = mi.Properties()
    props["max_depth"] = max_depth
    props["nee"] = nee
    props["path_fallback"] = path_fallback
    return GuidedPathIntegrator(props, guide=method.build(memory_limit))
