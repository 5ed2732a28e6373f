"""The Snakemake experiment harness: configuration checks, the expansion into runs, tables and figures, and the
workflow itself run end to end on the CI configuration (tiny scenes and budgets, `brdf` only).

The end-to-end tests share one run of `snakemake --cores 2 --configfile config/ci.yaml` in a temporary working
directory (`--directory`), so the repository is never written to.
"""

from __future__ import annotations

import copy
import json
import math
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from guiding import evaluation, figures, harness, imageio, tables
from guiding.errors import GuidingError
from workflow_runs import CI_CONFIG, ROOT, checkout_env, snakemake, snakemake_command

FULL_CONFIG = ROOT / "config" / "config.yaml"


def job_counts(output: str) -> dict[str, int]:
    """The 'Job stats' table of a Snakemake dry run: rule -> number of jobs."""
    import re

    table = output.rsplit("Job stats:", 1)[1].split("\n\n", 1)[0]
    return {rule: int(n) for rule, n in re.findall(r"^(\w+)\s+(\d+)$", table, flags=re.MULTILINE)}


def ci_config() -> dict:
    return harness.load_config(CI_CONFIG)


# ------------------------------------------------------------------------------------ configuration, plan

def test_full_config_expands_into_the_papers_experiments():
    plan = harness.plan(harness.load_config(FULL_CONFIG), check=False)
    by_experiment = {e: plan.experiment_runs(e) for e in plan.experiments()}
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
    assert plan.render_file(run, "image.exr") == "results/full/renders/equal_time/veach-ajar/ours/10s/seed0/image.exr"
    assert "--seconds 10 --exclude-passes 10" in plan.render_args(run)
    assert "--fixed-passes" not in plan.render_args(run)      # passes grow unless the config says otherwise
    fixed = harness.load_config(FULL_CONFIG)
    fixed["render"]["growing_passes"] = False
    assert "--fixed-passes" in harness.plan(fixed, check=False).render_args(run)
    ref = plan.reference_for(run)
    assert plan.reference_file(ref, "image.exr") == "results/full/references/veach-ajar/x0.25-spp16384/image.exr"
    assert len({r.key for r in plan.runs}) == len(plan.runs)


def test_ci_config_uses_only_methods_that_exist():
    plan = harness.plan(ci_config(), check=True)
    assert plan.warnings == [] and plan.config["strict"] is True
    assert {r.cli_method for r in plan.runs} == {"brdf", "ours", "ours-expected", "ours-S4-D4", "ours-S4-D8",
                                                 "ours-S8-D4", "ours-S8-D8", "mc-sphere_inv", "mc-hemi_rej_plus",
                                                 "sarsa-sphere_inv", "sarsa-hemi_rej_plus"}
    assert {r.scene for r in plan.runs} == {"cornell", "door-ajar"}


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
])
def test_bad_config_gives_one_message_naming_the_key(path, value, message):
    config = ci_config()
    _mutate(path, value)(config)
    if message is None:  # an unknown command-line method under strict: true
        config["experiments"]["equal_time"]["methods"] = ["brdf", "nope"]
        message = "methods: unknown to this checkout: no-such-method"
    with pytest.raises(harness.ConfigError) as error:
        harness.plan(config)
    assert message in str(error.value) and "\n" not in str(error.value)


def test_scene_missing_from_the_search_path_is_rejected_when_strict():
    config = ci_config()
    config["scenes"]["no-such-scene"] = {"scale": 0.1}
    config["experiments"]["equal_time"]["scenes"] = ["cornell", "no-such-scene"]
    with pytest.raises(harness.ConfigError, match="scenes: not on the scene search path: no-such-scene"):
        harness.plan(copy.deepcopy(config))
    config["strict"] = False
    assert any("no-such-scene" in w for w in harness.plan(config).warnings)


def test_template_collisions_are_rejected():
    config = ci_config()
    config["experiments"]["table1"]["method"] = "brdf"  # every cell would render (and store) `brdf`
    with pytest.raises(harness.ConfigError, match="occurs twice"):
        harness.plan(config)


def test_harness_path_command(capsys):
    assert harness.main(["path", "--configfile", str(CI_CONFIG), "equal_time", "door-ajar", "brdf"]) == 0
    assert capsys.readouterr().out.strip() == "results/ci/renders/equal_time/door-ajar/brdf/1s/seed0/image.exr"
    assert harness.main(["path", "--configfile", str(CI_CONFIG), "equal_time", "door-ajar", "sdtree"]) == 2


