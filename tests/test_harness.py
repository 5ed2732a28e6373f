"""The Snakemake experiment harness: configuration checks, the expansion into runs (methods as typed values), and the
workflow itself run end to end on the CI configuration (tiny scenes and budgets). Tables and figures from synthetic
runs: tests/test_harness_outputs.py.

The end-to-end tests share one run of `snakemake --cores 2 --configfile config/ci.yaml` in a temporary working
directory (`--directory`), so the repository is never written to.
"""

from __future__ import annotations

import copy
import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from guiding import imageio
from guiding.experiments import figures, harness
from guiding.experiments.configuration import ConfigError, load_config
from guiding.experiments.plan import plan
from workflow_runs import CI_CONFIG, ROOT, checkout_env, snakemake, snakemake_command

FULL_CONFIG = ROOT / "config" / "config.yaml"


def job_counts(output: str) -> dict[str, int]:
    """The 'Job stats' table of a Snakemake dry run: rule -> number of jobs."""
    import re

    table = output.rsplit("Job stats:", 1)[1].split("\n\n", 1)[0]
    return {rule: int(n) for rule, n in re.findall(r"^(\w+)\s+(\d+)$", table, flags=re.MULTILINE)}


def ci_config() -> dict:
    return load_config(CI_CONFIG)


# ------------------------------------------------------------------------------------ configuration, plan

def test_full_config_expands_into_the_papers_experiments():
    the_plan = plan(load_config(FULL_CONFIG), check=False)
    by_experiment = {e: the_plan.experiment_runs(e) for e in the_plan.experiments()}
    table1 = {r.method for r in by_experiment["table1"]}
    assert table1 == {f"ours-S{S}-D{D}" for S in (32, 16, 8, 4) for D in (32, 16, 8, 4)}
    table2 = {r.method for r in by_experiment["table2"]}
    assert {"mc-sphere_inv", "sarsa-hemi_rej_plus", "expected_sarsa-hemi_inv", "brdf", "quadtree-grid"} <= table2
    assert len(table2) == 3 * 4 + 2
    assert {r.method for r in by_experiment["equal_time"]} == {"brdf", "quadtree-grid", "ours-no-rejopt",
                                                               "ours-expected", "ours", "sdtree"}
    assert all(r.timed for r in by_experiment["equal_time"] + by_experiment["convergence"])
    assert not any(r.timed for r in by_experiment["table1"] + by_experiment["table2"])
    assert {r.budget.tag for r in by_experiment["table1"]} == {"spp1024"}
    assert {r.budget.tag for r in by_experiment["equal_time"]} == {"10s"}
    assert len({r.budget.tag for r in by_experiment["convergence"]}) > 3
    run = next(r for r in by_experiment["equal_time"] if r.scene == "veach-ajar" and r.method == "ours")
    assert the_plan.render_file(run, "image.exr") == "results/full/renders/equal_time/veach-ajar/ours/10s/seed0/image.exr"
    assert "--seconds 10 --exclude-passes 10" in the_plan.render_args(run)
    assert "--fixed-passes" not in the_plan.render_args(run)      # passes grow unless the config says otherwise
    fixed = load_config(FULL_CONFIG)
    fixed["render"]["growing_passes"] = False
    assert "--fixed-passes" in plan(fixed, check=False).render_args(run)
    ref = the_plan.reference_for(run)
    assert the_plan.reference_file(ref, "image.exr") == "results/full/references/veach-ajar/x0.25-spp16384/image.exr"
    assert len({r.key for r in the_plan.runs}) == len(the_plan.runs)


def test_ci_config_uses_only_methods_that_exist():
    the_plan = plan(ci_config(), check=True)
    assert the_plan.warnings == [] and the_plan.config["strict"] is True
    assert {r.spec.label for r in the_plan.runs} == {"brdf", "ours", "ours-expected", "ours-S4-D4", "ours-S4-D8",
                                                     "ours-S8-D4", "ours-S8-D8", "mc-sphere_inv", "mc-hemi_rej_plus",
                                                     "sarsa-sphere_inv", "sarsa-hemi_rej_plus", "path"}
    assert {r.scene for r in the_plan.runs} == {"cornell", "door-ajar"}


