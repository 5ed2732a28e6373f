"""Command line: ``python -m guiding {render, reference, evaluate, bench, demo, validate, sdtree-baseline,
show-guide, scenes, methods}``.

Bad input ends with one line on stderr and a non-zero exit, before any output is written; an interrupted run
(Ctrl-C: exit code 130) leaves no output files behind (they are written atomically, together, last of all).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from dataclasses import asdict
from pathlib import Path

from .bench_command import command_bench
from .errors import GuidingError
from .output_dirs import output_dir, prepare_output_dir
from .provenance import device_name, render_provenance
from .sdtree_baseline import SCENE_STUDIES

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130

#: The paper's hemi_inv without the BSDF share, shown beside ours in the single-bounce weight table.
PURE_HEMI_INV = ("mc-hemi_inv-pure", "sarsa-hemi_inv-pure", "expected_sarsa-hemi_inv-pure")

class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (not the usage text) and exit code 2."""

    def error(self, message):
        raise GuidingError(f"{self.prog}: {message}")


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {value}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not (value > 0 and math.isfinite(value)):   # inf would make an endless budget or an infinite resolution
        raise argparse.ArgumentTypeError(f"must be > 0 and finite, got {text}")
    return value


def _memory_size(text: str) -> int:
    from .methods import parse_size

    try:
        size = parse_size(text)
    except GuidingError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    if size <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return size


def _add_backend_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--variant", default="auto", help="auto | llvm_ad_rgb | cuda_ad_rgb (default: auto)")
    parser.add_argument("--threads", type=_positive_int, default=None, help="CPU worker threads (LLVM backend)")


