"""Frozen passes (guiding/frozen_pass.py) render what traced passes render.

A replayed pass reads the guide's tables as inputs and keys its recordings by the guide's ``trace_key``: a table the
replay missed, or a host-side value that shaped the trace and changed, would leave the later passes rendering with
the tables or code of an earlier one. So the same passes (same seeds, a schedule of pass sizes that repeats and
grows, the guide learning in between) are rendered twice, traced and frozen, and every pass image and every update's
statistics must agree exactly.

The comparison runs in a fresh process (this file run as a script), on one Dr.Jit thread so that sums are taken in
one order: in the test session, BSDFs that other tests loaded on their own are still alive, and Dr.Jit cannot
record a scene's BSDF calls then (``recordable``; such a render traces every pass, as the last test checks).
"""

import json
import subprocess
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from guiding.guides.methods import method_names, resolve

#: Pass sizes: the first passes alike (the learning passes), then a pass size met before, after another one.
SCHEDULE = (2, 2, 2, 4, 2, 4, 8, 4)
#: Every method of guided_path (``path`` is Mitsuba's own integrator): a guide that branches on host state without declaring it in its trace_key fails here. Among them
#: every kind of device state: SARSA and the memo tables, Monte Carlo's vertex log, the Expected SARSA value, refined
#: bins, the cells' alias tables, the uniform proposals' rejection loop, the SD-tree and quadtree forests (whose
#: arrays change size); ``ours`` with its statistics counters.
METHODS = [name for name in method_names() if resolve(name).mitsuba_integrator is None]
#: The key of ``_compare``'s result with a BSDF alive outside the scene.
OUTSIDE_BSDF = "with a BSDF outside the scene"
#: The guides whose training stops at this pass (the SD-tree's last iteration, a grid guide's ``learning_share``):
#: their passes then trace a kernel without recording.
TRAINING_STOPS = {"sdtree": 5, "ours-plus": 5}


def _passes(scene, method: str, freeze: bool) -> tuple[list, list, int | None]:
    """The pass images, update statistics and path counts of one render of ``SCHEDULE``, and the frozen
    recordings made."""
    from guiding.render.driver import PassDriver
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.guides.methods import make_guide

    props = mi.Properties()
    props["freeze"] = freeze
    integrator = GuidedPathIntegrator(props, guide=make_guide(method, **({"statistics": True} if method == "ours"
                                                                         else {})))
    driver = PassDriver(scene, integrator)
    driver.prepare(None)
    images, stats = [], []
    for index, spp in enumerate(SCHEDULE):
        if TRAINING_STOPS.get(method) == index:
            integrator.guide.stop_training()
        outcome = driver.run(seed=index, spp=spp)
        images.append(np.array(outcome.image))
        # The update's statistics, and the integrator's counters (inputs of the replay apart from the guide's).
        stats.append({key: value for key, value in outcome.update.stats.items() if "seconds" not in key}
                     | {"paths": outcome.paths, "hits": outcome.hits, "rays": outcome.rays})
    frozen = integrator.frozen_passes
    return images, stats, frozen.recordings if frozen else None


def _compare(scene_name: str) -> dict:
    """Per method: the largest difference of a pass image, whether the statistics agree, the recordings made. Then,
    under ``OUTSIDE_BSDF``, whether the scene is recordable and its passes frozen with a BSDF alive outside it."""
    from guiding.render.frozen_pass import recordable
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.scenes import load_scene

    scene = load_scene(scene_name, scale=0.125)
    results = {}
    for method in METHODS:
        traced, traced_stats, _ = _passes(scene, method, False)
        frozen, frozen_stats, recordings = _passes(scene, method, True)
        results[method] = {"difference": max(float(np.abs(a - b).max()) for a, b in zip(traced, frozen)),
                           "same_statistics": traced_stats == frozen_stats, "recordings": recordings}
    outside = mi.load_dict({"type": "diffuse"})
    integrator = GuidedPathIntegrator(mi.Properties())
    integrator.prepare(scene)
    results[OUTSIDE_BSDF] = {"recordable": recordable(scene), "frozen": integrator.frozen_passes is not None}
    del outside
    return results


@pytest.fixture(scope="module", params=["cornell", "mirror-box"])
def comparison(request):
    """``_compare`` of a scene in a fresh process (mirror-box: nothing to guide, the BSDF-sampling loop)."""
    done = subprocess.run([sys.executable, __file__, request.param], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("method", METHODS)
def test_frozen_passes_render_what_traced_passes_render(comparison, method):
    result = comparison[method]
    assert result["difference"] == 0 and result["same_statistics"], result
    # It did replay: fewer recordings than passes (one per pass size and trace key, and where inputs change shape).
    assert result["recordings"] is not None and result["recordings"] < len(SCHEDULE), result


def test_device_arrays_finds_every_table_once():
    """The replay's inputs: the arrays reachable through attributes, containers and nested objects, each once."""
    from guiding.render.frozen_pass import device_arrays
    from guiding.guides.methods import make_guide

    guide = make_guide("ours-plus")
    table = guide.record_table
    ids = [id(array) for array in device_arrays(guide)]
    assert len(ids) == len(set(ids))
    for array in (table.q, table.pass_targets, table.hemi_alias, table.pair_memo, table.refinement.pass_targets):
        assert id(array) in ids
    assert all(dr.is_array_v(array) for array in device_arrays(guide))


def test_a_bsdf_outside_the_scene_makes_passes_traced(comparison):
    """A BSDF alive outside the scene: no recording is attempted (its pass would have run, then failed), and the
    passes are traced. In the fresh process, where the same scene alone was recorded above."""
    assert comparison[OUTSIDE_BSDF] == {"recordable": False, "frozen": False}


if __name__ == "__main__":
    from guiding.backend import set_variant

    set_variant("llvm_ad_rgb", threads=1)
    print(json.dumps(_compare(sys.argv[1])))
