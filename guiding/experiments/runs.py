"""The experiment harness's experiments expanded into runs: each (experiment, scene, method, budget, seed) a
:class:`Run`, each (scene, scale) one :class:`Reference`.

A run's method is resolved once, here, into a typed :class:`~guiding.guides.methods.Method`: a name under
``methods`` with its ``set`` mapping (``{method: ours, set: {bsdf_fraction: 0.0}}``), Table 1's method with each cell's
``{spatial_resolution: S, directional_resolution: D}``, Table 2's ``{rule}-{sampler}`` grid methods. The render
gets it back as ``--method NAME --set FIELD=VALUE ...``; the run's name in paths and tables is a label, never read
back. An experiment with ``nee: true`` renders every method with next-event estimation (``--nee``; Mitsuba's
``path``, a method too, always has it); a method declared with ``path_fallback: true`` then also falls back to
``path`` where guiding does not pay (``--path-fallback``, :mod:`guiding.render.path_fallback`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

from guiding.errors import GuidingError
from guiding.experiments.configuration import ConfigError
from guiding.guides.methods import (BadSetting, Method, UnknownMethod, grid_method_name, resolve, setting_text,
                                    unknown_method)

EXPERIMENTS = ("table1", "table2", "equal_time", "convergence", "practical")
#: Experiments whose renders are timed by default (they run alone on the machine).
TIMED_BY_DEFAULT = {"equal_time", "convergence", "practical"}
#: What a run's label gets where its render does next-event estimation that the method itself does not imply.
NEE_LABEL_SUFFIX = " + NEE"

RULE_LABELS = {"expected_sarsa": "Expected SARSA", "mc": "MC", "sarsa": "SARSA"}
SAMPLER_LABELS = {"sphere_inv": "Sphere Inv", "hemi_inv": "Hemi Inv", "hemi_rej": "Hemi Rej",
                  "hemi_rej_plus": "Hemi Rej+"}


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
    spec: Method              # what the render runs: the method and the parameters set (typed)
    label: str
    seed: int
    budget: BudgetPoint
    scale: float
    timed: bool
    coords: tuple = ()        # (("S", 8), ("D", 16)) or (("rule", "mc"), ("sampler", "hemi_inv")) or (("extra", True),)
    nee: bool = False         # the experiment asks for next-event estimation (--nee)
    path_fallback: bool = False   # the method is declared with path_fallback (--path-fallback)

    @property
    def samples_emitters(self) -> bool:
        """Whether the render does next-event estimation: asked for, or Mitsuba's ``path``, which always does."""
        return self.nee or self.spec.mitsuba_integrator is not None

    @property
    def key(self) -> tuple:
        return (self.experiment, self.scene, self.method, self.budget.tag, str(self.seed))

    def dir(self, out: str) -> str:
        return f"{out}/renders/{self.experiment}/{self.scene}/{self.method}/{self.budget.tag}/seed{self.seed}"

    def method_args(self) -> list[str]:
        """The method as `python -m guiding render` takes it: ``--method NAME``, a ``--set`` per setting, and
        ``--nee`` where the experiment asks for it and the method is guided (Mitsuba's ``path`` always has it)."""
        settings = [["--set", f"{field}={setting_text(value)}"] for field, value in self.spec.settings]
        guided = self.spec.mitsuba_integrator is None
        nee = ["--nee"] if self.nee and guided else []
        fallback = ["--path-fallback"] if self.path_fallback and guided else []
        return ["--method", self.spec.name, *itertools.chain.from_iterable(settings), *nee, *fallback]

    def info(self) -> dict:
        """What metrics.json records about the run (with the budget flattened); ``cli_method`` is the method's
        label, as the render's stats.json records it; ``nee``: whether the render does next-event estimation."""
        return {"experiment": self.experiment, "scene": self.scene, "method": self.method,
                "cli_method": self.spec.label, "nee": self.samples_emitters, "label": self.label, "seed": self.seed,
                "budget": self.budget.tag,
                "budget_kind": self.budget.kind, "budget_value": self.budget.value, "scale": self.scale,
                "timed": self.timed, **dict(self.coords)}


