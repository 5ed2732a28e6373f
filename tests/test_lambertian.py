"""Lambertian BSDFs computed inline (`guiding.guides.grid.lambertian`): the same values, densities, samples and weights
as Mitsuba's own `eval_pdf_sample`, on both sides of one- and two-sided diffuse surfaces, and Mitsuba's call kept
for every other BSDF, even those whose flags say diffuse."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from guiding.guides.base import Guide
from guiding.guides.grid.guide import GridGuide
from guiding.guides.grid.lambertian import BOTH_SIDES, FRONT_SIDE, NOT_LAMBERTIAN, LambertianBsdfs, lambertian_sides
from guiding.guides.methods import make_guide
from guiding.experiments.testing import train
from guiding.render.integrator import GuidedPathIntegrator
from guiding.render.progressive import Budget, render

TEXTURE = {"type": "checkerboard", "color0": {"type": "rgb", "value": [0.8, 0.1, 0.2]},
           "color1": {"type": "rgb", "value": [0.1, 0.6, 0.3]}}
#: One square per BSDF, side by side along x, facing +z; and the sides the table must give each.
BSDFS = {
    "diffuse": ({"type": "diffuse", "reflectance": TEXTURE}, FRONT_SIDE),
    "twosided": ({"type": "twosided", "material": {"type": "diffuse", "reflectance": TEXTURE}}, BOTH_SIDES),
    "twosided_two_albedos": ({"type": "twosided", "front": {"type": "diffuse", "reflectance": TEXTURE},
                              "back": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.3, 0.3, 0.9]}}},
                             BOTH_SIDES),
    "blend": ({"type": "blendbsdf", "weight": 0.3, "bsdf_0": {"type": "diffuse"},
               "bsdf_1": {"type": "diffuse", "reflectance": TEXTURE}}, NOT_LAMBERTIAN),
    "twosided_plastic_back": ({"type": "twosided", "front": {"type": "diffuse"},
                               "back": {"type": "roughplastic"}}, NOT_LAMBERTIAN),
    "bumped": ({"type": "normalmap", "normalmap": {"type": "bitmap", "raw": True,
                                                   "data": mi.TensorXf(np.full((2, 2, 3), [0.6, 0.5, 0.9], np.float32))},
                "bsdf": {"type": "diffuse"}}, NOT_LAMBERTIAN),
}


@pytest.fixture(scope="module")
def squares():
    shapes = {name: {"type": "rectangle", "bsdf": bsdf,
                     "to_world": mi.ScalarTransform4f().translate([3.0 * i, 0, 0]).scale(0.9)}
              for i, (name, (bsdf, _)) in enumerate(BSDFS.items())}
    return mi.load_dict({"type": "scene", **shapes})


def _hits(scene, lanes: int, seed: int):
    """Surface interactions on every square, reached from above and below at random angles and positions."""
    rng = np.random.default_rng(seed)
    square = rng.integers(0, len(BSDFS), lanes)
    target = np.stack([3.0 * square + rng.uniform(-0.8, 0.8, lanes), rng.uniform(-0.8, 0.8, lanes),
                       np.zeros(lanes)], 1)
    incoming = rng.normal(size=(lanes, 3))
    incoming /= np.linalg.norm(incoming, axis=1, keepdims=True)
    origin = target + 2 * incoming
    ray = mi.Ray3f(mi.Point3f(*origin.T.astype(np.float32)), mi.Vector3f(*(-incoming).T.astype(np.float32)))
    si = scene.ray_intersect(ray)
    assert dr.all(si.is_valid())
    return si


def test_table_knows_which_bsdfs_are_lambertian(squares):
    """diffuse: front side only; twosided of diffuse (one or two albedos): both; a blend of two diffuse BSDFs, a
    twosided with a plastic back and a normal-mapped diffuse: Mitsuba's call (only the two plugins named are
    known)."""
    table = LambertianBsdfs(squares)
    for shape in squares.shapes():
        expected = BSDFS[shape.id()][1]
        assert lambertian_sides(shape.bsdf()) == expected, shape.id()
        bsdf = mi.BSDFPtr(shape.bsdf())
        assert table.sides(bsdf, mi.Bool(True))[0] == expected, shape.id()
    assert LambertianBsdfs().sides(mi.BSDFPtr(squares.shapes()[0].bsdf()), mi.Bool(True))[0] == NOT_LAMBERTIAN


def test_inline_only_where_every_guided_bsdf_is_lambertian(squares):
    """A scene whose guided BSDFs include one of another kind keeps Mitsuba's calls at every lane; asked about its
    Lambertian BSDFs only, it is computed inline; asked about none, nothing is inline."""
    assert not LambertianBsdfs(squares).inline
    assert LambertianBsdfs(squares, guided=lambda b: lambertian_sides(b) != NOT_LAMBERTIAN).inline
    assert not LambertianBsdfs(squares, guided=lambda b: False).inline
    assert not LambertianBsdfs().inline


def test_scene_with_instances_keeps_mitsubas_calls():
    """An instanced two-sided diffuse square beside a diffuse floor: the scene lists the instance, not the BSDF its
    rays hit, so nothing is inline (inline, its back side came out black where Mitsuba's twosided reflects)."""
    lambertian = {"type": "twosided", "material": {"type": "diffuse"}}
    scene = mi.load_dict({
        "type": "scene",
        "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"}},
        "group": {"type": "shapegroup", "square": {"type": "rectangle", "bsdf": lambertian}},
        "copy": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
                 "to_world": mi.ScalarTransform4f().translate([0, 0, 1])},
    })
    assert not LambertianBsdfs(scene, guided=lambda b: lambertian_sides(b) != NOT_LAMBERTIAN).inline
    no_instance = mi.load_dict({"type": "scene", "floor": {"type": "rectangle", "bsdf": lambertian}})
    assert LambertianBsdfs(no_instance).inline


