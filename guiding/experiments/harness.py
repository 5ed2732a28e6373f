"""The experiment harness behind the ``Snakefile``: its command line, and what the rules ask of it beside the plan.

The Snakefile stays thin: it asks :func:`guiding.experiments.plan.plan_or_exit` for a
:class:`~guiding.experiments.plan.Plan` (the configuration checked in :mod:`~guiding.experiments.configuration`,
expanded into runs in :mod:`~guiding.experiments.runs`) and turns it into rules; its jobs call this module's command
line. Everything here is plain Python (no Dr.Jit), so it is quick to import and to test.

Command line (used by the rules, handy by hand)::

    python -m guiding.experiments.harness path [--configfile F] EXPERIMENT SCENE METHOD [--seed S] [--budget B]
    python -m guiding.experiments.harness runs [--configfile F]          # every run of the configuration, one path a line
    python -m guiding.experiments.harness evaluate IMAGE STATS REFERENCE --run JSON --out metrics.json
    python -m guiding.experiments.harness provenance --config JSON --out-json F --out-html F STATS...
    python -m guiding.experiments.harness cause LOG --status N             # why a job failed, on stderr (the rules call it)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from guiding.errors import GuidingError
from guiding.experiments.configuration import DEFAULT_CONFIG, ConfigError, load_config
from guiding.experiments.plan import Plan, plan


# --------------------------------------------------------------------------------- workflow runs and reports

#: Where a completed workflow run records its resolved configuration (in Snakemake's folder of the working
#: directory), so that ``snakemake --report FILE`` without ``--configfile`` reports that run.
LAST_RUN_CONFIG = os.path.join(".snakemake", "guiding-last-run-config.json")


def report_requested(argv: list[str]) -> bool:
    """Whether the Snakemake command line ``argv`` asks for a report (``--report [FILE]``)."""
    return any(arg == "--report" or arg.startswith("--report=") for arg in argv)


def record_run_config(config: dict, path: str | os.PathLike = LAST_RUN_CONFIG) -> None:
    """Record the resolved ``config`` of a completed run at ``path`` (strict JSON; Snakemake reads it as a
    configfile)."""
    from guiding import strict_json
    from guiding.imageio import write_text_atomic

    write_text_atomic(path, strict_json.dumps(config))


def job_failure(log_text: str, status: int) -> str:
    """One line saying why a job failed, from its log ``log_text`` and exit ``status``: the command line's own
    ``error:`` line, or a traceback's last line, or the log's last line; a job killed by a signal says so."""
    lines = [line.strip() for line in log_text.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error:") or line.startswith("interrupted:")]
    if status > 128 and not errors:
        return f"killed by signal {status - 128}" + (f" (log ends: {lines[-1]})" if lines else "")
    if errors:
        return errors[-1]
    return lines[-1] if lines else f"exit status {status}, nothing in its log"


# ----------------------------------------------------------------------------------------------------- CLI

def _load_plan(configfile: str | None) -> Plan:
    return plan(load_config(configfile or DEFAULT_CONFIG), check=False)


def _path(args) -> None:
    the_plan = _load_plan(args.configfile)
    found = [r for r in the_plan.runs if (r.experiment, r.scene, r.method) == (args.experiment, args.scene, args.method)
             and (args.seed is None or r.seed == args.seed) and (args.budget is None or r.budget.tag == args.budget)]
    if not found:
        raise ConfigError(f"no run ({args.experiment}, {args.scene}, {args.method}) in this configuration")
    print(the_plan.render_file(found[0], "image.exr"))


def _runs(args) -> None:
    the_plan = _load_plan(args.configfile)
    for run in the_plan.runs:
        print(the_plan.render_file(run, "image.exr"))


def _evaluate(args) -> None:
    from guiding.experiments.evaluation import evaluate_run

    result = evaluate_run(args.image, args.stats, args.reference, args.out, json.loads(args.run))
    print(f"mae {result['mae']} relmse {result['relmse']} -> {args.out}")


def _provenance(args) -> None:
    from guiding import strict_json
    from guiding.imageio import write_text_atomic
    from guiding.provenance import provenance, provenance_html

    configfiles = [p for p in args.configfiles.split(os.pathsep) if p]
    data = provenance(json.loads(args.config), args.stats, configfiles)
    write_text_atomic(args.out_json, strict_json.dumps(data))
    write_text_atomic(args.out_html, provenance_html(data))


def _cause(args) -> None:
    text = Path(args.log).read_text(errors="replace") if Path(args.log).is_file() else ""
    print(f"job failed: {job_failure(text, args.status)} (log: {args.log})", file=sys.stderr)


COMMANDS = {"path": _path, "runs": _runs, "evaluate": _evaluate, "provenance": _provenance, "cause": _cause}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m guiding.experiments.harness", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)

    path = commands.add_parser("path", help="the render folder of one run of a configuration")
    path.add_argument("--configfile", help="default: config/config.yaml")
    path.add_argument("experiment")
    path.add_argument("scene")
    path.add_argument("method")
    path.add_argument("--seed", type=int, help="default: the first seed")
    path.add_argument("--budget", help="budget tag (spp1024, 10s); default: the first")

    runs = commands.add_parser("runs", help="every run of a configuration: its image.exr path")
    runs.add_argument("--configfile", help="default: config/config.yaml")

    evaluate = commands.add_parser("evaluate", help="metrics.json of one render")
    evaluate.add_argument("image")
    evaluate.add_argument("stats")
    evaluate.add_argument("reference")
    evaluate.add_argument("--run", default="{}", help="JSON object recorded as the run")
    evaluate.add_argument("--out", required=True)

    prov = commands.add_parser("provenance", help="provenance.json and provenance.html")
    prov.add_argument("--config", required=True, help="the resolved configuration as JSON")
    prov.add_argument("--configfiles", default="", help="the configuration files, separated by os.pathsep")
    prov.add_argument("--out-json", required=True)
    prov.add_argument("--out-html", required=True)
    prov.add_argument("stats", nargs="*")

    cause = commands.add_parser("cause", help="print why a job failed, from its log (the Snakefile's rules)")
    cause.add_argument("log")
    cause.add_argument("--status", type=int, required=True, help="the job's exit status")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        COMMANDS[args.command](args)
    except GuidingError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
