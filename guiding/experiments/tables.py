"""Result tables laid out like the paper's, as CSV and Markdown, with the published numbers beside ours.

Input: the metrics.json of every run of one experiment (written by ``python -m guiding.experiments.harness evaluate``; each
holds the run, its metrics, its stats and its provenance) and the experiment's layout (``Plan.experiment_spec``).
Output: ``{experiment}.csv`` (one row per cell: the mean over seeds, and the paper's number), ``{experiment}.md``
(the paper's layout, each cell "ours / paper"; the practical experiment: each method against Mitsuba's ``path``)
and ``{experiment}_runs.csv`` (one row per render, with the machine, device and versions it ran on).

The published numbers (method.md §8) come from other scenes or resolutions, an 8-bit reference and the authors'
GPU; they are shown for orientation, not as a target to match digit for digit.

Command line: ``python -m guiding.experiments.tables --spec JSON --csv F --md F --runs-csv F METRICS.json...``
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from guiding.experiments.runs import RULE_LABELS, SAMPLER_LABELS
from guiding.metrics import METRICS

# ------------------------------------------------------------------------------- published numbers (MAE)

#: Supplement Table 1: SARSA + Rej+, half-size images, equal spp; (S, D) -> MAE.
PAPER_TABLE1 = {
    (32, 32): 0.0936, (32, 16): 0.0564, (32, 8): 0.0435, (32, 4): 0.0466,
    (16, 32): 0.0489, (16, 16): 0.0380, (16, 8): 0.0367, (16, 4): 0.0448,
    (8, 32): 0.0376, (8, 16): 0.0347, (8, 8): 0.0362, (8, 4): 0.0443,
    (4, 32): 0.0351, (4, 16): 0.0344, (4, 8): 0.0363, (4, 4): 0.0461,
}
#: Supplement Table 2: equal spp (1024); (rule, sampler) -> MAE.
PAPER_TABLE2 = {
    ("expected_sarsa", "sphere_inv"): 0.0501, ("expected_sarsa", "hemi_inv"): 0.0466,
    ("expected_sarsa", "hemi_rej"): 0.0531, ("expected_sarsa", "hemi_rej_plus"): 0.0391,
    ("mc", "sphere_inv"): 0.0482, ("mc", "hemi_inv"): 0.0495, ("mc", "hemi_rej"): 0.0543,
    ("mc", "hemi_rej_plus"): 0.0380,
    ("sarsa", "sphere_inv"): 0.0504, ("sarsa", "hemi_inv"): 0.0475, ("sarsa", "hemi_rej"): 0.0551,
    ("sarsa", "hemi_rej_plus"): 0.0392,
}
#: Supplement Table 2's caption: the baselines at 1024 spp; command-line method -> MAE.
PAPER_TABLE2_EXTRA = {"brdf": 0.0645, "quadtree-grid": 0.0522}
#: Equal time (paper Fig. 1, supplement Figs. 1-3); scene -> command-line method -> MAE. The kitchen and
#: veach-ajar2 scenes are not available here.
PAPER_EQUAL_TIME = {
    "kitchen": {"brdf": 0.0227, "quadtree-grid": 0.0209, "ours-no-rejopt": 0.0198, "ours-expected": 0.0216,
                "ours": 0.0190},
    "staircase2": {"brdf": 0.0146, "quadtree-grid": 0.0101, "ours-no-rejopt": 0.0178, "ours-expected": 0.0107,
                   "ours": 0.0092},
    "veach-ajar": {"brdf": 0.0747, "quadtree-grid": 0.0640, "ours-no-rejopt": 0.2010, "ours-expected": 0.0772,
                   "ours": 0.0740},
    "veach-ajar2": {"brdf": 0.1233, "quadtree-grid": 0.1066, "ours-no-rejopt": 0.1222, "ours-expected": 0.1323,
                    "ours": 0.1029},
}

#: The metrics of every render (guiding.metrics.evaluate) beside the paper's MAE, in the order the CSVs show them.
OTHER_METRICS = [m for m in METRICS if m != "mae"]
RUN_COLUMNS = ["experiment", "scene", "method", "cli_method", "nee", "fallback", "label", "seed", "budget", "scale",
               "resolution", "spp", "seconds", "render_seconds", "compile_seconds", "budget_seconds_counted", "hit_rate", "mae",
               *OTHER_METRICS, "nonfinite_pixels", "host", "device", "variant", "threads", "mitsuba", "drjit", "date"]


def paper_value(experiment: str, row: dict) -> float:
    """The published MAE for a run's cell, or NaN."""
    if experiment == "table1" and "S" in row:
        return PAPER_TABLE1.get((row["S"], row["D"]), math.nan)
    if experiment == "table2":
        if _is_true(row.get("extra")):
            return PAPER_TABLE2_EXTRA.get(row["cli_method"], math.nan)
        if "rule" in row:
            return PAPER_TABLE2.get((row["rule"], row["sampler"]), math.nan)
    if experiment == "equal_time":
        return PAPER_EQUAL_TIME.get(row["scene"], {}).get(row["cli_method"], math.nan)
    return math.nan