def test_inline_values_match_mitsuba(squares):
    """At the Lambertian squares' lanes of 40 000 random hits (both sides of every square) with random directions
    ``wo`` on the whole sphere and random samples: value and density at ``wo``, sampled direction, its density and
    its weight as Mitsuba's ``eval_pdf_sample`` gives them (float32 rounding apart), and the same lanes zero."""
    lanes = 40_000
    si = _hits(squares, lanes, seed=3)
    bsdf = si.bsdf()
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(7, lanes)
    wo = mi.warp.square_to_uniform_sphere(sampler.next_2d())
    sample1, sample2 = sampler.next_1d(), sampler.next_2d()
    ctx = mi.BSDFContext()
    table = LambertianBsdfs(squares, guided=lambda b: lambertian_sides(b) != NOT_LAMBERTIAN)
    lambertian = table.sides(bsdf, mi.Bool(True)) != NOT_LAMBERTIAN
    compared = np.array(lambertian)
    ours = table.eval_pdf_sample(bsdf, ctx, si, wo, sample1, sample2, lambertian)
    theirs = bsdf.eval_pdf_sample(ctx, si, wo, sample1, sample2, lambertian)

    def arrays(result):
        value, pdf, bs, weight = result
        return {"value": np.array(value)[..., compared], "pdf": np.array(pdf)[compared],
                "weight": np.array(weight)[..., compared], "wo": np.array(bs.wo)[..., compared],
                "sample_pdf": np.array(bs.pdf)[compared]}

    a, b = arrays(ours), arrays(theirs)
    carries = b["weight"].max(axis=0) > 0      # lanes whose sample Mitsuba gives a weight: its direction matters
    for key in ("value", "pdf", "weight"):
        np.testing.assert_allclose(a[key], b[key], rtol=2e-6, atol=1e-7, err_msg=key)
        assert np.array_equal(a[key] == 0, b[key] == 0), key
    np.testing.assert_allclose(a["wo"][:, carries], b["wo"][:, carries], atol=1e-6)
    np.testing.assert_allclose(a["sample_pdf"][carries], b["sample_pdf"][carries], rtol=2e-6)
    # Every kind of lane was met: lit from the front, mirrored from the back, black from behind.
    front = np.array(mi.Frame3f.cos_theta(si.wi))[compared] > 0
    assert front.any() and (~front).any() and 0.2 < (b["value"].max(axis=0) > 0).mean() < 0.8