# ---------------------------------------------------------------------------------- tables (synthetic)

def _row(experiment, scene, method, seed, mae, budget="spp1024", spp=1024, seconds=2.0, **coords):
    return {"experiment": experiment, "scene": scene, "method": method, "cli_method": method, "label": method.upper(),
            "seed": seed, "budget": budget, "scale": 0.5, "timed": experiment in ("equal_time", "convergence"),
            "mae": mae, "mae_hdr": mae * 2, "relmse": mae * 3, "nonfinite_pixels": 0 if mae is not None else 7,
            **{name: None if mae is None else mae * k for k, name in enumerate(("mse", "relmse_trimmed", "smape",
                                                                               "flip"), start=4)},
            "render_seconds": seconds, "stats": {"spp": spp, "seconds": seconds + 0.5, "resolution": [64, 32],
                                                 "hit_rate": 0.25, "compile_seconds": 0.5},
            "provenance": {"host": "box", "device": "CPU: test", "variant": "llvm_ad_rgb", "threads": 2},
            "curve": [{"spp": spp, "render_seconds": seconds, "mae": mae}], **coords}


def _spec(plan_config, experiment):
    return harness.plan(plan_config, check=False).experiment_spec(experiment)


def test_table1_layout_mean_over_seeds_and_paper_numbers():
    config = harness.load_config(FULL_CONFIG)
    config["experiments"]["table1"].update(S=[8, 4], D=[16, 8])
    spec = _spec(config, "table1")
    rows = [_row("table1", "veach-ajar", f"ours-S{S}-D{D}", seed, 0.01 * S + 0.001 * D + 0.002 * seed, S=S, D=D)
            for S in (8, 4) for D in (16, 8) for seed in (0, 1)]
    cells, text, runs = tables.build(spec, rows)
    assert len(runs) == 8 and len(cells) == 4 and {"host", "device", "variant", "threads"} <= set(runs.columns)
    assert {"flip", "mse", "smape", "relmse_trimmed", "mae_hdr", "relmse"} <= set(runs.columns) & set(cells.columns)
    cell = cells[(cells.S == 8) & (cells.D == 16)].iloc[0]
    assert cell.mae == pytest.approx(0.08 + 0.016 + 0.001) and cell.seeds == 2
    assert cell.flip == pytest.approx(7 * cell.mae) and cell.mse == pytest.approx(4 * cell.mae)
    assert cell.paper_mae == pytest.approx(0.0347)
    assert "| S \\ D | 16 | 8 |" in text and "| **8** | 0.097 ± 0.0014 / 0.0347 |" in text
    assert "`box`: CPU: test" in text


def test_table1_takes_the_resolution_each_render_reports():
    """S and D come from the guide's own statistics in the render's stats.json, not from the method name."""
    config = harness.load_config(FULL_CONFIG)
    config["experiments"]["table1"].update(S=[8, 4], D=[16])
    spec = _spec(config, "table1")
    rows = [_row("table1", "veach-ajar", "ours-S8-D16", 0, 0.03, S=8, D=16),
            {**_row("table1", "veach-ajar", "ours-S4-D16", 0, 0.05, S=8, D=16), "guide": {"S": 4, "D": 16}}]
    cells, text, runs = tables.build(spec, rows)
    assert sorted(zip(cells.S, cells.mae)) == [(4, 0.05), (8, 0.03)]
    assert "| **4** | 0.05 /" in text


def test_table2_layout_with_extra_methods_and_a_nonfinite_run():
    config = harness.load_config(FULL_CONFIG)
    config["experiments"]["table2"].update(rules=["mc", "sarsa"], samplers=["sphere_inv", "hemi_rej_plus"])
    spec = _spec(config, "table2")
    rows = [_row("table2", "veach-ajar", f"{r}-{s}", 0, 0.04, rule=r, sampler=s)
            for r in ("mc", "sarsa") for s in ("sphere_inv", "hemi_rej_plus")]
    rows[0].update(mae=None, nonfinite_pixels=7)  # NaN/Inf pixels: reported, never averaged away
    rows += [_row("table2", "veach-ajar", "brdf", 0, 0.06, extra=True),
             _row("table2", "veach-ajar", "quadtree-grid", 0, 0.05, extra=True)]
    cells, text, _ = tables.build(spec, rows)
    assert len(cells) == 6
    assert "| rule | Sphere Inv | Hemi Rej+ |" in text
    assert "| **MC** | n/a (7 non-finite px) / 0.0482 | 0.04 / 0.038 |" in text
    assert "| BRDF | 0.06 / 0.0645 |" in text and "| QUADTREE-GRID | 0.05 / 0.0522 |" in text
    assert cells.loc[cells.method == "brdf", "paper_mae"].item() == pytest.approx(0.0645)