@dataclass(frozen=True)
class Reference:
    scene: str
    scale: float
    spp: int

    def dir(self, out: str) -> str:
        return f"{out}/references/{self.scene}/x{self.scale:g}-spp{self.spp}"


def experiment_timed(config: dict, experiment: str) -> bool:
    return config["experiments"][experiment].get("timed", experiment in TIMED_BY_DEFAULT)


def budget_points(config: dict, name: str) -> list[BudgetPoint]:
    budget = config["budgets"][name]
    kind = "spp" if "spp" in budget else "seconds"
    values = budget[kind] if isinstance(budget[kind], list) else [budget[kind]]
    return [BudgetPoint(kind, v, budget.get("exclude_passes", 0)) for v in values]


def _method(name: str, settings: dict, where: str) -> Method:
    """The method ``name`` with ``settings``; a name this checkout does not know stays a name with its settings
    (:func:`unknown_methods` finds them), a setting it does not take is a ConfigError naming ``where``."""
    try:
        return resolve(name, settings)
    except UnknownMethod:
        return unknown_method(name, settings)
    except BadSetting as error:
        raise ConfigError(f"{where}: {error}") from None


def _method_entries(config: dict, experiment: str) -> list[tuple[str, Method, str, tuple]]:
    """(name, method, label, coords) of every method of ``experiment``."""
    spec = config["experiments"][experiment]
    methods = config["methods"]

    def declared(name: str, where: str) -> tuple[str, Method, str, tuple]:
        if name not in methods:
            raise ConfigError(f"experiments.{experiment}.{where}: method '{name}' is not declared under 'methods' "
                              f"(declared: {', '.join(methods)})")
        entry = methods[name]
        return name, _method(entry.get("method", name), entry.get("set", {}), f"methods.{name}"), \
            entry.get("label", name), ()

    if experiment == "table1":
        entries = []
        for S, D in itertools.product(spec["S"], spec["D"]):
            method = _method(spec["method"], {"spatial_resolution": S, "directional_resolution": D},
                             f"experiments.{experiment}.method")
            entries.append((method.label, method, f"S{S} D{D}", (("S", S), ("D", D))))
        return entries
    if experiment == "table2":
        entries = []
        for rule, sampler in itertools.product(spec["rules"], spec["samplers"]):
            name = grid_method_name(rule, sampler)
            label = f"{RULE_LABELS[rule]} {SAMPLER_LABELS[sampler]}"
            entries.append((name, _method(name, {}, f"experiments.{experiment}"), label,
                            (("rule", rule), ("sampler", sampler))))
        for name in spec.get("extra_methods", []):
            name, method, label, _ = declared(name, "extra_methods")
            entries.append((name, method, label, (("extra", True),)))
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
        nee = spec.get("nee", False)
        fallbacks = {name for name, _, _, _ in entries if config["methods"].get(name, {}).get("path_fallback")}
        if fallbacks and not nee:
            raise ConfigError(f"{where}: method '{sorted(fallbacks)[0]}' falls back to Mitsuba's path "
                              "(path_fallback), which needs next-event estimation: set nee: true")
        if nee:
            entries = [(name, method, label if method.mitsuba_integrator else label + NEE_LABEL_SUFFIX, coords)
                       for name, method, label, coords in entries]
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
            for (name, method, label, coords), point, seed in itertools.product(entries, points,
                                                                                 spec.get("seeds", config["seeds"])):
                runs.append(Run(experiment, scene, name, method, label, seed, point, scale,
                                experiment_timed(config, experiment), coords, nee, name in fallbacks))
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


def unknown_methods(runs: list[Run]) -> list[str]:
    """Methods of the runs that this checkout does not know."""
    return sorted({r.spec.name for r in runs if not r.spec.known})
