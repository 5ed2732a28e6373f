"""Figures like the paper's: comparison grids (rows of scenes; the reference, then each method's zoomed crop with its
MAE and its false-colour HDR-FLIP error map, then the reference's crop), error-against-time curves, and a heat map
of Table 1 beside the published one on one colour scale.

Images are shown through the paper's tone map (the one its MAE uses, :func:`guiding.metrics.tone_map`), clipped
to [0, 1]. Matplotlib's object API is used (no pyplot state), with the Agg backend; files are written atomically.
Each figure has a function that returns it (``*_figure``, for tests to read its labels) and one that saves it.

Command line (what the Snakefile runs)::

    python -m guiding.experiments.figures comparison --job JSON --out F.png
    python -m guiding.experiments.figures convergence --job JSON --out F.png METRICS.json...
    python -m guiding.experiments.figures heatmap --csv table1.csv --out F.png
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from guiding.errors import GuidingError
from guiding.imageio import atomic_path, read_exr
from guiding.metrics import flip_map, mae_tonemapped, tone_map


def new_figure(width: float, height: float, layout: str = "constrained"):
    """An empty Matplotlib figure of ``width`` × ``height`` inches (no pyplot state); ``layout``: Matplotlib's
    layout engine ("compressed" packs grids of images without gaps)."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=110, layout=layout)


def save_figure(figure, out: str | Path) -> None:
    """Write ``figure`` as PNG to ``out`` (its folder made if needed), atomically."""
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        figure.savefig(tmp, format="png")


