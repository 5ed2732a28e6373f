"""The experiment harness's plan: a validated configuration's runs and references, and what the ``Snakefile`` asks of
them (paths, command lines, the specs of tables and figures).

Layout of what a configuration produces, under its ``out`` folder::

    references/{scene}/x{scale}-spp{spp}/image.exr, stats.json, preview.png      one per scene and scale
    renders/{experiment}/{scene}/{method}/{budget}/seed{seed}/image.exr, stats.json, preview.png, metrics.json
    tables/{experiment}.csv, .md, _runs.csv        figures/*.png        provenance.json, provenance.html
    logs/...                                        one log per job

``{budget}`` is ``spp1024`` for a samples-per-pixel budget and ``10s`` for a seconds budget.
"""

from __future__ import annotations

import copy
import os
import shlex
import sys
from dataclasses import asdict, dataclass, field

from guiding.errors import GuidingError
from guiding.experiments.configuration import SCHEMA, ConfigError, validate_schema
from guiding.experiments.runs import (EXPERIMENTS, Reference, Run, budget_points, expand, experiment_timed,
                                      missing_scenes, unknown_methods)

#: Wildcard patterns (also the Snakefile's wildcard constraints).
NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9_.+-]*"
BUDGET_PATTERN = r"spp[0-9]+|[0-9]+(?:\.[0-9]+)?s"
NEVER_PATTERN = r"(?!x)x"


@dataclass
class Plan:
    config: dict
    runs: list[Run]
    references: dict[tuple[str, float], Reference]
    warnings: list[str] = field(default_factory=list)

    # ------------------------------------------------------------------ lookups used by the Snakefile
    @property
    def out(self) -> str:
        return self.config["out"].rstrip("/")

    def experiments(self) -> list[str]:
        return [e for e in EXPERIMENTS if e in self.config["experiments"]]

    def run_for(self, wildcards) -> Run:
        key = (wildcards.experiment, wildcards.scene, wildcards.method, wildcards.budget, str(wildcards.seed))
        try:
            return self._by_key[key]
        except KeyError:
            raise ConfigError(f"no run {'/'.join(key)} in this configuration "
                              "(see `python -m guiding.experiments.harness runs`)") from None

    def scene_file(self, scene: str) -> list[str]:
        """The scene's XML file as a job input (so an edited scene re-renders), or nothing when it is not on the
        search path (the job then fails with the command line's own message)."""
        from guiding.scenes import find_scene

        try:
            return [str(find_scene(scene, self.config["scene_dirs"]))]
        except GuidingError:
            return []

    def reference_for(self, run: Run) -> Reference:
        return self.references[(run.scene, run.scale)]

    def experiment_runs(self, experiment: str) -> list[Run]:
        return [r for r in self.runs if r.experiment == experiment]

    def experiment_pattern(self, timed: bool) -> str:
        names = sorted({r.experiment for r in self.runs if r.timed == timed})
        return "|".join(names) if names else NEVER_PATTERN

    def __post_init__(self):
        self._by_key = {r.key: r for r in self.runs}

    # ------------------------------------------------------------------ paths
    def render_file(self, run: Run, name: str) -> str:
        return f"{run.dir(self.out)}/{name}"

    def reference_file(self, reference: Reference, name: str) -> str:
        return f"{reference.dir(self.out)}/{name}"

    def table_files(self, experiment: str) -> dict[str, str]:
        base = f"{self.out}/tables/{experiment}"
        return {"csv": f"{base}.csv", "md": f"{base}.md", "runs": f"{base}_runs.csv"}

    def figure_files(self) -> list[str]:
        figures = []
        experiments = self.experiments()
        if "table1" in experiments:
            figures.append(f"{self.out}/figures/table1_heatmap.png")
        for experiment in self.config["figures"]["comparison"]:
            if experiment in experiments:
                figures.append(f"{self.out}/figures/{experiment}_comparison.png")
        if "convergence" in experiments:
            figures.append(f"{self.out}/figures/convergence.png")
        return figures

    def provenance_files(self) -> dict[str, str]:
        return {"json": f"{self.out}/provenance.json", "html": f"{self.out}/provenance.html"}

    def targets(self) -> list[str]:
        files = [f for e in self.experiments() for f in self.table_files(e).values()]
        return files + self.figure_files() + list(self.provenance_files().values())

    # ------------------------------------------------------------------ commands
    def _common_args(self, scene: str, scale: float, seed: int) -> list[str]:
        args = ["--scene", scene, "--scale", f"{scale:g}", "--seed", str(seed), "--variant", self.config["variant"]]
        for folder in self.config["scene_dirs"]:
            args += ["--scene-dir", folder]
        return args

    def render_args(self, run: Run) -> str:
        """Arguments of `python -m guiding render` for ``run`` (without --threads and --out: those are no part of
        what the result depends on, so they are kept out of Snakemake's params)."""
        render = self.config["render"]
        args = ["render", *self._common_args(run.scene, run.scale, run.seed), *run.method_args(),
                *run.budget.cli_args(), "--pass-spp", str(render["pass_spp"]), "--max-depth", str(render["max_depth"])]
        if self.config["experiments"][run.experiment].get("snapshots"):
            args.append("--snapshots")
        if not render["growing_passes"]:
            args.append("--fixed-passes")
        return shlex.join(args)

    def reference_args(self, scene: str, scale: float, spp: int) -> str:
        ref = self.config["reference"]
        args = ["reference", *self._common_args(scene, scale, ref["seed"]), "--spp", str(spp),
                "--pass-spp", str(min(ref["pass_spp"], spp)), "--max-depth", str(self.config["render"]["max_depth"])]
        return shlex.join(args)

    @property
    def gpu(self) -> int:
        """GPUs a render job requests (the resource `gpu`, which the SLURM executor turns into --gpus)."""
        return 1 if self.config["variant"].startswith("cuda") else 0

    def timed_threads(self, cores: int | None) -> int:
        return self.config["timed_threads"] or cores or os.cpu_count() or 1

    # ------------------------------------------------------------------ table and figure specs
    def labels(self) -> dict[str, str]:
        return {name: entry.get("label", name) for name, entry in self.config["methods"].items()}

    def experiment_spec(self, experiment: str) -> dict:
        """What tables and figures need to lay out ``experiment`` (the order of rows and columns, labels)."""
        spec = copy.deepcopy(self.config["experiments"][experiment])
        spec["name"] = experiment
        spec["timed"] = experiment_timed(self.config, experiment)
        spec["labels"] = self.labels()
        spec["budget_points"] = [asdict(b) for b in budget_points(self.config, spec["budget"])]
        spec["crops"] = {s: self.config["scenes"][s].get("crop") for s in spec["scenes"]}
        spec["crop_fraction"] = self.config["figures"]["crop_fraction"]
        return spec


    def comparison_job(self, experiment: str) -> dict:
        """What :func:`guiding.experiments.figures.comparison` draws for ``experiment``: per scene, the first seed's
        renders at the experiment's last budget point, and the reference."""
        runs = self.experiment_runs(experiment)
        seed, tag = runs[0].seed, runs[-1].budget.tag
        rows = []
        for scene in self.config["experiments"][experiment]["scenes"]:
            chosen = [r for r in runs if r.scene == scene and r.seed == seed and r.budget.tag == tag]
            rows.append({"scene": scene, "reference": self.reference_file(self.reference_for(chosen[0]), "image.exr"),
                         "crop": self.config["scenes"][scene].get("crop"),
                         "entries": [{"label": r.label, "image": self.render_file(r, "image.exr"),
                                      "metrics": self.render_file(r, "metrics.json")} for r in chosen]})
        budget = runs[-1].budget
        budget_text = f"{int(budget.value)} spp" if budget.kind == "spp" else f"{budget.value:g} s"
        return {"title": f"{experiment}: {budget_text}, seed {seed}",
                "crop_fraction": self.config["figures"]["crop_fraction"], "rows": rows}

    def comparison_inputs(self, experiment: str) -> list[str]:
        job = self.comparison_job(experiment)
        return [f for row in job["rows"] for f in
                [row["reference"], *[e[k] for e in row["entries"] for k in ("image", "metrics")]]]