def test_equal_time_and_convergence_tables():
    config = harness.load_config(FULL_CONFIG)
    spec = _spec(config, "equal_time")
    rows = [_row("equal_time", scene, m, 0, 0.01 if m == "ours" else 0.02, budget="10s", spp=512)
            for scene in spec["scenes"] for m in spec["methods"]]
    for row in rows:
        row["stats"].update(budget={"seconds": 10, "pass_spp": 8, "exclude_passes": 10}, budget_seconds_counted=10.0)
    rows[-1]["provenance"] = {**rows[-1]["provenance"], "host": "other"}
    cells, text, _ = tables.build(spec, rows)
    assert len(cells) == len(spec["scenes"]) * len(spec["methods"])
    veach = cells[cells.scene == "veach-ajar"].set_index("method")
    assert veach.loc["ours", "paper_mae"] == pytest.approx(0.0740) and math.isnan(veach.loc["sdtree", "paper_mae"])
    # Half brdf's error in the same time: four times its efficiency; the 80 uncounted spp are not counted.
    assert veach.loc["ours", "efficiency_vs_brdf"] == pytest.approx(4.0)
    assert veach.loc["brdf", "efficiency_vs_brdf"] == pytest.approx(1.0) and veach.loc["ours", "spp_counted"] == 432
    assert "432 spp" in text and "| 4× |" in text
    assert "| scene | BRDF | Quadtree | Ours w/o rejection opt | Ours w/o SARSA | Ours | SD-tree |" in text
    assert "more than one machine" in text  # a timed experiment split over machines is flagged

    spec = _spec(config, "convergence")
    rows = [_row("convergence", s, m, 0, 1.0 / spp, budget=f"spp{spp}", spp=spp, seconds=spp / 100)
            for s in spec["scenes"] for m in spec["methods"] for spp in (32, 64)]
    cells, text, _ = tables.build(spec, rows)
    assert len(cells) == len(spec["scenes"]) * len(spec["methods"]) * 2
    assert "| scene | method | spp32 | spp64 |" in text and "0.03125 @ 0.32 s" in text


def test_convergence_table_from_snapshot_curves():
    """One render per method with snapshots: its curve points become the table's spp columns, the final image
    keeps the render's budget column, and the runs table still has one row per render."""
    config = harness.load_config(FULL_CONFIG)
    spec = _spec(config, "convergence")
    rows = []
    for method in spec["methods"]:
        row = _row("convergence", "door-ajar", method, 0, 0.01, budget="10s", spp=200, seconds=10.0)
        row["curve"] = [{"spp": s, "render_seconds": s / 20, "mae": 1 / s, "mae_hdr": 2 / s, "relmse": 3 / s,
                         "nonfinite_pixels": 0} for s in (8, 16, 32)] + [row["curve"][0]]
        rows.append(row)
    cells, text, runs = tables.build(spec, rows)
    assert len(runs) == len(spec["methods"])
    assert "| scene | method | spp8 | spp16 | spp32 | 10s |" in text
    assert "| **door-ajar** | BRDF | 0.125 @ 0.4 s | 0.0625 @ 0.8 s | 0.03125 @ 1.6 s | 0.01 @ 10 s |" in text
    brdf = cells[cells.method == "brdf"].set_index("budget")
    assert brdf.loc["spp16", "spp"] == 16 and brdf.loc["10s", "spp"] == 200
    assert brdf.loc["spp32", "relmse"] == pytest.approx(3 / 32)


# --------------------------------------------------------------------------------- figures (synthetic)

def test_auto_crop_finds_the_noisy_region():
    error = np.zeros((40, 60))
    error[25:35, 40:50] = 1.0
    assert figures.crop_box(error.shape, None, [error], fraction=0.25) == (40, 25, 10, 10)
    assert figures.crop_box((40, 60, 3), [0.5, 0.5, 0.25, 0.25]) == (30, 20, 15, 10)


