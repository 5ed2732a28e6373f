"""Benchmarks: cost per sample of every method as a ratio against ``brdf`` and Mitsuba's ``path``, timed in the
same process.

Passes of the compared integrators are interleaved (A, B, A, B, …) after a warm-up, so that machine noise hits
them alike. Kernel time comes from Dr.Jit's kernel history (execution time of the pass's kernels; compilation is
reported apart); wall time adds the Python tracing of the integrator, which every ``mi.render`` call repeats.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np
import pandas as pd

from .driver import PassDriver, pass_seed


@dataclass
class PassTiming:
    """One timed pass: wall time, its parts from Dr.Jit's kernel history, the guide update after it, counters."""

    wall: float                 # launch to synchronisation, Python tracing and compilation included
    kernel: float               # execution time of the pass's kernels
    compile: float              # code generation and backend compilation
    update: float               # the guide's update after the pass
    refine: float               # the part of ``update`` an SD-tree spent refining
    paths: int = 0
    hits: int = 0
    rays: int = 0
    guided: int | None = None   # vertices the guide sampled (the rest, e.g. delta or glossy, skip guiding)
    memo_pairs: int = 0         # (cell, normal bin) pairs with memo tables (only those paths visited)


def _timed_pass(driver: PassDriver, spp: int, seed: int) -> PassTiming:
    outcome = driver.run(seed, spp)
    stats = outcome.update.stats
    return PassTiming(wall=outcome.seconds, kernel=outcome.kernels.execution_seconds,
                      compile=outcome.kernels.compile_seconds, update=outcome.update_seconds,
                      refine=stats.get("refine_seconds", 0.0), paths=outcome.paths, hits=outcome.hits,
                      rays=outcome.rays, guided=stats.get("guided_samples"), memo_pairs=stats.get("memo_pairs", 0))


def interleaved_passes(scene: mi.Scene, integrators: dict[str, object], passes: int = 12, pass_spp: int = 8,
                       warmup: int = 2) -> dict[str, list[PassTiming]]:
    """``warmup + passes`` passes of every integrator, interleaved (A, B, A, B, …) so that machine noise hits
    them alike; returns the timed passes (warm-up passes dropped, except that compile time of every pass is
    kept in the first timed record's ``compile``)."""
    drivers = {name: PassDriver(scene, integrator) for name, integrator in integrators.items()}
    for driver in drivers.values():
        driver.prepare()
    timings = {name: [] for name in integrators}
    for index in range(warmup + passes):
        for name, driver in drivers.items():
            timings[name].append(_timed_pass(driver, pass_spp, pass_seed(0, index)))
    timed = {}
    for name, records in timings.items():
        timed[name] = records[warmup:]
        timed[name][0].compile += sum(r.compile for r in records[:warmup])
    return timed


