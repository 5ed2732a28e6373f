"""How the SD-tree's final image is made of its last iterations, measured (``python -m guiding sdtree-baseline
--part combination``, results/sdtree_combination/).

The renderer weighs the last four iterations by their spp (:func:`guiding.render.iterations.combine_iterations`), weights fixed
before the images are drawn. Müller 2019's weights, the inverse of each iteration's variance estimated from its own
samples (:func:`self_weighted_image`, the renderer's combination before), give an iteration that caught a rare,
bright path less weight because it is brighter: its image is pulled down. Weights estimated from the other half of
each iteration's passes (:func:`split_halves_image`) do not see the samples they weigh, but the halves' variance
estimates are noisier, and an iteration's samples train the guide of the next, so later estimates still depend on
them. The study renders each seed once and makes every combination from the same passes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from guiding.render.iterations import COMBINED_ITERATIONS, iteration_variance

#: The study's scenes at the resolutions of the paper experiments (config/paper.yaml; the shipped glass-lamp, whose
#: light reaches the room only through rare paths, at 1/16: 40 × 30).
COMBINATION_SCENES = (("glass-lamp", 0.0625), ("cornell-box", 0.125), ("veach-ajar", 0.0625),
                      ("staircase2", 0.0625), ("living-room", 0.0625))
#: The methods whose final image combines iterations.
COMBINATION_METHODS = ("sdtree", "sdtree-learned")
#: The combinations compared: the render's own (spp weights), the last iteration alone, Müller's weights from each
#: iteration's own samples, and weights from the other half of its passes.
COMBINATIONS = ("spp weights (default)", "last iteration (sdtree-last)", "own-variance weights (before)",
                "split-halves weights")
#: Leading passes a seconds budget does not count (config/paper.yaml's equal-time budget: its first 80 spp).
EXCLUDED_PASSES = 10
#: Passes of the short `path` render that estimates a reference's standard error, each of 1/256 of its spp.
REFERENCE_ERROR_PASSES = 24


@dataclass
class Iteration:
    """One iteration's image from its passes: its spp, the spp-weighted mean of its pass images, and the estimated
    variance of that mean (:func:`~guiding.render.iterations.iteration_variance`; None for a single pass)."""

    spp: int
    image: np.ndarray
    variance: float | None


def iteration_images(passes: list[tuple[int, int, np.ndarray]]) -> list[Iteration]:
    """The iterations of a render from ``(spp, iteration, image)`` of each of its passes (``on_pass`` of
    :func:`~guiding.render.progressive.render` gives the spp and, in the guide's statistics, the iteration), in order."""
    out = []
    for k in sorted({iteration for _, iteration, _ in passes}):
        spps = np.array([spp for spp, iteration, _ in passes if iteration == k], dtype=np.float64)
        images = np.stack([image for _, iteration, image in passes if iteration == k]).astype(np.float64)
        first, second = np.tensordot(spps, images, axes=1), np.tensordot(spps, images * images, axes=1)
        total = int(spps.sum())
        out.append(Iteration(total, first / total, iteration_variance(first, second, total, len(spps))))
    return out


def _inverse_variance_weights(iterations: list[Iteration]) -> np.ndarray:
    """``1/V_k`` normalised, 0 where there is no estimate or a zero one (no pass found light); all 0 if none has."""
    inverse = np.array([1.0 / it.variance if it.variance else 0.0 for it in iterations])
    return inverse / inverse.sum() if inverse.any() else inverse


def self_weighted_image(iterations: list[Iteration]) -> np.ndarray:
    """Müller 2019's combination, the renderer's before: the last four iterations weighted by the inverse of the
    variance estimated from their own passes (the last alone where none has an estimate)."""
    window = iterations[-COMBINED_ITERATIONS:]
    weights = _inverse_variance_weights(window)
    if not weights.any():
        return window[-1].image
    return sum(w * it.image for w, it in zip(weights, window))


def split_halves_image(passes: list[tuple[int, int, np.ndarray]]) -> np.ndarray:
    """The last four iterations' passes split in two halves (alternately, in order), each half weighted by the
    inverse variances of the other half's iterations, and the two means averaged (the last iteration alone where
    a half has no estimate)."""
    halves: tuple[list, list] = ([], [])
    for k in sorted({iteration for _, iteration, _ in passes})[-COMBINED_ITERATIONS:]:
        records = [record for record in passes if record[1] == k]
        if len(records) < 2:     # an iteration of one pass has nothing for the second half
            continue
        for j, record in enumerate(records):
            halves[j % 2].append(record)
    first, second = (iteration_images(half) for half in halves)
    weights_first, weights_second = _inverse_variance_weights(first), _inverse_variance_weights(second)
    if not (weights_first.any() and weights_second.any()):
        return iteration_images(passes)[-1].image
    return 0.5 * (sum(w * it.image for w, it in zip(weights_second, first))
                  + sum(w * it.image for w, it in zip(weights_first, second)))


def reference_standard_error(scene, spp: int, seed: int) -> float:
    """The relative standard error of the image mean (over pixels and channels) of an ``spp``-spp `path` reference
    of ``scene``, from the spread of the image means of :data:`REFERENCE_ERROR_PASSES` passes of ``spp/256`` spp
    (the variance of a mean falls as 1/spp)."""
    import mitsuba as mi

    from guiding.experiments.sdtree_baseline import MAX_DEPTH
    from guiding.experiments.validation import pass_means

    pass_spp = max(1, spp // 256)
    means = pass_means(scene, mi.load_dict({"type": "path", "max_depth": MAX_DEPTH}), REFERENCE_ERROR_PASSES,
                       pass_spp, seed).mean(axis=1)
    return float(np.sqrt(means.var(ddof=1) * pass_spp / spp) / means.mean())


def _render_passes(scene, method: str, budget, seed: int):
    """One render (the method's default combination) and ``(spp, iteration, image)`` of its passes, each pass in the
    renderer's iteration (under a seconds budget the passes after training stopped belong to the iteration that
    became the final one, while the guide counts them in the next)."""
    import mitsuba as mi

    from guiding.experiments.sdtree_baseline import MAX_DEPTH
    from guiding.guides.methods import make_guide
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.render.progressive import render

    props = mi.Properties()
    props["max_depth"] = MAX_DEPTH
    passes = []
    result = render(scene, GuidedPathIntegrator(props, guide=make_guide(method)), budget, seed=seed, progress=False,
                    on_pass=lambda stats, image: passes.append((stats.spp, stats.spp_total, image)))
    ends = [it.spp_end for it in result.iterations]
    return result, [(spp, int(np.searchsorted(ends, total)), image) for spp, total, image in passes]


def combination_runs(scene, scene_name: str, scale: float, methods: tuple[str, ...], budget,
                     seeds: tuple[int, ...], reference: np.ndarray) -> list[dict]:
    """One record per (method, seed, combination) of ``scene`` (``scene_name`` at ``scale``) rendered with
    ``budget`` (:class:`~guiding.render.progressive.Budget`): the image mean relative to the reference's, the MAE and the spp;
    and per (method, seed) the variance per sample of the last four iterations, relative to the last's."""
    from guiding.metrics import mae_tonemapped

    reference_mean = reference.astype(np.float64).mean()
    records = []
    for method in methods:
        for seed in seeds:
            result, passes = _render_passes(scene, method, budget, seed)
            iterations = iteration_images(passes)
            images = dict(zip(COMBINATIONS, (result.image, iterations[-1].image, self_weighted_image(iterations),
                                             split_halves_image(passes))))
            window = iterations[-COMBINED_ITERATIONS:]
            per_sample = [it.variance * it.spp if it.variance else np.nan for it in window]
            for combination, image in images.items():
                records.append({"scene": scene_name, "scale": scale, "method": method, "seed": seed,
                                "combination": combination,
                                "mean_vs_reference": float(np.asarray(image, np.float64).mean() / reference_mean - 1),
                                "mae": mae_tonemapped(image, reference), "spp": result.spp,
                                "variance_per_sample": [v / per_sample[-1] for v in per_sample]})
    return records


def combination_table(scenes=COMBINATION_SCENES, methods: tuple[str, ...] = COMBINATION_METHODS, spp: int = 1024,
                      seeds: tuple[int, ...] = tuple(range(12)), reference_spp: int = 32768,
                      cache: Path = Path("results"), seconds: float | None = None):
    """Per scene, method and combination: the image mean relative to the `path` reference's (mean over ``seeds``,
    its standard error with the reference's, and ``z`` = the difference over it), its difference to the last
    iteration's image mean in the same render (mean and standard error over ``seeds``), the MAE (mean, standard
    error, relative to the last iteration's), and the variance per sample of the last four iterations relative to the
    last's (means over seeds: how far the spp weights are from the inverse-variance weights); and every run.

    Parameters:
      scenes: (name, scale) pairs (default :data:`COMBINATION_SCENES`).
      methods: the SD-tree methods (default ``sdtree`` and ``sdtree-learned``).
      spp: samples per pixel of every render (default 1024), unless ``seconds`` is given.
      seconds: a seconds budget of every render instead, its first :data:`EXCLUDED_PASSES` passes not counted (as
        the equal-time experiment of config/paper.yaml); timed: the renders must have the machine to themselves.
      seeds: render seeds (default 0 to 11).
      reference_spp: spp of the `path` references (default 32768).
      cache: folder of the cached references (:func:`guiding.experiments.sdtree_baseline.reference_image`).
    Returns (summary, runs) as DataFrames.
    """
    import pandas as pd

    from guiding.experiments.sdtree_baseline import REFERENCE_SEED, reference_image
    from guiding.render.progressive import Budget
    from guiding.scenes import load_scene

    budget = Budget(spp=spp) if seconds is None else Budget(seconds=seconds, exclude_passes=EXCLUDED_PASSES)
    records, reference_errors = [], {}
    for scene_name, scale in scenes:
        scene = load_scene(scene_name, scale)
        reference = reference_image(scene_name, scale, reference_spp, cache)
        reference_errors[scene_name, scale] = reference_standard_error(scene, reference_spp, REFERENCE_SEED + 1)
        records += combination_runs(scene, scene_name, scale, methods, budget, seeds, reference)
    runs = pd.DataFrame(records)
    # The last iteration's image is unbiased and made of the same passes: the difference to it, render by render,
    # shows a combination's bias without the noise of the samples both images hold.
    render_keys = ["scene", "scale", "method", "seed"]
    last_mean = runs[runs["combination"] == COMBINATIONS[1]].set_index(render_keys)["mean_vs_reference"]
    runs.insert(runs.columns.get_loc("mean_vs_reference") + 1, "mean_minus_last",
                runs["mean_vs_reference"] - last_mean.loc[pd.MultiIndex.from_frame(runs[render_keys])].to_numpy())
    keys = ["scene", "scale", "method", "combination"]
    summary = runs.groupby(keys, sort=False).agg(
        mean_vs_reference=("mean_vs_reference", "mean"), mean_se=("mean_vs_reference", "sem"),
        mean_minus_last=("mean_minus_last", "mean"), mean_minus_last_se=("mean_minus_last", "sem"),
        mae=("mae", "mean"), mae_se=("mae", "sem"), spp=("spp", "mean"), seeds=("seed", "count")).reset_index()
    summary.insert(summary.columns.get_loc("mean_se") + 1, "reference_se",
                   [reference_errors[key] for key in zip(summary["scene"], summary["scale"])])
    standard_error = np.sqrt(summary["mean_se"] ** 2 + summary["reference_se"] ** 2)
    summary.insert(summary.columns.get_loc("reference_se") + 1, "z", summary["mean_vs_reference"] / standard_error)
    row_keys = pd.MultiIndex.from_frame(summary[["scene", "scale", "method"]])
    last = summary[summary["combination"] == COMBINATIONS[1]].set_index(["scene", "scale", "method"])["mae"]
    summary.insert(summary.columns.get_loc("mae_se") + 1, "mae_vs_last",
                   summary["mae"] / last.loc[row_keys].to_numpy() - 1)
    variance = runs[runs["combination"] == COMBINATIONS[0]].groupby(["scene", "scale", "method"], sort=False)[
        "variance_per_sample"].apply(lambda rows: " / ".join(f"{v:.2f}" for v in pd.DataFrame(list(rows)).mean()))
    summary["variance_per_sample_last_four"] = variance.loc[row_keys].to_numpy()
    runs["variance_per_sample"] = runs["variance_per_sample"].map(lambda v: " / ".join(f"{x:.2f}" for x in v))
    return summary, runs