def _mutate(path, value):
    def apply(config):
        node = config
        for key in path[:-1]:
            node = node[key]
        if value is KeyError:
            del node[path[-1]]
        else:
            node[path[-1]] = value
    return apply


@pytest.mark.parametrize("path, value, message", [
    (("experiments", "table1", "SS"), [4], "experiments.table1: unknown key 'SS'"),
    (("experiments", "table1", "S"), [5], "experiments.table1.S[0]: 5 is not one of"),
    (("variant",), "cuda", "variant: \"cuda\" is not one of"),
    (("scenes", "cornell", "scal"), 0.1, "scenes.cornell: unknown key 'scal'"),
    (("budgets", "equal_spp"), {"spp": 16, "seconds": 2}, "budgets.equal_spp: give exactly one of 'spp' and 'seconds'"),
    (("budgets", "equal_spp", "spp"), 0, "budgets.equal_spp.spp: 0 is less than the minimum of 1"),
    (("out",), KeyError, "'out' is a required property"),
    (("experiments", "table3"), {}, "experiments: unknown key 'table3'"),
    (("experiments", "equal_time", "methods"), ["nope"], "method 'nope' is not declared under 'methods'"),
    (("experiments", "equal_time", "scenes"), ["kitchen"], "scene 'kitchen' is not declared under 'scenes'"),
    (("experiments", "equal_time", "budget"), "fast", "budget: 'fast' is not declared under 'budgets'"),
    (("budgets", "equal_spp", "spp"), [8, 16], "only the convergence experiment takes a list"),
    (("methods", "nope"), {"method": "no-such-method"}, None),
    (("methods", "ours", "set"), {"spatial_res": 4}, "methods.ours: method 'ours' has no parameter 'spatial_res'"),
    (("methods", "ours", "set"), {"spatial_resolution": "4"},
     "methods.ours: method 'ours': spatial_resolution='4' is not an integer"),
    (("methods", "ours", "set"), {"spatial_resolution": 0}, "methods.ours: method 'ours' with spatial_resolution=0"),
    (("methods", "ours", "set"), {"rule": ["mc"]}, "methods.ours.set.rule: ['mc'] is not of type"),
    (("experiments", "practical", "nee"), "yes", "experiments.practical.nee: 'yes' is not of type 'boolean'"),
    (("methods", "path", "set"), {"max_depth": 4}, "methods.path: method 'path' takes no parameters"),
    (("methods", "brdf", "set"), {"bsdf_fraction": 0.5}, "methods.brdf: method 'brdf' takes no parameters"),
    (("experiments", "table1", "method"), "brdf", "experiments.table1.method: method 'brdf' takes no parameters"),
    (("experiments", "table1", "method"), "sdtree", "experiments.table1.method: method 'sdtree' has no parameter"),
])
def test_bad_config_gives_one_message_naming_the_key(path, value, message):
    config = ci_config()
    _mutate(path, value)(config)
    if message is None:  # an unknown command-line method under strict: true
        config["experiments"]["equal_time"]["methods"] = ["brdf", "nope"]
        message = "methods: unknown to this checkout: no-such-method"
    with pytest.raises(ConfigError) as error:
        plan(config)
    assert message in str(error.value) and "\n" not in str(error.value)


def test_scene_missing_from_the_search_path_is_rejected_when_strict():
    config = ci_config()
    config["scenes"]["no-such-scene"] = {"scale": 0.1}
    config["experiments"]["equal_time"]["scenes"] = ["cornell", "no-such-scene"]
    with pytest.raises(ConfigError, match="scenes: not on the scene search path: no-such-scene"):
        plan(copy.deepcopy(config))
    config["strict"] = False
    assert any("no-such-scene" in w for w in plan(config).warnings)


def test_name_collisions_are_rejected():
    config = ci_config()
    config["methods"]["mc-sphere_inv"] = {}   # a Table 2 cell again, below the grid
    config["experiments"]["table2"]["extra_methods"] = ["brdf", "mc-sphere_inv"]
    with pytest.raises(ConfigError, match="'mc-sphere_inv' occurs twice"):
        plan(config)


