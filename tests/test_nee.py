"""Next-event estimation in the guided path loop: the two strategies' MIS weights sum to one at sampled vertices,
and every kind of guide with ``nee`` converges to what Mitsuba's own ``path`` integrator computes, on tilted
geometry, under an environment emitter and under a small sphere light."""

from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi

import numpy as np
import pytest

from guiding.errors import GuidingError
from guiding.experiments.testing import scene_vertices, train
from guiding.experiments.validation import Z_LIMIT, pass_means, z_scores
from guiding.guides import BSDFGuide, Guide
from guiding.guides.methods import make_guide
from guiding.render.emitter_sampling import (PreviousVertex, hit_weight, mis_weight, sample_emitter_direction,
                                             weigh_emitter_sample)
from guiding.render import defaults
from guiding.render.driver import PassDriver, pass_seed
from guiding.render.integrator import GuidedPathIntegrator, continuation_probability
from guiding.render.progressive import Budget, render
from guiding.scenes import load_scene

FILM = {"type": "hdrfilm", "width": 48, "height": 48, "rfilter": {"type": "box"}}
WHITE = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.7}}


def _floor_and_blocks(emitter: dict, camera_origin=(0, 2.2, 3.2)) -> dict:
    """A floor with two blocks and a ball, seen from above at an angle, lit by ``emitter`` alone."""
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 45, "film": FILM,
                   "to_world": mi.ScalarTransform4f().look_at(origin=camera_origin, target=(0, 0.3, 0), up=(0, 1, 0))},
        "floor": {"type": "rectangle", "bsdf": WHITE,
                  "to_world": mi.ScalarTransform4f().rotate((1, 0, 0), -90).scale(3)},
        "block": {"type": "cube", "bsdf": WHITE,
                  "to_world": mi.ScalarTransform4f().translate((-0.6, 0.4, -0.2)).rotate((0, 1, 0), 30).scale(0.4)},
        "wall": {"type": "cube", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.3, 0.2]}},
                 "to_world": mi.ScalarTransform4f().translate((0.4, 0.6, -1.0)).scale((1.2, 0.6, 0.1))},
        "ball": {"type": "sphere", "center": (0.7, 0.35, 0.4), "radius": 0.35,
                 "bsdf": {"type": "roughplastic", "alpha": 0.2}},
        "emitter": emitter,
    }


def _environment() -> dict:
    """An environment map with a bright, small patch (a sun) over a dim sky: importance sampling matters."""
    height, width = 32, 64
    sky = np.full((height, width, 3), 0.3, dtype=np.float32)
    sky[height // 2:] = 0.02
    sky[5:7, 20:23] = 400.0
    return {"type": "envmap", "bitmap": mi.Bitmap(sky)}


def _sphere_light() -> dict:
    return {"type": "sphere", "center": (0.2, 1.6, 0.3), "radius": 0.08,
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 60.0}}}


@pytest.fixture(scope="module")
def scenes():
    return {"cornell-tilted": load_scene("cornell-tilted", scale=0.125),
            "environment": mi.load_dict(_floor_and_blocks(_environment())),
            "sphere light": mi.load_dict(_floor_and_blocks(_sphere_light()))}


def _nee_integrator(method: str, **properties) -> GuidedPathIntegrator:
    props = mi.Properties()
    props["nee"] = True
    for key, value in properties.items():
        props[key] = value
    return GuidedPathIntegrator(props, guide=make_guide(method))