def test_figures_draw_from_synthetic_runs(tmp_path):
    rng = np.random.default_rng(1)
    reference = np.full((24, 32, 3), 0.5, np.float32)
    imageio.write_exr(tmp_path / "ref.exr", reference)
    entries = []
    for i, label in enumerate(["BRDF", "Ours"]):
        image = reference + rng.normal(0, 0.1 / (i + 1), reference.shape).astype(np.float32)
        imageio.write_exr(tmp_path / f"{i}.exr", image)
        (tmp_path / f"{i}.json").write_text(json.dumps({"mae": 0.1 / (i + 1)}))
        entries.append({"label": label, "image": str(tmp_path / f"{i}.exr"), "metrics": str(tmp_path / f"{i}.json")})
    job = {"title": "t", "crop_fraction": 0.3, "rows": [
        {"scene": "a", "reference": str(tmp_path / "ref.exr"), "crop": None, "entries": entries},
        {"scene": "b", "reference": str(tmp_path / "ref.exr"), "crop": [0.1, 0.1, 0.5, 0.5], "entries": entries[:1]}]}
    figures.comparison(job, tmp_path / "comparison.png")

    metrics = []
    for method, snapshots in (("brdf", False), ("ours", True)):
        for spp in (64, 128, 256):
            row = _row("convergence", "a", method, 0, 1 / spp, budget=f"spp{spp}", spp=spp, seconds=spp / 100)
            if snapshots:  # per-pass snapshots: one render gives the whole curve
                row["curve"] = [{"spp": s, "render_seconds": s / 100, "mae": 1 / s} for s in (8, 16, 32, spp)]
            path = tmp_path / f"m-{method}-{spp}.json"
            path.write_text(json.dumps(row))
            metrics.append(str(path))
    series = figures.convergence_series([json.loads(Path(p).read_text()) for p in metrics])
    assert [t for t, _ in series["a"]["BRDF"]] == [0.64, 1.28, 2.56]
    assert len(series["a"]["OURS"]) == 4
    figures.convergence({"scenes": ["a"]}, metrics, tmp_path / "convergence.png")

    pd.DataFrame([{"scene": "a", "S": s, "D": d, "mae": 0.01 * s / d} for s in (8, 4) for d in (16, 8)]).to_csv(
        tmp_path / "t1.csv", index=False)
    figures.heatmap(tmp_path / "t1.csv", tmp_path / "heatmap.png")
    from PIL import Image

    for name in ("comparison", "convergence", "heatmap"):
        with Image.open(tmp_path / f"{name}.png") as image:
            assert image.format == "PNG" and min(image.size) > 100


def _comparison_job(tmp_path, labels, crop=(0.25, 0.25, 0.5, 0.5)):
    """Synthetic renders for a comparison figure: a reference with structure and noisier images of it."""
    rng = np.random.default_rng(2)
    reference = (rng.random((32, 48, 3)) + np.linspace(0, 2, 48)[None, :, None]).astype(np.float32)
    imageio.write_exr(tmp_path / "ref.exr", reference)
    entries = []
    for i, label in enumerate(labels):
        image = reference * rng.lognormal(0, 0.3 / (i + 1), reference.shape).astype(np.float32)
        imageio.write_exr(tmp_path / f"{i}.exr", image)
        (tmp_path / f"{i}.json").write_text(json.dumps({"mae": 0.5 + i}))
        entries.append({"label": label, "image": str(tmp_path / f"{i}.exr"), "metrics": str(tmp_path / f"{i}.json")})
    return {"title": "t", "crop_fraction": 0.3, "rows": [{"scene": "a", "reference": str(tmp_path / "ref.exr"),
                                                          "crop": list(crop), "entries": entries}]}


def test_comparison_shows_each_crops_own_mae_and_its_error_map(tmp_path):
    from guiding.metrics import mae_tonemapped

    job = _comparison_job(tmp_path, ["BRDF", "Ours"])
    figure = figures.comparison_figure(job)
    reference = imageio.read_exr(job["rows"][0]["reference"])
    x, y, w, h = figures.crop_box(reference.shape, job["rows"][0]["crop"])
    for i, entry in enumerate(job["rows"][0]["entries"]):
        crop_ax = next(ax for ax in figure.axes if ax.get_title().startswith(entry["label"] + "\n"))
        image = imageio.read_exr(entry["image"])
        crop_mae = mae_tonemapped(image[y:y + h, x:x + w], reference[y:y + h, x:x + w])
        assert crop_ax.get_xlabel() == f"MAE {crop_mae:.4f}"       # the crop's own MAE, under it
        assert crop_ax.get_title() == f"{entry['label']}\nimage MAE {0.5 + i:.4f}"   # the image's, by the label
        assert crop_ax.images[0].get_array().shape[:2] == (h, w)
    maps = [ax for ax in figure.axes if ax.images and ax.images[0].get_cmap().name == "magma"]
    assert len(maps) == 2 and all(ax.get_xlabel().startswith("FLIP 0.") for ax in maps)
    assert all(ax.images[0].get_clim() == (0, 1) for ax in maps)
    colorbars = [ax for ax in figure.axes if ax.get_ylabel() == "HDR-FLIP error"]
    assert len(colorbars) == 1
    assert "MAE under each crop" not in figure.get_suptitle()


