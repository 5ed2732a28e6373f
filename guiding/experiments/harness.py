"""The experiment harness behind the ``Snakefile``: configuration checks, experiments expanded into runs, paths.

The Snakefile stays thin: it asks :func:`plan` for a :class:`Plan` (the validated configuration, every run, every
reference) and turns it into rules. Everything here is plain Python (no Dr.Jit), so it is quick to import and to
test.

Layout of what a configuration produces, under its ``out`` folder::

    references/{scene}/x{scale}-spp{spp}/image.exr, stats.json, preview.png      one per scene and scale
    renders/{experiment}/{scene}/{method}/{budget}/seed{seed}/image.exr, stats.json, preview.png, metrics.json
    tables/{experiment}.csv, .md, _runs.csv        figures/*.png        provenance.json, provenance.html
    logs/...                                        one log per job

``{budget}`` is ``spp1024`` for a samples-per-pixel budget and ``10s`` for a seconds budget.

Command line (used by the rules, handy by hand)::

    python -m guiding.experiments.harness path [--configfile F] EXPERIMENT SCENE METHOD [--seed S] [--budget B]
    python -m guiding.experiments.harness runs [--configfile F]          # every run of the configuration, one path a line
    python -m guiding.experiments.harness evaluate IMAGE STATS REFERENCE --run JSON --out metrics.json
    python -m guiding.experiments.harness provenance --config JSON --out-json F --out-html F STATS...
    python -m guiding.experiments.harness cause LOG --status N             # why a job failed, on stderr (the rules call it)
"""

from __future__ import annotations

import argparse
import copy
import itertools
import json
import os
import shlex
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

from guiding.errors import GuidingError

PROJECT_ROOT = Path(__file__).resolve().parents[2]
SCHEMA = PROJECT_ROOT / "config" / "schema.yaml"
DEFAULT_CONFIG = PROJECT_ROOT / "config" / "config.yaml"

EXPERIMENTS = ("table1", "table2", "equal_time", "convergence")
#: Experiments whose renders are timed by default (they run alone on the machine).
TIMED_BY_DEFAULT = {"equal_time", "convergence"}

RULE_LABELS = {"expected_sarsa": "Expected SARSA", "mc": "MC", "sarsa": "SARSA"}
SAMPLER_LABELS = {"sphere_inv": "Sphere Inv", "hemi_inv": "Hemi Inv", "hemi_rej": "Hemi Rej",
                  "hemi_rej_plus": "Hemi Rej+"}

#: Wildcard patterns (also the Snakefile's wildcard constraints).
NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9_.+-]*"
BUDGET_PATTERN = r"spp[0-9]+|[0-9]+(?:\.[0-9]+)?s"
NEVER_PATTERN = r"(?!x)x"


class ConfigError(GuidingError):
    """The configuration is wrong; the message names the key and says what is expected."""


# ----------------------------------------------------------------------------------------------- validation

def load_config(path: str | os.PathLike) -> dict:
    import yaml

    try:
        with open(path) as file:
            data = yaml.safe_load(file)
    except OSError as error:
        raise ConfigError(f"cannot read config '{path}': {error.strerror}") from None
    except yaml.YAMLError as error:
        raise ConfigError(f"config '{path}' is not valid YAML: {str(error).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config '{path}' must be a mapping of keys to values")
    return data


def _key_path(parts) -> str:
    text = ""
    for part in parts:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "(top level)"


def _format_schema_error(error) -> str:
    """One line naming the offending key for a jsonschema ValidationError."""
    where = _key_path(error.absolute_path)
    if error.validator == "additionalProperties":
        allowed = sorted(error.schema.get("properties", {}))
        unknown = sorted(set(error.instance) - set(allowed)) if isinstance(error.instance, dict) else []
        if unknown and allowed:
            keys = ", ".join(f"'{k}'" for k in unknown)
            return f"{where}: unknown key {keys} (allowed: {', '.join(allowed)})"
        if unknown:  # a name → object mapping (scenes, methods, budgets): the value is what is wrong
            return f"{where}.{unknown[0]}: {error.message}"
    if error.validator == "required":
        return f"{where}: {error.message}"
    if error.validator == "enum":
        choices = ", ".join(json.dumps(c) for c in error.validator_value)
        return f"{where}: {json.dumps(error.instance)} is not one of {choices}"
    if error.validator == "oneOf" and isinstance(error.instance, dict) and {"spp", "seconds"} & set(error.schema.get(
            "properties", {})):
        given = sorted({"spp", "seconds"} & set(error.instance))
        return f"{where}: give exactly one of 'spp' and 'seconds' (got {' and '.join(given) or 'neither'})"
    if error.validator == "propertyNames":
        return f"{where}: bad name {json.dumps(error.instance)} (letters, digits and _ . + - only)"
    return f"{where}: {error.message}"


