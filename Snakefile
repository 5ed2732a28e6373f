"""The experiment DAG: references -> renders -> metrics -> tables, figures, provenance (docs/harness.md).

Thin on purpose: guiding/experiments/plan.py expands the configuration into runs and paths, `python -m guiding`
renders, guiding/experiments/tables.py and figures.py draw. Without --configfile, config/config.yaml is used (for --report: the
configuration of the last completed run); a --configfile replaces it (no merging), --config KEY=VALUE overrides
single keys.
"""

import json
import os
import sys

from snakemake.exceptions import WorkflowError

from guiding.experiments import harness
from guiding.experiments.plan import BUDGET_PATTERN, NAME_PATTERN, plan_or_exit
from guiding.experiments.runs import EXPERIMENTS

if not workflow.config_settings.configfiles:
    # A report describes a run: without --configfile, the one that last completed here (onsuccess below).
    if harness.report_requested(sys.argv) and os.path.exists(harness.LAST_RUN_CONFIG):

        configfile: harness.LAST_RUN_CONFIG

    else:

        configfile: os.path.join(workflow.basedir, "config", "config.yaml")


PLAN = plan_or_exit(
    config,
    schema=os.path.join(workflow.basedir, "config", "schema.yaml"),
    check=not workflow.remote_exec,
    source=", ".join(map(str, workflow.config_settings.configfiles)) or "config/config.yaml",
)
OUT = PLAN.out


def out(*parts):
    """A path under the configuration's output folder."""
    return os.path.join(OUT, *parts)


REFERENCE = "references/{scene}/x{scale}-spp{spp}"
RENDER = "renders/{experiment}/{scene}/{method}/{budget}/seed{seed}"
RUN_LOG = "{experiment}/{scene}/{method}/{budget}/seed{seed}.log"
# The jobs run the same Python as Snakemake (kept out of the commands, so it is no rerun trigger).
os.environ.setdefault("GUIDING_PYTHON", sys.executable)


# Output to the job's log; on failure, the cause from the log on stderr (and the command's exit status kept).
LOG_AND_CAUSE = (
    " > {log:q} 2>&1 || {{ status=$?;"
    ' "$GUIDING_PYTHON" -m guiding.experiments.harness cause {log:q} --status $status; exit $status; }}'
)


def logged(command):
    """``command`` with its output in the job's log; when it fails, why (the command line's one-line error, or a
    traceback's last line) is printed on stderr, so that it stands in Snakemake's own output, not only in the log."""
    return "".join((command, LOG_AND_CAUSE))


onsuccess:
    harness.record_run_config(config)


def all_cores():
    try:
        return workflow.cores
    except WorkflowError:  # no --cores (e.g. a cluster run with --jobs): timed_threads or this machine's
        return None


report: "docs/report/workflow.rst"


wildcard_constraints:
    scene=NAME_PATTERN,
    method=NAME_PATTERN,
    budget=BUDGET_PATTERN,
    seed=r"[0-9]+",
    scale=r"[0-9]+(\.[0-9]+)?",
    spp=r"[0-9]+",
    experiment="|".join(EXPERIMENTS),


localrules:
    all,
    tables,
    figures,
    evaluate,
    table,
    figure_comparison,
    figure_convergence,
    figure_heatmap,
    provenance,


rule all:
    input:
        PLAN.targets(),


rule tables:
    input:
        [f for e in PLAN.experiments() for f in PLAN.table_files(e).values()],


rule figures:
    input:
        PLAN.figure_files(),


rule reference:
    input:
        scene=lambda wc: PLAN.scene_file(wc.scene),
    output:
        image=out(REFERENCE, "image.exr"),
        stats=out(REFERENCE, "stats.json"),
        preview=out(REFERENCE, "preview.png"),
    log:
        out("logs/reference/{scene}-x{scale}-spp{spp}.log"),
    params:
        args=lambda wc: PLAN.reference_args(wc.scene, float(wc.scale), int(wc.spp)),
    threads: PLAN.config["threads"]
    resources:
        gpu=PLAN.gpu,
    cache: "omit-software"  # with --cache reference and $SNAKEMAKE_OUTPUT_CACHE: shared between output folders
    shell:
        logged('"$GUIDING_PYTHON" -m guiding {params.args} --threads {threads} --out $(dirname {output.image:q})')


# Untimed renders (equal spp): many side by side, `threads` Dr.Jit threads each.
rule render:
    input:
        scene=lambda wc: PLAN.scene_file(wc.scene),
    output:
        image=out(RENDER, "image.exr"),
        stats=out(RENDER, "stats.json"),
        preview=out(RENDER, "preview.png"),
    log:
        out("logs", "render", RUN_LOG),
    wildcard_constraints:
        experiment=PLAN.experiment_pattern(timed=False),
    params:
        args=lambda wc: PLAN.render_args(PLAN.run_for(wc)),
    threads: PLAN.config["threads"]
    resources:
        gpu=PLAN.gpu,
    shell:
        logged('"$GUIDING_PYTHON" -m guiding {params.args} --threads {threads} --out $(dirname {output.image:q})')


