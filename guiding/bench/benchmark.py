"""Benchmarks: cost per sample of every method as a ratio against ``brdf`` and Mitsuba's ``path``, timed in the
same process.

Passes of the compared integrators are interleaved (A, B, A, B, …) after a warm-up, so that machine noise hits
them alike. Kernel time comes from Dr.Jit's kernel history (execution time of the pass's kernels; compilation is
reported apart); wall time adds the Python tracing of the integrator, which every ``mi.render`` call repeats.

Cost breakdown (:func:`breakdown_table`): in the same interleaved run, every guided method is also timed with the
parts of its bounce switched on one by one, and the ``trace-only`` kernel gives the machine's throughput limit.
Grid guides: ``[classify]`` (vertex lookup and guided mask, BSDF sampling), ``[+sample]`` (guided directions, BSDF
weights), ``[+pdf]`` (the exact mixture density: the full sampler, nothing recorded), ``[+record]`` (the guide as
rendered, statistics off: the method's own row) and ``[+statistics]`` (its per-pass counters on; the benchmark's
``guided_per_ray`` comes from this variant); ``[bsdf paths]`` (the whole bounce computed and recorded, the path
continued along the BSDF's sample: the guide's work at ``brdf``'s paths; its increment is over the method itself,
minus what the guided paths themselves cost); ``[hot rows]`` (the rejection samplers' ``bins`` proposal: the whole
bounce, every vertex drawing from and reading densities in the first pair's alias row, which stays cached: its
increment over the method itself is minus what the rows' cache misses cost, together with what drawing every
vertex's directions from one distribution changes (results/bench/README.md, "The `[hot rows]` stage");
``rays_per_path`` shows how far its paths are from the method's, and a missed target's bottleneck gives the change
per ray too).
Tree guides: ``[no record]`` (the method's own trees, as they
are at each pass, sampled by a kernel that records nothing) and ``[+record]``. The partial stages are the
benchmark's instruments (:mod:`guiding.bench.instruments`): their images are not meant to be correct, and they learn
their tables only in the warm-up passes.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pandas as pd

from guiding.bench.instruments import (BsdfPathsStage, ClassifyStage, HotRowsStage, PdfStage, SampleStage,
                                       SamplingOnly, instrumented_guide)
from guiding.guides.methods import grid_parameters, make_guide
from guiding.render.defaults import MAX_DEPTH, PASS_SPP
from guiding.render.driver import PassDriver, pass_seed


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


def interleaved_passes(scene: mi.Scene, integrators: dict[str, object], passes: int = 12, pass_spp: int = PASS_SPP,
                       warmup: int = 2, before_pass=None) -> dict[str, list[PassTiming]]:
    """``warmup + passes`` passes of every integrator, interleaved (A, B, A, B, …) so that machine noise hits
    them alike; returns the timed passes (warm-up passes dropped, except that compile time of every pass is
    kept in the first timed record's ``compile``). ``before_pass(name)``, if given, runs before each pass of the
    integrator ``name`` (outside the timed region)."""
    drivers = {name: PassDriver(scene, integrator) for name, integrator in integrators.items()}
    for driver in drivers.values():
        driver.prepare()
    timings = {name: [] for name in integrators}
    for index in range(warmup + passes):
        for name, driver in drivers.items():
            if before_pass is not None:
                before_pass(name)
            timings[name].append(_timed_pass(driver, pass_spp, pass_seed(0, index)))
    timed = {}
    for name, records in timings.items():
        timed[name] = records[warmup:]
        timed[name][0].compile += sum(r.compile for r in records[:warmup])
    return timed


TRACE_ONLY = "trace-only"


def _instrument(instrument):
    """The breakdown stage of one of :mod:`guiding.bench.instruments`' grid guides: the instrumented guide of a method
    (None where the instrument does not apply to it)."""
    def build(method: str, guide):
        return instrumented_guide(method, instrument) if instrument.applies_to(grid_parameters(method)) else None
    return build


#: Grid guides' breakdown: (stage, the variant's name suffix, what builds the variant's guide from the method's name
#: and its own guide; None: the method itself).
GRID_STAGES = [("classify", "[classify]", _instrument(ClassifyStage)),
               ("+sample", "[+sample]", _instrument(SampleStage)),
               ("+pdf", "[+pdf]", _instrument(PdfStage)),
               ("+record", "", None),
               ("+statistics", "[+statistics]", lambda method, guide: make_guide(method, statistics=True)),
               ("bsdf paths", "[bsdf paths]", _instrument(BsdfPathsStage)),
               # Only where a drawn bin's direction is tried by rejection: another row's bins taken without rejection
               # lie below the surface, and shorten the paths.
               ("hot rows", "[hot rows]", _instrument(HotRowsStage))]
#: Stages that are not a step of the sequence: their increment is over the method itself (for ``bsdf paths``, minus
#: what the guided paths themselves cost; for ``hot rows``, minus what the alias rows' cache misses and the paths'
#: own directions cost).
OUTSIDE_SEQUENCE = {"bsdf paths", "hot rows"}
#: Tree guides' breakdown: the method's trees sampled without recording, then the guide itself.
TREE_STAGES = [("no record", "[no record]", lambda method, guide: SamplingOnly(guide)), ("+record", "", None)]


class TraceOnlyIntegrator(mi.SamplingIntegrator):
    """The throughput limit of the machine: camera rays, then a walk of incoherent rays (uniform directions on the
    sphere from each hit, up to ``max_depth`` rays per path, ending on a miss) traced with ``scene.ray_intersect``
    as the path loop traces them (all ray flags), and nothing else: no BSDF, no emission, no roulette. Counts its
    paths and rays as ``guided_path`` does, so that the benchmark reports its rays per second."""

    counts_paths = True   # read by the pass driver

    def __init__(self, max_depth: int):
        super().__init__(mi.Properties())
        self.max_depth = max_depth
        self.reset_counters()

    def reset_counters(self) -> None:
        self.path_count, self.hit_count, self.ray_count = mi.UInt32(0), mi.UInt32(0), mi.UInt32(0)

    @dr.syntax
    def sample(self, scene, sampler, ray, medium=None, active=True):
        ray = mi.Ray3f(ray)
        active = dr.full(mi.Bool, True, dr.width(ray.o)) & active
        started = mi.Bool(active)
        depth, hits = mi.UInt32(0), mi.Float(0)
        while dr.hint(active, max_iterations=self.max_depth, label="Trace only"):
            si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=(depth == 0))
            depth += 1
            hits += dr.select(si.is_valid(), 1.0, 0.0)
            ray = si.spawn_ray(mi.warp.square_to_uniform_sphere(sampler.next_2d(active)))
            active &= si.is_valid() & (depth < self.max_depth)
        dr.scatter_reduce(dr.ReduceOp.Add, self.path_count, mi.UInt32(1), mi.UInt32(0), started)
        dr.scatter_reduce(dr.ReduceOp.Add, self.hit_count, mi.UInt32(1), mi.UInt32(0), started & (hits > 0))
        dr.scatter_reduce(dr.ReduceOp.Add, self.ray_count, depth, mi.UInt32(0), started)
        return mi.Spectrum(hits / self.max_depth), mi.Bool(True), []


def breakdown_variants(method: str, guide) -> list[tuple[str, str, object]]:
    """The breakdown of ``method`` whose own integrator has ``guide``: (stage, integrator name, guide or None for the
    method's own integrator)."""
    if method == "brdf":
        return []
    variants = []
    for stage, suffix, build in (GRID_STAGES if grid_parameters(method) is not None else TREE_STAGES):
        if build is None:
            variants.append((stage, method, None))
        elif (variant := build(method, guide)) is not None:
            variants.append((stage, method + suffix, variant))
    return variants


def benchmark(scenes: list[tuple[str, float]], methods: list[str], passes: int = 12, pass_spp: int = PASS_SPP,
              max_depth: int = MAX_DEPTH, breakdown: bool = True, nee: bool = False) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per scene and method: kernel time per spp (also as ratios to ``brdf`` and Mitsuba ``path`` timed in the
    same run), Python tracing per pass, compile time, guide update share, memory, hit rate, rays per second (and as
    a fraction of the ``trace-only`` kernel's), and what the guide skips: the share of vertices it guides and the
    memoised (cell, normal bin) pairs. With ``breakdown``, the cost breakdown of every guided method (timed in the
    same interleaved run; see the module's docstring): returns (benchmark table, breakdown table). With ``nee``,
    every ``guided_path`` integrator (``brdf`` included) does next-event estimation, as ``path`` does."""
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.scenes import load_scene

    rows, breakdown_rows = [], []
    for number, (name, scale) in enumerate(scenes, 1):
        print(f"bench: scene {number}/{len(scenes)} {name} (scale {scale:g}): path, brdf, {', '.join(methods)}, "
              f"{passes} timed passes each", file=sys.stderr, flush=True)
        scene = load_scene(name, scale)
        integrators = {"path": mi.load_dict({"type": "path", "max_depth": max_depth}),
                       TRACE_ONLY: TraceOnlyIntegrator(max_depth)}
        props = mi.Properties()
        props["max_depth"] = max_depth
        props["nee"] = nee
        stages = {}
        for method in dict.fromkeys(["brdf", *methods]):
            integrators[method] = GuidedPathIntegrator(props, guide=make_guide(method))
            stages[method] = breakdown_variants(method, integrators[method].guide) if breakdown else []
            for _, variant, guide in stages[method]:
                if guide is not None:
                    integrators[variant] = GuidedPathIntegrator(props, guide=guide)
        timed = interleaved_passes(scene, integrators, passes=passes, pass_spp=pass_spp)
        kernel_per_spp = {m: float(np.median([r.kernel for r in records])) / pass_spp
                          for m, records in timed.items()}
        brdf_passes = timed["brdf"]
        trace = timed[TRACE_ONLY]
        trace_rays_per_s = sum(r.rays for r in trace) / sum(r.kernel for r in trace)
        for method, stage_list in stages.items():
            previous = kernel_per_spp["brdf"]
            for stage, variant, _ in stage_list:
                cost = kernel_per_spp[variant]
                before = kernel_per_spp[method] if stage in OUTSIDE_SEQUENCE else previous
                breakdown_rows.append({"scene": name, "method": method, "stage": stage, "integrator": variant,
                                       "kernel_ms_per_spp": 1e3 * cost, "ratio_to_brdf": cost / kernel_per_spp["brdf"],
                                       "increment_ms_per_spp": 1e3 * (cost - before),
                                       "increment_ratio": (cost - before) / kernel_per_spp["brdf"],
                                       "rays_per_path": _rays_per_path(timed[variant])})
                if stage not in OUTSIDE_SEQUENCE:
                    previous = cost
        for method, records in timed.items():
            if method not in stages and method not in ("path", TRACE_ONLY):
                continue      # a breakdown variant: in the breakdown table only
            counted = timed.get(f"{method}[+statistics]", records)
            counts = getattr(integrators[method], "counts_paths", False)   # Mitsuba's path counts nothing
            mrays = sum(r.rays for r in records) / sum(r.kernel for r in records) / 1e6 if counts else None
            guide = getattr(integrators[method], "guide", None)
            memory = guide.stats().get("memory_bytes", 0) if guide is not None else 0
            total = sum(r.wall + r.update for r in records)
            nothing_to_guide = method not in ("path", TRACE_ONLY, "brdf") and not integrators[method].guides_scene
            rows.append({
                "scene": name, "resolution": _resolution(scene), "method": method,
                "kernel_ms_per_spp": 1e3 * kernel_per_spp[method],
                "ratio_to_brdf": kernel_per_spp[method] / kernel_per_spp["brdf"],
                **paired_quartiles(records, brdf_passes),
                "ratio_to_path": kernel_per_spp[method] / kernel_per_spp["path"],
                "wall_ms_per_spp": 1e3 * float(np.median([r.wall for r in records])) / pass_spp,
                "trace_ms_per_pass": 1e3 * float(np.median([max(r.wall - r.kernel - r.compile, 0.0)
                                                            for r in records])),
                "compile_s": sum(r.compile for r in records),
                "update_ms": 1e3 * float(np.mean([r.update for r in records])),
                "update_share": sum(r.update for r in records) / total,
                "refine_share": sum(r.refine for r in records) / total,
                "memory_MiB": memory / 2**20,
                "hit_rate": sum(r.hits for r in records) / sum(r.paths for r in records) if counts else None,
                "Mrays_per_s": mrays,
                "share_of_trace_limit": mrays * 1e6 / trace_rays_per_s if mrays is not None else None,
                "guided_per_ray": _guided_per_ray(counted, nothing_to_guide),
                "memo_pairs": records[-1].memo_pairs,
                "nothing_to_guide": nothing_to_guide,
            })
    return pd.DataFrame(rows), pd.DataFrame(breakdown_rows)


def paired_quartiles(records: list[PassTiming], baseline: list[PassTiming]) -> dict[str, float]:
    """The quartiles of the per-pass ratios of kernel time to ``baseline``'s pass of the same index (interleaved, so
    the two ran seconds apart): the spread of the paired ratios, beside ``ratio_to_brdf`` (a ratio of medians, which
    need not lie between them)."""
    ratios = [r.kernel / b.kernel for r, b in zip(records, baseline, strict=True)]
    q25, q75 = np.quantile(ratios, [0.25, 0.75])
    return {"ratio_q25": float(q25), "ratio_q75": float(q75)}


def _guided_per_ray(records: list, nothing_to_guide: bool) -> float | None:
    """Guided vertices per ray traced, from the guide's pass counters (None where the guide has none); 0 in a scene
    with nothing to guide, whose passes run without the guide (the pass driver drops it: no counter runs)."""
    if nothing_to_guide:
        return 0.0
    if records[-1].guided is None:
        return None
    return sum(r.guided for r in records) / max(sum(r.rays for r in records), 1)


#: The pass modes ``bench --part pass-schedule`` compares: (growing passes, frozen passes). ``fixed``: passes of 8 spp,
#: each traced; ``growing``: :mod:`guiding.render.pass_schedule`'s sizes, each pass traced; ``frozen``: growing passes
#: replaying the path loop's recording (:mod:`guiding.render.frozen_pass`; the default).
PASS_MODES = {"fixed": (False, False), "growing": (True, False), "frozen": (True, True)}


def pass_schedule_table(scenes: list[tuple[str, float]], methods: list[str], spp: int = 512, rounds: int = 2,
                        max_depth: int = MAX_DEPTH) -> pd.DataFrame:
    """Per scene and method: the counted seconds (render and update, compilation excluded) of a render of ``spp``
    spp in each of the :data:`PASS_MODES`, the renders alternating, ``rounds`` times (medians); the speed-up of each
    mode over the one before, and each mode's cost per spp over ``brdf``'s in the same mode (what decides an
    equal-time comparison). The fixed and the frozen passes' costs split into the kernels' execution, the guide's
    updates and the rest of each pass (tracing the loop in Python, launching, synchronising)."""
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.render.progressive import Budget, render
    from guiding.scenes import load_scene

    rows = []
    for number, (name, scale) in enumerate(scenes, 1):
        print(f"bench: scene {number}/{len(scenes)} {name} (scale {scale:g}): {', '.join(methods)}, {rounds} "
              f"rounds of {spp} spp in each pass mode ({', '.join(PASS_MODES)})", file=sys.stderr, flush=True)
        scene = load_scene(name, scale)
        for method in methods:
            seconds = {mode: [] for mode in PASS_MODES}
            passes, parts = {}, {"fixed": [], "frozen": []}      # the modes whose cost is split into parts
            for index in range(rounds):
                for mode, (growing, freeze) in PASS_MODES.items():
                    props = mi.Properties()
                    props["max_depth"], props["freeze"] = max_depth, freeze
                    result = render(scene, GuidedPathIntegrator(props, guide=make_guide(method)),
                                    Budget(spp=spp, growing_passes=growing), seed=index, progress=False)
                    seconds[mode].append(result.counted_seconds())
                    passes[mode] = len(result.passes)
                    if mode in parts:
                        parts[mode].append(_pass_parts(result.passes))
            row = {"scene": name, "resolution": _resolution(scene), "method": method}
            row.update({f"passes_{mode}": passes[mode] for mode in PASS_MODES})
            row.update({f"ms_per_spp_{mode}": 1e3 * float(np.median(seconds[mode])) / spp for mode in PASS_MODES})
            row["speed_up_growing"] = row["ms_per_spp_fixed"] / row["ms_per_spp_growing"]
            row["speed_up_frozen"] = row["ms_per_spp_growing"] / row["ms_per_spp_frozen"]
            row.update({f"{part}_ms_per_spp_{mode}": 1e3 * float(np.median([p[part] for p in parts[mode]])) / spp
                        for mode in parts for part in ("kernel", "update", "rest")})
            rows.append(row)
    frame = pd.DataFrame(rows)
    brdf = frame[frame["method"] == "brdf"].set_index("scene")
    for mode in PASS_MODES:
        frame[f"ratio_to_brdf_{mode}"] = frame[f"ms_per_spp_{mode}"] / frame["scene"].map(brdf[f"ms_per_spp_{mode}"])
    return frame


def _pass_parts(passes) -> dict[str, float]:
    """The counted seconds of a render's passes (:meth:`PassStats.counted_seconds`) in three parts: the kernels'
    execution, the guide's updates, and the rest of the passes (compilation left out)."""
    kernel = sum(p.kernel_seconds for p in passes)
    return {"kernel": kernel, "update": sum(p.update_seconds for p in passes),
            "rest": sum(max(p.seconds - p.compile_seconds, 0.0) for p in passes) - kernel}


#: Issue targets: (what, method, column, bound, applies on the GPU only / CPU only / both).
TARGETS = [
    ("`ours` ≤ 1.2× `brdf` per spp (CPU)", "ours", "ratio_to_brdf", 1.2, "cpu"),
    ("`ours` ≤ 1.3× `brdf` per spp (GPU)", "ours", "ratio_to_brdf", 1.3, "gpu"),
    ("grid update ≤ 2 % of pass time (`ours`)", "ours", "update_share", 0.02, "both"),
    ("SD-tree refinement ≤ 10 % of training time", "sdtree", "refine_share", 0.10, "both"),
    ("`brdf` ≤ 1.0× Mitsuba `path` per spp", "brdf", "ratio_to_path", 1.0, "both"),
    ("`ours-expected` ≤ 1.2× `brdf` per spp", "ours-expected", "ratio_to_brdf", 1.2, "both"),
    ("`sarsa-sphere_inv` ≤ 1.15× `brdf` per spp", "sarsa-sphere_inv", "ratio_to_brdf", 1.15, "both"),
    ("`sarsa-hemi_inv` ≤ 1.15× `brdf` per spp", "sarsa-hemi_inv", "ratio_to_brdf", 1.15, "both"),
    ("`sdtree` ≤ 1.3× `brdf` per spp", "sdtree", "ratio_to_brdf", 1.3, "both"),
    ("`quadtree-grid` ≤ 1.3× `brdf` per spp", "quadtree-grid", "ratio_to_brdf", 1.3, "both"),
    ("`brdf` ≥ 50 % of the trace-only throughput", "brdf", "share_of_trace_limit", -0.5, "both"),
]
#: Where a guided method has nothing to guide (no BSDF of the scene is one it guides: mirror-box for every method,
#: glossy-box for those guiding purely diffuse surfaces), it should cost at most this factor of ``brdf``.
NO_GUIDABLE_BOUND = 1.05


def target_table(frame: pd.DataFrame, device_kind: str, breakdown: pd.DataFrame | None = None) -> pd.DataFrame:
    """Each target that applies to ``device_kind`` (``cpu`` or ``gpu``), per scene: the measured value, whether it
    is met, and for a missed one where its time goes in the same run (:func:`bottleneck`; ``breakdown``: the run's
    cost breakdown, if it was timed)."""
    rows = []
    for what, method, column, bound, kind in TARGETS:
        if kind not in (device_kind, "both"):
            continue
        for _, row in frame[frame["method"] == method].iterrows():
            if row["nothing_to_guide"] and column == "ratio_to_brdf":
                continue      # judged by the no-guidable bound below
            met = row[column] >= -bound if bound < 0 else row[column] <= bound   # a negative bound is a minimum
            rows.append({"target": what, "scene": row["scene"], "measured": row[column],
                         **_spread(row, column), "met": bool(met),
                         "bottleneck": "" if met else bottleneck(row, column, breakdown)})
    for _, row in frame[frame["nothing_to_guide"]].iterrows():
        met = bool(row["ratio_to_brdf"] <= NO_GUIDABLE_BOUND)
        rows.append({"target": f"nothing to guide: `{row['method']}` ≤ {NO_GUIDABLE_BOUND}× `brdf`",
                     "scene": row["scene"], "measured": row["ratio_to_brdf"], **_spread(row, "ratio_to_brdf"),
                     "met": met, "bottleneck": "" if met else "the passes run brdf's kernel: machine noise"})
    return pd.DataFrame(rows)


def _spread(row: pd.Series, column: str) -> dict[str, float | None]:
    """The paired per-pass quartiles of a ratio to ``brdf`` (:func:`paired_quartiles`); None for other columns."""
    known = column == "ratio_to_brdf"
    return {"pass_q25": row["ratio_q25"] if known else None, "pass_q75": row["ratio_q75"] if known else None}


def bottleneck(row: pd.Series, column: str, breakdown: pd.DataFrame | None) -> str:
    """Where the time of a missed target goes, from the same run: for a cost ratio, the parts of the method's bounce
    over ``brdf`` (its cost breakdown's stages up to the method itself, the largest named) and, where it was timed,
    what the ``hot rows`` stage saves (its increment, and per ray: its paths' lengths differ a little); for the
    update share the update's (or the trees' rebuild's) time per pass against the pass's kernel time."""
    if column == "ratio_to_brdf" and breakdown is not None and not breakdown.empty:
        rows = breakdown[(breakdown["scene"] == row["scene"]) & (breakdown["method"] == row["method"])]
        rows = rows.reset_index(drop=True)
        position = rows.index[rows["integrator"] == row["method"]]
        stages = rows.iloc[: position[0] + 1] if len(position) else rows.iloc[:0]
        if not stages.empty:
            largest = stages.loc[stages["increment_ratio"].idxmax(), "stage"]
            parts = ", ".join(f"{stage} {increment:+.2f}" for stage, increment
                              in zip(stages["stage"], stages["increment_ratio"]))
            hot, own = rows[rows["stage"] == "hot rows"], stages.iloc[-1]
            misses = ""
            if len(hot):
                cached = hot.iloc[0]
                per_ray = ((cached["ratio_to_brdf"] / cached["rays_per_path"])
                           / (own["ratio_to_brdf"] / own["rays_per_path"]))
                misses = (f"; with one alias row for all ({cached['integrator']}): {cached['increment_ratio']:+.2f}, "
                          f"{per_ray - 1:+.0%} per ray")
            return f"the bounce's parts, × brdf's time: {parts}; largest: {largest}{misses}"
    if column == "update_share":
        return (f"the update: {row['update_ms']:.1f} ms per pass ({int(row['memo_pairs'])} visited pairs), the "
                f"pass's kernels {row['kernel_ms_per_spp']:.1f} ms per spp")
    if column == "refine_share":
        return (f"the trees' rebuild in an update of {row['update_ms']:.1f} ms per pass, the pass's kernels "
                f"{row['kernel_ms_per_spp']:.1f} ms per spp")
    if column == "ratio_to_brdf":
        return "no cost breakdown in this run (--no-breakdown)"
    return "where the kernels' time goes: python -m guiding bench --part profile"


def _rays_per_path(records: list[PassTiming]) -> float:
    return sum(r.rays for r in records) / max(sum(r.paths for r in records), 1)


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