# ====================================================================================== MIS weights
@pytest.mark.parametrize("scene_name", ["cornell-tilted", "environment", "sphere light"])
@pytest.mark.parametrize("method", ["brdf", "ours", "sdtree"])
def test_mis_weights_of_emitter_and_guide_sampling_sum_to_one(scenes, scene_name, method):
    """At vertices camera paths reach, for each emitter sample: its weight (:func:`weigh_emitter_sample`, with the
    BSDF's value from the guide's ``sample_and_eval``, as in the path loop) and the weight the loop gives the same
    emission found by the guide's direction (:func:`hit_weight`, from the density the guide reports for it) sum to
    one. A trained guide, so that its density is not the BSDF's."""
    scene = scenes[scene_name]
    guide = train(scene, make_guide(method), spp=32, seed=1) if method != "brdf" else make_guide(method)
    guide.prepare(scene) if method == "brdf" else None
    si = scene_vertices(scene, count=2000, seed=2)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(5, dr.width(si.p))
    bsdf, ctx = si.bsdf(), mi.BSDFContext()
    active = mi.Bool(True)
    light = sample_emitter_direction(scene, sampler, si, bsdf, active)
    value, bsdf_pdf, bs, _ = guide.sample_and_eval(scene, sampler, si, bsdf, ctx, active, light.wo, light.active)
    nee = weigh_emitter_sample(light, value, bsdf_pdf, guide, si, bsdf, ctx)
    # The emission the guide's direction towards the emitter sample would find, weighted as the loop weighs it.
    hit = scene.ray_intersect(si.spawn_ray(si.to_world(nee.wo)))
    previous = PreviousVertex(mi.Interaction3f(si), guide.pdf(si, bsdf, ctx, nee.wo, active), mi.Bool(False))
    found = hit_weight(scene, hit, previous, active)
    lit = (nee.emitter_pdf > 0) & (nee.guide_pdf > 0) & dr.any(nee.contribution != 0)
    lit = lit & dr.any(hit.emitter(scene).eval(hit) != 0)
    total = (nee.weight + found).numpy()[lit.numpy()]
    assert total.size > 100, f"only {total.size} lit emitter samples"
    # To float32 rounding: the emitter's density at the traced hit point is recomputed from that point's distance
    # and cosine, not copied from the emitter sample (a few 1e-4 relative on grazing samples).
    np.testing.assert_allclose(total, 1.0, rtol=1e-3)
    # Not by construction (an emitter sample weighted 1 and a found emission weighted 0 would sum to one too): the
    # guide's direction takes a share somewhere, if a small one where the light is small.
    assert (1 - nee.weight.numpy()[lit.numpy()]).max() > 1e-5
    # The loop weighs a found emission with the density the guide's sample reports (bs.pdf), the weights above use
    # `pdf`: the two agree at the directions the guide draws.
    drawn = ((bs.pdf > 0) & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)).numpy()
    assert drawn.sum() > 1000
    np.testing.assert_allclose(guide.pdf(si, bsdf, ctx, bs.wo, active).numpy()[drawn], bs.pdf.numpy()[drawn],
                               rtol=1e-4)


@pytest.mark.parametrize("scene_name", ["cornell-tilted", "sphere light"])
def test_bsdf_sampling_evaluates_and_samples_in_one_call_as_in_two(scenes, scene_name):
    """BSDF sampling's ``sample_and_eval`` (Mitsuba's ``eval_pdf_sample``, one BSDF call) returns what a guide's
    evaluate-then-sample returns with the same random numbers, to the bit: the loop's images are unchanged by the
    merged call."""
    scene = scenes[scene_name]
    si = scene_vertices(scene, count=2000, seed=4)
    bsdf, ctx, active = si.bsdf(), mi.BSDFContext(), mi.Bool(True)
    results = []
    for guide in (Guide(), BSDFGuide()):
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(7, dr.width(si.p))
        light = sample_emitter_direction(scene, sampler, si, bsdf, active)
        value, bsdf_pdf, bs, weight = guide.sample_and_eval(scene, sampler, si, bsdf, ctx, active, light.wo,
                                                            light.active)
        lit = light.active.numpy()
        results.append((value.numpy()[:, lit], bsdf_pdf.numpy()[lit], bs.wo.numpy(), bs.pdf.numpy(), weight.numpy()))
    assert results[0][1].size > 500 and (results[0][1] > 0).sum() > 500
    for separate, merged in zip(*results):
        np.testing.assert_array_equal(merged, separate)


def test_russian_roulette_weighs_beta_by_eta_squared_and_keeps_the_papers_floor():
    """q = min(max(max_rgb(β)·η², 0.05), 1), computed by hand: η² as path's (inside glass η = 1.5 lifts β·η²), the
    paper's floor where path caps at 0.95, and without η (no NEE) the paper's q unchanged."""
    β = mi.Spectrum([0.02, 0.2, 0.01], [0.03, 0.5, 0.02], [0.01, 0.3, 0.04])    # lanes: max_rgb 0.03, 0.5, 0.04
    with_nee = continuation_probability(β, mi.Float([1.5, 1.5, 1.0]), 0.05).numpy()
    assert with_nee == pytest.approx([0.0675, 1.0, 0.05])
    assert continuation_probability(β, None, 0.05).numpy() == pytest.approx([0.05, 0.5, 0.05])
    assert continuation_probability(β, mi.Float([1.0, 1.0, 1 / 1.5]), 0.01).numpy() == pytest.approx(
        [0.03, 0.5, 0.04 / 2.25])


def test_power_heuristic():
    assert mis_weight(mi.Float(1.0), mi.Float(1.0))[0] == pytest.approx(0.5)
    assert mis_weight(mi.Float(3.0), mi.Float(1.0))[0] == pytest.approx(0.9)
    assert mis_weight(mi.Float(0.0), mi.Float(0.0))[0] == 0.0
    assert mis_weight(mi.Float(np.inf), mi.Float(1.0))[0] == 0.0


