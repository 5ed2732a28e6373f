"""The command line's render commands: ``render``, ``reference``, ``evaluate``, ``show-guide``, ``demo``, and the
``scenes`` and ``methods`` lists."""

from __future__ import annotations

import json
import os
import sys
from dataclasses import asdict
from datetime import datetime
from pathlib import Path

from guiding.cli.parser import parse_args
from guiding.errors import GuidingError
from guiding.output_dirs import output_dir, prepare_output_dir
from guiding.provenance import render_provenance


def samples_emitters(integrator) -> bool:
    """Whether a render's integrator does next-event estimation: ``guided_path`` with ``nee``, and Mitsuba's ``path``
    (the only Mitsuba integrator the commands render with)."""
    return bool(getattr(integrator, "nee", True))


def _image_metadata(scene_name: str, args, method: str, integrator, budget, provenance: dict, combine: str) -> dict:
    """What every EXR file of a render carries in its header (imageio.write_exr; the spp are added per file): the
    method and its guide's parameters, the render's parameters (``combine``: its final-image mode), seed, scene,
    variant, device and versions."""
    from guiding.provenance import software_versions

    guide = getattr(integrator, "guide", None)
    parameters = {"budget": asdict(budget), "max_depth": args.max_depth, "scale": args.scale, "combine": combine,
                  "nee": samples_emitters(integrator),
                  "path_fallback": bool(getattr(integrator, "path_fallback", False))}
    return {"method": method, "scene": scene_name, "seed": args.seed, "parameters": parameters,
            "guide": {k: v for k, v in (guide.stats() if guide is not None else {}).items()
                      if not isinstance(v, (dict, list))},
            **{k: provenance[k] for k in ("variant", "device", "threads", "host", "date")},
            "versions": software_versions()}


def _clock() -> str:
    """Wall-clock time to the microsecond with its UTC offset: a render's ``started`` and ``finished`` in stats.json,
    from which the harness's tests tell whether two timed renders overlapped (on a cluster, in different jobs)."""
    return datetime.now().astimezone().isoformat(timespec="microseconds")


def _render_to(out: Path, scene_name: str, args, integrator, method: str, budget, variant: str) -> dict:
    from guiding.experiments import guide_state
    from guiding import imageio
    from guiding import strict_json
    from guiding.render.progress import SnapshotWriter
    from guiding.render.progressive import render, resolve_combine
    from guiding.scenes import find_scene, load_scene

    started = _clock()
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
    finished = _clock()
    film_size = [int(v) for v in scene.sensors()[0].film().size()]
    stats = {"scene": scene_name, "scene_file": str(find_scene(scene_name, args.scene_dir)), "scale": args.scale,
             "resolution": film_size, "method": method, "seed": args.seed, "max_depth": args.max_depth,
             "nee": samples_emitters(integrator),
             **result.summary(), "guide": getattr(getattr(integrator, "guide", None), "stats", dict)(),
             "started": started, "finished": finished, "provenance": provenance,
             "per_pass": [asdict(p) for p in result.passes]}
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


def command_render(args) -> None:
    """Render ``args.scene`` with ``args.method`` (a resolved :class:`~guiding.guides.methods.Method`)."""
    from guiding.backend import set_variant
    from guiding.render.progressive import Budget
    from guiding.scenes import find_scene

    method = args.method
    budget = Budget(spp=args.spp, seconds=args.seconds, pass_spp=args.pass_spp, exclude_passes=args.exclude_passes,
                    growing_passes=not args.fixed_passes)
    find_scene(args.scene, args.scene_dir)
    method.check_memory(args.memory_limit)
    variant = set_variant(args.variant, args.threads)
    from guiding.render.integrator import integrator_for

    if args.path_fallback and not args.nee:
        raise GuidingError("--path-fallback hands passes to Mitsuba's path, which samples emitters: add --nee")
    integrator = integrator_for(method, args.max_depth, args.nee, args.memory_limit, args.path_fallback)
    guide = getattr(integrator, "guide", None)
    if args.save_guide and (guide is None or not guide.records()):
        raise GuidingError(f"--save-guide: method '{method.label}' learns nothing to save")
    with output_dir(args.out) as out:
        stats = _render_to(out, args.scene, args, integrator, method.label, budget, variant)
    print(f"{method.label}{' with nee' if args.nee else ''} on {args.scene}: {stats['spp']} spp in {stats['seconds']:.2f} s "
          f"(compile {stats['compile_seconds']:.2f} s), hit rate {stats['hit_rate']:.4f}{_fallback_text(stats)} -> {out}")


def _fallback_text(stats: dict) -> str:
    """What Mitsuba's path rendered, for the render's last line: the path fallback's decision, or every pass where
    the guide has nothing to guide ('' where it rendered nothing)."""
    decision = stats.get("path_fallback")
    if decision is None:
        return ""
    if not decision["spp"]:
        return f", every pass Mitsuba's path: {decision['reason']}"
    return f", path fallback: {decision['reason']} (after {decision['spp']} spp)"