def _add_scene_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", required=True, help="scene name (see `scenes`) or path to a scene XML file")
    parser.add_argument("--scale", type=_positive_float, default=1.0, help="resolution scale (default 1)")
    parser.add_argument("--scene-dir", action="append", default=[], help="extra scene folder (repeatable)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--pass-spp", type=_positive_int, default=8,
                        help="samples per pixel of the first passes; later ones grow to pass_spp*2^k up to the "
                        "guide's next update (default 8)")
    parser.add_argument("--max-depth", type=_positive_int, default=16)
    parser.add_argument("--out", required=True, help="output folder (image.exr, preview.png, stats.json)")
    parser.add_argument("--quiet", action="store_true", help="no progress display")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="guiding", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    render = commands.add_parser("render", help="render a scene with a method")
    _add_scene_options(render)
    render.add_argument("--method", required=True, help="method name (see `methods`)")
    budget = render.add_mutually_exclusive_group(required=True)
    budget.add_argument("--spp", type=_positive_int, help="samples per pixel budget")
    budget.add_argument("--seconds", type=_positive_float, help="time budget in seconds")
    render.add_argument("--exclude-passes", type=int, default=0,
                        help="leading passes not counted against a seconds budget (default 0)")
    render.add_argument("--fixed-passes", action="store_true",
                        help="every pass has --pass-spp spp (by default later passes grow where the guide allows)")
    render.add_argument("--combine", choices=["last", "automatic", "inverse-variance"], default=None,
                        help="final image of a guide with iterations (sdtree): the last iteration, the last one "
                        "with training stopped by the variance, or the last four weighted by their spp "
                        "(default: the method's own, inverse-variance for sdtree)")
    render.add_argument("--snapshots", action="store_true",
                        help="also write the image after every pass_spp*2^k spp as image_snapNNNNN.exr")
    render.add_argument("--memory-limit", type=_memory_size, default=None,
                        help="largest guide tables allowed, e.g. 512M or 16G (default $GUIDING_MEMORY_LIMIT or 8G)")
    render.add_argument("--save-guide", action="store_true",
                        help="also write what the guide learned as guide.npz (for `show-guide`)")
    _add_backend_options(render)

    reference = commands.add_parser("reference", help="render a reference with Mitsuba's `path` integrator")
    _add_scene_options(reference)
    reference.add_argument("--spp", type=_positive_int, required=True)
    _add_backend_options(reference)
    reference.set_defaults(pass_spp=64)

    evaluate = commands.add_parser("evaluate", help="print the metrics of IMAGE against REF as JSON")
    evaluate.add_argument("image")
    evaluate.add_argument("ref")
    evaluate.add_argument("--error-map", metavar="PNG", help="also write the HDR-FLIP error map (false colour)")

    show = commands.add_parser("show-guide", help="draw the directional distribution a render's guide learned "
                               "(render --save-guide) in one cell, or at the first vertex seen through a pixel")
    show.add_argument("render_dir", help="the render's output folder (with guide.npz and stats.json)")
    where = show.add_mutually_exclusive_group()
    where.add_argument("--cell", type=int, help="cell (grid) or D-tree (sdtree) index (default: the best trained)")
    where.add_argument("--pixel", type=int, nargs=2, metavar=("X", "Y"),
                       help="the cell of the first surface seen through pixel (X, Y) of the render")
    show.add_argument("--out", help="PNG file (default RENDER_DIR/guide_cellN.png)")
    show.add_argument("--variant", default="llvm_ad_rgb", help="variant used to find bins and cast the ray")

    bench = commands.add_parser("bench", help="cost per spp of every method vs `brdf` and Mitsuba's `path` "
                                "(same process, interleaved passes)")
    bench.add_argument("--part", choices=["cost", "pass-schedule", "kernel-size", "profile", "gathers"],
                       default="cost",
                       help="cost: cost per spp and its breakdown (default); pass-schedule: renders with fixed, "
                       "growing and frozen passes (results/pass_schedule); kernel-size: each method's render kernel in "
                       "machine instructions (CPU; results/bench/kernel_instructions); profile: each method's CPU time by "
                       "code, JIT kernels against Embree and the rest (Linux perf; results/bench/profile_cpu); gathers: "
                       "each method with table reads compiled into gather instructions and into scalar loads (CPU with "
                       "AVX2; results/bench/hardware_gathers)")
    bench.add_argument("--scenes", help="comma-separated NAME:SCALE list (default: cost: the four shared scenes at 1/4 "
                       "resolution, glossy-box and mirror-box, the scenes with nothing to guide; pass-schedule: those "
                       "of config/paper.yaml's equal-time experiment; kernel-size: the four at 1/16; profile and "
                       "gathers: the four at 1/4)")
    bench.add_argument("--passes", type=_positive_int, default=8, help="timed passes per integrator (default 8)")
    bench.add_argument("--methods", help="methods timed against brdf (comma-separated; default: cost: every kind, "
                       "pass-schedule: brdf, ours, ours-plus, sdtree; gathers: ours, sdtree)")
    bench.add_argument("--out", help="output folder (default results/bench, results/pass_schedule)")
    bench.add_argument("--no-breakdown", action="store_true",
                       help="skip the cost breakdown (the guided methods' stages, results/bench/cost_breakdown.md)")
    _add_backend_options(bench)

    demo = commands.add_parser("demo", help="the main job: reference, then each method at equal spp, then MAE")
    demo.add_argument("--scene", default="door-ajar")
    demo.add_argument("--scale", type=_positive_float, default=0.5)
    demo.add_argument("--methods", default="brdf,ours", help="comma-separated method names (default brdf,ours)")
    demo.add_argument("--spp", type=_positive_int, default=256, help="spp of each method (default 256)")
    demo.add_argument("--reference-spp", type=_positive_int, default=4096)
    demo.add_argument("--out", default="results/demo")
    _add_backend_options(demo)

    validate = commands.add_parser("validate", help="grid guide checks written to results/: unbiasedness of every "
                                   "rule x sampler, and learning (MAE, hit rate) at equal spp")
    validate.add_argument("--out", default="results")
    validate.add_argument("--quick", action="store_true", help="smaller budgets (a smoke run)")
    validate.add_argument("--part", choices=("all", "refinement", "learning"), default="all",
                          help="all checks (default), or only ours-plus's refined bins at equal spp, or only the "
                          "equal-spp MAE of every method (results/learning.md)")
    _add_backend_options(validate)

    baseline = commands.add_parser("sdtree-baseline", help="SD-tree baseline figures written to results/: equal-spp "
                                   "MAE of its previous and present setups beside brdf, quadtree-grid and ours, and "
                                   "the S-tree threshold at several image sizes")
    baseline.add_argument("--out", default="results", help="output folder (default results; references are cached "
                          "under OUT/sdtree_baseline/references)")
    baseline.add_argument("--part", choices=["all", "equal-spp", "threshold", *SCENE_STUDIES, "combination"],
                          default="all",
                          help="which table to make (default all; improved-preset: sdtree with the learned BSDF share "
                          "and the stochastic spatial filter of Müller 2019, each and together, on the four shared "
                          "scenes, results/sdtree_improved_preset.md; bsdf-share: sdtree at fixed BSDF shares there, "
                          "results/sdtree_bsdf_share.md; combination: the final image of sdtree and sdtree-learned "
                          "from their last iterations, weighted by spp, by their own variance or by the other half's, "
                          "against the last alone, on glass-lamp and the shared scenes, "
                          "results/sdtree_combination/equal_spp.md)")
    baseline.add_argument("--scene", default="veach-ajar")
    baseline.add_argument("--scale", type=_positive_float, default=0.0625,
                          help="resolution scale of the equal-spp table (default 0.0625: 80x45)")
    baseline.add_argument("--spp", type=_positive_int, default=1024, help="spp of every render (default 1024)")
    baseline.add_argument("--seconds", type=_positive_float, default=None,
                          help="combination only: a seconds budget of every render instead of --spp, its first "
                          "passes not counted as in config/paper.yaml's equal time; timed: run it alone on the machine")
    baseline.add_argument("--seeds", default="0,1,2", help="comma-separated render seeds (default 0,1,2)")
    baseline.add_argument("--reference-spp", type=_positive_int, default=131072,
                          help="spp of the `path` reference of the equal-spp table and of the threshold study's first "
                          "scale (default 131072)")
    baseline.add_argument("--preset-scenes", default=None,
                          help="comma-separated NAME:SCALE list of the scenes of the improved-preset, bsdf-share and "
                          "combination tables (default: the four shared scenes at the paper experiments' scales, and "
                          "glass-lamp at 0.0625 first for combination)")
    baseline.add_argument("--threshold-scales", default="0.0625,0.125,0.25",
                          help="comma-separated scales of the threshold study (default 0.0625,0.125,0.25); their "
                          "references have the same samples per image as the first's")
    _add_backend_options(baseline)

    commands.add_parser("scenes", help="list the scenes on the search path")
    commands.add_parser("methods", help="list the method names")
    return parser