def test_comparison_of_many_methods_wraps_into_lines_of_readable_crops(tmp_path):
    """Table 2's 15 methods: rows of at most MAX_COLUMNS crops, not one strip of tiny ones."""
    job = _comparison_job(tmp_path, [f"M{i}" for i in range(15)])
    figure = figures.comparison_figure(job)
    width, height = figure.get_size_inches()
    assert width / height < 4
    crops = [ax for ax in figure.axes if ax.get_title().startswith("M")]
    rows = {round(ax.get_position().y0, 3) for ax in crops}
    assert len(crops) == 15 and len(rows) == 2 and max(len([a for a in crops if round(a.get_position().y0, 3) == r])
                                                       for r in rows) == figures.MAX_COLUMNS
    figure.savefig(tmp_path / "wrapped.png")
    from PIL import Image

    with Image.open(tmp_path / "wrapped.png") as png:
        assert png.size[0] / png.size[1] < 4 and png.size[1] > 500


def test_heatmap_panels_share_one_colour_scale(tmp_path):
    pd.DataFrame([{"scene": scene, "S": s, "D": d, "mae": 0.01 * s / d + offset}
                  for scene, offset in (("a", 0.0), ("b", 0.2)) for s in (8, 4) for d in (16, 8)]).to_csv(
        tmp_path / "t1.csv", index=False)
    figure = figures.heatmap_figure(tmp_path / "t1.csv")
    panels = [ax for ax in figure.axes if ax.images]
    assert [ax.get_title() for ax in panels] == ["ours: a", "ours: b", "paper (supplement Table 1)"]
    limits = {ax.images[0].get_clim() for ax in panels}
    assert len(limits) == 1
    low, high = limits.pop()
    assert (low, high) == pytest.approx((0.01 * 4 / 16, 0.2 + 0.01 * 8 / 8))   # ours' extremes, beyond the paper's
    assert len(figure.axes) == len(panels) + 1          # one colour bar for all


def _labelled_ticks(axis) -> list[str]:
    """Texts of the labelled major ticks of a drawn axis that lie inside its view."""
    low, high = sorted(axis.get_view_interval())
    return [label.get_text() for location, label in zip(axis.get_majorticklocs(), axis.get_majorticklabels())
            if low <= location <= high and label.get_text()]


