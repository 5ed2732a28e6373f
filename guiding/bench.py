"""Benchmarks: cost per sample of our methods as a ratio against baselines timed in the same process.

Passes of the compared integrators are interleaved (A, B, A, B, …) after a warm-up, so that machine noise hits
them alike, and each figure is the median over passes of kernel wall time per spp (device synchronised).
"""

from __future__ import annotations

import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pandas as pd

from .render import pass_seed


def _timed_pass(scene: mi.Scene, integrator, spp: int, seed: int) -> float:
    start = time.perf_counter()
    image = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
    dr.eval(image)
    dr.sync_thread()
    return time.perf_counter() - start


def seconds_per_spp(scene: mi.Scene, integrators: dict[str, object], passes: int = 12, pass_spp: int = 8,
                    warmup: int = 2) -> dict[str, dict[str, float]]:
    """Median seconds per spp of each integrator's render kernel and median seconds of its guide's update,
    its passes interleaved with the others'."""
    render_times = {name: [] for name in integrators}
    update_times = {name: [] for name in integrators}
    for integrator in integrators.values():
        guide = getattr(integrator, "guide", None)
        if guide is not None:
            guide.prepare(scene)
    for index in range(warmup + passes):
        for name, integrator in integrators.items():
            seconds = _timed_pass(scene, integrator, pass_spp, pass_seed(0, index))
            start = time.perf_counter()
            guide = getattr(integrator, "guide", None)
            if guide is not None:
                guide.update((index + 1) * pass_spp)
                dr.sync_thread()
            if index >= warmup:
                render_times[name].append(seconds / pass_spp)
                update_times[name].append(time.perf_counter() - start)
    return {name: {"seconds_per_spp": float(np.median(render_times[name])),
                   "update_seconds": float(np.median(update_times[name]))} for name in integrators}


def baseline_vs_mitsuba(scenes: list[tuple[str, float]], passes: int = 12, max_depth: int = 16) -> pd.DataFrame:
    """Time per spp of the ``brdf`` baseline against Mitsuba's ``path`` integrator (NEE + MIS), per scene."""
    from .integrator import GuidedPathIntegrator
    from .scenes import load_scene

    rows = []
    for name, scale in scenes:
        scene = load_scene(name, scale)
        props = mi.Properties()
        props["max_depth"] = max_depth
        timings = seconds_per_spp(scene, {"brdf": GuidedPathIntegrator(props),
                                          "path": mi.load_dict({"type": "path", "max_depth": max_depth})},
                                  passes=passes)
        brdf, path = timings["brdf"]["seconds_per_spp"], timings["path"]["seconds_per_spp"]
        rows.append({"scene": name, "scale": scale, "resolution": _resolution(scene),
                     "brdf_ms_per_spp": 1e3 * brdf, "path_ms_per_spp": 1e3 * path, "ratio_brdf_over_path": brdf / path})
    return pd.DataFrame(rows)


def methods_vs_brdf(scenes: list[tuple[str, float]], methods: list[str], passes: int = 12,
                    pass_spp: int = 8) -> pd.DataFrame:
    """Per method: kernel time per spp as a ratio to ``brdf`` (same run), and the guide update's share of a pass."""
    from .integrator import GuidedPathIntegrator
    from .methods import make_guide
    from .scenes import load_scene

    rows = []
    for name, scale in scenes:
        scene = load_scene(name, scale)
        integrators = {m: GuidedPathIntegrator(guide=make_guide(m)) for m in ["brdf", *methods]}
        timings = seconds_per_spp(scene, integrators, passes=passes, pass_spp=pass_spp)
        brdf = timings["brdf"]["seconds_per_spp"]
        for method in methods:
            t = timings[method]
            pass_seconds = t["seconds_per_spp"] * pass_spp
            rows.append({"scene": name, "resolution": _resolution(scene), "method": method,
                         "ms_per_spp": 1e3 * t["seconds_per_spp"], "brdf_ms_per_spp": 1e3 * brdf,
                         "ratio_to_brdf": t["seconds_per_spp"] / brdf, "update_ms": 1e3 * t["update_seconds"],
                         "update_share_of_pass": t["update_seconds"] / (pass_seconds + t["update_seconds"]),
                         "table_MiB": integrators[method].guide.stats().get("table_bytes", 0) / 2**20})
    return pd.DataFrame(rows)


def _resolution(scene: mi.Scene) -> str:
    size = [int(v) for v in scene.sensors()[0].film().size()]
    return f"{size[0]}x{size[1]}"


def write_table(frame: pd.DataFrame, stem: Path, title: str, device: str, command: str) -> None:
    """``stem.csv`` and ``stem.md`` (the Markdown names the device, the date and the command that made it)."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    frame.to_csv(stem.with_suffix(".csv"), index=False, float_format="%.4g")
    markdown = frame.to_markdown(index=False, floatfmt=".4g")
    stem.with_suffix(".md").write_text(f"# {title}\n\nDevice: {device}. Generated {time.strftime('%Y-%m-%d')} by "
                                       f"`{command}`.\n\n{markdown}\n")

