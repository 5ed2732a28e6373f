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
                    warmup: int = 2) -> dict[str, float]:
    """Median seconds per spp of each integrator, its passes interleaved with the others'."""
    times = {name: [] for name in integrators}
    for index in range(warmup + passes):
        for name, integrator in integrators.items():
            seconds = _timed_pass(scene, integrator, pass_spp, pass_seed(0, index))
            guide = getattr(integrator, "guide", None)
            if guide is not None:
                guide.update((index + 1) * pass_spp)
            if index >= warmup:
                times[name].append(seconds / pass_spp)
    return {name: float(np.median(values)) for name, values in times.items()}


def baseline_vs_mitsuba(scenes: list[tuple[str, float]], passes: int = 12, max_depth: int = 16) -> pd.DataFrame:
    """Time per spp of the ``brdf`` baseline against Mitsuba's ``path`` integrator (NEE + MIS), per scene."""
    from .integrator import GuidedPathIntegrator
    from .scenes import load_scene

    rows = []
    for name, scale in scenes:
        scene = load_scene(name, scale)
        props = mi.Properties()
        props["max_depth"] = max_depth
        ours = GuidedPathIntegrator(props)
        ours.guide.prepare(scene)
        timings = seconds_per_spp(scene, {"brdf": ours, "path": mi.load_dict({"type": "path",
                                                                              "max_depth": max_depth})},
                                  passes=passes)
        size = [int(v) for v in scene.sensors()[0].film().size()]
        rows.append({"scene": name, "scale": scale, "resolution": f"{size[0]}x{size[1]}",
                     "brdf_ms_per_spp": 1e3 * timings["brdf"], "path_ms_per_spp": 1e3 * timings["path"],
                     "ratio_brdf_over_path": timings["brdf"] / timings["path"]})
    return pd.DataFrame(rows)


def write_table(frame: pd.DataFrame, stem: Path, title: str, device: str, command: str) -> None:
    """``stem.csv`` and ``stem.md`` (the Markdown names the device, the date and the command that made it)."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    frame.to_csv(stem.with_suffix(".csv"), index=False, float_format="%.4g")
    markdown = frame.to_markdown(index=False, floatfmt=".4g")
    stem.with_suffix(".md").write_text(f"# {title}\n\nDevice: {device}. Generated {time.strftime('%Y-%m-%d')} by "
                                       f"`{command}`.\n\n{markdown}\n")