def validate_schema(config: dict, schema: str | os.PathLike = SCHEMA) -> dict:
    """Validate ``config`` against the JSON schema with ``snakemake.utils.validate`` (which fills in the schema's
    defaults, in place); a failure is one :class:`ConfigError` line naming the key."""
    from snakemake.exceptions import WorkflowError
    from snakemake.utils import validate

    try:
        validate(config, str(Path(schema).resolve()))
    except WorkflowError:
        import jsonschema
        from snakemake.common.configfile import _load_configfile

        schema_dict = _load_configfile(str(schema), filetype="Schema")
        best = jsonschema.exceptions.best_match(jsonschema.Draft202012Validator(schema_dict).iter_errors(config))
        raise ConfigError(_format_schema_error(best) if best is not None else "config does not match its schema") \
            from None
    return config


# ------------------------------------------------------------------------------------------------- the plan

@dataclass(frozen=True)
class BudgetPoint:
    kind: str                 # "spp" or "seconds"
    value: float
    exclude_passes: int = 0

    @property
    def tag(self) -> str:
        return f"spp{int(self.value)}" if self.kind == "spp" else f"{self.value:g}s"

    def cli_args(self) -> list[str]:
        if self.kind == "spp":
            return ["--spp", str(int(self.value))]
        return ["--seconds", f"{self.value:g}", "--exclude-passes", str(self.exclude_passes)]


@dataclass(frozen=True)
class Run:
    """One render: an experiment's (scene, method, budget, seed) and what it takes to make it."""

    experiment: str
    scene: str
    method: str               # name in paths and tables
    cli_method: str           # what `python -m guiding render --method` gets
    label: str
    seed: int
    budget: BudgetPoint
    scale: float
    timed: bool
    coords: tuple = ()        # (("S", 8), ("D", 16)) or (("rule", "mc"), ("sampler", "hemi_inv")) or (("extra", True),)

    @property
    def key(self) -> tuple:
        return (self.experiment, self.scene, self.method, self.budget.tag, str(self.seed))

    def dir(self, out: str) -> str:
        return f"{out}/renders/{self.experiment}/{self.scene}/{self.method}/{self.budget.tag}/seed{self.seed}"

    def info(self) -> dict:
        """What metrics.json records about the run (with the budget flattened)."""
        return {"experiment": self.experiment, "scene": self.scene, "method": self.method,
                "cli_method": self.cli_method, "label": self.label, "seed": self.seed, "budget": self.budget.tag,
                "budget_kind": self.budget.kind, "budget_value": self.budget.value, "scale": self.scale,
                "timed": self.timed, **dict(self.coords)}