def test_methods_are_typed_values_the_render_gets_back():
    """A run's method is resolved once, with its settings typed: Table 1's cells set S and D of its method (their
    names are labels: the same folders as before), a declared method's `set` reaches the render as `--set`, and the
    command line resolves the render's arguments into the same value."""
    from guiding.cli.parser import parse_args
    from guiding.guides.methods import resolve

    config = ci_config()
    config["methods"]["ours-pure"] = {"method": "ours", "set": {"bsdf_fraction": 0, "statistics": True},
                                      "label": "Ours, no BSDF share"}
    config["methods"]["ours-coarse"] = {"method": "ours-S4"}    # the shorthand, resolved at the edge
    config["experiments"]["equal_time"]["methods"] += ["ours-pure", "ours-coarse"]
    the_plan = plan(config)
    table1 = {r.method: r for r in the_plan.experiment_runs("table1")}
    assert set(table1) == {"ours-S4-D4", "ours-S4-D8", "ours-S8-D4", "ours-S8-D8"}
    cell = table1["ours-S8-D4"]
    assert cell.spec == resolve("ours", {"spatial_resolution": 8, "directional_resolution": 4})
    assert (cell.spec.parameters.spatial_resolution, cell.spec.parameters.directional_resolution) == (8, 4)
    assert "--method ours --set spatial_resolution=8 --set directional_resolution=4 " in the_plan.render_args(cell)
    runs = {r.method: r for r in the_plan.experiment_runs("equal_time") if r.scene == "cornell"}
    pure = runs["ours-pure"]
    assert pure.spec.parameters.bsdf_fraction == 0.0 and pure.spec.parameters.statistics is True
    assert "--method ours --set bsdf_fraction=0.0 --set statistics=true " in the_plan.render_args(pure)
    assert pure.info()["cli_method"] == pure.spec.label == "ours (bsdf_fraction=0.0, statistics=True)"
    assert runs["ours-coarse"].spec == resolve("ours", {"spatial_resolution": 4})
    for run in (cell, pure, runs["ours-coarse"], runs["brdf"]):
        args = parse_args([*the_plan.render_args(run).split(), "--out", "unused"])
        assert args.method == run.spec


def test_unknown_method_is_a_warning_unless_strict():
    """A configuration written for another checkout: its unknown method (with its settings) still plans, warns,
    and its render gets the name and settings as given."""
    config = ci_config()
    config.update(strict=False)
    config["methods"]["future"] = {"method": "ours-next", "set": {"spatial_resolution": 4}}
    config["experiments"]["equal_time"]["methods"] = ["brdf", "future"]
    the_plan = plan(config)
    assert the_plan.warnings == ["methods unknown to this checkout (their renders will fail): ours-next"]
    run = next(r for r in the_plan.runs if r.method == "future")
    assert "--method ours-next --set spatial_resolution=4 " in the_plan.render_args(run)
    assert run.spec.label == "ours-next-S4"


def test_harness_path_command(capsys):
    assert harness.main(["path", "--configfile", str(CI_CONFIG), "equal_time", "door-ajar", "brdf"]) == 0
    assert capsys.readouterr().out.strip() == "results/ci/renders/equal_time/door-ajar/brdf/1s/seed0/image.exr"
    assert harness.main(["path", "--configfile", str(CI_CONFIG), "equal_time", "door-ajar", "sdtree"]) == 2



# ------------------------------------------------------------------------------- the workflow, end to end

def _finite(frame: pd.DataFrame, column: str) -> bool:
    return bool(np.isfinite(frame[column].astype(float)).all())