# -------------------------------------------------------------------------------------------- data frames

def load_metrics(paths: list[str]) -> list[dict]:
    return [json.loads(Path(p).read_text()) for p in paths]


def runs_frame(rows: list[dict]) -> pd.DataFrame:
    """One row per render: the run, its metrics, and the machine and device it ran on."""
    records = []
    for row in rows:
        stats, prov = row.get("stats", {}), row.get("provenance", {})
        record = {**{k: v for k, v in row.items() if k not in ("stats", "provenance", "curve", "guide")},
                  # The resolution a render reports is the one it ran at, whatever the method name said.
                  **{k: row["guide"][k] for k in ("S", "D") if k in row.get("guide", {})},
                  "resolution": "x".join(map(str, stats.get("resolution") or [])), "spp": stats.get("spp"),
                  "spp_counted": _counted_spp(stats),
                  "seconds": stats.get("seconds"), "compile_seconds": stats.get("compile_seconds"),
                  "budget_seconds_counted": stats.get("budget_seconds_counted"), "hit_rate": stats.get("hit_rate"),
                  # What renders the rest of the budget after the path fallback's check ("guide" or "path").
                  "fallback": (stats.get("path_fallback") or {}).get("chosen"),
                  **{k: prov.get(k) for k in ("host", "device", "variant", "threads", "mitsuba", "drjit", "date")}}
        records.append(record)
    frame = pd.DataFrame.from_records(records)
    if "nee" not in frame:      # renders evaluated before next-event estimation existed did without it
        frame["nee"] = False
    # Renders evaluated before a metric existed have no value for it: NaN, like a metric of non-finite pixels (null).
    frame = frame.reindex(columns=[*frame.columns, *(m for m in METRICS if m not in frame.columns)])
    for column in METRICS:
        frame[column] = pd.to_numeric(frame[column], errors="coerce")
    extra = [c for c in frame.columns if c not in RUN_COLUMNS]
    return frame[[c for c in RUN_COLUMNS if c in frame.columns] + extra]


def _counted_spp(stats: dict):
    """The spp that count against a seconds budget: those after the excluded leading passes."""
    spp, budget = stats.get("spp"), stats.get("budget") or {}
    if spp is None or not budget.get("seconds"):
        return spp
    return spp - (budget.get("exclude_passes") or 0) * (budget.get("pass_spp") or 0)


def cells_frame(runs: pd.DataFrame, experiment: str, keys: list[str], baseline: str = "brdf") -> pd.DataFrame:
    """Mean over seeds per cell (``keys``), with the spread, the seed count, the paper's number and the efficiency
    1/(MAE²·t) relative to the ``baseline`` method's (the cell that rendered it, by its command-line method) in the
    same scene (and budget), as ``efficiency_vs_{baseline}``: t is the counted seconds of a timed render, the
    render + update seconds of an untimed one."""
    runs = runs.assign(cost_seconds=runs["budget_seconds_counted"].fillna(runs["render_seconds"]))
    grouped = runs.groupby(keys, sort=False, dropna=False)
    cells = grouped.agg(mae=("mae", "mean"), mae_std=("mae", "std"), relmse_std=("relmse", "std"),
                        **{metric: (metric, "mean") for metric in OTHER_METRICS}, seeds=("seed", "count"),
                        spp=("spp", "mean"), spp_counted=("spp_counted", "mean"),
                        render_seconds=("render_seconds", "mean"), cost_seconds=("cost_seconds", "mean"),
                        hit_rate=("hit_rate", "mean"), nonfinite_pixels=("nonfinite_pixels", "sum"),
                        device=("device", _joined)).reset_index()
    first = grouped.first().reset_index()
    for column in ("cli_method", "nee", "label", "S", "D", "rule", "sampler", "extra"):
        if column in first and column not in cells:
            cells[column] = first[column].values
    efficiency = 1.0 / (cells["mae"] ** 2 * cells["cost_seconds"])
    peers = [k for k in keys if k != "method"]       # the cells the baseline's is compared with: same scene (and budget)
    reference = cells.loc[cells["cli_method"] == baseline, peers].assign(baseline_efficiency=efficiency)
    reference = reference.drop_duplicates(peers)
    per_cell = cells[peers].merge(reference, on=peers, how="left")["baseline_efficiency"].to_numpy()   # NaN: none
    cells[f"efficiency_vs_{baseline}"] = efficiency.to_numpy() / per_cell
    cells["paper_mae"] = [paper_value(experiment, row) for row in cells.to_dict("records")]
    return cells


