"""Next-event estimation in the harness: an experiment's `nee`, `path` as a method, and the practical experiment
(each method against Mitsuba's path at equal time) as config/paper.yaml declares it and as its table reports it
from synthetic runs. The CI configuration's practical experiment end to end: tests/test_harness.py."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest

from guiding.experiments import tables
from guiding.experiments.configuration import ConfigError, load_config
from guiding.experiments.plan import plan
from test_harness_outputs import _row, _spec

ROOT = Path(__file__).resolve().parent.parent
CI_CONFIG = ROOT / "config" / "ci.yaml"
PAPER_CONFIG = ROOT / "config" / "paper.yaml"


def ci_config() -> dict:
    return load_config(CI_CONFIG)


def test_paper_config_runs_the_practical_experiment_on_every_scene():
    """`practical`: Mitsuba's path against sdtree, ours and ours-plus with next-event estimation, and ours-plus with
    the path fallback, learning from a quarter of the budget, and both, at the paper's equal-time budget, on the four
    shared scenes at the paper's scales and on every shipped scene at 1/8."""
    the_plan = plan(load_config(PAPER_CONFIG), check=False)
    runs = the_plan.experiment_runs("practical")
    shipped = {folder.name for folder in (ROOT / "scenes").iterdir() if (folder / "scene.xml").is_file()}
    scales = {r.scene: r.scale for r in runs}
    assert set(scales) == shipped | {"cornell-box", "veach-ajar", "staircase2", "living-room"}
    assert all(scales[scene] == 0.125 for scene in shipped | {"cornell-box"})
    assert all(scales[scene] == 0.0625 for scene in ("veach-ajar", "staircase2", "living-room"))
    assert scales["cornell-box"] == the_plan.config["scenes"]["cornell-box"]["scale"]
    methods = {"path", "sdtree", "ours", "ours-plus", "ours-plus-fallback", "ours-plus-quarter",
               "ours-plus-quarter-fallback"}
    assert {r.method for r in runs} == methods and {r.seed for r in runs} == {0, 1, 2}
    assert len(runs) == len(scales) * len(methods) * 3 and all(r.timed and r.samples_emitters for r in runs)
    equal_time = the_plan.experiment_runs("equal_time")[0]
    for run in runs:
        args = the_plan.render_args(run)
        assert "--seconds 10 --exclude-passes 10" in args and run.budget == equal_time.budget
        if run.method == "path":   # Mitsuba's path tracer, which always samples emitters: no --nee to ignore
            assert "--method path " in args and "--nee" not in args and run.label == "Mitsuba path"
        elif run.method == "ours-plus-fallback":
            assert "--method ours-plus --nee --path-fallback " in args and run.path_fallback
        elif run.method == "ours-plus-quarter":
            assert "--method ours-plus --set learning_share=0.25 --nee " in args and not run.path_fallback
        elif run.method == "ours-plus-quarter-fallback":
            assert "--method ours-plus --set learning_share=0.25 --nee --path-fallback " in args and run.path_fallback
        else:
            assert f"--method {run.method} --nee " in args and run.label.endswith(" + NEE") and not run.path_fallback
    assert not any(r.nee or "--nee" in the_plan.render_args(r) for r in the_plan.runs if r.experiment != "practical")
    assert f"{the_plan.out}/figures/practical_comparison.png" in the_plan.figure_files()


def test_nee_is_an_experiment_setting_and_path_a_method_anywhere():
    """`nee: true` (default false) gives an experiment's guided renders --nee; `path` renders in any experiment,
    and metrics.json records whether each render samples emitters."""
    config = ci_config()
    config["experiments"]["equal_time"]["methods"] = ["brdf", "path"]
    the_plan = plan(copy.deepcopy(config))
    assert the_plan.config["experiments"]["equal_time"]["nee"] is False
    runs = {r.method: r for r in the_plan.experiment_runs("equal_time") if r.scene == "cornell"}
    assert "--nee" not in the_plan.render_args(runs["brdf"]) and runs["brdf"].info()["nee"] is False
    assert "--method path " in the_plan.render_args(runs["path"]) and runs["path"].info()["nee"] is True
    config["experiments"]["equal_time"]["nee"] = True
    runs = {r.method: r for r in plan(config).experiment_runs("equal_time") if r.scene == "cornell"}
    assert "--method brdf --nee " in plan(config).render_args(runs["brdf"]) and runs["brdf"].info()["nee"] is True
    assert runs["brdf"].label == "BRDF + NEE" and runs["path"].label == "Mitsuba path"