# ===================================================================================== agreement
#: Every kind of guide: BSDF sampling, the grid with each sampler and rule family, the smooth-BSDF grid, the trees.
METHODS = ["brdf", "ours", "ours-expected", "ours-plus", "mc-sphere_inv", "sarsa-hemi_inv", "sdtree",
           "sdtree-learned", "quadtree-grid"]
PASSES, SPP = 24, 16


@pytest.fixture(scope="module")
def references(scenes):
    return {name: pass_means(scene, mi.load_dict({"type": "path", "max_depth": 16}), PASSES, SPP, seed=1000)
            for name, scene in scenes.items()}


@pytest.mark.parametrize("scene_name", ["cornell-tilted", "environment", "sphere light"])
@pytest.mark.parametrize("method", METHODS)
def test_guided_nee_matches_mitsuba_path(scenes, references, scene_name, method):
    ours = pass_means(scenes[scene_name], _nee_integrator(method), PASSES, SPP, seed=7)
    reference = references[scene_name]
    z = z_scores(ours, reference)
    assert (z < Z_LIMIT).all(), f"z-scores {z}, means {ours.mean(0)} vs {reference.mean(0)}"
    # The test must be able to fail: the standard error is small next to the signal.
    assert (ours.std(axis=0, ddof=1) / len(ours) ** 0.5 < 0.02 * reference.mean(axis=0)).all()


def test_learning_only_what_nee_leaves_still_converges(scenes, references):
    """``learn_nee_light=False`` changes what the guide learns, never the estimator."""
    ours = pass_means(scenes["sphere light"], _nee_integrator("ours", learn_nee_light=False), PASSES, SPP, seed=8)
    z = z_scores(ours, references["sphere light"])
    assert (z < Z_LIMIT).all(), f"z-scores {z}"


def test_nee_without_emitters_says_so_in_one_line():
    scene = mi.load_dict({"type": "scene", "sensor": {"type": "perspective", "film": FILM},
                          "floor": {"type": "rectangle", "bsdf": WHITE}})
    with pytest.raises(GuidingError, match="has none"):
        _nee_integrator("brdf").prepare(scene)


def _floor_lit_by(**emitters) -> mi.Scene:
    return mi.load_dict({"type": "scene", "sensor": {"type": "perspective", "film": FILM},
                         "floor": {"type": "rectangle", "bsdf": WHITE}, **emitters})


def test_nee_refuses_emitters_mitsuba_cannot_sample_in_one_line():
    """A surface that emits in one direction only (``directionalarea``: no emitter sample reaches it) and Mitsuba's
    ``timed_sunsky`` (whose directions it cannot sample in a traced call; with another emitter beside it Dr.Jit
    aborts the process) are refused before the first pass, naming the emitter; without nee they render as before.
    The ``timed_sunsky`` case runs in a child process: once a scene with that emitter is loaded, Mitsuba's ``path``
    fails on every other scene of the process too."""
    import subprocess
    import sys

    one_way = {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate((0, 2, 0)).rotate((1, 0, 0), 90),
               "emitter": {"type": "directionalarea"}}
    with pytest.raises(GuidingError) as refused:
        _nee_integrator("ours").prepare(_floor_lit_by(lamp=one_way))
    messages = [str(refused.value)]
    GuidedPathIntegrator(mi.Properties(), guide=make_guide("ours")).prepare(_floor_lit_by(lamp=one_way))
    script = ("import sys; sys.path.insert(0, 'tests'); import mitsuba as mi; mi.set_variant('llvm_ad_rgb'); "
              "from test_nee import _floor_lit_by, _nee_integrator; from guiding.errors import GuidingError; "
              "scene = _floor_lit_by(sky={'type': 'timed_sunsky'}, bulb={'type': 'point'}); "
              "_nee_integrator('brdf', nee=False).prepare(scene)\n"
              "try: _nee_integrator('ours').prepare(scene)\n"
              "except GuidingError as error: print(error)")
    child = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                           cwd=Path(__file__).parent.parent)
    assert child.returncode == 0, child.stderr[-2000:]
    messages.append(child.stdout.rstrip("\n"))
    named = ("'directionalarea' (it emits in one direction only", "'timed_sunsky' (Mitsuba ")
    for name, message in zip(named, messages):
        assert message.startswith(f"nee cannot sample the emitter {name}") and "\n" not in message, message
    for sampled in ({"type": "point"}, {"type": "spot"}, {"type": "directional"}, {"type": "constant"},
                    {"type": "sunsky"}, {"type": "projector"}, _sphere_light(), _environment()):
        _nee_integrator("brdf").prepare(_floor_lit_by(light=sampled))