@dataclass(frozen=True)
class Reference:
    scene: str
    scale: float
    spp: int

    def dir(self, out: str) -> str:
        return f"{out}/references/{self.scene}/x{self.scale:g}-spp{self.spp}"


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
            raise ConfigError(f"no run {'/'.join(key)} in this configuration (see `python -m guiding.experiments.harness runs`)")\
                from None

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
        args = ["render", *self._common_args(run.scene, run.scale, run.seed), "--method", run.cli_method,
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
        """What :func:`guiding.experiments.figures.comparison` draws for ``experiment``: per scene, the first seed's renders at
        the experiment's last budget point, and the reference."""
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


def experiment_timed(config: dict, experiment: str) -> bool:
    return config["experiments"][experiment].get("timed", experiment in TIMED_BY_DEFAULT)


def budget_points(config: dict, name: str) -> list[BudgetPoint]:
    budget = config["budgets"][name]
    kind = "spp" if "spp" in budget else "seconds"
    values = budget[kind] if isinstance(budget[kind], list) else [budget[kind]]
    return [BudgetPoint(kind, v, budget.get("exclude_passes", 0)) for v in values]


def _method_entries(config: dict, experiment: str) -> list[tuple[str, str, str, tuple]]:
    """(name, cli method, label, coords) of every method of ``experiment``."""
    spec = config["experiments"][experiment]
    methods = config["methods"]

    def declared(name: str, where: str) -> tuple[str, str, str, tuple]:
        if name not in methods:
            raise ConfigError(f"experiments.{experiment}.{where}: method '{name}' is not declared under 'methods' "
                              f"(declared: {', '.join(methods)})")
        return name, methods[name].get("method", name), methods[name].get("label", name), ()

    def fill(**fields) -> str:
        try:
            return spec["method"].format(**fields)
        except (KeyError, IndexError, ValueError):
            names = ", ".join("{" + f + "}" for f in fields)
            raise ConfigError(f"experiments.{experiment}.method: bad template {spec['method']!r} "
                              f"(fields: {names})") from None

    if experiment == "table1":
        entries = []
        for S, D in itertools.product(spec["S"], spec["D"]):
            name = fill(S=S, D=D)
            entries.append((name, name, f"S{S} D{D}", (("S", S), ("D", D))))
        return entries
    if experiment == "table2":
        entries = []
        for rule, sampler in itertools.product(spec["rules"], spec["samplers"]):
            name = fill(rule=rule, sampler=sampler)
            label = f"{RULE_LABELS[rule]} {SAMPLER_LABELS[sampler]}"
            entries.append((name, name, label, (("rule", rule), ("sampler", sampler))))
        for name in spec.get("extra_methods", []):
            name, cli, label, _ = declared(name, "extra_methods")
            entries.append((name, cli, label, (("extra", True),)))
        return entries
    return [declared(name, "methods") for name in spec["methods"]]


def expand(config: dict) -> tuple[list[Run], dict[tuple[str, float], Reference]]:
    """Every run and every reference of a validated configuration; cross-references are checked here."""
    runs: list[Run] = []
    references: dict[tuple[str, float], Reference] = {}
    for experiment in EXPERIMENTS:
        if experiment not in config["experiments"]:
            continue
        spec = config["experiments"][experiment]
        where = f"experiments.{experiment}"
        if spec["budget"] not in config["budgets"]:
            raise ConfigError(f"{where}.budget: '{spec['budget']}' is not declared under 'budgets' "
                              f"(declared: {', '.join(config['budgets'])})")
        points = budget_points(config, spec["budget"])
        if experiment != "convergence" and len(points) > 1:
            raise ConfigError(f"{where}.budget: '{spec['budget']}' has several values; only the convergence "
                              "experiment takes a list")
        entries = _method_entries(config, experiment)
        names = [e[0] for e in entries]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ConfigError(f"{where}: method name {duplicates[0]!r} occurs twice (its runs would share a folder)")
        for scene in spec["scenes"]:
            if scene not in config["scenes"]:
                raise ConfigError(f"{where}.scenes: scene '{scene}' is not declared under 'scenes' "
                                  f"(declared: {', '.join(config['scenes'])})")
            scene_cfg = config["scenes"][scene]
            scale = float(spec.get("scale", scene_cfg["scale"]))
            ref_spp = scene_cfg.get("reference_spp", config["reference"]["spp"])
            references.setdefault((scene, scale), Reference(scene, scale, ref_spp))
            for (name, cli, label, coords), point, seed in itertools.product(entries, points,
                                                                              spec.get("seeds", config["seeds"])):
                runs.append(Run(experiment, scene, name, cli, label, seed, point, scale,
                                experiment_timed(config, experiment), coords))
    return runs, references


def missing_scenes(config: dict, runs: list[Run]) -> list[str]:
    """Scenes of the runs that are not on the scene search path."""
    from guiding.scenes import find_scene

    missing = []
    for scene in sorted({r.scene for r in runs}):
        try:
            find_scene(scene, config["scene_dirs"])
        except GuidingError:
            missing.append(scene)
    return missing


def check_methods(runs: list[Run]) -> list[str]:
    """Command-line methods this checkout does not know (empty when the method registry cannot be imported)."""
    try:
        from guiding.guides import methods as registry
    except Exception:  # noqa: BLE001 - a registry being edited must not stop a dry run
        return []
    check = getattr(registry, "check_method", None)
    unknown = []
    for cli in sorted({r.cli_method for r in runs}):
        if check is not None:
            try:
                check(cli)
            except registry.UnknownMethod:
                unknown.append(cli)
            except Exception:  # noqa: BLE001
                pass
        elif cli not in registry.method_names():
            unknown.append(cli)
    return unknown


def plan(config: dict, schema: str | os.PathLike = SCHEMA, check: bool = True) -> Plan:
    """Validate ``config`` (in place: schema defaults are filled in) and expand it into a :class:`Plan`."""
    validate_schema(config, schema)
    runs, references = expand(config)
    warnings = []
    if check:
        unknown = check_methods(runs)
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


def main(argv: list[str] | None = None) -> int:
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

    args = parser.parse_args(argv)
    if args.command == "cause":
        text = Path(args.log).read_text(errors="replace") if Path(args.log).is_file() else ""
        print(f"job failed: {job_failure(text, args.status)} (log: {args.log})", file=sys.stderr)
        return 0
    from guiding import strict_json
    from guiding.experiments.evaluation import evaluate_run
    from guiding.imageio import write_text_atomic
    from guiding.provenance import provenance, provenance_html

    try:
        if args.command == "path":
            the_plan = _load_plan(args.configfile)
            found = [r for r in the_plan.runs if (r.experiment, r.scene, r.method) == (args.experiment, args.scene,
                                                                                        args.method)
                     and (args.seed is None or r.seed == args.seed)
                     and (args.budget is None or r.budget.tag == args.budget)]
            if not found:
                raise ConfigError(f"no run ({args.experiment}, {args.scene}, {args.method}) in this configuration")
            print(the_plan.render_file(found[0], "image.exr"))
        elif args.command == "runs":
            the_plan = _load_plan(args.configfile)
            for run in the_plan.runs:
                print(the_plan.render_file(run, "image.exr"))
        elif args.command == "evaluate":
            result = evaluate_run(args.image, args.stats, args.reference, args.out, json.loads(args.run))
            print(f"mae {result['mae']} relmse {result['relmse']} -> {args.out}")
        elif args.command == "provenance":
            configfiles = [p for p in args.configfiles.split(os.pathsep) if p]
            data = provenance(json.loads(args.config), args.stats, configfiles)
            write_text_atomic(args.out_json, strict_json.dumps(data))
            write_text_atomic(args.out_html, provenance_html(data))
    except GuidingError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
