"""The harness's outputs from synthetic runs: tables laid out like the paper's (with its numbers beside ours), the
figures (comparison grids, error against time, the Table 1 heat map), and a run's metrics from its snapshots."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from guiding import imageio
from guiding.errors import GuidingError
from guiding.experiments import evaluation, figures, tables
from guiding.experiments.configuration import load_config
from guiding.experiments.plan import plan

ROOT = Path(__file__).resolve().parent.parent
FULL_CONFIG = ROOT / "config" / "config.yaml"


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
    return plan(plan_config, check=False).experiment_spec(experiment)


def test_table1_layout_mean_over_seeds_and_paper_numbers():
    config = load_config(FULL_CONFIG)
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
    config = load_config(FULL_CONFIG)
    config["experiments"]["table1"].update(S=[8, 4], D=[16])
    spec = _spec(config, "table1")
    rows = [_row("table1", "veach-ajar", "ours-S8-D16", 0, 0.03, S=8, D=16),
            {**_row("table1", "veach-ajar", "ours-S4-D16", 0, 0.05, S=8, D=16), "guide": {"S": 4, "D": 16}}]
    cells, text, runs = tables.build(spec, rows)
    assert sorted(zip(cells.S, cells.mae)) == [(4, 0.05), (8, 0.03)]
    assert "| **4** | 0.05 /" in text


def test_table2_layout_with_extra_methods_and_a_nonfinite_run():
    config = load_config(FULL_CONFIG)
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
    config = load_config(FULL_CONFIG)
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
    config = load_config(FULL_CONFIG)
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
    # What the tables need of the stats is kept: the budget (the counted spp leave the excluded passes out) and nee.
    stats.update(budget={"seconds": 1, "pass_spp": 8, "exclude_passes": 1}, nee=True)
    (tmp_path / "stats.json").write_text(json.dumps(stats))
    kept = evaluation.evaluate_run(str(tmp_path / "image.exr"), str(tmp_path / "stats.json"),
                                   str(tmp_path / "ref.exr"), str(tmp_path / "metrics.json"))["stats"]
    assert kept["budget"]["exclude_passes"] == 1 and kept["nee"] is True
    assert tables.runs_frame([{"mae": 0.1, "stats": kept}]).spp_counted.item() == 8
    # A listed name that leaves the render folder is refused.
    stats["snapshots"][0]["file"] = "../image_snap00008.exr"
    (tmp_path / "stats.json").write_text(json.dumps(stats))
    with pytest.raises(GuidingError, match="not a file name"):
        evaluation.evaluate_run(str(tmp_path / "image.exr"), str(tmp_path / "stats.json"), str(tmp_path / "ref.exr"),
                             str(tmp_path / "metrics.json"))