def test_ci_workflow_runs_end_to_end(ci_run):
    workdir, seconds = ci_run
    out = workdir / "results" / "ci"
    t1 = pd.read_csv(out / "tables" / "table1.csv")
    assert sorted(t1[["scene", "S", "D"]].itertuples(index=False, name=None)) == [
        ("cornell", 4, 4), ("cornell", 4, 8), ("cornell", 8, 4), ("cornell", 8, 8)]
    assert t1.set_index(["S", "D"]).paper_mae[(8, 8)] == pytest.approx(0.0362)
    # The guide works from the second pass: cells of BSDF sampling only (same seed) would all be equal.
    assert t1.mae.nunique() == len(t1), t1.mae.tolist()
    t2 = pd.read_csv(out / "tables" / "table2.csv")
    assert {(r.rule, r.sampler) for r in t2.itertuples() if isinstance(r.rule, str)} == {
        ("mc", "sphere_inv"), ("mc", "hemi_rej_plus"), ("sarsa", "sphere_inv"), ("sarsa", "hemi_rej_plus")}
    et = pd.read_csv(out / "tables" / "equal_time.csv")
    assert sorted(et[["scene", "method"]].itertuples(index=False, name=None)) == [
        (scene, method) for scene in ("cornell", "door-ajar") for method in ("brdf", "ours", "ours-expected")]
    assert (et.spp > 16).all()  # a 1 s budget reaches more samples than the 16 spp of the equal-spp runs
    # Convergence: one 32-spp render per method, its snapshots at 8 and 16 spp give the rest of the curve.
    conv = pd.read_csv(out / "tables" / "convergence.csv")
    assert sorted(conv[["method", "budget"]].itertuples(index=False, name=None)) == [
        (method, f"spp{spp}") for method in ("brdf", "ours") for spp in (16, 32, 8)]
    conv_metrics = []
    for method in ("brdf", "ours"):
        folder = out / "renders" / "convergence" / "door-ajar" / method / "spp32" / "seed0"
        stats = json.loads((folder / "stats.json").read_text())
        assert [(s["spp"], s["file"]) for s in stats["snapshots"]] == [
            (spp, f"image_snap{spp:05d}.exr") for spp in (8, 16, 32)]
        assert all((folder / s["file"]).stat().st_mode & 0o777 == 0o644 for s in stats["snapshots"])
        conv_metrics.append(json.loads((folder / "metrics.json").read_text()))
        assert [c["spp"] for c in conv_metrics[-1]["curve"]] == [8, 16, 32]
    series = figures.convergence_series(conv_metrics)  # what convergence.png draws: each render's whole curve
    assert {label: len(points) for label, points in series["door-ajar"].items()} == {"BRDF": 3, "Ours": 3}
    for frame in (t1, t2, et, conv):
        assert _finite(frame, "mae") and _finite(frame, "relmse") and (frame.mae > 0).all()
        assert (frame.nonfinite_pixels == 0).all()
    for experiment in ("table1", "table2", "equal_time", "convergence", "practical"):
        runs = pd.read_csv(out / "tables" / f"{experiment}_runs.csv")
        assert runs.host.notna().all() and runs.device.str.len().gt(0).all() and (runs.variant == "llvm_ad_rgb").all()
        for metric in ("flip", "mse", "smape", "relmse_trimmed"):   # beside the paper's MAE, for every render
            assert _finite(runs, metric) and (runs[metric] > 0).all(), (experiment, metric)
        assert (runs.flip < 1).all() and (runs.smape < 1).all() and (runs.relmse_trimmed <= runs.relmse).all()
        assert (out / "tables" / f"{experiment}.md").read_text().startswith("# ")
    timed = pd.read_csv(out / "tables" / "equal_time_runs.csv")
    assert (timed.threads == 2).all()  # a timed render took every core given (--cores 2)
    assert (pd.read_csv(out / "tables" / "table1_runs.csv").threads == 1).all()
    assert "| **cornell** |" in (out / "tables" / "equal_time.md").read_text()
    for name in ("table1_heatmap", "equal_time_comparison", "convergence", "practical_comparison"):
        assert (out / "figures" / f"{name}.png").stat().st_size > 1000
    prov = json.loads((out / "provenance.json").read_text())
    assert prov["config"]["out"] == "results/ci" and prov["versions"]["mitsuba"]
    assert {r["experiment"] for r in prov["renders"]} == {"table1", "table2", "equal_time", "convergence",
                                                          "practical", "reference"}
    assert seconds < 300


