"""Figures like the paper's: comparison grids with zoomed crops and MAE labels, error-against-time curves, and a
heat map of Table 1 beside the published one.

Images are shown through the paper's tone map (the one its MAE uses, :func:`guiding.metrics.tone_map`), clipped
to [0, 1]. Matplotlib's object API is used (no pyplot state), with the Agg backend; files are written atomically.

Command line (what the Snakefile runs)::

    python -m guiding.figures comparison --job JSON --out F.png
    python -m guiding.figures convergence --job JSON --out F.png METRICS.json...
    python -m guiding.figures heatmap --csv table1.csv --out F.png
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from .imageio import atomic_path, read_exr
from .metrics import tone_map


def _figure(width: float, height: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=110, layout="constrained")


def _save(figure, out: str | Path) -> None:
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

def comparison(job: dict, out: str | Path) -> None:
    """One row per scene: the reference with the crop marked, then each method's crop with its MAE, then the
    reference's crop. ``job``: {"title", "crop_fraction", "rows": [{"scene", "reference", "crop",
    "entries": [{"label", "image", "metrics"}]}]}."""
    from matplotlib.patches import Rectangle

    rows = job["rows"]
    columns = 2 + max(len(r["entries"]) for r in rows)
    figure = _figure(1.7 * columns, 1.95 * len(rows) + 0.4)
    figure.suptitle(job.get("title", ""), fontsize=10)
    axes = figure.subplots(len(rows), columns, squeeze=False)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
        for spine in ax.spines.values():
            spine.set_visible(False)
    for row_axes, row in zip(axes, rows):
        reference = read_exr(row["reference"])
        ref_shown = display(reference)
        images = [read_exr(e["image"]) for e in row["entries"]]
        shown = [display(img) for img in images]
        box = crop_box(reference.shape, row.get("crop"), [np.abs(s - ref_shown) for s in shown],
                       job.get("crop_fraction", 0.3))
        row_axes[0].imshow(ref_shown, interpolation="nearest")
        row_axes[0].add_patch(Rectangle((box[0] - 0.5, box[1] - 0.5), box[2], box[3], fill=False, edgecolor="red",
                                        linewidth=1.2))
        row_axes[0].set_ylabel(row["scene"], fontsize=9)
        row_axes[0].set_title("Reference", fontsize=8)
        for ax, entry, image in zip(row_axes[1:], row["entries"], shown):
            mae = json.loads(Path(entry["metrics"]).read_text()).get("mae")
            ax.imshow(_crop(image, box), interpolation="nearest")
            ax.set_title(entry["label"], fontsize=8)
            ax.set_xlabel(f"{mae:.4f}" if mae is not None else "MAE n/a (non-finite)", fontsize=8)
            for spine in ax.spines.values():
                spine.set_visible(True)
        last = row_axes[1 + len(shown)]
        last.imshow(_crop(ref_shown, box), interpolation="nearest")
        last.set_title("Reference", fontsize=8)
        last.set_xlabel("MAE", fontsize=8)
        for ax in row_axes[2 + len(shown):]:
            ax.set_visible(False)
    _save(figure, out)


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


def convergence(job: dict, metrics_files: list[str], out: str | Path) -> None:
    """Error, and error × time, against time: one column per scene, one line per method (log axes where the
    data spans enough)."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    rows = [json.loads(Path(p).read_text()) for p in metrics_files]
    present = {row["scene"] for row in rows}
    scenes = [s for s in job.get("scenes", sorted(present)) if s in present]
    figure = _figure(4.2 * len(scenes), 3.0 * len(CONVERGENCE_ROWS))
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
            for axis, setter, data in ((ax.xaxis, ax.set_xscale, times), (ax.yaxis, ax.set_yscale, values)):
                if data and min(data) > 0 and max(data) / min(data) > 3:  # log only where it spans enough
                    setter("log")
                    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))
                    axis.set_minor_formatter(NullFormatter())
            ax.set_title(scene, fontsize=10)
            ax.set_xlabel("render + update seconds (compilation excluded)", fontsize=8)
            ax.set_ylabel(ylabel, fontsize=8)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
    figure.suptitle(job.get("title", "Error against time"), fontsize=10)
    _save(figure, out)


# ---------------------------------------------------------------------------------------------- heat map

def heatmap(cells_csv: str | Path, out: str | Path) -> None:
    """Table 1 as heat maps: ours (per scene) beside the paper's, rows S, columns D, values annotated."""
    import pandas as pd

    from .tables import PAPER_TABLE1

    cells = pd.read_csv(cells_csv)
    panels = [(f"ours: {scene}", {(int(r.S), int(r.D)): r.mae for r in group.itertuples()})
              for scene, group in cells.groupby("scene", sort=False)]
    panels.append(("paper (supplement Table 1)", PAPER_TABLE1))
    widths = [len({d for _, d in values}) for _, values in panels]
    figure = _figure(sum(1.0 * w + 2.0 for w in widths), 0.8 * max(len({s for s, _ in v}) for _, v in panels) + 1.6)
    axes = figure.subplots(1, len(panels), squeeze=False, width_ratios=[w + 1.2 for w in widths])[0]
    for ax, (title, values) in zip(axes, panels):
        S = sorted({s for s, _ in values}, reverse=True)
        D = sorted({d for _, d in values}, reverse=True)
        grid = np.array([[values.get((s, d), np.nan) for d in D] for s in S], dtype=float)
        finite = grid[np.isfinite(grid)]
        image = ax.imshow(grid, cmap="viridis_r", vmin=finite.min() if finite.size else None,
                          vmax=finite.max() if finite.size else None)
        for i in range(len(S)):
            for j in range(len(D)):
                spread = np.ptp(finite) if finite.size else 0.0
                dark = spread > 0 and np.isfinite(grid[i, j]) and (grid[i, j] - finite.min()) / spread > 0.55
                ax.text(j, i, f"{grid[i, j]:.4f}" if np.isfinite(grid[i, j]) else "—", ha="center", va="center",
                        fontsize=7, color="white" if dark else "black")
        ax.set_xticks(range(len(D)), [str(d) for d in D])
        ax.set_yticks(range(len(S)), [str(s) for s in S])
        ax.set_xlabel("D (directional)", fontsize=8)
        ax.set_ylabel("S (spatial)", fontsize=8)
        ax.set_title(title, fontsize=9)
        figure.colorbar(image, ax=ax, shrink=0.8, label="MAE")
    _save(figure, out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m guiding.figures", description=__doc__.splitlines()[0])
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
