"""What one render is worth: its metrics against the reference and its error-vs-time curve (``metrics.json``)."""

from __future__ import annotations

import json
from pathlib import Path

from guiding import strict_json
from guiding.errors import GuidingError
from guiding.imageio import write_text_atomic
from guiding.metrics import METRICS


def render_seconds_at(per_pass: list[dict], spp: int) -> float:
    """Render + update time up to ``spp`` samples per pixel, compilation excluded (the curves' time axis)."""
    total = 0.0
    for p in per_pass:
        if p["spp_total"] > spp:
            break
        total += p["seconds"] + p["update_seconds"] - p["compile_seconds"]
    return total


#: What each point of an error-vs-time curve keeps of the metrics.
CURVE_METRICS = (*METRICS, "nonfinite_pixels")


def evaluate_run(image: str, stats: str, reference: str, out: str, run: dict | None = None) -> dict:
    """metrics.json of one render: the run, its metrics against the reference, its stats, the guide's parameters as
    the render reports them (``guide``: S, D, rule, ...), its provenance, and an error-vs-time curve.

    The curve has a point for every snapshot listed in stats.json (``python -m guiding render --snapshots``;
    stats.json is written last, so files of an interrupted render are never listed) and one for the final image
    (which replaces the snapshot the renderer takes of it). Each point: spp, ``render_seconds`` (render + update
    seconds up to that pass, compilation excluded: the figures' time axis), the seconds counted against the
    budget when the renderer recorded them, and the metrics.
    """
    from guiding import imageio
    from guiding.metrics import evaluate

    stats_data = json.loads(Path(stats).read_text())
    ref = imageio.read_exr(reference)
    metrics = evaluate(imageio.read_exr(image), ref)
    per_pass = stats_data.get("per_pass", [])
    final_spp = stats_data["spp"]
    curve = []
    for snap in stats_data.get("snapshots", []):
        if snap["spp"] == final_spp:
            continue  # the final image itself
        if Path(snap["file"]).name != snap["file"]:
            raise GuidingError(f"{stats}: snapshot file {snap['file']!r} is not a file name in the render folder")
        snap_metrics = evaluate(imageio.read_exr(Path(image).parent / snap["file"]), ref)
        curve.append({"spp": snap["spp"], "render_seconds": render_seconds_at(per_pass, snap["spp"]),
                      "counted_seconds": snap.get("seconds"),
                      **{k: snap_metrics[k] for k in CURVE_METRICS}})
    curve.append({"spp": final_spp, "render_seconds": render_seconds_at(per_pass, final_spp),
                  "counted_seconds": stats_data.get("budget_seconds_counted"),
                  **{k: metrics[k] for k in CURVE_METRICS}})
    keep = ("scene", "method", "seed", "scale", "resolution", "spp", "seconds", "compile_seconds", "budget",
            "budget_seconds_counted", "passes", "hit_rate", "max_depth", "nee", "spp_in_image", "combine",
            "training_stopped", "path_fallback")
    guide = {k: v for k, v in stats_data.get("guide", {}).items() if not isinstance(v, (dict, list))}
    result = {**(run or {}), **metrics, "render_seconds": render_seconds_at(per_pass, stats_data["spp"]),
              "stats": {k: stats_data.get(k) for k in keep}, "guide": guide,
              "provenance": stats_data.get("provenance", {}),
              "curve": sorted(curve, key=lambda c: c["spp"])}
    write_text_atomic(out, strict_json.dumps(result))
    return result