def display(image: np.ndarray) -> np.ndarray:
    """Linear RGB → what the figures show (the paper's tone map, non-finite pixels black, clipped to [0, 1])."""
    return np.clip(np.nan_to_num(tone_map(image), nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)


# ----------------------------------------------------------------------------------------------- crops

def crop_box(shape: tuple[int, ...], crop: list[float] | None, errors: list[np.ndarray] | None = None,
             fraction: float = 0.3) -> tuple[int, int, int, int]:
    """(x, y, w, h) in pixels: ``crop`` given as fractions [x, y, w, h], or else the square window (side
    ``fraction`` of the shorter image side) where the mean of the error images is largest."""
    height, width = shape[:2]
    if crop is not None:
        x, y = int(round(crop[0] * width)), int(round(crop[1] * height))
        w, h = max(1, int(round(crop[2] * width))), max(1, int(round(crop[3] * height)))
        x, y = min(x, width - 1), min(y, height - 1)
        return x, y, min(w, width - x), min(h, height - y)
    side = max(1, min(height, width, int(round(fraction * min(height, width)))))
    if not errors:
        return (width - side) // 2, (height - side) // 2, side, side
    error = np.nan_to_num(np.mean([e.mean(axis=-1) if e.ndim == 3 else e for e in errors], axis=0))
    table = np.pad(error, ((1, 0), (1, 0))).cumsum(0).cumsum(1)  # summed-area table
    sums = table[side:, side:] - table[:-side, side:] - table[side:, :-side] + table[:-side, :-side]
    y, x = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return int(x), int(y), side, side


def _crop(image: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    x, y, w, h = box
    return image[y:y + h, x:x + w]


# ------------------------------------------------------------------------------------------ comparison

#: Most method columns on one line of a comparison grid; a scene with more methods (Table 2) wraps onto more lines.
MAX_COLUMNS = 8
#: Inches per crop in the comparison grids.
CELL_INCHES = 1.75
#: Width of the reference's overview column, in crops.
OVERVIEW_CELLS = 1.8
#: Colour map of the FLIP error maps (the one flip-evaluator itself uses).
ERROR_CMAP = "magma"


def _comparison_row(row: dict, crop_fraction: float) -> dict:
    """What one scene of a comparison grid shows: its ``reference``, ``images`` and HDR-FLIP ``errors`` (None where
    undefined), linear RGB as read from the EXR files, and the crop ``box`` (the row's, or the window of largest
    error)."""
    reference = read_exr(row["reference"])
    images = [read_exr(entry["image"]) for entry in row["entries"]]
    errors = [flip_map(image, reference) for image in images]
    box = crop_box(reference.shape, row.get("crop"), [e for e in errors if e is not None]
                   or [np.abs(display(i) - display(reference)) for i in images], crop_fraction)
    return {**row, "reference_image": reference, "images": images, "errors": errors, "box": box}


def _finite_text(value: float | None, name: str, digits: int) -> str:
    return f"{name} {value:.{digits}f}" if value is not None and np.isfinite(value) else f"{name} n/a (non-finite)"


def _bare(ax, frame: bool = False) -> None:
    """No ticks on an image axis; a thin frame only where ``frame``."""
    ax.set_xticks([])
    ax.set_yticks([])
    for spine in ax.spines.values():
        spine.set_visible(frame)


def _method_cells(figure, crop_cell, error_cell, entry: dict, image: np.ndarray, error: np.ndarray | None,
                  reference: np.ndarray, box: tuple[int, int, int, int]):
    """Draw one method of a comparison grid: its crop in grid cell ``crop_cell`` (the crop's MAE below it, the whole
    image's MAE by the label) and its FLIP error map in ``error_cell`` below it. Returns the error image drawn, or
    None where FLIP is undefined."""
    crop_ax = figure.add_subplot(crop_cell, anchor="S")   # crop and error map keep together in roomy cells
    crop_ax.imshow(display(_crop(image, box)), interpolation="nearest")
    image_mae = json.loads(Path(entry["metrics"]).read_text()).get("mae")
    crop_ax.set_title(f"{entry['label']}\n{_finite_text(image_mae, 'image MAE', 4)}", fontsize=7)
    crop_ax.set_xlabel(_finite_text(mae_tonemapped(_crop(image, box), _crop(reference, box)), "MAE", 4), fontsize=8)
    _bare(crop_ax, frame=True)
    error_ax = figure.add_subplot(error_cell, anchor="N")
    shown = None
    if error is not None:
        shown = error_ax.imshow(_crop(error, box), cmap=ERROR_CMAP, vmin=0, vmax=1, interpolation="nearest")
    error_ax.set_xlabel(_finite_text(None if error is None else float(_crop(error, box).mean()), "FLIP", 3),
                        fontsize=8)
    _bare(error_ax, frame=True)
    return shown


def _scene_block(figure, grid, first_row: int, row: dict, lines: int, columns: int):
    """Draw one scene's rows of a comparison grid (two per line: crops, error maps) from ``first_row`` of
    ``grid``; ``row`` as :func:`_comparison_row` returns it. Returns the last FLIP image drawn (for the colour
    bar), or None."""
    from matplotlib.patches import Rectangle

    reference, box = row["reference_image"], row["box"]
    overview = figure.add_subplot(grid[first_row:first_row + 2 * lines, 0])
    overview.imshow(display(reference), interpolation="nearest")
    overview.add_patch(Rectangle((box[0] - 0.5, box[1] - 0.5), box[2], box[3], fill=False, edgecolor="red",
                                 linewidth=1.2))
    overview.set_title("Reference", fontsize=8)
    overview.set_ylabel(row["scene"], fontsize=10)
    _bare(overview)
    shown = None
    for i, (entry, image, error) in enumerate(zip(row["entries"], row["images"], row["errors"])):
        line, column = divmod(i, columns)
        top = first_row + 2 * line
        shown = _method_cells(figure, grid[top, 1 + column], grid[top + 1, 1 + column], entry, image, error,
                              reference, box) or shown
    reference_crop = figure.add_subplot(grid[first_row, columns + 1], anchor="S")
    reference_crop.imshow(display(_crop(reference, box)), interpolation="nearest")
    reference_crop.set_title("Reference", fontsize=8)
    _bare(reference_crop, frame=True)
    return shown


def comparison_figure(job: dict):
    """The comparison grid of ``job`` (a Matplotlib figure): per scene, the reference with the crop marked (left),
    then for each method its crop with the crop's tone-mapped MAE below it and the whole image's MAE beside its
    label, and under that its HDR-FLIP error map (false colour, 0–1, one colour bar) with the crop's mean FLIP; the
    reference's crop last. Scenes with more than :data:`MAX_COLUMNS` methods wrap onto further lines.

    ``job``: {"title", "crop_fraction", "rows": [{"scene", "reference", "crop", "entries": [{"label", "image",
    "metrics"}]}]} (``crop``: [x, y, w, h] as fractions, or None for the window of largest error).
    """
    rows = [_comparison_row(row, job.get("crop_fraction", 0.3)) for row in job["rows"]]
    columns = min(MAX_COLUMNS, max(len(r["entries"]) for r in rows))
    lines = [-(-len(r["entries"]) // columns) for r in rows]
    # Each line is a row of crops and a row of error maps, as tall as the scene's crop is for its width; the
    # figure's size leaves each crop CELL_INCHES wide, with room for the texts around it, so no row has gaps.
    heights = [r["box"][3] / r["box"][2] for r, count in zip(rows, lines) for _ in range(2 * count)]
    texts = [0.55 if i % 2 == 0 else 0.3 for i in range(len(heights))]
    widths = [OVERVIEW_CELLS, *[1] * columns, 1, 0.12]
    figure = new_figure(CELL_INCHES * sum(widths) + 0.9, CELL_INCHES * sum(heights) + sum(texts) + 0.6)
    figure.suptitle(f"{job.get('title', '')}\nUnder each crop its MAE (tone-mapped), under that its HDR-FLIP error "
                    "map and mean FLIP; beside each label the whole image's MAE", fontsize=9)
    grid = figure.add_gridspec(len(heights), len(widths), width_ratios=widths, height_ratios=heights)
    shown, first = None, 0
    for row, count in zip(rows, lines):
        shown = _scene_block(figure, grid, first, row, count, columns) or shown
        first += 2 * count
    if shown is not None:
        figure.colorbar(shown, cax=figure.add_subplot(grid[:, -1]), label="HDR-FLIP error")
    return figure


def comparison(job: dict, out: str | Path) -> None:
    """Write :func:`comparison_figure` of ``job`` to ``out`` (PNG)."""
    save_figure(comparison_figure(job), out)


def error_map(image: np.ndarray, reference: np.ndarray, out: str | Path) -> None:
    """Write the HDR-FLIP error map of linear RGB ``image`` against ``reference`` to ``out`` (PNG, false colour
    0–1 with a colour bar and the mean); a GuidingError where FLIP is undefined (non-finite pixels, black
    reference)."""
    error = flip_map(image, reference)
    if error is None:
        raise GuidingError("no FLIP error map: an image has non-finite pixels or the reference is black")
    height, width = error.shape
    figure = new_figure(min(12.0, max(4.0, width / 60)) + 1.2, min(12.0, max(4.0, width / 60)) * height / width + 0.8)
    ax = figure.subplots()
    shown = ax.imshow(error, cmap=ERROR_CMAP, vmin=0, vmax=1, interpolation="nearest")
    ax.set_title(f"HDR-FLIP error, mean {error.mean():.4f}", fontsize=9)
    _bare(ax)
    figure.colorbar(shown, ax=ax, label="HDR-FLIP error")
    save_figure(figure, out)


# ------------------------------------------------------------------------------------------ convergence

def convergence_series(rows: list[dict], metric: str = "mae") -> dict[str, dict[str, list[tuple[float, float]]]]:
    """scene → label → [(render seconds, ``metric``)], sorted by time.

    Renders with per-pass snapshots (more than one curve point) give their whole curve (first seed); otherwise
    each render gives one point (its final image) and the seeds are averaged per budget."""
    series: dict[str, dict[str, list[tuple[float, float]]]] = defaultdict(dict)
    groups = defaultdict(list)
    for row in rows:
        groups[(row["scene"], row.get("label", row["method"]))].append(row)
    for (scene, label), items in groups.items():
        if any(len(r.get("curve", [])) > 1 for r in items):
            first_seed = min(r["seed"] for r in items)
            best = max((r for r in items if r["seed"] == first_seed), key=lambda r: r["stats"]["spp"])
            points = [(c["render_seconds"], c.get(metric)) for c in best["curve"]]
        else:
            by_budget = defaultdict(list)
            for r in items:
                by_budget[r["budget"]].append((r["render_seconds"], r.get(metric)))
            points = [(float(np.mean([p[0] for p in pts])),
                       float(np.mean([p[1] for p in pts])) if all(p[1] is not None for p in pts) else math.nan)
                      for pts in by_budget.values()]
        series[scene][label] = sorted((t, m if m is not None else math.nan) for t, m in points)
    return series


#: Rows of the convergence figure: (curve metric, y label, its value at time t). The two efficiency rows are
#: error × time, flat for an estimator whose error falls as 1/t; lower is more efficient.
CONVERGENCE_ROWS = (
    ("mae", "MAE (tone-mapped)", lambda error, t: error),
    ("mae", "MAE² · t (efficiency)", lambda error, t: error ** 2 * t),
    ("relmse", "relMSE · t (efficiency)", lambda error, t: error * t),
)


def log_ticks(low: float, high: float) -> list[float]:
    """Tick values of a log axis from ``low`` to ``high`` (> 0), at least three where possible: the decades, or
    1-2-5 per decade, or 1-1.5-2-3-5-7 per decade, the sparsest of these that gives three. Matplotlib labels only
    the decades of a log axis, none at all on one that spans less than a decade."""
    decades = range(math.floor(math.log10(low)), math.ceil(math.log10(high)) + 1)
    ticks: list[float] = []
    for mantissas in ((1,), (1, 2, 5), (1, 1.5, 2, 3, 5, 7)):
        ticks = [m * 10.0 ** e for e in decades for m in mantissas if low <= m * 10.0 ** e <= high]
        if len(ticks) >= 3:
            break
    return ticks


def _log_axis(ax, axis: str) -> None:
    """Switch ``axis`` ("x" or "y") of ``ax`` to a log scale with labelled ticks (:func:`log_ticks`)."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter

    getattr(ax, f"set_{axis}scale")("log")
    low, high = sorted(getattr(ax, f"get_{axis}lim")())
    target = getattr(ax, f"{axis}axis")
    target.set_major_locator(FixedLocator(log_ticks(low, high)))
    target.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    target.set_minor_formatter(NullFormatter())


def convergence_figure(job: dict, metrics_files: list[str]):
    """Error, and error × time, against time (a Matplotlib figure): one column per scene (``job["scenes"]``, those
    with data), one line per method, a log axis where the data spans more than a factor 3, every axis labelled."""
    rows = [json.loads(Path(p).read_text()) for p in metrics_files]
    present = {row["scene"] for row in rows}
    scenes = [s for s in job.get("scenes", sorted(present)) if s in present]
    figure = new_figure(4.2 * len(scenes), 3.0 * len(CONVERGENCE_ROWS))
    grid = figure.subplots(len(CONVERGENCE_ROWS), len(scenes), squeeze=False)
    for (metric, ylabel, value), axes in zip(CONVERGENCE_ROWS, grid):
        series = convergence_series(rows, metric)
        for ax, scene in zip(axes, scenes):
            curves = {label: [(t, value(e, t)) for t, e in points] for label, points in series[scene].items()}
            for label, points in curves.items():
                times, values = zip(*points)
                ax.plot(times, values, marker="o", markersize=3, label=label)
            times = [t for points in curves.values() for t, _ in points]
            values = [v for points in curves.values() for _, v in points if np.isfinite(v)]
            for axis, data in (("x", times), ("y", values)):
                if data and min(data) > 0 and max(data) / min(data) > 3:  # log only where it spans enough
                    _log_axis(ax, axis)
            ax.set_title(scene, fontsize=10)
            ax.set_xlabel("render + update seconds (compilation excluded)", fontsize=8)
            ax.set_ylabel(ylabel, fontsize=8)
            ax.grid(True, which="major", alpha=0.3)
            ax.legend(fontsize=7)
    figure.suptitle(job.get("title", "Error against time"), fontsize=10)
    return figure


def convergence(job: dict, metrics_files: list[str], out: str | Path) -> None:
    """Write :func:`convergence_figure` to ``out`` (PNG)."""
    save_figure(convergence_figure(job, metrics_files), out)


# ---------------------------------------------------------------------------------------------- heat map

def heatmap_figure(cells_csv: str | Path):
    """Table 1 as heat maps (a Matplotlib figure): ours (one panel per scene) beside the paper's, rows S, columns D,
    values annotated, every panel on one colour scale with one colour bar, so that colours compare across panels."""
    import pandas as pd
    from matplotlib.colors import Normalize

    from guiding.experiments.tables import PAPER_TABLE1

    cells = pd.read_csv(cells_csv)
    panels = [(f"ours: {scene}", {(int(r.S), int(r.D)): r.mae for r in group.itertuples()})
              for scene, group in cells.groupby("scene", sort=False)]
    panels.append(("paper (supplement Table 1)", PAPER_TABLE1))
    finite = np.array([v for _, values in panels for v in values.values() if np.isfinite(v)])
    norm = Normalize(finite.min(), finite.max()) if finite.size else Normalize(0, 1)
    widths = [len({d for _, d in values}) for _, values in panels]
    figure = new_figure(sum(1.0 * w + 1.2 for w in widths) + 1.2,
                        0.8 * max(len({s for s, _ in v}) for _, v in panels) + 1.6)
    axes = figure.subplots(1, len(panels), squeeze=False, width_ratios=widths)[0]
    for ax, (title, values) in zip(axes, panels):
        S = sorted({s for s, _ in values}, reverse=True)
        D = sorted({d for _, d in values}, reverse=True)
        grid = np.array([[values.get((s, d), np.nan) for d in D] for s in S], dtype=float)
        image = ax.imshow(grid, cmap="viridis_r", norm=norm)
        for (i, j), value in np.ndenumerate(grid):
            dark = np.isfinite(value) and norm(value) > 0.55   # the dark end of viridis_r: white text
            ax.text(j, i, f"{value:.4f}" if np.isfinite(value) else "—", ha="center", va="center", fontsize=7,
                    color="white" if dark else "black")
        ax.set_xticks(range(len(D)), [str(d) for d in D])
        ax.set_yticks(range(len(S)), [str(s) for s in S])
        ax.set_xlabel("D (directional)", fontsize=8)
        ax.set_ylabel("S (spatial)", fontsize=8)
        ax.set_title(title, fontsize=9)
    figure.colorbar(image, ax=list(axes), shrink=0.8, label="MAE (tone-mapped), lower is better")
    return figure


def heatmap(cells_csv: str | Path, out: str | Path) -> None:
    """Write :func:`heatmap_figure` of the Table 1 cells CSV ``cells_csv`` to ``out`` (PNG)."""
    save_figure(heatmap_figure(cells_csv), out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m guiding.experiments.figures", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    comp = commands.add_parser("comparison")
    comp.add_argument("--job", required=True)
    comp.add_argument("--out", required=True)
    conv = commands.add_parser("convergence")
    conv.add_argument("--job", required=True)
    conv.add_argument("--out", required=True)
    conv.add_argument("metrics", nargs="+")
    heat = commands.add_parser("heatmap")
    heat.add_argument("--csv", required=True)
    heat.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    if args.command == "comparison":
        comparison(json.loads(args.job), args.out)
    elif args.command == "convergence":
        convergence(json.loads(args.job), args.metrics, args.out)
    else:
        heatmap(args.csv, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
