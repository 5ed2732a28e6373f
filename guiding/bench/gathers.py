"""``bench --part gathers``: each method's kernel time per spp with its table reads compiled into the CPU's gather
instruction and into LLVM's loop of one scalar load per lane (:func:`guiding.llvm_gathers.use_hardware_gathers`).

The two builds of every method (and of Mitsuba's ``path``) render the same passes from the same seeds, interleaved
pass by pass in one process, so that machine noise hits them alike; each build learns its own guide, and the two
learn the same tables (the builds' results are bit-identical). Dr.Jit's kernel cache keys on the target, so each
build compiles, and then replays, its own kernels.
"""

from __future__ import annotations

import sys

import mitsuba as mi
import numpy as np
import pandas as pd

from guiding.llvm_gathers import llvm_target_kept, use_hardware_gathers
from guiding.bench.benchmark import _resolution, interleaved_passes
from guiding.render.defaults import MAX_DEPTH, PASS_SPP

#: Suffix of the integrator names of the builds with scalar loads.
SCALAR_LOADS = " [scalar loads]"


def gathers_table(scenes: list[tuple[str, float]], methods: list[str], passes: int = 8, pass_spp: int = PASS_SPP,
                  max_depth: int = MAX_DEPTH) -> pd.DataFrame:
    """Per scene and method (``path`` and ``brdf`` first): median kernel time per spp of both builds, the speed-up
    of the gather instruction (scalar-load time over gather time), and the ratio to ``brdf`` in each build."""
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.guides.methods import make_guide
    from guiding.scenes import load_scene

    props = mi.Properties()
    props["max_depth"] = max_depth

    def integrator(method: str):
        if method == "path":
            return mi.load_dict({"type": "path", "max_depth": max_depth})
        return GuidedPathIntegrator(props, guide=make_guide(method))

    names = list(dict.fromkeys(["path", "brdf", *methods]))
    rows = []
    with llvm_target_kept():
        for number, (name, scale) in enumerate(scenes, 1):
            print(f"bench: scene {number}/{len(scenes)} {name} (scale {scale:g}): {', '.join(names)}, with gather "
                  f"instructions and with scalar loads, {passes} timed passes each", file=sys.stderr, flush=True)
            scene = load_scene(name, scale)
            integrators = {}
            for method in names:
                integrators[method] = integrator(method)
                integrators[method + SCALAR_LOADS] = integrator(method)
            timed = interleaved_passes(scene, integrators, passes=passes, pass_spp=pass_spp,
                                       before_pass=lambda build: use_hardware_gathers(not build.endswith(SCALAR_LOADS)))
            per_spp = {build: float(np.median([r.kernel for r in records])) / pass_spp
                       for build, records in timed.items()}
            for method in names:
                gathers, loads = per_spp[method], per_spp[method + SCALAR_LOADS]
                rows.append({"scene": name, "resolution": _resolution(scene), "method": method,
                             "gather_ms_per_spp": 1e3 * gathers, "scalar_loads_ms_per_spp": 1e3 * loads,
                             "speed_up": loads / gathers,
                             "ratio_to_brdf_gathers": gathers / per_spp["brdf"],
                             "ratio_to_brdf_scalar_loads": loads / per_spp["brdf" + SCALAR_LOADS]})
    return pd.DataFrame(rows)
