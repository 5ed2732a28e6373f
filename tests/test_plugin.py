"""The `guided_path` plugin used the way Mitsuba users use plugins: loaded from XML or a dict and rendered with plain
``mi.render``, it trains its guide (progressive passes with updates in between), as ``python -m guiding render``."""

import mitsuba as mi
import numpy as np
import pytest

import guiding  # noqa: F401  (registers guided_path for the variant the tests set)
from guiding.render.integrator import GuidedPathIntegrator
from guiding.guides.methods import make_guide
from guiding.metrics import mae_tonemapped
from guiding.render.progressive import Budget, render
from guiding.scenes import load_scene

SPP = 256


def test_mi_render_trains_the_guide_like_the_renderer():
    scene = load_scene("door-ajar", scale=0.2)
    reference = render(scene, mi.load_dict({"type": "path", "max_depth": 16}), Budget(spp=1024, pass_spp=64),
                       seed=7, progress=False).image
    plugin = mi.load_dict({"type": "guided_path", "method": "ours", "statistics": True})
    image = np.asarray(mi.render(scene, integrator=plugin, spp=SPP, seed=1))
    renderer = render(scene, GuidedPathIntegrator(guide=make_guide("ours")), Budget(spp=SPP), seed=1,
                      progress=False)
    # The same passes with the same seeds: the same image as the renderer's.
    assert plugin.guide.trained and plugin.last_result.spp == SPP
    assert sum(p.guide.get("guided_samples", 0) for p in plugin.last_result.passes) > 0
    np.testing.assert_allclose(image[..., :3], renderer.image, rtol=1e-4, atol=1e-5)
    brdf = mi.render(scene, integrator=mi.load_dict({"type": "guided_path", "method": "brdf"}), spp=SPP, seed=1)
    assert mae_tonemapped(image[..., :3], reference) < mae_tonemapped(np.asarray(brdf)[..., :3], reference)


def test_plugin_resolves_its_method_once_with_the_shorthand():
    """The plugin's `method` is a name (XML, load_dict), resolved into the method's guide in its constructor."""
    plugin = mi.load_dict({"type": "guided_path", "method": "ours-S4-D8", "statistics": True})
    parameters = plugin.guide.parameters
    assert (parameters.spatial_resolution, parameters.directional_resolution, parameters.statistics) == (4, 8, True)
    assert parameters == make_guide("ours", spatial_resolution=4, directional_resolution=8, statistics=True).parameters


def test_xml_integrator_trains_under_mi_render():
    scene = mi.load_string("""
    <scene version="3.0.0">
        <integrator type="guided_path">
            <string name="method" value="ours"/>
            <integer name="pass_spp" value="4"/>
        </integrator>
        <sensor type="perspective">
            <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
            <sampler type="independent"><integer name="sample_count" value="16"/></sampler>
            <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
        </sensor>
        <shape type="rectangle"><bsdf type="diffuse"/></shape>
        <emitter type="constant"/>
    </scene>""")
    image = mi.render(scene)
    integrator = scene.integrator()
    assert image.shape[:2] == (16, 16)
    assert integrator.guide.trained
    assert [p.spp for p in integrator.last_result.passes] == [4, 4, 4, 4]


def test_the_plugin_takes_the_methods_parameters_as_properties():
    """A property the integrator does not read is a parameter of the method's guide, typed as in XML (what `--set`
    gives the command line); one the method does not take is refused, naming it."""
    plugin = mi.load_string("""
    <integrator type="guided_path" version="3.0.0">
        <string name="method" value="ours-plus"/>
        <boolean name="nee" value="true"/>
        <boolean name="path_fallback" value="true"/>
        <float name="learning_share" value="0.25"/>
        <integer name="spatial_resolution" value="4"/>
        <string name="rule" value="expected_sarsa"/>
        <boolean name="freeze" value="false"/>
    </integrator>""")
    assert plugin.nee and plugin.path_fallback and not plugin.freeze
    assert plugin.guide.parameters == make_guide("ours-plus", learning_share=0.25, spatial_resolution=4,
                                                 rule="expected_sarsa").parameters
    assert plugin.guide.learning_share() == 0.25
    for stray, named in (({"learning_shares": 0.25}, "no parameter 'learning_shares'"),
                         ({"spatial_resolution": 2.5}, "spatial_resolution=2.5 is not an integer"),
                         ({"method": "brdf", "learning_share": 0.25}, "takes no parameters"),
                         ({"max_dpeth": 4}, "no parameter 'max_dpeth'.*nor is it a property of guided_path itself")):
        with pytest.raises(RuntimeError, match=named):
            mi.load_dict({"type": "guided_path", "method": "ours", **stray})