def test_ci_practical_table_is_each_method_against_path(ci_run):
    """The practical experiment end to end: `ours` renders with next-event estimation (the render says so), Mitsuba's
    `path` renders through the same command, timed, and the table's efficiency is, as docs/harness.md defines it,
    path's MAE²·t over the method's (t: the counted seconds), 1 for path; the counted spp leave out the excluded
    leading pass."""
    workdir, _ = ci_run
    out = workdir / "results" / "ci"
    table = pd.read_csv(out / "tables" / "practical.csv").set_index("method")
    assert list(table.index) == ["path", "ours", "ours-fallback"] and table.nee.all()
    assert table.label.tolist() == ["Mitsuba path", "Ours + NEE", "Ours (path fallback) + NEE"]
    metrics = {method: json.loads((out / "renders" / "practical" / "cornell" / method / "1s" / "seed0" /
                                   "metrics.json").read_text()) for method in ("path", "ours")}
    cost = {m: r["mae"] ** 2 * r["stats"]["budget_seconds_counted"] for m, r in metrics.items()}
    assert table.loc["path", "efficiency_vs_path"] == pytest.approx(1.0)
    assert table.loc["ours", "efficiency_vs_path"] == pytest.approx(cost["path"] / cost["ours"], rel=1e-5)
    assert table.loc["ours", "efficiency_vs_path"] != pytest.approx(1.0, abs=1e-3)
    for method, run in metrics.items():
        assert run["nee"] is True and run["stats"]["nee"] is True and run["cli_method"] == method
        assert run["stats"]["budget_seconds_counted"] >= 1.0 and table.loc[method, "mae"] == pytest.approx(run["mae"], rel=1e-5)
        assert table.loc[method, "spp_counted"] == run["stats"]["spp"] - 8    # one excluded pass of 8 spp
    assert imageio.read_exr_metadata(out / "renders" / "practical" / "cornell" / "ours" / "1s" / "seed0" /
                                     "image.exr")["parameters"]["nee"] is True
    et = pd.read_csv(out / "tables" / "equal_time.csv")
    assert not et.nee.any() and (et.spp_counted == et.spp - 8).all()
    text = (out / "tables" / "practical.md").read_text()
    assert "| scene | Mitsuba path | Ours + NEE | Ours (path fallback) + NEE |" in text and "| **cornell** | 1× |" in text
    assert "**geometric mean**" in text and "Next-event estimation in every render." in text
    # The fallback's decision: in stats.json, in the runs table, and its count in the practical table.
    fallback = json.loads((out / "renders" / "practical" / "cornell" / "ours-fallback" / "1s" / "seed0" /
                           "metrics.json").read_text())["stats"]["path_fallback"]
    assert fallback["chosen"] in ("guide", "path") and fallback["guide_mae"] > 0 and fallback["path_mae"] > 0
    runs = pd.read_csv(out / "tables" / "practical_runs.csv").set_index("method")
    assert runs.loc["ours-fallback", "fallback"] == fallback["chosen"] and pd.isna(runs.loc["ours", "fallback"])
    assert f"| **cornell** |  |  | {fallback['chosen']} 1/1 |" in text
    log = (out / "logs" / "render_timed" / "practical" / "cornell" / "ours" / "1s" / "seed0.log").read_text()
    assert "ours with nee on cornell: " in log


def test_ci_outputs_are_strict_json_and_carry_their_metadata(ci_run):
    """Every JSON file parses without NaN/Infinity (a reference's hit rate is null); every EXR says what made it;
    the jobs' logs show their progress (plain lines, with an ETA) and no error."""
    workdir, _ = ci_run
    out = workdir / "results" / "ci"

    def refuse(token):
        raise ValueError(f"non-standard JSON token {token}")

    files = sorted(out.rglob("*.json"))
    assert len(files) > 30   # every stats.json and metrics.json, provenance.json
    for path in files:
        json.loads(path.read_text(), parse_constant=refuse)
    reference = next((out / "references").rglob("stats.json"))
    assert json.loads(reference.read_text())["hit_rate"] is None
    render = out / "renders" / "table2" / "door-ajar" / "mc-sphere_inv" / "spp16" / "seed0"
    metadata = imageio.read_exr_metadata(render / "image.exr")
    assert (metadata["method"], metadata["scene"], metadata["seed"], metadata["spp"]) == ("mc-sphere_inv",
                                                                                          "door-ajar", 0, 16)
    assert metadata["variant"] == "llvm_ad_rgb" and metadata["threads"] == 1 and metadata["versions"]["mitsuba"]
    assert metadata["guide"]["rule"] == "mc" and metadata["parameters"]["scale"] == 0.1
    assert imageio.read_exr_metadata(reference.parent / "image.exr")["method"] == "reference-path"
    log = (out / "logs" / "render" / "table2" / "door-ajar" / "mc-sphere_inv" / "spp16" / "seed0.log").read_text()
    assert "render: 16/16 spp (100%), " in log and "ETA" in log and "\r" not in log