def _image_metadata(scene_name: str, args, method: str, integrator, budget, provenance: dict, combine: str) -> dict:
    """What every EXR file of a render carries in its header (imageio.write_exr; the spp are added per file): the
    method and its guide's parameters, the render's parameters (``combine``: its final-image mode), seed, scene,
    variant, device and versions."""
    from .provenance import software_versions

    guide = getattr(integrator, "guide", None)
    parameters = {"budget": asdict(budget), "max_depth": args.max_depth, "scale": args.scale, "combine": combine}
    return {"method": method, "scene": scene_name, "seed": args.seed, "parameters": parameters,
            "guide": {k: v for k, v in (guide.stats() if guide is not None else {}).items()
                      if not isinstance(v, (dict, list))},
            **{k: provenance[k] for k in ("variant", "device", "threads", "host", "date")},
            "versions": software_versions()}


def _render_to(out: Path, scene_name: str, args, integrator, method: str, budget, variant: str) -> dict:
    from . import guide_state, imageio, strict_json
    from .render import SnapshotWriter, render, resolve_combine
    from .scenes import find_scene, load_scene

    scene = load_scene(scene_name, args.scale, args.scene_dir)
    provenance = render_provenance(variant)
    combine = resolve_combine(getattr(args, "combine", None), integrator)
    metadata = _image_metadata(scene_name, args, method, integrator, budget, provenance, combine)
    snapshots = SnapshotWriter(out, metadata) if getattr(args, "snapshots", False) else None
    try:
        result = render(scene, integrator, budget, seed=args.seed, progress=False if args.quiet else None,
                        combine=combine, snapshot=snapshots)
    except BaseException:   # interrupted or failed: snapshots written so far are partial outputs
        for entry in snapshots.entries if snapshots is not None else []:
            (out / entry["file"]).unlink(missing_ok=True)
        raise
    film_size = [int(v) for v in scene.sensors()[0].film().size()]
    stats = {"scene": scene_name, "scene_file": str(find_scene(scene_name, args.scene_dir)), "scale": args.scale,
             "resolution": film_size, "method": method, "seed": args.seed, "max_depth": args.max_depth,
             **result.summary(), "guide": getattr(getattr(integrator, "guide", None), "stats", dict)(),
             "provenance": provenance, "per_pass": [asdict(p) for p in result.passes]}
    if snapshots is not None:
        stats["snapshots"] = snapshots.entries  # stats.json is written last: only the files it lists are complete
    state = guide_state.capture(integrator.guide) if getattr(args, "save_guide", False) else None
    names = ["image.exr", "preview.png", "stats.json", *([guide_state.STATE_FILE] if state is not None else [])]
    with imageio.atomic_outputs(*(out / name for name in names)) as (exr, png, js, *npz):
        imageio.write_exr(exr, result.image, {**metadata, "spp": result.spp, "spp_in_image": result.spp_in_image})
        imageio.write_png(png, result.image)
        Path(js).write_text(strict_json.dumps(stats))
        if state is not None:
            guide_state.save(npz[0], state)
    return stats


