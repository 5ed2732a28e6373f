"""The command line's arguments: one parser per command, and the method resolved once, where it comes in.

``render --method NAME [--set FIELD=VALUE ...]`` leaves the parser as one :class:`~guiding.guides.methods.Method`
(``args.method``): the name and its settings resolved together, each value read as its parameter field's type.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

from guiding.errors import GuidingError
from guiding.experiments.sdtree_baseline import SCENE_STUDIES
from guiding.render import defaults

DESCRIPTION = "Command line: python -m guiding COMMAND (grid path guiding for Mitsuba 3 and its experiments)"


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


#: What a demo entry's name ends with to render with next-event estimation (``ours+nee``), and then with the path
#: fallback too (``ours-plus+nee+fallback``).
NEE_SUFFIX = "+nee"
FALLBACK_SUFFIX = "+fallback"


@dataclass(frozen=True)
class DemoEntry:
    """One render of the demo: a method name (resolved when its render's arguments are parsed), whether it
    renders with next-event estimation, written ``NAME+nee`` (Mitsuba's ``path`` always has it), and whether with
    the path fallback too, ``NAME+nee+fallback``."""

    method: str
    nee: bool = False
    path_fallback: bool = False

    @property
    def name(self) -> str:
        """As written on the command line, and the name of the render's folder."""
        return self.method + (NEE_SUFFIX if self.nee else "") + (FALLBACK_SUFFIX if self.path_fallback else "")

    def render_args(self) -> list[str]:
        return ["--method", self.method, *(["--nee"] if self.nee else []),
                *(["--path-fallback"] if self.path_fallback else [])]

    @classmethod
    def parse(cls, name: str) -> DemoEntry:
        fallback = name.endswith(FALLBACK_SUFFIX)
        name = name.removesuffix(FALLBACK_SUFFIX)
        if fallback and not name.endswith(NEE_SUFFIX):
            raise argparse.ArgumentTypeError(f"'{name}{FALLBACK_SUFFIX}': the path fallback needs next-event "
                                             f"estimation, write {name}{NEE_SUFFIX}{FALLBACK_SUFFIX}")
        return cls(name.removesuffix(NEE_SUFFIX), name.endswith(NEE_SUFFIX), fallback)


def _demo_entries(text: str) -> tuple[DemoEntry, ...]:
    """``path,brdf,ours+nee`` -> the demo's entries, in order; an entry twice would render into one folder."""
    names = [name.strip() for name in text.split(",") if name.strip()]
    if not names:
        raise argparse.ArgumentTypeError("no method given")
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        raise argparse.ArgumentTypeError(f"'{twice[0]}' is given twice")
    return tuple(DemoEntry.parse(name) for name in names)


def _memory_size(text: str) -> int:
    from guiding.guides.methods import parse_size

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
    parser.add_argument("--pass-spp", type=_positive_int, default=defaults.PASS_SPP,
                        help="samples per pixel of the first passes; later ones grow to pass_spp*2^k up to the "
                        "guide's next update (default %(default)s)")
    parser.add_argument("--max-depth", type=_positive_int, default=defaults.MAX_DEPTH,
                        help="longest path, in vertices after the camera (default %(default)s)")
    parser.add_argument("--out", required=True, help="output folder (image.exr, preview.png, stats.json)")
    parser.add_argument("--quiet", action="store_true", help="no progress display")


def _add_render(commands) -> None:
    render = commands.add_parser("render", help="render a scene with a method")
    _add_scene_options(render)
    render.add_argument("--method", required=True, help="method name (see `methods`); grid methods also take the "
                        "shorthand -S<n>-D<n> (ours-S4-D32 is ours with S = 4, D = 32), quadtree-grid -S<n>")
    render.add_argument("--set", dest="settings", action="append", default=[], metavar="FIELD=VALUE",
                        help="set a parameter of the method's guide (repeatable), e.g. --set spatial_resolution=16: "
                        "a field of its parameters (guiding/guides/parameters.py), the value read as the field's "
                        "type (numbers, true/false, none)")
    budget = render.add_mutually_exclusive_group(required=True)
    budget.add_argument("--spp", type=_positive_int, help="samples per pixel budget")
    budget.add_argument("--seconds", type=_positive_float, help="time budget in seconds")
    render.add_argument("--nee", action="store_true",
                        help="next-event estimation with MIS against the method's own density (`path` always has it)")
    render.add_argument("--path-fallback", action="store_true",
                        help="with --nee: render the rest of the budget with Mitsuba's path where guiding does not "
                        "pay (checked after a tenth of the budget) or where the method has nothing to guide")
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


def _add_reference_evaluate_and_show_guide(commands) -> None:
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


def _add_bench(commands) -> None:
    bench = commands.add_parser("bench", help="cost per spp of every method vs `brdf` and Mitsuba's `path` "
                                "(same process, interleaved passes)")
    bench.add_argument("--part", choices=["cost", "pass-schedule", "kernel-size", "profile", "gathers"],
                       default="cost",
                       help="cost: cost per spp and its breakdown (default); pass-schedule: renders with fixed, "
                       "growing and frozen passes (results/pass_schedule); kernel-size: each method's render kernel "
                       "in machine instructions (CPU; results/bench/kernel_instructions); profile: each method's CPU "
                       "time by code, JIT kernels against Embree and the rest (Linux perf; results/bench/profile_cpu); "
                       "gathers: each method with table reads compiled into gather instructions and into scalar loads "
                       "(CPU with AVX2; results/bench/hardware_gathers)")
    bench.add_argument("--scenes", help="comma-separated NAME:SCALE list (default: cost: the four shared scenes at 1/4 "
                       "resolution, glossy-box and mirror-box, the scenes with nothing to guide; pass-schedule: those "
                       "of config/paper.yaml's equal-time experiment; kernel-size: the four at 1/16; profile and "
                       "gathers: the four at 1/4)")
    bench.add_argument("--passes", type=_positive_int, default=8, help="timed passes per integrator (default 8)")
    bench.add_argument("--methods", help="methods timed against brdf (comma-separated; default: cost: every kind, "
                       "pass-schedule: brdf, ours, ours-plus, sdtree; gathers: ours, sdtree)")
    bench.add_argument("--out", help="output folder (default results/bench, results/pass_schedule)")
    bench.add_argument("--nee", action="store_true",
                       help="cost: every guided_path method, brdf included, with next-event estimation (as path)")
    bench.add_argument("--no-breakdown", action="store_true",
                       help="skip the cost breakdown (the guided methods' stages, results/bench/cost_breakdown.md)")
    _add_backend_options(bench)


#: The demo's methods: the practical answer (Mitsuba's path against the guided methods with next-event
#: estimation) beside the paper's comparison (BSDF sampling against ours, both without).
DEMO_METHODS = "path,brdf,ours,ours+nee,ours-plus+nee,ours-plus+nee+fallback,sdtree+nee"


def _add_demo_and_validate(commands) -> None:
    demo = commands.add_parser("demo", help="the main job: a reference, then Mitsuba's path, BSDF sampling and the "
                               "guided methods, with and without next-event estimation, at equal time; their errors")
    demo.add_argument("--scene", default="door-ajar")
    demo.add_argument("--scale", type=_positive_float, default=0.5)
    demo.add_argument("--methods", type=_demo_entries, default=DEMO_METHODS,
                      help="comma-separated method names, each with +nee to render it with next-event estimation, "
                      "+nee+fallback with the path fallback too (Mitsuba's path where guiding does not pay) "
                      f"(default {DEMO_METHODS}; `path` is Mitsuba's own path tracer, which always has it)")
    budget = demo.add_mutually_exclusive_group()
    budget.add_argument("--seconds", type=_positive_float, default=5.0,
                        help="seconds of each method, compilation excluded (default %(default)g: equal time)")
    budget.add_argument("--spp", type=_positive_int, help="spp of each method instead (equal spp)")
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


def _add_sdtree_baseline(commands) -> None:
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
                          "results/sdtree_combination/equal_spp.md, or equal_time.md with --seconds)")
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


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="guiding", description=DESCRIPTION)
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _add_render(commands)
    _add_reference_evaluate_and_show_guide(commands)
    _add_bench(commands)
    _add_demo_and_validate(commands)
    _add_sdtree_baseline(commands)
    commands.add_parser("scenes", help="list the scenes on the search path")
    commands.add_parser("methods", help="list the method names")
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line's arguments; for ``render``, ``args.method`` is the method (name and ``--set`` settings)
    resolved into a :class:`~guiding.guides.methods.Method` (GuidingError, one line, if it is none)."""
    args = build_parser().parse_args(argv)
    if args.command == "render":
        from guiding.guides.methods import parse_settings, resolve

        method = resolve(args.method)
        args.method = method.with_settings(parse_settings(method, args.settings))
    return args