def test_mitsuba_still_cannot_sample_timed_sunsky_emitters():
    """Why timed_sunsky is refused: Mitsuba's own path integrator fails on it (in a child process: with a second
    emitter the failure aborts the process). When a Mitsuba release samples it, this fails: lift the refusal."""
    import subprocess
    import sys

    script = ("import mitsuba as mi; mi.set_variant('llvm_ad_rgb'); "
              "scene = mi.load_dict({'type': 'scene', 'sensor': {'type': 'perspective', 'film': {'type': 'hdrfilm', "
              "'width': 8, 'height': 8}}, 'floor': {'type': 'rectangle'}, 'sky': {'type': 'timed_sunsky'}}); "
              "mi.render(scene, integrator=mi.load_dict({'type': 'path'}), spp=1)")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode != 0 and "not permitted" in done.stderr, done.stderr[-2000:]


def test_the_plugin_takes_nee_from_xml_and_load_dict():
    import guiding  # noqa: F401  (registers guided_path for the variant the tests set)

    from_dict = mi.load_dict({"type": "guided_path", "method": "ours", "nee": True, "learn_nee_light": False})
    from_xml = mi.load_string('<integrator version="3.0.0" type="guided_path"><string name="method" value="ours"/>'
                              '<boolean name="nee" value="true"/></integrator>')
    default = mi.load_dict({"type": "guided_path"})
    assert (from_dict.nee, from_dict.learn_nee_light) == (True, False)
    assert (from_xml.nee, from_xml.learn_nee_light) == (True, True)
    assert not default.nee and "nee=True" in from_xml.to_string()
    # With nee, paths are as long as Mitsuba's path's: Russian roulette from its depth.
    assert (from_xml.rr_depth, default.rr_depth) == (defaults.RR_DEPTH_NEE, defaults.RR_DEPTH) == (5, 8)


# ============================================================================ what the guides learn
LIGHT_AREA = 1.0                 # a rectangle scaled by 0.5: 1 × 1
LIGHT_RADIANCE = 5.0


@dataclass
class _Segment:
    """A spy's path state: the previous vertex and the density of the direction sampled there; sums per path of the
    emission handed to ``record`` at the light and of what the hand computation says it must be."""

    p: mi.Point3f = None
    pdf: mi.Float = None
    learned: mi.Color3f = None
    expected: mi.Color3f = None
    hits: mi.Float = None
    DRJIT_STRUCT = {"p": mi.Point3f, "pdf": mi.Float, "learned": mi.Color3f, "expected": mi.Color3f, "hits": mi.Float}


class _EmissionSpy(Guide):
    """BSDF sampling that checks the emission the path loop hands ``record`` where a sampled direction found the
    light: ``Le`` itself (``learn_nee_light``: Q stays the incident radiance, the targets of the rule tests), or
    ``Le`` times the power heuristic's weight against emitter sampling, computed here by hand from the geometry."""

    name = "emission-spy"

    def __init__(self, learns_full_light: bool):
        self.learns_full_light = learns_full_light
        self.totals = dr.zeros(mi.Float, 4)     # Σ learned, Σ expected, Σ |learned − expected|, hits; over paths

    def guides_any(self, scene):
        return True

    def records(self):
        return True

    def new_paths(self, size, max_depth):
        return _Segment(dr.zeros(mi.Point3f, size), dr.zeros(mi.Float, size), dr.zeros(mi.Color3f, size),
                        dr.zeros(mi.Color3f, size), dr.zeros(mi.Float, size))

    def record(self, state, si, emitted, bs, weight, continues, active, vertex=None):
        at_light = active & si.is_valid() & (si.p.z > 0.5) & (state.pdf > 0)
        to_light = si.p - state.p
        distance2 = dr.squared_norm(to_light)
        light_pdf = distance2 / (dr.abs(dr.dot(si.n, to_light)) / dr.sqrt(distance2) * LIGHT_AREA)
        weight_by_hand = dr.square(state.pdf) / (dr.square(state.pdf) + dr.square(light_pdf))
        expected = LIGHT_RADIANCE * (1.0 if self.learns_full_light else weight_by_hand)
        state.learned += dr.select(at_light, emitted, 0)
        state.expected += dr.select(at_light, mi.Color3f(expected), 0)
        state.hits += dr.select(at_light, 1.0, 0.0)
        state.p, state.pdf = mi.Point3f(si.p), mi.Float(bs.pdf)
        return state

    def finish_paths(self, state):
        for slot, value in enumerate((state.learned.x, state.expected.x, dr.abs(state.learned.x - state.expected.x),
                                      state.hits)):
            dr.scatter_reduce(dr.ReduceOp.Add, self.totals, value, slot)