def _command_render(args) -> None:
    from .backend import set_variant
    from .methods import check_method, make_guide
    from .render import Budget
    from .scenes import find_scene

    budget = Budget(spp=args.spp, seconds=args.seconds, pass_spp=args.pass_spp, exclude_passes=args.exclude_passes,
                    growing_passes=not args.fixed_passes)
    find_scene(args.scene, args.scene_dir)
    check_method(args.method, args.memory_limit)
    variant = set_variant(args.variant, args.threads)
    guide = make_guide(args.method, args.memory_limit)
    if args.save_guide and not guide.records():
        raise GuidingError(f"--save-guide: method '{args.method}' learns nothing to save")
    from .integrator import GuidedPathIntegrator
    import mitsuba as mi

    props = mi.Properties()
    props["max_depth"] = args.max_depth
    integrator = GuidedPathIntegrator(props, guide=guide)
    with output_dir(args.out) as out:
        stats = _render_to(out, args.scene, args, integrator, args.method, budget, variant)
    print(f"{args.method} on {args.scene}: {stats['spp']} spp in {stats['seconds']:.2f} s "
          f"(compile {stats['compile_seconds']:.2f} s), hit rate {stats['hit_rate']:.4f} -> {out}")


def _command_reference(args) -> None:
    from .backend import set_variant
    from .render import Budget
    from .scenes import find_scene

    budget = Budget(spp=args.spp, pass_spp=min(args.pass_spp, args.spp))
    find_scene(args.scene, args.scene_dir)
    variant = set_variant(args.variant, args.threads)
    import mitsuba as mi

    integrator = mi.load_dict({"type": "path", "max_depth": args.max_depth})
    with output_dir(args.out) as out:
        stats = _render_to(out, args.scene, args, integrator, "reference-path", budget, variant)
    print(f"reference of {args.scene}: {stats['spp']} spp in {stats['seconds']:.1f} s -> {out}")


def _command_evaluate(args) -> None:
    from . import strict_json
    from .imageio import read_exr
    from .metrics import evaluate

    image, ref = read_exr(args.image), read_exr(args.ref)
    metrics = evaluate(image, ref)
    if args.error_map:
        from .figures import error_map

        error_map(image, ref, args.error_map)
    print(strict_json.dumps(metrics))


def _command_show_guide(args) -> None:
    """Draw a saved guide's distribution in one cell: ``--cell``, the cell of the first vertex seen through
    ``--pixel``, or the best trained cell."""
    from . import guide_state
    from .backend import set_variant

    folder = Path(args.render_dir)
    state = guide_state.load(folder / guide_state.STATE_FILE)
    stats = json.loads((folder / "stats.json").read_text())
    set_variant(args.variant)
    marks, where = {}, ""
    if args.pixel is not None:
        point, marks = guide_state.first_vertex(stats, *args.pixel)
        cell = guide_state.cell_of_point(state, point)
        where = f"pixel ({args.pixel[0]}, {args.pixel[1]}) sees p = ({', '.join(f'{c:.3g}' for c in point)}); "
    else:
        cell = guide_state.best_cell(state) if args.cell is None else guide_state.check_cell(state, args.cell)
    out = Path(args.out) if args.out else folder / f"guide_cell{cell}.png"
    title = (f"{stats.get('method')} on {stats.get('scene')}, {stats.get('spp')} spp: {where}cell {cell} "
             f"of {guide_state.cell_count(state)}")
    guide_state.draw(state, cell, out, title, marks)
    print(f"{title} -> {out}")


