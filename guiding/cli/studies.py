"""The command line's study commands: ``validate`` (the grid guide's checks) and ``sdtree-baseline`` (the SD-tree
baseline's tables), each writing its tables under results/."""

from __future__ import annotations

from guiding.errors import GuidingError
from guiding.experiments.sdtree_baseline import SCENE_STUDIES
from guiding.output_dirs import prepare_output_dir
from guiding.provenance import device_name

#: The paper's hemi_inv without the BSDF share, shown beside ours in the single-bounce weight table.
PURE_HEMI_INV = ("mc-hemi_inv-pure", "sarsa-hemi_inv-pure", "expected_sarsa-hemi_inv-pure")


def command_validate(args) -> None:
    from guiding.backend import set_variant

    variant = set_variant(args.variant, args.threads)
    out = prepare_output_dir(args.out)
    from guiding.bench.benchmark import write_table
    import pandas as pd

    from guiding.experiments.validation import (UNBIASEDNESS_METHODS, UNBIASEDNESS_SCENES, bounce_weight_table,
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
    from guiding.bench.benchmark import write_table
    from guiding.experiments.validation import LEARNING_SEEDS, learning_table

    seeds = LEARNING_SEEDS[:1] if args.quick else LEARNING_SEEDS
    learning = learning_table(spp=64 if args.quick else 256, reference_spp=256 if args.quick else 4096, seeds=seeds)
    command = "python -m guiding validate" + (" --part learning" if args.part == "learning" else "")
    write_table(learning, out / "learning", "Equal spp on door-ajar (scale 0.25): MAE vs a `path` reference (means "
                f"over seeds {', '.join(map(str, seeds))}; `mae_se`: the MAE's standard error)", device, command)
    print(learning.to_string(index=False))


def command_sdtree_baseline(args) -> None:
    from guiding.backend import set_variant
    from guiding.scenes import find_scene

    find_scene(args.scene)
    try:
        seeds = tuple(int(v) for v in args.seeds.split(",") if v)
        scales = tuple(float(v) for v in args.threshold_scales.split(",") if v)
    except ValueError:
        raise GuidingError(f"bad --seeds '{args.seeds}' or --threshold-scales '{args.threshold_scales}': "
                           "comma-separated numbers expected") from None
    if not seeds or not all(scale > 0 for scale in scales):
        raise GuidingError("sdtree-baseline: give at least one seed, and scales > 0")
    if args.seconds is not None and args.part != "combination":
        raise GuidingError("sdtree-baseline: --seconds is for --part combination only")
    from guiding.bench.command import parse_scene_list
    from guiding.experiments.sdtree_baseline import PRESET_SCENES, equal_spp_table, scenes_table, threshold_table

    from guiding.experiments.sdtree_combination import COMBINATION_SCENES

    studies = {part: study for part, study in SCENE_STUDIES.items() if args.part in ("all", part)}
    study_scenes = parse_scene_list(args.preset_scenes) if args.preset_scenes else list(PRESET_SCENES)
    combination_scenes = parse_scene_list(args.preset_scenes) if args.preset_scenes else list(COMBINATION_SCENES)
    combination = args.part in ("all", "combination")
    for name, _ in (study_scenes if studies else []) + (combination_scenes if combination else []):
        find_scene(name)
    variant = set_variant(args.variant, args.threads)
    out = prepare_output_dir(args.out)
    from guiding.bench.benchmark import write_table

    device = device_name(variant)
    cache = out / "sdtree_baseline"
    common = f"--scene {args.scene} --spp {args.spp} --seeds {args.seeds}" + _backend_options(args)
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
                   + _backend_options(args))
        write_table(summary, out / study.output, f"{study.title} at equal spp: {scenes}, {args.spp} spp, seeds "
                    f"{args.seeds}, MAE against a {args.reference_spp}-spp `path` reference (`mae_vs_first`: "
                    "relative to `brdf`; `break_even_cost`: the cost per spp relative to `brdf`'s below which a row "
                    "would have the lower MAE at equal time, with MAE ∝ 1/sqrt(spp))", device, command,
                    sections={"Runs": runs})
        print(summary.to_string(index=False))
    if combination:
        _combination_study(args, combination_scenes, seeds, out, cache, device)


def _backend_options(args) -> str:
    """The ``--variant`` and ``--threads`` of a recorded command, where they differ from the defaults."""
    return ((f" --variant {args.variant}" if args.variant != "auto" else "")
            + (f" --threads {args.threads}" if args.threads else ""))


def _combination_study(args, scenes: list[tuple[str, float]], seeds: tuple[int, ...], out, cache, device: str) -> None:
    """``sdtree-baseline --part combination``: results/sdtree_combination/equal_spp.md, or equal_time.md under
    ``--seconds`` (:mod:`guiding.experiments.sdtree_combination`)."""
    from guiding.bench.benchmark import write_table
    from guiding.experiments.sdtree_combination import EXCLUDED_PASSES, combination_table

    summary, runs = combination_table(scenes, spp=args.spp, seeds=seeds, reference_spp=args.reference_spp,
                                      cache=cache, seconds=args.seconds)
    timed = args.seconds is not None
    budget = f"--seconds {args.seconds:g}" if timed else f"--spp {args.spp}"
    command = (f"python -m guiding sdtree-baseline --part combination {budget} --seeds {args.seeds} "
               f"--reference-spp {args.reference_spp}"
               + (f" --preset-scenes {args.preset_scenes}" if args.preset_scenes else "")
               + _backend_options(args))
    listed = ", ".join(f"{name} at scale {scale:g}" for name, scale in scenes)
    spent = f"{args.seconds:g} s (first {EXCLUDED_PASSES} passes not counted)" if timed else f"{args.spp} spp"
    write_table(summary, out / "sdtree_combination" / ("equal_time" if timed else "equal_spp"), "The SD-tree's "
                f"final image from its last iterations at equal {'time' if timed else 'spp'}: {listed}, {spent}, "
                f"seeds {args.seeds}; every combination made from the same "
                f"renders' passes; image means and MAE against a {args.reference_spp}-spp `path` reference "
                "(`mean_vs_reference`: relative difference of the image means, `mean_se` its standard error "
                "over seeds, `reference_se` the reference's, `z` the difference over both; `mean_minus_last`: "
                "the difference to the last iteration's image mean in the same render; `mae_vs_last`: "
                "relative to the last iteration's; `variance_per_sample_last_four`: of the last four "
                "iterations, relative to the last's)", device, command, sections={"Runs": runs})
    print(summary.to_string(index=False))
