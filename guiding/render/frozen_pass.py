"""Passes replayed without tracing: the path loop of ``guided_path`` is traced once per configuration and its kernels
are launched again by later passes (Dr.Jit's ``dr.freeze``).

Tracing the path loop in Python and assembling its kernel cost a pass about as much as the kernel itself at the
small image sizes of the experiments, and the paper's ``ours`` pays it after every 8-spp pass (the measurements:
results/pass_schedule/README.md). A frozen pass launches the recorded kernels with
the pass's inputs: the scene, the seed, and every Dr.Jit array of the guide and the integrator's counters, gathered
afresh each pass (:func:`device_arrays`), so the tables an update rebuilt are the ones read.

What Dr.Jit cannot see as an input is a Python value that shapes the traced code; a guide declares those in
:meth:`~guiding.guides.base.Guide.trace_key` (whether it records, whether it is trained, …); the pass's spp and the
film's size (the path state's width is a literal of the kernel) and the integrator's depths are part of the key
too. A new key traces and records once more. ``tests/test_frozen_pass.py`` checks that frozen passes give the same
images as traced ones, pass by pass, for every kind of guide.

Whether Dr.Jit can record a scene is probed once, when the integrator prepares for it (:func:`recordable`): a BSDF
created outside the scene after that makes the next recording fail, in the middle of the render.
"""

from __future__ import annotations

import gc
import weakref

import drjit as dr
import mitsuba as mi


def device_arrays(root) -> list:
    """Every Dr.Jit array reachable from ``root`` through the attributes, dictionaries, lists and tuples of
    Python objects (Mitsuba objects excluded: the scene is an input of its own), each once."""
    arrays, seen, stack = [], set(), [root]
    while stack:
        value = stack.pop()
        if value is None or isinstance(value, (bool, int, float, str, type)) or id(value) in seen:
            continue
        seen.add(id(value))
        if dr.is_array_v(value):
            arrays.append(value)
        elif isinstance(value, dict):
            stack.extend(value.values())
        elif isinstance(value, (list, tuple)):
            stack.extend(value)
        elif isinstance(value, mi.Object):
            continue
        elif hasattr(value, "__dict__"):
            stack.extend(vars(value).values())
    return arrays


def recordable(scene: mi.Scene) -> bool:
    """Whether Dr.Jit can record the path loop's calls of ``scene``'s BSDFs and emitters: a recording traverses
    every live instance of a called class through its inputs, and fails on one outside the scene (a BSDF loaded on
    its own, as the samplers' tests do) or when the class has none (a scene without emitters). Probed with a
    recording of one call of each, which has no side effects, rather than found out by a pass's, which has."""
    if not scene.emitters():
        return False

    @dr.freeze
    def probe(scene):
        si = dr.zeros(mi.SurfaceInteraction3f, 1)
        shapes = scene.shapes_dr()
        return shapes.bsdf().eval_diffuse_reflectance(si) + shapes.emitter().eval(si)

    try:
        dr.eval(probe(scene))
    except RuntimeError:
        return False
    return True


class FrozenPasses:
    """The passes of one integrator on one scene, traced once per :meth:`~guiding.guides.base.Guide.trace_key`
    and spp, replayed otherwise.

    Holds neither the integrator (weakly referenced) nor the scene (recognised by its id): the integrator keeps this
    object, and a reference cycle would leave the recordings to the garbage collector, which Dr.Jit aborts on when
    it frees them in the middle of another recording.

    Parameters:
      integrator: the ``guided_path`` integrator whose ``sample`` the passes run.
      scene: the scene it was prepared for.
      renderer: makes the Mitsuba integrator that ``mi.render`` is given, once per recording (the integrator's
        pass renderer).
    """

    def __init__(self, integrator, scene: mi.Scene, renderer):
        self.scene_id = id(scene)
        self._integrator = weakref.ref(integrator)
        owner = self._integrator

        def inputs(*args, **kwargs):
            integrator = owner()
            return (device_arrays(integrator.path_guide), integrator.path_count, integrator.hit_count,
                    integrator.ray_count)

        # A render records once per pass size and key, and the SD-tree once more per iteration: more than
        # Dr.Jit's default of 10 is expected, not a sign of needless tracing.
        @dr.freeze(state_fn=inputs, warn_after=100)
        def render(scene, sensor, seed, spp, key):
            return mi.render(scene, integrator=renderer(owner()), sensor=sensor, seed=seed, spp=spp)

        self._render = render

    def render(self, scene: mi.Scene, sensor: mi.Sensor, seed: int, spp: int) -> mi.TensorXf:
        """One pass of ``spp`` samples per pixel of ``sensor`` with sampler seed ``seed``."""
        integrator = self._integrator()
        guide = integrator.path_guide
        key = (guide.trace_key(), integrator.max_depth, integrator.rr_depth, integrator.rr_min, integrator.nee,
               integrator.learn_nee_light,
               tuple(sensor.film().crop_size()))     # the paths' width is a literal of the kernel
        # No garbage collection inside: Dr.Jit aborts when a collection frees another frozen function's recordings
        # in the middle of a recording, and a reference cycle anywhere in the process may hold one.
        collecting = gc.isenabled()
        gc.disable()
        try:
            return self._render(scene, sensor, dr.opaque(mi.UInt32, seed), spp, key)
        finally:
            if collecting:
                gc.enable()

    @property
    def recordings(self) -> int:
        """How many times the path loop was traced (one per configuration met, and when its inputs change shape)."""
        return self._render.n_recordings