def benchmark(scenes: list[tuple[str, float]], methods: list[str], passes: int = 12, pass_spp: int = 8,
              max_depth: int = 16) -> pd.DataFrame:
    """Per scene and method: kernel time per spp (also as ratios to ``brdf`` and Mitsuba ``path`` timed in the
    same run), Python tracing per pass, compile time, guide update share, memory, hit rate, rays per second, and
    what the guide skips: the share of vertices it guides and the memoised (cell, normal bin) pairs."""
    from .integrator import GuidedPathIntegrator
    from .methods import make_guide
    from .scenes import load_scene

    rows = []
    for number, (name, scale) in enumerate(scenes, 1):
        print(f"bench: scene {number}/{len(scenes)} {name} (scale {scale:g}): path, brdf, {', '.join(methods)}, "
              f"{passes} timed passes each", file=sys.stderr, flush=True)
        scene = load_scene(name, scale)
        integrators = {"path": mi.load_dict({"type": "path", "max_depth": max_depth})}
        for method in dict.fromkeys(["brdf", *methods]):
            props = mi.Properties()
            props["max_depth"] = max_depth
            integrators[method] = GuidedPathIntegrator(props, guide=make_guide(method))
        timed = interleaved_passes(scene, integrators, passes=passes, pass_spp=pass_spp)
        kernel_per_spp = {m: float(np.median([r.kernel for r in records])) / pass_spp
                          for m, records in timed.items()}
        for method, records in timed.items():
            guide = getattr(integrators[method], "guide", None)
            memory = guide.stats().get("memory_bytes", 0) if guide is not None else 0
            total = sum(r.wall + r.update for r in records)
            kernel_seconds = sum(r.kernel for r in records)
            rows.append({
                "scene": name, "resolution": _resolution(scene), "method": method,
                "kernel_ms_per_spp": 1e3 * kernel_per_spp[method],
                "ratio_to_brdf": kernel_per_spp[method] / kernel_per_spp["brdf"],
                "ratio_to_path": kernel_per_spp[method] / kernel_per_spp["path"],
                "wall_ms_per_spp": 1e3 * float(np.median([r.wall for r in records])) / pass_spp,
                "trace_ms_per_pass": 1e3 * float(np.median([max(r.wall - r.kernel - r.compile, 0.0)
                                                            for r in records])),
                "compile_s": sum(r.compile for r in records),
                "update_ms": 1e3 * float(np.mean([r.update for r in records])),
                "update_share": sum(r.update for r in records) / total,
                "refine_share": sum(r.refine for r in records) / total,
                "memory_MiB": memory / 2**20,
                "hit_rate": sum(r.hits for r in records) / max(sum(r.paths for r in records), 1)
                if method != "path" else None,
                "Mrays_per_s": sum(r.rays for r in records) / kernel_seconds / 1e6 if method != "path" else None,
                "guided_per_ray": sum(r.guided for r in records) / max(sum(r.rays for r in records), 1)
                if records[-1].guided is not None else None,
                "memo_pairs": records[-1].memo_pairs,
            })
    return pd.DataFrame(rows)


#: Issue targets: (what, method, column, bound, applies on the GPU only / CPU only / both).
TARGETS = [
    ("`ours` ≤ 1.2× `brdf` per spp (CPU)", "ours", "ratio_to_brdf", 1.2, "cpu"),
    ("`ours` ≤ 1.3× `brdf` per spp (GPU)", "ours", "ratio_to_brdf", 1.3, "gpu"),
    ("grid update ≤ 2 % of pass time (`ours`)", "ours", "update_share", 0.02, "both"),
    ("SD-tree refinement ≤ 10 % of training time", "sdtree", "refine_share", 0.10, "both"),
    ("`brdf` ≤ 1.0× Mitsuba `path` per spp", "brdf", "ratio_to_path", 1.0, "both"),
]


def target_table(frame: pd.DataFrame, device_kind: str) -> pd.DataFrame:
    """Each target that applies to ``device_kind`` (``cpu`` or ``gpu``), per scene: the measured value and
    whether it is met."""
    rows = []
    for what, method, column, bound, kind in TARGETS:
        if kind not in (device_kind, "both"):
            continue
        for _, row in frame[frame["method"] == method].iterrows():
            rows.append({"target": what, "scene": row["scene"], "measured": row[column],
                         "met": bool(row[column] <= bound)})
    return pd.DataFrame(rows)


def _resolution(scene: mi.Scene) -> str:
    size = [int(v) for v in scene.sensors()[0].film().size()]
    return f"{size[0]}x{size[1]}"


def write_table(frame: pd.DataFrame, stem: Path, title: str, device: str, command: str,
                sections: dict[str, pd.DataFrame] | None = None) -> None:
    """``stem.csv`` and ``stem.md`` (the Markdown names the device, the date and the command that made it, and
    appends ``sections``, titled tables)."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    frame.to_csv(stem.with_suffix(".csv"), index=False, float_format="%.4g")
    markdown = frame.to_markdown(index=False, floatfmt=".4g")
    for heading, table in (sections or {}).items():
        markdown += f"\n\n## {heading}\n\n{table.to_markdown(index=False, floatfmt='.4g')}"
    stem.with_suffix(".md").write_text(f"# {title}\n\nDevice: {device}. Generated {time.strftime('%Y-%m-%d')} by "
                                       f"`{command}`.\n\n{markdown}\n")