def _command_demo(args) -> None:
    """Reference (cached) + each method at equal spp on one scene, and a Markdown table of the errors."""
    from .backend import set_variant
    from .methods import check_method
    from .scenes import find_scene

    methods = [m for m in args.methods.split(",") if m]
    for method in methods:
        check_method(method)
    find_scene(args.scene)
    variant = set_variant(args.variant, args.threads)
    out = prepare_output_dir(args.out)
    import pandas as pd

    from .imageio import read_exr
    from .metrics import evaluate

    common = ["--scene", args.scene, "--scale", str(args.scale), "--variant", variant]
    reference = out / f"reference-{args.reference_spp}spp"
    if not (reference / "stats.json").exists():
        _command_reference(build_parser().parse_args(["reference", *common, "--spp", str(args.reference_spp),
                                                      "--out", str(reference)]))
    rows = []
    for method in methods:
        target = out / method
        _command_render(build_parser().parse_args(["render", *common, "--method", method, "--spp", str(args.spp),
                                                   "--out", str(target)]))
        stats = json.loads((target / "stats.json").read_text())
        errors = evaluate(read_exr(target / "image.exr"), read_exr(reference / "image.exr"))
        rows.append({"method": method, "spp": stats["spp"], "seconds": stats["seconds"],
                     "hit_rate": stats["hit_rate"], "mae": errors["mae"], "relmse": errors["relmse"]})
    table = pd.DataFrame(rows).to_markdown(index=False, floatfmt=".4g")
    (out / "summary.md").write_text(f"# {args.scene} at scale {args.scale}, {args.spp} spp\n\n{table}\n")
    print(table)


def _command_validate(args) -> None:
    from .backend import set_variant

    variant = set_variant(args.variant, args.threads)
    out = prepare_output_dir(args.out)
    from .bench import write_table
    import pandas as pd

    from .validation import (UNBIASEDNESS_METHODS, UNBIASEDNESS_SCENES, bounce_weight_table,
                             refinement_table, smooth_share_table, unbiasedness_table)

    device = device_name(variant)
    if args.part == "learning":
        _validate_learning(args, out, device)
        return
    spp, reference_spp = (32, 256) if args.quick else (512, 8192)
    refinement = refinement_table(spp=spp, reference_spp=reference_spp)
    write_table(refinement, out / "ours_plus_refinement", f"ours-plus with and without (sub_resolution 1) its "
                f"refined bins at equal spp ({spp} spp, seeds 0 and 1, the scales of config/paper.yaml): MAE vs a "
                f"`path` reference of {reference_spp} spp", device, "python -m guiding validate --part refinement")
    print(refinement.to_string(index=False))
    if args.part == "refinement":
        return
    budgets = {name: (scale, 6, 8) if args.quick else (scale, passes, spp)
               for name, (scale, passes, spp) in UNBIASEDNESS_SCENES.items()}
    unbiased = pd.concat([unbiasedness_table(name, budget=budget) for name, budget in budgets.items()])
    described = "; ".join(f"{name} at scale {scale}, {passes} passes x {spp} spp"
                          for name, (scale, passes, spp) in budgets.items())
    write_table(unbiased, out / "grid_unbiasedness", f"Image mean of every rule x sampler vs Mitsuba `path` "
                f"({described}; `path` has twice the passes; agrees = all channels within 4 standard errors)",
                device, "python -m guiding validate")
    print(unbiased.to_string(index=False))
    methods = ["brdf", "sdtree", "quadtree-grid", *UNBIASEDNESS_METHODS, *PURE_HEMI_INV]
    weights = pd.concat([bounce_weight_table(name, methods, vertices=200 if args.quick else 1000,
                                             samples=512 if args.quick else 4096) for name in budgets])
    write_table(weights, out / "bounce_weights", "Single-bounce weights f·cos/p at real diffuse vertices after 64 spp "
                "of training (scale 0.1; 1000 vertices x 4096 directions; ratios to the vertex albedo)",
                device, "python -m guiding validate")
    print(weights.to_string(index=False))
    _validate_learning(args, out, device)
    share = smooth_share_table(spp=32 if args.quick else 256, reference_spp=256 if args.quick else 8192)
    write_table(share, out / "ours_plus_share", "ours-plus's least BSDF share at glossy vertices "
                "(`smooth_bsdf_share`) at equal spp (scale 1/16, seeds 0 and 1): MAE vs a `path` reference",
                device, "python -m guiding validate")
    print(share.to_string(index=False))