def plan(config: dict, schema: str | os.PathLike = SCHEMA, check: bool = True) -> Plan:
    """Validate ``config`` (in place: schema defaults are filled in) and expand it into a :class:`Plan`."""
    validate_schema(config, schema)
    runs, references = expand(config)
    warnings = []
    if check:
        unknown = unknown_methods(runs)
        if unknown and config["strict"]:
            raise ConfigError(f"methods: unknown to this checkout: {', '.join(unknown)} "
                              "(see `python -m guiding methods`; or set strict: false)")
        if unknown:
            warnings.append(f"methods unknown to this checkout (their renders will fail): {', '.join(unknown)}")
        missing = missing_scenes(config, runs)
        if missing and config["strict"]:
            raise ConfigError(f"scenes: not on the scene search path: {', '.join(missing)} (see `python -m guiding "
                              "scenes`; add folders with scene_dirs or $GUIDING_SCENES; or set strict: false)")
        if missing:
            warnings.append(f"scenes not on the scene search path (their jobs will fail): {', '.join(missing)}")
    return Plan(config, runs, references, warnings)


def plan_or_exit(config: dict, schema: str | os.PathLike = SCHEMA, check: bool = True, source: str = "") -> Plan:
    """:func:`plan` for the Snakefile: a bad configuration ends the process with one line on stderr."""
    try:
        result = plan(config, schema, check)
    except ConfigError as error:
        print(f"config error{f' in {source}' if source else ''}: {error}", file=sys.stderr)
        sys.exit(1)
    for warning in result.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    return result