def test_second_run_has_nothing_to_do(ci_run):
    workdir, _ = ci_run
    result = snakemake("-n", "--configfile", CI_CONFIG, "--directory", workdir)
    assert result.returncode == 0 and "Nothing to be done" in result.stdout + result.stderr


def test_single_run_rerun_redoes_that_render_and_what_depends_on_it(ci_run):
    workdir, _ = ci_run
    target = "results/ci/renders/equal_time/door-ajar/brdf/1s/seed0/image.exr"
    result = snakemake("-n", "--configfile", CI_CONFIG, "--directory", workdir, "--forcerun", target)
    assert result.returncode == 0, result.stderr[-2000:]
    counts = job_counts(result.stdout)
    assert counts["render_timed"] == 1 and counts["evaluate"] == 1 and "render" not in counts
    assert counts["table"] == 1 and "reference" not in counts


def _report_files(report: Path) -> dict[str, bytes]:
    """File name -> content of every result embedded in a Snakemake HTML report (as data URIs)."""
    import base64
    import re

    return {name: base64.b64decode(data) for name, data in
            re.findall(r"filename=([^;\"]+);base64,([A-Za-z0-9+/=]+)", report.read_text())}


def test_report_after_the_run_holds_every_table_figure_and_the_provenance(ci_run):
    """`snakemake --report FILE` after the run, without repeating --configfile: it reports the configuration that
    ran (the issue: "table1.csv marked for report but does not exist")."""
    workdir, _ = ci_run
    report = workdir / "report.html"
    result = snakemake("--directory", workdir, "--report", report)
    assert result.returncode == 0, result.stderr[-2000:]
    embedded = _report_files(report)
    out = workdir / "results" / "ci"
    expected = [out / "tables" / f"{e}{suffix}" for e in ("table1", "table2", "equal_time", "convergence",
                                                          "practical") for suffix in (".csv", ".md", "_runs.csv")]
    expected += [out / "figures" / f"{name}.png" for name in ("table1_heatmap", "equal_time_comparison",
                                                               "convergence", "practical_comparison")]
    expected.append(out / "provenance.html")
    for path in expected:
        assert embedded.get(path.name) == path.read_bytes(), path.name
    assert b"| **cornell** |" in embedded["equal_time.md"]   # the paper's layout, in the report


def test_a_failing_job_prints_its_cause(tmp_path):
    """A job's one-line error is printed by the workflow itself, not only written to the job's log."""
    import yaml

    (tmp_path / "scenes" / "broken").mkdir(parents=True)
    (tmp_path / "scenes" / "broken" / "scene.xml").write_text(
        (ROOT / "scenes" / "cornell" / "scene.xml").read_text().replace('type="diffuse"', 'type="no-such-bsdf"', 1))
    config = ci_config()
    config.update(scene_dirs=[str(tmp_path / "scenes")], scenes={"broken": {"scale": 0.1}}, figures={"comparison": []},
                  experiments={"equal_time": {"scenes": ["broken"], "budget": "equal_spp", "timed": False,
                                              "methods": ["brdf"]}})
    (tmp_path / "broken.yaml").write_text(yaml.safe_dump(config))
    result = snakemake("--cores", 1, "--configfile", tmp_path / "broken.yaml", "--directory", tmp_path / "work",
                       "--keep-going")
    assert result.returncode != 0
    causes = [line for line in result.stderr.splitlines() if line.startswith("job failed: ")]
    assert len(causes) == 2   # the reference and the render
    assert all("error: cannot load scene 'broken'" in line and 'type "no-such-bsdf"' in line and "(log: " in line
               for line in causes)


def test_job_failure_names_the_cause():
    log = "render: 8/16 spp (50%)\nTraceback (most recent call last):\n  ...\nValueError: bad things\n"
    assert harness.job_failure(log, 1) == "ValueError: bad things"
    assert harness.job_failure("render: 8/16\nerror: unknown scene 'x'\n", 2) == "error: unknown scene 'x'"
    assert harness.job_failure("render: 8/16 spp (50%)\n", 137) == ("killed by signal 9 (log ends: render: 8/16 spp "
                                                                  "(50%))")
    assert harness.job_failure("", 1) == "exit status 1, nothing in its log"