def test_practical_table_is_efficiency_relative_to_path():
    """Per scene and method: MAE and relMSE over seeds with their spread, counted spp, and the efficiency relative
    to Mitsuba's path, path's MAE²·t over the method's (t: the counted seconds; at equal time (MAE_path/MAE)²)."""
    config = load_config(PAPER_CONFIG)
    config["experiments"]["practical"].update(scenes=["cornell-box", "veach-ajar"], methods=["path", "ours", "sdtree"])
    spec = _spec(config, "practical")
    mae = {"path": 0.04, "ours": 0.02, "sdtree": 0.05}
    counted = {"path": 10.0, "ours": 10.0, "sdtree": 12.5}   # a render that overran its budget pays for it
    rows = []
    for scene in spec["scenes"]:
        for method in spec["methods"]:
            for seed in (0, 1):
                row = _row("practical", scene, method, seed, mae[method] * (1 + 0.1 * seed), budget="10s", spp=1000)
                row.update(nee=True, label="Mitsuba path" if method == "path" else f"{method} + NEE")
                row["stats"].update(budget={"seconds": 10, "pass_spp": 8, "exclude_passes": 10},
                                    budget_seconds_counted=counted[method])
                rows.append(row)
    cells, text, runs = tables.build(spec, rows)
    cell = cells.set_index(["scene", "method"])
    ratio = {m: (mae["path"] ** 2 * counted["path"]) / (mae[m] ** 2 * counted[m]) for m in mae}
    for scene in spec["scenes"]:
        for method in spec["methods"]:
            assert cell.loc[(scene, method), "efficiency_vs_path"] == pytest.approx(ratio[method])
    assert ratio["ours"] == pytest.approx(4.0) and ratio["sdtree"] == pytest.approx(0.512)
    ours = cell.loc[("veach-ajar", "ours")]
    assert ours.mae == pytest.approx(0.021) and ours.mae_std == pytest.approx(0.002 / 2 ** 0.5)
    assert ours.relmse == pytest.approx(0.063) and ours.relmse_std == pytest.approx(0.006 / 2 ** 0.5)
    assert ours.spp_counted == 920 and ours.nee and ours.seeds == 2 and ours.label == "ours + NEE"
    assert list(cells.columns[:6]) == ["scene", "method", "cli_method", "nee", "label", "efficiency_vs_path"]
    assert "| scene | Mitsuba path | ours + NEE | sdtree + NEE |" in text
    assert "| **veach-ajar** | 1× | 4× | 0.512× |" in text
    assert "| **geometric mean** | 1× | 4× | 0.512× |" in text
    assert "| **cornell-box** | 0.042 ± 0.0028 | 0.021 ± 0.0014 | 0.0525 ± 0.0035 |" in text
    assert "920 spp, 12.5 s" in text and "(MAE of path / MAE of the method)²" in text
    assert len(runs) == 12 and runs.nee.all()


def test_a_path_fallback_needs_an_experiment_with_nee():
    config = ci_config()
    config["methods"]["ours-fallback"] = {"method": "ours", "path_fallback": True}
    config["experiments"]["equal_time"]["methods"] = ["brdf", "ours-fallback"]
    with pytest.raises(ConfigError, match="experiments.equal_time: method 'ours-fallback' falls back to Mitsuba's "
                                          "path .* set nee: true"):
        plan(config, check=False)


def test_practical_table_says_what_the_path_fallback_chose():
    config = load_config(PAPER_CONFIG)
    config["experiments"]["practical"].update(scenes=["cornell-box", "veach-ajar"],
                                              methods=["path", "ours-plus", "ours-plus-fallback"])
    spec = _spec(config, "practical")
    chosen = {"cornell-box": ["path", "path", "guide"], "veach-ajar": ["guide"] * 3}
    rows = []
    for scene in spec["scenes"]:
        for method in spec["methods"]:
            for seed in range(3):
                row = _row("practical", scene, method, seed, 0.02, budget="10s", spp=1000)
                row["stats"].update(budget={"seconds": 10, "pass_spp": 8, "exclude_passes": 10},
                                    budget_seconds_counted=10.0)
                if method == "ours-plus-fallback":
                    row["stats"]["path_fallback"] = {"chosen": chosen[scene][seed]}
                rows.append(row)
    _, text, runs = tables.build(spec, rows)
    assert runs.fallback.notna().sum() == 6
    assert "| **cornell-box** |  |  | path 2/3, guide 1/3 |" in text
    assert "| **veach-ajar** |  |  | guide 3/3 |" in text
