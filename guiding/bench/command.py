"""The ``bench`` command: its default scenes and methods, and the tables it writes (cost per spp with its breakdown,
fixed against growing passes, kernel sizes, CPU profile)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from guiding.errors import GuidingError
from guiding.output_dirs import prepare_output_dir
from guiding.provenance import device_name

#: What ``bench`` times by default: the shared scenes (method.md) and every kind of method.
BENCH_SCENES = ("cornell-box", "veach-ajar", "staircase2", "living-room")
#: Benchmarked beside them, at 256x256 (scale 1): the project's scenes where guided methods have nothing to guide and
#: should cost what brdf does (mirror-box: every method; glossy-box: the methods guiding purely diffuse surfaces).
BENCH_EXTRA_SCENES = ("glossy-box:1", "mirror-box:1")
#: What ``bench --part pass-schedule`` times by default: the methods whose passes differ (``ours`` keeps the paper's
#: update after every pass), on the scenes and scales of ``config/paper.yaml``'s equal-time experiment.
PASS_SCHEDULE_METHODS = ("brdf", "ours", "ours-plus", "sdtree")
PASS_SCHEDULE_SCENES = ("cornell-box:0.125", "veach-ajar:0.0625", "staircase2:0.0625", "living-room:0.0625",
                        "glossy-room:0.125", "sun-blinds:0.125")
#: The scenes of each part of ``bench`` unless ``--scenes`` is given: the cost at 1/4 resolution beside the scenes
#: with nothing to guide; kernel sizes (which do not depend on the resolution) at 1/16; the profile at 1/4.
DEFAULT_SCENES = {"cost": (*(f"{s}:0.25" for s in BENCH_SCENES), *BENCH_EXTRA_SCENES),
                  "pass-schedule": PASS_SCHEDULE_SCENES,
                  "kernel-size": tuple(f"{s}:0.0625" for s in BENCH_SCENES),
                  "profile": tuple(f"{s}:0.25" for s in BENCH_SCENES),
                  "gathers": tuple(f"{s}:0.25" for s in BENCH_SCENES)}
#: What ``bench --part gathers`` times by default beside ``path`` and ``brdf``: the paper's method and the baseline.
GATHERS_METHODS = ("ours", "sdtree")
BENCH_METHODS = ("ours", "ours-uniform-proposals", "ours-no-rejopt", "ours-expected", "sarsa-sphere_inv",
                 "sarsa-hemi_inv", "sdtree", "quadtree-grid")


def parse_scene_list(text: str) -> list[tuple[str, float]]:
    pairs = []
    for item in filter(None, text.split(",")):
        name, _, scale = item.partition(":")
        try:
            pairs.append((name, float(scale) if scale else 1.0))
        except ValueError:
            raise GuidingError(f"bad scene entry '{item}': expected NAME or NAME:SCALE") from None
    return pairs


@dataclass(frozen=True)
class _BenchRun:
    """What every part of ``bench`` works with: the scenes and methods (as given, and parsed), the output folder, the
    device, and the options that change what the renders run on, as given (for the tables' command lines)."""

    args: object
    scenes: list
    methods: list
    out: Path
    variant: str
    device: str

    @property
    def backend_options(self) -> str:
        args = self.args
        return ((f" --variant {args.variant}" if args.variant != "auto" else "")
                + (f" --threads {args.threads}" if args.threads else ""))

    def command(self, part: str, passes: bool = True) -> str:
        """The ``bench`` command line that makes a part's table."""
        args = self.args
        return (f"python -m guiding bench{f' --part {part}' if part != 'cost' else ''} --scenes {args.scenes} "
                f"--methods {args.methods}" + (f" --passes {args.passes}" if passes else ""))


def _kernel_size(run: _BenchRun) -> None:
    from guiding.bench.benchmark import write_table
    from guiding.bench.kernel_size import kernel_table

    frame = kernel_table(run.scenes, run.methods)
    write_table(frame, run.out / "kernel_instructions", "Machine instructions of each method's render kernel (the "
                "largest module compiled in its first passes; see guiding/kernel_size.py)", run.device,
                run.command("kernel-size", passes=False))
    print(frame.to_string(index=False))


def _profile(run: _BenchRun) -> None:
    from guiding.bench.benchmark import write_table
    from guiding.bench.cpu_profile import PASS_SPP, WARMUP_PASSES, profile_table

    passes = run.args.passes
    frame = profile_table(run.scenes, run.methods, passes)
    write_table(frame, run.out / "profile_cpu", f"CPU time per spp by code, sampled by Linux perf ({passes} "
                f"passes of {PASS_SPP} spp after {WARMUP_PASSES} warm-up passes, llvm_ad_rgb on one Dr.Jit "
                "thread; `jit_kernels`: the compiled path loop, split into `jit_table_access` (samples at a "
                "gather, load or store through a computed address, or the instruction after one) and `jit_other`; "
                "`embree`: ray traversal; see guiding/cpu_profile.py)", run.device, run.command("profile"))
    print(frame.to_string(index=False))


def _gathers(run: _BenchRun) -> None:
    from guiding.llvm_gathers import gathers_choosable
    from guiding.bench.benchmark import write_table
    from guiding.bench.gathers import gathers_table

    if not run.variant.startswith("llvm") or not gathers_choosable():
        raise GuidingError("bench --part gathers compares two CPU builds, which only a CPU with AVX2 and without "
                           "AVX-512 has (run it with --variant llvm_ad_rgb there)")
    passes = run.args.passes
    frame = gathers_table(run.scenes, run.methods, passes)
    write_table(frame, run.out / "hardware_gathers", "Table reads compiled into the CPU's gather instruction against "
                f"LLVM's loop of scalar loads (median kernel time per spp of {passes} interleaved passes of 8 "
                "spp after 2 warm-up passes, both builds in one run; `speed_up`: scalar-load time over gather "
                "time; see guiding/gather_bench.py)", device_name(run.variant, reads=False),
                run.command("gathers") + run.backend_options)
    print(frame.to_string(index=False))


def _pass_schedule(run: _BenchRun) -> None:
    from guiding.bench.benchmark import pass_schedule_table, write_table

    frame = pass_schedule_table(run.scenes, run.methods)
    write_table(frame, run.out / f"pass_schedule_{_tag(run.variant)}", "Pass modes: counted seconds of 512-spp "
                "renders with fixed 8-spp passes, growing passes, and growing frozen passes (render + update, "
                "compilation excluded; medians of 2 alternating rounds; `speed_up_growing`: fixed over growing, "
                "`speed_up_frozen`: growing over frozen)", run.device,
                run.command("pass-schedule", passes=False) + run.backend_options)
    print(frame.to_string(index=False))


def _cost(run: _BenchRun) -> None:
    from guiding.bench.benchmark import benchmark, target_table, write_table

    args, tag = run.args, _tag(run.variant)
    frame, breakdown = benchmark(run.scenes, run.methods, passes=args.passes, breakdown=not args.no_breakdown,
                                 nee=args.nee)
    command = (run.command("cost") + run.backend_options + (" --no-breakdown" if args.no_breakdown else "")
               + (" --nee" if args.nee else ""))
    name = f"benchmark_{tag}" + ("_nee" if args.nee else "")
    write_table(frame, run.out / name, "Cost per spp of every method vs `brdf` and Mitsuba `path` "
                + ("(every guided_path method, `brdf` included, with next-event estimation) " if args.nee else "") +
                f"(same run, {args.passes} interleaved passes of 8 spp after 2 warm-up passes, max depth 16; "
                "`trace-only`: the throughput limit, `share_of_trace_limit`: rays/s as a fraction of its)",
                run.device, command, sections={"Targets": target_table(frame, tag, breakdown)})
    if not breakdown.empty:
        write_table(breakdown, run.out / ("cost_breakdown" + ("_nee" if args.nee else "")), "Cost breakdown of every guided method: kernel time per "
                    "spp with the parts of the bounce switched on one by one (same interleaved run as "
                    f"{name}; `increment`: the stage's cost over the previous stage, the first over `brdf`; "
                    "partial stages are a benchmark instrument whose images are not meant to be correct)",
                    run.device, command)
        print(breakdown.to_string(index=False))
    print(frame.to_string(index=False))


def _tag(variant: str) -> str:
    return "gpu" if variant.startswith("cuda") else "cpu"


#: What each ``--part`` of ``bench`` runs.
PARTS = {"cost": _cost, "pass-schedule": _pass_schedule, "kernel-size": _kernel_size, "profile": _profile,
         "gathers": _gathers}


def command_bench(args) -> None:
    """``python -m guiding bench``: the scenes and methods checked (before anything is written), then the part's
    table under the output folder."""
    from guiding.backend import set_variant
    from guiding.guides.methods import check_method
    from guiding.scenes import find_scene

    schedule, gathers = args.part == "pass-schedule", args.part == "gathers"
    args.scenes = args.scenes or ",".join(DEFAULT_SCENES[args.part])
    args.methods = args.methods or ",".join(PASS_SCHEDULE_METHODS if schedule else GATHERS_METHODS if gathers
                                            else BENCH_METHODS)
    args.out = args.out or ("results/pass_schedule" if schedule else "results/bench")
    scenes = parse_scene_list(args.scenes)
    for name, _ in scenes:
        find_scene(name)
    methods = [m for m in args.methods.split(",") if m]
    for method in methods:
        check_method(method)
    variant = set_variant(args.variant, args.threads)
    out = prepare_output_dir(args.out)
    PARTS[args.part](_BenchRun(args, scenes, methods, out, variant, device_name(variant)))