def command_reference(args) -> None:
    from guiding.backend import set_variant
    from guiding.render.progressive import Budget
    from guiding.scenes import find_scene

    budget = Budget(spp=args.spp, pass_spp=min(args.pass_spp, args.spp))
    find_scene(args.scene, args.scene_dir)
    variant = set_variant(args.variant, args.threads)
    import mitsuba as mi

    integrator = mi.load_dict({"type": "path", "max_depth": args.max_depth})
    with output_dir(args.out) as out:
        stats = _render_to(out, args.scene, args, integrator, "reference-path", budget, variant)
    print(f"reference of {args.scene}: {stats['spp']} spp in {stats['seconds']:.1f} s -> {out}")


def command_evaluate(args) -> None:
    from guiding import strict_json
    from guiding.imageio import read_exr
    from guiding.metrics import evaluate

    image, ref = read_exr(args.image), read_exr(args.ref)
    metrics = evaluate(image, ref)
    if args.error_map:
        from guiding.experiments.figures import error_map

        error_map(image, ref, args.error_map)
    print(strict_json.dumps(metrics))


def command_show_guide(args) -> None:
    """Draw a saved guide's distribution in one cell: ``--cell``, the cell of the first vertex seen through
    ``--pixel``, or the best trained cell."""
    from guiding.experiments import guide_state
    from guiding.backend import set_variant

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


def _demo_row(render, reference: Path) -> dict:
    """One line of the demo's summary: what ``render`` (its parsed arguments) made, against ``reference``."""
    from guiding.imageio import read_exr
    from guiding.metrics import evaluate

    target = Path(render.out)
    stats = json.loads((target / "stats.json").read_text())
    errors = evaluate(read_exr(target / "image.exr"), read_exr(reference / "image.exr"))
    fallback = (stats.get("path_fallback") or {}).get("chosen", "")
    return {"method": render.method.label, "nee": stats["nee"], "fallback": fallback, "spp": stats["spp"],
            "seconds": stats["budget_seconds_counted"], "mae": errors["mae"], "relmse": errors["relmse"]}


def command_demo(args) -> None:
    """A reference (cached per scene, scale and spp), then each of ``args.methods``
    (:class:`~guiding.cli.parser.DemoEntry` values) under one budget, equal time by default, and a Markdown table of
    their errors (``summary.md``) with each method's efficiency relative to Mitsuba's ``path`` (its MAE²·t over the
    method's, t the seconds counted, compilation excluded): the practical question first."""
    from guiding.backend import set_variant
    from guiding.scenes import find_scene

    find_scene(args.scene)
    variant = set_variant(args.variant, args.threads)
    common = ["--scene", args.scene, "--scale", str(args.scale), "--variant", variant]
    budget = ["--spp", str(args.spp)] if args.spp else ["--seconds", f"{args.seconds:g}"]
    # Every render's arguments (so its method) are parsed before anything is written: bad input writes nothing.
    renders = [parse_args(["render", *common, *entry.render_args(), *budget,
                           "--out", str(Path(args.out) / entry.name)]) for entry in args.methods]
    out = prepare_output_dir(args.out)
    import pandas as pd

    reference = out / f"reference-{Path(args.scene).stem}-x{args.scale:g}-{args.reference_spp}spp"
    if not (reference / "stats.json").exists():
        command_reference(parse_args(["reference", *common, "--spp", str(args.reference_spp),
                                      "--out", str(reference)]))
    rows = []
    for render in renders:
        command_render(render)
        rows.append(_demo_row(render, reference))
    frame = pd.DataFrame(rows)
    cost = frame["mae"] ** 2 * frame["seconds"]
    if (frame["method"] == "path").any():
        frame["efficiency_vs_path"] = cost[frame["method"] == "path"].iloc[0] / cost
    table = frame.to_markdown(index=False, floatfmt=".4g")
    each = f"{args.spp} spp" if args.spp else f"{args.seconds:g} s"
    (out / "summary.md").write_text(
        f"# {args.scene} at scale {args.scale}, {each} each\n\n{table}\n\nseconds: rendering counted against the "
        "budget (compilation excluded); nee: next-event estimation (Mitsuba's `path` always has it); fallback: what "
        "rendered the rest of the budget after the path fallback's check (`+fallback`); "
        "efficiency_vs_path: path's MAE²·seconds over the method's (above 1: path's error in less time).\n")
    print(table)


def command_scenes(args) -> None:
    from guiding.scenes import available_scenes, search_path

    for name in available_scenes():
        print(name)
    print("search path: " + os.pathsep.join(str(p) for p in search_path()), file=sys.stderr)


def command_methods(args) -> None:
    from guiding.guides.methods import method_names

    print("\n".join(method_names()))