def _is_true(value) -> bool:
    return isinstance(value, (bool, np.bool_)) and bool(value)


def _joined(values) -> str:
    return "; ".join(sorted({str(v) for v in values}))


# ------------------------------------------------------------------------------------------------ Markdown

def fmt(value, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    return f"{value:.{digits}g}" if isinstance(value, float) else str(value)


def ours_paper(cell: dict | None) -> str:
    if cell is None:
        return "(not run)"
    if math.isnan(cell["mae"]):
        ours = f"n/a ({int(cell['nonfinite_pixels'])} non-finite px)"
    else:
        ours = fmt(cell["mae"]) + (f" ± {fmt(cell['mae_std'], 2)}" if cell.get("seeds", 1) > 1 else "")
    return f"{ours} / {fmt(cell['paper_mae'])}"


def efficiency(cell: dict | None) -> str:
    return "(not run)" if cell is None else f"{fmt(cell['efficiency_vs_brdf'], 3)}×"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def provenance_note(runs: pd.DataFrame, timed: bool) -> str:
    devices = runs.groupby(["host", "device", "variant", "threads"], dropna=False).size().reset_index(name="renders")
    lines = [f"- `{r.host}`: {r.device}, {r.variant}, threads {fmt(r.threads)}: {r.renders} render(s)"
             for r in devices.itertuples()]
    note = "Rendered on:\n" + "\n".join(lines)
    if timed and len(devices) > 1:
        note += ("\n\n**Warning:** this timed experiment ran on more than one machine or device: its times do not "
                 "compare.")
    return note


def _budget_text(spec: dict) -> str:
    parts = []
    for point in spec["budget_points"]:
        if point["kind"] == "spp":
            parts.append(f"{int(point['value'])} spp")
        else:
            parts.append(f"{point['value']:g} s (first {point['exclude_passes']} passes not counted)")
    return ", ".join(parts)


def _header(spec: dict, runs: pd.DataFrame, title: str) -> str:
    scales = ", ".join(f"{s} at {r}" for s, r in runs.groupby("scene", sort=False)["resolution"].first().items())
    timing = "timed (each render alone on the machine)" if spec["timed"] else "untimed"
    return (f"# {title}\n\nBudget: {_budget_text(spec)}; {timing}. "
            f"Resolutions: {scales}. MAE of the tone-mapped images against a float reference (mean over "
            f"{runs['seed'].nunique()} seed(s)). "
            + ("Next-event estimation in every render. " if spec.get("nee") else "")
            + ("" if spec["name"] in ("convergence", "practical") else "Each cell: **ours / paper** (— where the "
               "paper has no number; the paper's scenes, resolutions and 8-bit reference differ)."))


def table1(spec: dict, runs: pd.DataFrame) -> tuple[pd.DataFrame, str]:
    cells = cells_frame(runs, "table1", ["scene", "method"])
    parts = [_header(spec, runs, "Table 1: spatial (S) x directional (D) resolution of ours, equal spp")]
    for scene in spec["scenes"]:
        lookup = {(c["S"], c["D"]): c for c in cells[cells["scene"] == scene].to_dict("records")}
        rows = [[f"**{S}**", *[ours_paper(lookup.get((S, D))) for D in spec["D"]]] for S in spec["S"]]
        parts.append(f"## {scene}\n\n" + markdown_table(["S \\ D", *map(str, spec["D"])], rows))
    parts.append(provenance_note(runs, spec["timed"]))
    columns = ["scene", "S", "D", "method", "cli_method", "nee", "mae", "mae_std", "seeds", "paper_mae",
               *OTHER_METRICS, "spp", "render_seconds", "hit_rate", "nonfinite_pixels", "device"]
    return cells[columns], "\n\n".join(parts) + "\n"


def table2(spec: dict, runs: pd.DataFrame) -> tuple[pd.DataFrame, str]:
    cells = cells_frame(runs, "table2", ["scene", "method"])
    parts = [_header(spec, runs, "Table 2: learning rule x sampler, equal spp")]
    for scene in spec["scenes"]:
        scene_cells = cells[cells["scene"] == scene].to_dict("records")
        grid = {(c["rule"], c["sampler"]): c for c in scene_cells if isinstance(c.get("rule"), str)}
        rows = [[f"**{RULE_LABELS[rule]}**", *[ours_paper(grid.get((rule, s))) for s in spec["samplers"]]]
                for rule in spec["rules"]]
        text = f"## {scene}\n\n"
        if rows:
            text += markdown_table(["rule", *[SAMPLER_LABELS[s] for s in spec["samplers"]]], rows)
        extras = [c for c in scene_cells if _is_true(c.get("extra"))]
        if extras:
            text += "\n\n" + markdown_table(["method", "MAE ours / paper", "efficiency vs BRDF"],
                                           [[c["label"], ours_paper(c), efficiency(c)] for c in extras])
        if rows:
            text += ("\n\nEfficiency 1/(MAE²·t) relative to BRDF (t: render + update seconds):\n\n"
                     + markdown_table(["rule", *[SAMPLER_LABELS[s] for s in spec["samplers"]]],
                                      [[f"**{RULE_LABELS[rule]}**", *[efficiency(grid.get((rule, s)))
                                                                     for s in spec["samplers"]]]
                                       for rule in spec["rules"]]))
        parts.append(text)
    parts.append(provenance_note(runs, spec["timed"]))
    for column in ("rule", "sampler", "extra"):
        if column not in cells:
            cells[column] = None
    columns = ["scene", "rule", "sampler", "method", "cli_method", "nee", "label", "mae", "mae_std", "seeds",
               "paper_mae", "efficiency_vs_brdf", *OTHER_METRICS, "spp", "render_seconds", "hit_rate",
               "nonfinite_pixels", "device"]
    return cells[columns], "\n\n".join(parts) + "\n"


def equal_time(spec: dict, runs: pd.DataFrame) -> tuple[pd.DataFrame, str]:
    cells = cells_frame(runs, "equal_time", ["scene", "method"])
    labels = [spec["labels"].get(m, m) for m in spec["methods"]]
    lookup = {(c["scene"], c["method"]): c for c in cells.to_dict("records")}
    mae_rows = [[f"**{scene}**", *[ours_paper(lookup.get((scene, m))) for m in spec["methods"]]]
                for scene in spec["scenes"]]
    def reached(cell: dict | None) -> str:
        if cell is None:
            return "(not run)"
        return (f"{fmt(cell['spp_counted'], 6)} spp, {fmt(cell['render_seconds'], 3)} s, "
                f"hit {fmt(cell['hit_rate'], 3)}")

    spp_rows = [[f"**{scene}**", *[reached(lookup.get((scene, m))) for m in spec["methods"]]]
                for scene in spec["scenes"]]
    efficiency_rows = [[f"**{scene}**", *[efficiency(lookup.get((scene, m))) for m in spec["methods"]]]
                       for scene in spec["scenes"]]
    text = "\n\n".join([
        _header(spec, runs, "Equal time"),
        markdown_table(["scene", *labels], mae_rows),
        "Efficiency 1/(MAE²·t) relative to BRDF (t: the counted seconds):",
        markdown_table(["scene", *labels], efficiency_rows),
        "Counted samples (mean over seeds; the excluded leading passes not included), render + update time of the "
        "whole render (compilation excluded), hit rate:",
        markdown_table(["scene", *labels], spp_rows),
        provenance_note(runs, spec["timed"])]) + "\n"
    columns = ["scene", "method", "cli_method", "nee", "label", "mae", "mae_std", "seeds", "paper_mae",
               "efficiency_vs_brdf", *OTHER_METRICS, "spp", "spp_counted", "render_seconds", "hit_rate",
               "nonfinite_pixels", "device"]
    return cells[columns], text


def curve_rows(rows: list[dict]) -> list[dict]:
    """One row per point of each render's error-vs-time curve, for the convergence table: a snapshot's budget is
    ``spp{N}``, the final image keeps the render's budget. A render without snapshots stays one row."""
    points = []
    for row in rows:
        curve = row.get("curve", [])
        if len(curve) < 2:
            points.append(row)
            continue
        for i, point in enumerate(curve):
            final = i == len(curve) - 1
            points.append({**row, "budget": row["budget"] if final else f"spp{point['spp']}",
                           **{k: point.get(k, row.get(k)) for k in (*METRICS, "nonfinite_pixels", "render_seconds")},
                           "stats": {**row.get("stats", {}), "spp": point["spp"]}})
    return points


def convergence(spec: dict, runs: pd.DataFrame, points: pd.DataFrame | None = None) -> tuple[pd.DataFrame, str]:
    """Convergence table: ``points`` (default ``runs``) holds one row per curve point (:func:`curve_rows`)."""
    points = runs if points is None else points
    cells = cells_frame(points, "convergence", ["scene", "method", "budget"])
    budgets = list(points.groupby("budget", sort=False)["spp"].mean().sort_values(kind="stable").index)
    lookup = {(c["scene"], c["method"], c["budget"]): c for c in cells.to_dict("records")}
    rows = []
    for scene in spec["scenes"]:
        for method in spec["methods"]:
            row = [f"**{scene}**", spec["labels"].get(method, method)]
            for budget in budgets:
                c = lookup.get((scene, method, budget))
                row.append(f"{fmt(c['mae'])} @ {fmt(c['render_seconds'], 3)} s" if c else "(not run)")
            rows.append(row)
    text = "\n\n".join([
        _header(spec, runs, "Convergence: error against time"),
        "Each cell: MAE @ render + update seconds (compilation excluded); with per-pass snapshots (`--snapshots`), "
        "the spp columns are points on one render's curve.",
        markdown_table(["scene", "method", *budgets], rows),
        provenance_note(runs, spec["timed"])]) + "\n"
    columns = ["scene", "method", "cli_method", "nee", "label", "budget", "mae", "mae_std", "seeds", *OTHER_METRICS,
               "spp", "render_seconds", "hit_rate", "nonfinite_pixels", "device"]
    return cells[columns], text


#: What the practical table says its efficiency is (docs/harness.md defines it the same way).
PRACTICAL_EFFICIENCY = ("Efficiency relative to Mitsuba's `path`: its MAE²·t over the method's, t the counted "
                        "seconds (the excluded leading passes not included); at equal time this is (MAE of path / MAE "
                        "of the method)². Above 1: the method reaches path's error in less time (2× takes half the "
                        "time). Last row: the geometric mean over the scenes.")


def _mean_spread(cell: dict | None, metric: str) -> str:
    """A cell's mean of ``metric`` over seeds with its standard deviation ("n/a" where a pixel was not finite)."""
    if cell is None:
        return "(not run)"
    if math.isnan(cell[metric]):
        return f"n/a ({int(cell['nonfinite_pixels'])} non-finite px)"
    spread = cell.get(f"{metric}_std", math.nan)
    return fmt(cell[metric]) + (f" ± {fmt(spread, 2)}" if cell.get("seeds", 1) > 1 else "")


def _fallback_choices(spec: dict, runs: pd.DataFrame, header: list[str]) -> list[str]:
    """For the methods with the path fallback (--path-fallback), per scene, what rendered the rest of the budget
    in how many seeds; nothing when no run has one."""
    if "fallback" not in runs or runs["fallback"].isna().all():
        return []
    counts = runs.dropna(subset=["fallback"]).groupby(["scene", "method"])["fallback"]

    def choices(scene: str, method: str) -> str:
        if (scene, method) not in counts.groups:
            return ""
        chosen = counts.get_group((scene, method)).value_counts()
        return ", ".join(f"{strategy} {count}/{chosen.sum()}" for strategy, count in chosen.items())

    rows = [[f"**{scene}**", *[choices(scene, m) for m in spec["methods"]]] for scene in spec["scenes"]]
    return ["What rendered the rest of the budget after the path fallback's check (seeds), for the methods that "
            "have one, and `path` where a method has nothing to guide (then every pass is Mitsuba's `path`):",
            markdown_table(header, rows)]


def practical(spec: dict, runs: pd.DataFrame) -> tuple[pd.DataFrame, str]:
    """Each method against Mitsuba's ``path`` at equal time, per scene: the efficiency relative to ``path``
    (:data:`PRACTICAL_EFFICIENCY`), MAE and relMSE (mean ± standard deviation over seeds), counted spp."""
    cells = cells_frame(runs, "practical", ["scene", "method"], baseline="path")
    labels = runs.groupby("method", sort=False)["label"].first().to_dict()
    header = ["scene", *[labels.get(m, spec["labels"].get(m, m)) for m in spec["methods"]]]
    lookup = {(c["scene"], c["method"]): c for c in cells.to_dict("records")}

    def rows(show) -> list[list[str]]:
        return [[f"**{scene}**", *[show(lookup.get((scene, m))) for m in spec["methods"]]] for scene in spec["scenes"]]

    def times(cell: dict | None) -> str:
        return "(not run)" if cell is None else f"{fmt(cell['efficiency_vs_path'], 3)}×"

    efficiency = cells.set_index("method")["efficiency_vs_path"]
    overall = ["**geometric mean**", *[fmt(float(np.exp(np.log(efficiency[[m]]).mean())), 3) + "×"
                                       if m in efficiency.index else "(not run)" for m in spec["methods"]]]
    text = "\n\n".join([
        _header(spec, runs, "Practical: each method against Mitsuba's path at equal time"),
        PRACTICAL_EFFICIENCY, markdown_table(header, rows(times) + [overall]),
        "MAE (tone-mapped; mean ± standard deviation over seeds):",
        markdown_table(header, rows(lambda c: _mean_spread(c, "mae"))),
        "relMSE (mean ± standard deviation over seeds):",
        markdown_table(header, rows(lambda c: _mean_spread(c, "relmse"))),
        "Counted samples per pixel (mean over seeds) in the counted seconds:",
        markdown_table(header, rows(lambda c: "(not run)" if c is None else
                                    f"{fmt(c['spp_counted'], 6)} spp, {fmt(c['cost_seconds'], 3)} s")),
        *_fallback_choices(spec, runs, header),
        provenance_note(runs, spec["timed"])]) + "\n"
    columns = ["scene", "method", "cli_method", "nee", "label", "efficiency_vs_path", "mae", "mae_std", "relmse",
               "relmse_std", "seeds", "spp_counted", "cost_seconds", *[m for m in OTHER_METRICS if m != "relmse"],
               "spp", "render_seconds", "hit_rate", "nonfinite_pixels", "device"]
    return cells.reindex(columns=columns), text


BUILDERS = {"table1": table1, "table2": table2, "equal_time": equal_time, "convergence": convergence,
            "practical": practical}


def build(spec: dict, rows: list[dict]) -> tuple[pd.DataFrame, str, pd.DataFrame]:
    """(cells CSV frame, Markdown text, runs CSV frame) of one experiment."""
    runs = runs_frame(rows)
    if spec["name"] == "convergence":
        cells, text = convergence(spec, runs, runs_frame(curve_rows(rows)))
    else:
        cells, text = BUILDERS[spec["name"]](spec, runs)
    return cells, text, runs


def write(spec: dict, metrics_files: list[str], csv: str, md: str, runs_csv: str) -> None:
    from guiding.imageio import write_text_atomic

    cells, text, runs = build(spec, load_metrics(metrics_files))
    write_text_atomic(csv, cells.to_csv(index=False, float_format="%.6g"))
    write_text_atomic(md, text)
    write_text_atomic(runs_csv, runs.to_csv(index=False, float_format="%.6g"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m guiding.experiments.tables", description=__doc__.splitlines()[0])
    parser.add_argument("--spec", required=True, help="the experiment's layout as JSON (Plan.experiment_spec)")
    parser.add_argument("--csv", required=True)
    parser.add_argument("--md", required=True)
    parser.add_argument("--runs-csv", required=True)
    parser.add_argument("metrics", nargs="+")
    args = parser.parse_args(argv)
    write(json.loads(args.spec), args.metrics, args.csv, args.md, args.runs_csv)
    print(Path(args.md).read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