def _validate_learning(args, out, device: str) -> None:
    """results/learning.md: every method's MAE and hit rate at equal spp on door-ajar."""
    from .bench import write_table
    from .validation import LEARNING_SEEDS, learning_table

    seeds = LEARNING_SEEDS[:1] if args.quick else LEARNING_SEEDS
    learning = learning_table(spp=64 if args.quick else 256, reference_spp=256 if args.quick else 4096, seeds=seeds)
    command = "python -m guiding validate" + (" --part learning" if args.part == "learning" else "")
    write_table(learning, out / "learning", "Equal spp on door-ajar (scale 0.25): MAE vs a `path` reference (means "
                f"over seeds {', '.join(map(str, seeds))}; `mae_se`: the MAE's standard error)", device, command)
    print(learning.to_string(index=False))


def _command_sdtree_baseline(args) -> None:
    from .backend import set_variant
    from .scenes import find_scene

    find_scene(args.scene)
    try:
        seeds = tuple(int(v) for v in args.seeds.split(",") if v)
        scales = tuple(float(v) for v in args.threshold_scales.split(",") if v)
    except ValueError:
        raise GuidingError(f"bad --seeds '{args.seeds}' or --threshold-scales '{args.threshold_scales}': "
                           "comma-separated numbers expected") from None
    if not seeds or not all(scale > 0 for scale in scales):
        raise GuidingError("sdtree-baseline: give at least one seed, and scales > 0")
    from .bench_command import parse_scene_list
    from .sdtree_baseline import PRESET_SCENES, equal_spp_table, scenes_table, threshold_table
    from .sdtree_combination import COMBINATION_SCENES, EXCLUDED_PASSES, combination_table

    studies = {part: study for part, study in SCENE_STUDIES.items() if args.part in ("all", part)}
    study_scenes = parse_scene_list(args.preset_scenes) if args.preset_scenes else list(PRESET_SCENES)
    combination_scenes = parse_scene_list(args.preset_scenes) if args.preset_scenes else list(COMBINATION_SCENES)
    combination = args.part in ("all", "combination")
    for name, _ in (study_scenes if studies else []) + (combination_scenes if combination else []):
        find_scene(name)
    variant = set_variant(args.variant, args.threads)
    out = prepare_output_dir(args.out)
    from .bench import write_table

    device = device_name(variant)
    cache = out / "sdtree_baseline"
    common = (f"--scene {args.scene} --spp {args.spp} --seeds {args.seeds}"
              + (f" --variant {args.variant}" if args.variant != "auto" else "")
              + (f" --threads {args.threads}" if args.threads else ""))
    if args.part in ("all", "equal-spp"):
        summary, runs = equal_spp_table(args.scene, args.scale, args.spp, seeds, args.reference_spp, cache)
        command = (f"python -m guiding sdtree-baseline --part equal-spp {common} --scale {args.scale:g} "
                   f"--reference-spp {args.reference_spp}")
        write_table(summary, out / "sdtree_baseline", f"The SD-tree baseline at equal spp: {args.scene} at scale "
                    f"{args.scale:g}, {args.spp} spp, seeds {args.seeds}, MAE against a {args.reference_spp}-spp "
                    "`path` reference (`mae_vs_first`: relative to the first row)", device, command,
                    sections={"Runs": runs})
        print(summary.to_string(index=False))
    if args.part in ("all", "threshold") and scales:
        summary, runs = threshold_table(scales, args.scene, args.spp, seeds, args.reference_spp, cache)
        command = (f"python -m guiding sdtree-baseline --part threshold {common} --reference-spp "
                   f"{args.reference_spp} --threshold-scales " + ",".join(f"{scale:g}" for scale in scales))
        write_table(summary, out / "sdtree_threshold", f"The S-tree threshold c·sqrt(paths / (4·1280·720)) at "
                    f"several image sizes: `sdtree` on {args.scene}, {args.spp} spp, seeds {args.seeds}; "
                    "`stree_leaves`: leaves of the final S-tree, `last_threshold`: the vertices a leaf needed to "
                    "split at the last refinement", device, command, sections={"Runs": runs})
        print(summary.to_string(index=False))
    scenes = ", ".join(f"{name} at scale {scale:g}" for name, scale in study_scenes)
    for part, study in studies.items():
        summary, runs = scenes_table(study_scenes, args.spp, seeds, args.reference_spp, cache, study.variants)
        command = (f"python -m guiding sdtree-baseline --part {part} --spp {args.spp} --seeds {args.seeds} "
                   f"--reference-spp {args.reference_spp}"
                   + (f" --preset-scenes {args.preset_scenes}" if args.preset_scenes else "")
                   + (f" --threads {args.threads}" if args.threads else ""))
        write_table(summary, out / study.output, f"{study.title} at equal spp: {scenes}, {args.spp} spp, seeds "
                    f"{args.seeds}, MAE against a {args.reference_spp}-spp `path` reference (`mae_vs_first`: "
                    "relative to `brdf`; `break_even_cost`: the cost per spp relative to `brdf`'s below which a row "
                    "would have the lower MAE at equal time, with MAE ∝ 1/sqrt(spp))", device, command,
                    sections={"Runs": runs})
        print(summary.to_string(index=False))
    if combination:
        summary, runs = combination_table(combination_scenes, spp=args.spp, seeds=seeds,
                                          reference_spp=args.reference_spp, cache=cache, seconds=args.seconds)
        timed = args.seconds is not None
        budget = f"--seconds {args.seconds:g}" if timed else f"--spp {args.spp}"
        command = (f"python -m guiding sdtree-baseline --part combination {budget} --seeds {args.seeds} "
                   f"--reference-spp {args.reference_spp}"
                   + (f" --preset-scenes {args.preset_scenes}" if args.preset_scenes else "")
                   + (f" --threads {args.threads}" if args.threads else ""))
        scenes = ", ".join(f"{name} at scale {scale:g}" for name, scale in combination_scenes)
        spent = f"{args.seconds:g} s (first {EXCLUDED_PASSES} passes not counted)" if timed else f"{args.spp} spp"
        write_table(summary, out / "sdtree_combination" / ("equal_time" if timed else "equal_spp"), "The SD-tree's "
                    f"final image from its last iterations at equal {'time' if timed else 'spp'}: {scenes}, {spent}, "
                    f"seeds {args.seeds}; every combination made from the same "
                    f"renders' passes; image means and MAE against a {args.reference_spp}-spp `path` reference "
                    "(`mean_vs_reference`: relative difference of the image means, `mean_se` its standard error "
                    "over seeds, `reference_se` the reference's, `z` the difference over both; `mean_minus_last`: "
                    "the difference to the last iteration's image mean in the same render; `mae_vs_last`: "
                    "relative to the last iteration's; `variance_per_sample_last_four`: of the last four "
                    "iterations, relative to the last's)", device, command, sections={"Runs": runs})
        print(summary.to_string(index=False))


def _command_scenes(args) -> None:
    from .scenes import available_scenes, search_path

    for name in available_scenes():
        print(name)
    print("search path: " + os.pathsep.join(str(p) for p in search_path()), file=sys.stderr)


def _command_methods(args) -> None:
    from .methods import method_names

    print("\n".join(method_names()))


COMMANDS = {"render": _command_render, "reference": _command_reference, "evaluate": _command_evaluate,
            "bench": command_bench, "validate": _command_validate, "demo": _command_demo,
            "sdtree-baseline": _command_sdtree_baseline,
            "show-guide": _command_show_guide, "scenes": _command_scenes, "methods": _command_methods}


def _interrupted(error: BaseException) -> bool:
    """Whether ``error`` is, or was caused by, Ctrl-C: a KeyboardInterrupt raised inside Python code that Dr.Jit
    calls back (while tracing a loop) can reach us wrapped in another exception."""
    while error is not None:
        if isinstance(error, KeyboardInterrupt):
            return True
        error = error.__cause__ or error.__context__
    return False


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        COMMANDS[args.command](args)
    except GuidingError as error:
        print(f"error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BaseException as error:
        if not _interrupted(error):
            raise
        print("interrupted: no output was written", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0