def test_bad_config_is_rejected_before_any_job(tmp_path):
    config = ci_config()
    config["experiments"]["table1"]["S"] = [5]
    import yaml

    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(config))
    result = snakemake("--cores", 1, "--configfile", tmp_path / "bad.yaml", "--directory", tmp_path / "work")
    assert result.returncode != 0
    errors = [line for line in result.stderr.splitlines() if "config error" in line]
    assert len(errors) == 1 and "experiments.table1.S[0]: 5 is not one of" in errors[0]
    assert not (tmp_path / "work" / "results").exists()


def test_full_config_and_slurm_profile_dry_run(tmp_path):
    result = snakemake("-n", "--directory", tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    the_plan = plan(load_config(FULL_CONFIG), check=False)
    counts = job_counts(result.stdout)
    assert counts["render"] == sum(not r.timed for r in the_plan.runs) > 0
    assert counts["render_timed"] == sum(r.timed for r in the_plan.runs) > 0
    assert counts["evaluate"] == len(the_plan.runs) and counts["reference"] == len(the_plan.references)
    assert counts["table"] == len(the_plan.experiments()) and counts["figure_heatmap"] == 1
    # The SLURM profile: resources and config overrides resolve (tests/test_slurm.py runs it on SLURM).
    result = snakemake("-n", "--profile", ROOT / "config" / "profiles" / "slurm", "--executor", "local",
                       "--directory", tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "--variant cuda_ad_rgb" in result.stdout and "gpu=1" in result.stdout and "--exclusive" in result.stdout


def test_lint_runs_and_only_asks_for_software_environments(tmp_path):
    """`snakemake --lint`: the one lint left is the request for a conda environment or container per rule (the
    software is this package, installed by scripts/setup.sh)."""
    import re

    result = snakemake("--lint", "--directory", tmp_path)
    titles = set(re.findall(r"^    \* (.*):$", result.stdout + result.stderr, flags=re.MULTILINE))
    assert titles == {"Specify a conda environment or container for each rule."}, titles


def _render_processes(group: int) -> list[int]:
    """Pids of `python -m guiding render` processes in process group ``group`` (started by this test)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            args = (entry / "cmdline").read_bytes().split(b"\0")
            if os.getpgid(int(entry.name)) == group and b"guiding" in args and b"render" in args:
                found.append(int(entry.name))
        except (OSError, ProcessLookupError):
            continue
    return found


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to find the render process")
@pytest.mark.parametrize("victim", ["render", "workflow"])
def test_interrupted_render_leaves_no_output_a_rerun_would_trust(tmp_path, victim):
    """Kill a long timed render mid-way: only the render (Snakemake sees the failure and deletes the job's
    outputs) or the whole workflow at once (nobody cleans up: the CLI's atomic writes and Snakemake's
    incomplete-job markers must keep the rerun from trusting anything)."""
    import yaml

    config = ci_config()
    config["budgets"]["equal_time"]["seconds"] = 120
    (tmp_path / "long.yaml").write_text(yaml.safe_dump(config))
    folder = tmp_path / "results/ci/renders/equal_time/cornell/brdf/120s/seed0"
    target = "results/ci/renders/equal_time/cornell/brdf/120s/seed0/stats.json"
    args = snakemake_command("--cores", 1, "--configfile", tmp_path / "long.yaml", "--directory", tmp_path, target)
    process = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               start_new_session=True, env=checkout_env())
    try:
        deadline = time.time() + 60
        while not (pids := _render_processes(process.pid)) and time.time() < deadline:
            time.sleep(0.2)
        assert pids, "the render never started"
        time.sleep(2.0)  # well inside the render (Dr.Jit started, passes running)
        if victim == "render":
            os.kill(pids[0], signal.SIGKILL)
            output, _ = process.communicate(timeout=60)
            assert process.returncode != 0 and b"Error in rule render_timed" in output
        else:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait(timeout=30)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    for name in ("image.exr", "stats.json", "preview.png"):
        assert not (folder / name).exists()
    dry_run = snakemake("-n", "--configfile", tmp_path / "long.yaml", "--directory", tmp_path, target)
    text = dry_run.stdout + dry_run.stderr
    assert ("rule render_timed" in text and "Missing output files" in text) or "IncompleteFilesException" in text