# Timed renders (equal time, convergence) never share the machine: they take every core Snakemake was given (so
# no other local job runs beside them) and the resource `timing` (give --resources timing=1 to serialise them
# across executors too; the SLURM profile also asks for an exclusive node).
rule render_timed:
    input:
        scene=lambda wc: PLAN.scene_file(wc.scene),
    output:
        image=out(RENDER, "image.exr"),
        stats=out(RENDER, "stats.json"),
        preview=out(RENDER, "preview.png"),
    log:
        out("logs", "render_timed", RUN_LOG),
    wildcard_constraints:
        experiment=PLAN.experiment_pattern(timed=True),
    params:
        args=lambda wc: PLAN.render_args(PLAN.run_for(wc)),
    threads: lambda wc: PLAN.timed_threads(all_cores())
    resources:
        gpu=PLAN.gpu,
        timing=1,
    shell:
        logged('"$GUIDING_PYTHON" -m guiding {params.args} --threads {threads} --out $(dirname {output.image:q})')


rule evaluate:
    input:
        image=out(RENDER, "image.exr"),
        stats=out(RENDER, "stats.json"),
        reference=lambda wc: PLAN.reference_file(PLAN.reference_for(PLAN.run_for(wc)), "image.exr"),
    output:
        out(RENDER, "metrics.json"),
    log:
        out("logs", "evaluate", RUN_LOG),
    params:
        run=lambda wc: json.dumps(PLAN.run_for(wc).info()),
    shell:
        logged(
            '"$GUIDING_PYTHON" -m guiding.experiments.harness evaluate {input.image:q} {input.stats:q} {input.reference:q}'
            " --run {params.run:q} --out {output:q}"
        )


rule table:
    input:
        lambda wc: [PLAN.render_file(r, "metrics.json") for r in PLAN.experiment_runs(wc.experiment)],
    output:
        csv=report(
            out("tables/{experiment}.csv"),
            caption="docs/report/table.rst",
            category="Tables",
            labels={"experiment": "{experiment}", "content": "cells (mean over seeds) and the paper's numbers"},
        ),
        md=report(
            out("tables/{experiment}.md"),
            caption="docs/report/markdown.rst",
            category="Tables",
            labels={"experiment": "{experiment}", "content": "laid out like the paper's table, ours / paper"},
        ),
        runs=report(
            out("tables/{experiment}_runs.csv"),
            caption="docs/report/runs.rst",
            category="Tables",
            labels={"experiment": "{experiment}", "content": "every render, with its machine and device"},
        ),
    log:
        out("logs/table/{experiment}.log"),
    params:
        spec=lambda wc: json.dumps(PLAN.experiment_spec(wc.experiment)),
    shell:
        logged(
            '"$GUIDING_PYTHON" -m guiding.experiments.tables --spec {params.spec:q} --csv {output.csv:q} --md {output.md:q}'
            " --runs-csv {output.runs:q} {input:q}"
        )


rule figure_comparison:
    input:
        lambda wc: PLAN.comparison_inputs(wc.experiment),
    output:
        report(
            out("figures/{experiment}_comparison.png"),
            caption="docs/report/comparison.rst",
            category="Figures",
            labels={"figure": "{experiment} comparison"},
        ),
    log:
        out("logs/figures/{experiment}_comparison.log"),
    params:
        job=lambda wc: json.dumps(PLAN.comparison_job(wc.experiment)),
    shell:
        logged('"$GUIDING_PYTHON" -m guiding.experiments.figures comparison --job {params.job:q} --out {output:q}')


rule figure_convergence:
    input:
        [PLAN.render_file(r, "metrics.json") for r in PLAN.experiment_runs("convergence")],
    output:
        report(
            out("figures/convergence.png"),
            caption="docs/report/convergence.rst",
            category="Figures",
            labels={"figure": "error against time"},
        ),
    log:
        out("logs/figures/convergence.log"),
    params:
        job=lambda wc: json.dumps({"scenes": PLAN.config["experiments"].get("convergence", {}).get("scenes", [])}),
    shell:
        logged('"$GUIDING_PYTHON" -m guiding.experiments.figures convergence --job {params.job:q} --out {output:q} {input:q}')


rule figure_heatmap:
    input:
        out("tables/table1.csv"),
    output:
        report(
            out("figures/table1_heatmap.png"),
            caption="docs/report/heatmap.rst",
            category="Figures",
            labels={"figure": "Table 1 heat map"},
        ),
    log:
        out("logs/figures/table1_heatmap.log"),
    shell:
        logged('"$GUIDING_PYTHON" -m guiding.experiments.figures heatmap --csv {input:q} --out {output:q}')


rule provenance:
    input:
        renders=[PLAN.render_file(r, "stats.json") for r in PLAN.runs],
        references=[PLAN.reference_file(r, "stats.json") for r in PLAN.references.values()],
    output:
        json=out("provenance.json"),
        html=report(
            out("provenance.html"),
            caption="docs/report/provenance.rst",
            category="Provenance",
            labels={"content": "configuration, code, software, machines and devices"},
        ),
    log:
        out("logs/provenance.log"),
    params:
        config=lambda wc: json.dumps(config),  # a function: the config's templates hold braces
        configfiles=lambda wc: os.pathsep.join(map(str, workflow.config_settings.configfiles)),
    shell:
        logged(
            '"$GUIDING_PYTHON" -m guiding.experiments.harness provenance --config {params.config:q}'
            " --configfiles {params.configfiles:q}"
            " --out-json {output.json:q} --out-html {output.html:q} {input:q}"
        )