def test_every_convergence_axis_has_labelled_ticks(tmp_path):
    """Log axes spanning less than a decade (the issue: no y numbers, an x axis showing only "10")."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    paths = []
    for method, scale in (("brdf", 1.0), ("ours", 0.8)):
        row = _row("convergence", "a", method, 0, 0.05, budget="30s", spp=256, seconds=30)
        row["curve"] = [{"spp": s, "render_seconds": 3 * s / 8, "mae": scale * 0.07 * (s / 8) ** -0.6,
                         "relmse": scale * (s / 8) ** -0.9} for s in (8, 16, 32, 64)]
        paths.append(tmp_path / f"{method}.json")
        paths[-1].write_text(json.dumps(row))
    figure = figures.convergence_figure({"scenes": ["a"]}, [str(p) for p in paths])
    FigureCanvasAgg(figure).draw()
    axes = [ax for ax in figure.axes if ax.lines]
    assert len(axes) == len(figures.CONVERGENCE_ROWS)
    assert any(ax.get_yscale() == "log" and ax.get_ylim()[1] / ax.get_ylim()[0] < 10 for ax in axes)
    for ax in axes:
        assert len(_labelled_ticks(ax.xaxis)) >= 2 and len(_labelled_ticks(ax.yaxis)) >= 2, ax.get_ylabel()


def test_log_ticks_label_every_span():
    assert figures.log_ticks(0.021, 0.07) == [0.03, 0.05, 0.07]
    assert figures.log_ticks(2.5, 30) == [5, 10, 20]
    assert figures.log_ticks(1e-3, 10) == [1e-3, 1e-2, 1e-1, 1, 10]


def test_evaluate_reads_snapshots_listed_in_stats(tmp_path):
    """The `--snapshots` contract (docs/harness.md): only the files stats.json lists, the final image replacing
    its own snapshot, time from the per-pass record."""
    reference = np.full((8, 8, 3), 0.5, np.float32)
    imageio.write_exr(tmp_path / "ref.exr", reference)
    imageio.write_exr(tmp_path / "image.exr", reference * 1.1)
    imageio.write_exr(tmp_path / "image_snap00008.exr", reference * 1.5)
    imageio.write_exr(tmp_path / "image_snap00016.exr", reference * 3.0)   # listed as the final one: not read
    imageio.write_exr(tmp_path / "image_snap00004.exr", reference * 9.0)   # not listed: never read
    passes = [{"spp_total": 8 * (i + 1), "seconds": 0.1, "update_seconds": 0.01, "compile_seconds": 0.05 * (i == 0)}
              for i in range(2)]
    snapshots = [{"spp": 8, "file": "image_snap00008.exr", "seconds": 0.06},
                 {"spp": 16, "file": "image_snap00016.exr", "seconds": 0.17}]
    stats = {"spp": 16, "budget_seconds_counted": 0.17, "per_pass": passes, "provenance": {"host": "h"},
             "snapshots": snapshots}
    (tmp_path / "stats.json").write_text(json.dumps(stats))
    result = evaluation.evaluate_run(str(tmp_path / "image.exr"), str(tmp_path / "stats.json"),
                                  str(tmp_path / "ref.exr"), str(tmp_path / "metrics.json"), {"method": "m"})
    assert [c["spp"] for c in result["curve"]] == [8, 16]
    assert result["curve"][0]["mae"] > result["curve"][1]["mae"] == result["mae"] > 0
    assert result["curve"][0]["render_seconds"] == pytest.approx(0.06)
    assert [c["counted_seconds"] for c in result["curve"]] == [0.06, 0.17]
    assert result["render_seconds"] == pytest.approx(0.17)
    assert json.loads((tmp_path / "metrics.json").read_text())["method"] == "m"
    # A listed name that leaves the render folder is refused.
    stats["snapshots"][0]["file"] = "../image_snap00008.exr"
    (tmp_path / "stats.json").write_text(json.dumps(stats))
    with pytest.raises(GuidingError, match="not a file name"):
        evaluation.evaluate_run(str(tmp_path / "image.exr"), str(tmp_path / "stats.json"), str(tmp_path / "ref.exr"),
                             str(tmp_path / "metrics.json"))


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
    for experiment in ("table1", "table2", "equal_time", "convergence"):
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
    for name in ("table1_heatmap", "equal_time_comparison", "convergence"):
        assert (out / "figures" / f"{name}.png").stat().st_size > 1000
    prov = json.loads((out / "provenance.json").read_text())
    assert prov["config"]["out"] == "results/ci" and prov["versions"]["mitsuba"]
    assert {r["experiment"] for r in prov["renders"]} == {"table1", "table2", "equal_time", "convergence",
                                                          "reference"}
    assert seconds < 300


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
    expected = [out / "tables" / f"{e}{suffix}" for e in ("table1", "table2", "equal_time", "convergence")
                for suffix in (".csv", ".md", "_runs.csv")]
    expected += [out / "figures" / f"{name}.png" for name in ("table1_heatmap", "equal_time_comparison",
                                                               "convergence")]
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
    plan = harness.plan(harness.load_config(FULL_CONFIG), check=False)
    counts = job_counts(result.stdout)
    assert counts["render"] == sum(not r.timed for r in plan.runs) > 0
    assert counts["render_timed"] == sum(r.timed for r in plan.runs) > 0
    assert counts["evaluate"] == len(plan.runs) and counts["reference"] == len(plan.references)
    assert counts["table"] == len(plan.experiments()) and counts["figure_heatmap"] == 1
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
    plan = snakemake("-n", "--configfile", tmp_path / "long.yaml", "--directory", tmp_path, target)
    text = plan.stdout + plan.stderr
    assert ("rule render_timed" in text and "Missing output files" in text) or "IncompleteFilesException" in text