@pytest.mark.parametrize("method", ["ours", "ours-expected"])
def test_inline_bsdfs_learn_what_mitsubas_calls_learn(cornell, method):
    """Trained on the shipped Cornell box (one- and two-sided diffuse) with the same seed, a grid guide learns the
    same sums and counts with its Lambertian BSDFs inline (Expected SARSA's albedo read once in ``locate``, and
    called for at the last vertices, where ``locate`` reads nothing) as with Mitsuba's calls everywhere: the same
    paths, the same targets."""
    learned = {}
    for inline in (True, False):
        with pytest.MonkeyPatch.context() as patch:
            if not inline:     # on the class, not the guide: a guide holding itself in a closure outlives the test
                prepare = GridGuide.prepare
                patch.setattr(GridGuide, "prepare", lambda self, scene: _with_calls(prepare, self, scene))
            guide = make_guide(method)
            # Short paths: many end at max_depth, where locate reads nothing and Expected SARSA's record calls.
            train(cornell, guide, spp=24, seed=1, max_depth=4)
        learned[inline] = guide.record_table.totals()
    assert LambertianBsdfs(cornell, guided=lambda b: lambertian_sides(b) != NOT_LAMBERTIAN).inline
    sums, counts = learned[True]
    np.testing.assert_allclose(sums, learned[False][0], rtol=1e-6)
    np.testing.assert_array_equal(counts, learned[False][1])
    assert counts.sum() > 10_000


def _with_calls(prepare, guide, scene):
    """``GridGuide.prepare`` with every BSDF left to Mitsuba's calls."""
    prepare(guide, scene)
    guide._bsdfs = LambertianBsdfs()


def _lambertian(bsdf) -> bool:
    return lambertian_sides(bsdf) != NOT_LAMBERTIAN


def test_emitter_evaluated_inline_only_where_every_smooth_bsdf_is():
    """Next-event estimation evaluates the BSDF at every vertex with a smooth lobe: inline only where each of those
    is a Lambertian BSDF computed inline (a glass sphere, all delta lobes, does not count; a rough plastic the guide
    does not guide does, and so does a Lambertian BSDF the guide does not guide)."""
    diffuse = {"type": "twosided", "material": {"type": "diffuse"}}
    with_glass = mi.load_dict({"type": "scene", "floor": {"type": "rectangle", "bsdf": diffuse},
                               "ball": {"type": "sphere", "bsdf": {"type": "dielectric"}}})
    with_plastic = mi.load_dict({"type": "scene", "floor": {"type": "rectangle", "bsdf": diffuse},
                                 "ball": {"type": "sphere", "bsdf": {"type": "roughplastic"}}})
    one_sided = mi.load_dict({"type": "scene", "floor": {"type": "rectangle", "bsdf": diffuse},
                              "ball": {"type": "sphere", "bsdf": {"type": "diffuse"}}})
    assert LambertianBsdfs(with_glass, guided=_lambertian).inline_emitter_eval
    assert LambertianBsdfs(with_plastic, guided=_lambertian).inline
    assert not LambertianBsdfs(with_plastic, guided=_lambertian).inline_emitter_eval
    two_sided_only = LambertianBsdfs(one_sided, guided=lambda b: lambertian_sides(b) == BOTH_SIDES)
    assert two_sided_only.inline and not two_sided_only.inline_emitter_eval
    assert not LambertianBsdfs(with_glass, guided=lambda b: False).inline_emitter_eval


@pytest.mark.parametrize("method", ["ours", "ours-expected", "ours-plus"])
def test_nee_with_the_emitter_evaluated_inline_renders_mitsubas_calls_image(cornell, method):
    """With next-event estimation on the shipped Cornell box (every smooth BSDF Lambertian), the BSDF's value towards
    the emitter computed inline from the albedo the guided sample reads (Expected SARSA's read in ``locate``, the
    others' read for it) gives, with the same seed, the image of Mitsuba's calls everywhere, to float32 rounding;
    and a trained guide then never evaluates the BSDF through Mitsuba's call first (the base class's way)."""
    images = {}
    for inline in (True, False):
        trained_calls = []
        with pytest.MonkeyPatch.context() as patch:
            if not inline:
                prepare = GridGuide.prepare
                patch.setattr(GridGuide, "prepare", lambda self, scene: _with_calls(prepare, self, scene))
            evaluate_then_sample = Guide.sample_and_eval

            def spy(guide, *args, **kwargs):
                trained_calls.append(guide.trained)
                return evaluate_then_sample(guide, *args, **kwargs)

            patch.setattr(Guide, "sample_and_eval", spy)
            props = mi.Properties()
            props["nee"] = True
            integrator = GuidedPathIntegrator(props, guide=make_guide(method))
            images[inline] = render(cornell, integrator, Budget(spp=32), seed=5, progress=False).image
        assert integrator.guide._bsdfs.inline_emitter_eval == inline
        assert any(trained_calls) != inline
    np.testing.assert_allclose(images[True], images[False], rtol=1e-5, atol=1e-6)
    assert images[True].mean() > 0