@pytest.mark.parametrize("learns_full_light", [True, False])
def test_guides_learn_the_emission_their_rule_defines(learns_full_light):
    """With nee, the emission a sampled direction finds reaches the learning rules unweighted by default, so that
    their targets (SARSA's ``Le(x′) + (f·cos/p)·Q(x′, ω′)``, the Monte Carlo walk, Expected SARSA's) and Q, the
    incident radiance, are those of the rule tests (tests/test_grid_learning.py); with ``learn_nee_light`` false,
    times the MIS weight ``p_dir² / (p_dir² + p_light²)`` with ``p_light = d² / (|cos θ_light|·A)``, by hand here."""
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 50, "film": FILM,
                   "to_world": mi.ScalarTransform4f().look_at(origin=(0, -3, 0.5), target=(0, 0, 0), up=(0, 0, 1))},
        "floor": {"type": "rectangle", "bsdf": WHITE, "to_world": mi.ScalarTransform4f().scale(3)},
        "light": {"type": "rectangle", "emitter": {"type": "area", "radiance": {"type": "rgb", "value": LIGHT_RADIANCE}},
                  "to_world": mi.ScalarTransform4f().translate((0, 0, 1)).rotate((1, 0, 0), 180).scale(0.5)}})
    spy = _EmissionSpy(learns_full_light)
    integrator = _nee_integrator("brdf", max_depth=2, freeze=False, learn_nee_light=learns_full_light)
    integrator.guide = spy
    integrator.prepare(scene)
    integrator.render_pass(scene, scene.sensors()[0], seed=3, spp=32)
    learned, expected, difference, hits = spy.totals.numpy()
    assert hits > 1000                          # paths that found the light by a sampled direction
    assert difference < 1e-4 * expected, (learned, expected, difference)
    # Able to fail: the two choices hand the rules different emission (MIS weights below 1 on average).
    full = LIGHT_RADIANCE * hits
    assert learned == pytest.approx(full, rel=1e-5) if learns_full_light else learned < 0.9 * full


def _relative_variance(scene: mi.Scene, integrator, passes: int = 24, spp: int = 64) -> float:
    """Mean over pixels and channels of the per-pixel variance of ``passes`` pass images over their mean² + 0.01."""
    driver = PassDriver(scene, integrator)
    driver.prepare()
    images = np.array([np.asarray(driver.run(pass_seed(5, index), spp).image)[..., :3] for index in range(passes)])
    return float((images.var(axis=0, ddof=1) / (images.mean(axis=0) ** 2 + 0.01)).mean())


def test_brdf_with_nee_is_as_noisy_as_path_behind_glass():
    """Russian roulette with NEE weighs β by η², as path's (``q = max(max_rgb(β)·η², 0.05)``): the paper's
    ``max(max_rgb(β), 0.05)`` ended the paths inside glass that path keeps, and had 1.35× path's relative variance on
    glossy-box."""
    scene = load_scene("glossy-box", scale=0.125)
    ours = _relative_variance(scene, _nee_integrator("brdf"))
    path = _relative_variance(scene, mi.load_dict({"type": "path", "max_depth": 16}))
    assert ours / path < 1.15, f"relative variance {ours} against path's {path}"


def test_with_nothing_to_guide_the_passes_are_mitsubas_path():
    """With NEE, a guide that learns but has nothing to guide (mirror-box: delta lobes only) hands its passes to
    Mitsuba's ``path``, the same estimator at its own cost: the image is path's, pass for pass. ``brdf``, the loop's
    reference, keeps the loop."""
    scene = load_scene("mirror-box", scale=0.0625)
    budget = Budget(spp=32, growing_passes=False)
    ours = render(scene, _nee_integrator("ours-plus"), budget, seed=7, progress=False)
    path = render(scene, mi.load_dict({"type": "path", "max_depth": 16}), budget, seed=7, progress=False)
    assert np.array_equal(ours.image, path.image) and ours.image.max() > 0
    assert all(np.isnan(p.hit_rate) for p in ours.passes)    # path counts no paths
    assert "nothing to guide" in ours.path_fallback["reason"]   # stats.json says who rendered
    brdf = render(scene, _nee_integrator("brdf"), budget, seed=7, progress=False)
    assert not np.array_equal(brdf.image, path.image) and all(p.hit_rate > 0 for p in brdf.passes)
