"""Statistical checks shared by the tests and the result tables: image means of two estimators compared with a
tolerance derived from their measured variance."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

import mitsuba as mi

from guiding.guides import RULES, SAMPLERS
from guiding.render.driver import PassDriver, pass_seed
from guiding.render.progressive import Budget, render

if TYPE_CHECKING:
    import pandas as pd

#: Allowed difference in standard errors. With three channels, an unbiased pair fails with probability < 1e-3.
Z_LIMIT = 4.0


def pass_means(scene: mi.Scene, integrator, passes: int, spp: int, seed: int = 0) -> np.ndarray:
    """Per-channel image mean of each of ``passes`` passes, shape (passes, 3).

    A guide attached to the integrator is prepared and updated between passes, as the progressive renderer does:
    every pass is an unbiased estimate given the tables the previous passes built.
    """
    driver = PassDriver(scene, integrator)
    driver.prepare()
    means = []
    for index in range(passes):
        image = driver.run(pass_seed(seed, index), spp).image
        means.append(np.asarray(image, dtype=np.float64)[..., :3].mean(axis=(0, 1)))
    return np.array(means)


def _difference_standard_error(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per channel, the standard error of ``mean(a) − mean(b)`` for independent pass means."""
    return np.sqrt(a.var(axis=0, ddof=1) / len(a) + b.var(axis=0, ddof=1) / len(b))


def z_scores(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-channel |mean(a) − mean(b)| in units of the standard error of that difference."""
    return np.abs(a.mean(axis=0) - b.mean(axis=0)) / _difference_standard_error(a, b)


def relative_standard_error(a: np.ndarray, b: np.ndarray) -> float:
    """The standard error of ``mean(a) − mean(b)`` relative to ``mean(b)``, averaged over channels: the smallest
    relative bias a comparison of these pass means can detect is about ``Z_LIMIT`` times this."""
    return float((_difference_standard_error(a, b) / np.abs(b.mean(axis=0))).mean())


def path_render_means(scene: mi.Scene, renders: int, spp: int) -> np.ndarray:
    """Per-channel image means of ``renders`` whole renders of Mitsuba's ``path`` at ``spp`` (seeds 100, 101, …),
    shape (renders, 3): the reference of estimators whose renders are compared whole (their passes are not
    independent, as those of a render that decides between strategies)."""
    path = mi.load_dict({"type": "path", "max_depth": 16})
    return np.array([render(scene, path, Budget(spp=spp), seed=100 + seed, progress=False).image.mean(axis=(0, 1))
                     for seed in range(renders)])


def assert_means_agree(means: np.ndarray, reference: np.ndarray, note: str = "") -> None:
    """AssertionError unless the per-channel means of ``means`` and ``reference`` (one row per render or pass) agree
    within :data:`Z_LIMIT` standard errors, or if the comparison could not fail: its standard error must be under
    2 % of the reference's mean."""
    z = z_scores(means, reference)
    assert (z < Z_LIMIT).all(), f"z-scores {z} {note}, means {means.mean(0)} vs {reference.mean(0)}"
    assert (means.std(axis=0, ddof=1) / len(means) ** 0.5 < 0.02 * reference.mean(axis=0)).all()


#: The unbiasedness checks' scenes and budgets, (scale, passes, spp per pass), set from the measured variance: the
#: relative standard error of the difference to ``path`` is about 3 % on door-ajar (a light seen only through a gap)
#: and 0.3 % on cornell-tilted (whose normals all lie away from their normal bins' centres). door-ajar takes many
#: small passes: the first passes, before the guide has learnt the gap, are skewed, and with few passes they decide
#: the standard error (at 24 passes of scale 0.2, one seed in a dozen reached z = 4.1 with no bias).
UNBIASEDNESS_SCENES = {"door-ajar": (0.1, 96, 32), "cornell-tilted": (0.125, 48, 32)}
#: Every rule × sampler, ``ours`` with the paper's uniform proposals, and ``ours-plus`` (refined bins).
UNBIASEDNESS_METHODS = [f"{rule}-{sampler}" for rule in RULES for sampler in SAMPLERS] + ["ours-uniform-proposals", "ours-plus"]


def path_reference(scene: mi.Scene, passes: int, spp: int) -> np.ndarray:
    """Pass means of Mitsuba's ``path`` integrator (twice the passes of the method it is compared with)."""
    return pass_means(scene, mi.load_dict({"type": "path", "max_depth": 16}), 2 * passes, spp, seed=1000)


def unbiasedness_table(scene_name: str, methods: list[str] = UNBIASEDNESS_METHODS,
                       budget: tuple[float, int, int] | None = None) -> pd.DataFrame:
    """Image mean of each method against Mitsuba's ``path`` integrator on ``scene_name`` (budget from
    UNBIASEDNESS_SCENES unless given), with the relative difference, its standard error and the largest z-score."""
    import pandas as pd

    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.guides.methods import make_guide
    from guiding.scenes import load_scene

    scale, passes, spp = budget or UNBIASEDNESS_SCENES[scene_name]
    scene = load_scene(scene_name, scale)
    reference = path_reference(scene, passes, spp)
    rows = []
    for method in methods:
        means = pass_means(scene, GuidedPathIntegrator(guide=make_guide(method)), passes, spp, seed=1)
        z = z_scores(means, reference)
        relative = means.mean(axis=0) / reference.mean(axis=0) - 1
        rows.append({"scene": scene_name, "method": method, "relative_difference": float(relative.mean()),
                     "relative_standard_error": relative_standard_error(means, reference),
                     "max_z": float(z.max()), "agrees": bool((z < Z_LIMIT).all())})
    return pd.DataFrame(rows)


def bounce_weight_table(scene_name: str, methods: list[str], scale: float = 0.1, train_spp: int = 64,
                        vertices: int = 1000, samples: int = 4096) -> pd.DataFrame:
    """Single-bounce weights ``f·cos/p`` of each method at real diffuse vertices of the scene, after training:
    mean over albedo (1 when unbiased), second moment over albedo² (1 for cosine sampling) and the largest."""
    import pandas as pd

    from guiding.guides.methods import make_guide
    from guiding.scenes import load_scene
    from guiding.experiments.testing import scene_vertices, single_bounce_weights, train

    scene = load_scene(scene_name, scale)
    points = scene_vertices(scene, vertices, seed=3)
    rows = []
    for method in methods:
        guide = train(scene, make_guide(method), spp=train_spp, seed=1)
        weights = single_bounce_weights(guide, points, samples=samples, scene=scene)
        mean, standard_error = weights.mean_ratio()
        rows.append({"scene": scene_name, "method": method, "mean_over_albedo": mean,
                     "standard_error": standard_error, "second_moment_over_albedo2": weights.second_moment_ratio(),
                     "largest_over_albedo": weights.largest_ratio()})
    return pd.DataFrame(rows)


def _equal_spp_rows(scene_name: str, scale: float, spp: int, reference_spp: int, seeds: tuple[int, ...],
                    configurations: list[tuple[dict, str, dict]]) -> list[dict]:
    """One row per (configuration, seed): MAE, relMSE, hit rate and time at equal spp against a `path` reference.
    ``configurations``: (the row's fields, method name, ``make_guide`` overrides)."""
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.guides.methods import make_guide
    from guiding.metrics import evaluate
    from guiding.scenes import load_scene

    scene = load_scene(scene_name, scale)
    reference = render(scene, mi.load_dict({"type": "path", "max_depth": 16}),
                       Budget(spp=reference_spp, pass_spp=64), seed=1000, progress=False)
    rows = []
    for fields, method, overrides in configurations:
        for seed in seeds:
            result = render(scene, GuidedPathIntegrator(guide=make_guide(method, **overrides)), Budget(spp=spp),
                            seed=seed, progress=False)
            errors = evaluate(result.image, reference.image)
            rows.append({**fields, "seed": seed, "spp": result.spp, "mae": errors["mae"], "relmse": errors["relmse"],
                         "hit_rate": result.hit_rate, "seconds": result.seconds,
                         "update_seconds": sum(p.update_seconds for p in result.passes),
                         "refined_bins": result.passes[-1].guide.get("refined_bins", 0)})
    return rows


#: The seeds of validate's learning table (``--quick``: the first alone).
LEARNING_SEEDS = (1, 2, 3, 4)


def learning_table(scene_name: str = "door-ajar", scale: float = 0.25, spp: int = 256, reference_spp: int = 4096,
                   methods: tuple[str, ...] = ("brdf", "ours", "ours-uniform-proposals", "ours-no-rejopt",
                                               "ours-expected", "sdtree", "quadtree-grid"),
                   seeds: tuple[int, ...] = LEARNING_SEEDS) -> pd.DataFrame:
    """MAE, relMSE, hit rate and time of each method at equal spp against a `path` reference: means over ``seeds``,
    the MAE's standard error (``mae_se``; NaN with one seed, whose spread is unknown) and the renders behind each
    row (``seeds``), so that a change of a method's MAE can be told from the spread of its renders."""
    import pandas as pd

    frame = pd.DataFrame(_equal_spp_rows(scene_name, scale, spp, reference_spp, seeds,
                                         [({"method": m}, m, {}) for m in methods]))
    return frame.groupby("method", sort=False).agg(
        spp=("spp", "first"), mae=("mae", "mean"), mae_se=("mae", "sem"), relmse=("relmse", "mean"),
        hit_rate=("hit_rate", "mean"), seconds=("seconds", "mean"), update_seconds=("update_seconds", "mean"),
        refined_bins=("refined_bins", "max"), seeds=("seed", "count")).reset_index()


#: The scenes of the ours-plus BSDF share study: the shipped glossy room, and the two shared scenes with rough
#: plastic and metal.
SHARE_SCENES = ("glossy-room", "living-room", "staircase2")


def smooth_share_table(scenes: tuple[str, ...] = SHARE_SCENES, shares: tuple[float, ...] = (0.25, 0.5, 0.75),
                       scale: float = 0.0625, spp: int = 256, reference_spp: int = 8192,
                       seeds: tuple[int, ...] = (0, 1)) -> pd.DataFrame:
    """``ours-plus``'s least BSDF share at glossy vertices (``smooth_bsdf_share``) at equal spp, beside ``ours``:
    mean and spread over ``seeds`` of the MAE of each scene and share, with the hit rate and time."""
    import pandas as pd

    rows = []
    for scene in scenes:
        configurations = [({"scene": scene, "method": "ours", "smooth_bsdf_share": None}, "ours", {})]
        configurations += [({"scene": scene, "method": "ours-plus", "smooth_bsdf_share": share}, "ours-plus",
                            {"smooth_bsdf_share": share}) for share in shares]
        rows += _equal_spp_rows(scene, scale, spp, reference_spp, seeds, configurations)
    frame = pd.DataFrame(rows)
    keys = ["scene", "method", "smooth_bsdf_share"]
    return frame.groupby(keys, sort=False, dropna=False).agg(
        mae=("mae", "mean"), mae_std=("mae", "std"), relmse=("relmse", "mean"), hit_rate=("hit_rate", "mean"),
        seconds=("seconds", "mean"), seeds=("seed", "count")).reset_index()


#: The scenes of the ours-plus refinement study, each at the scale of config/paper.yaml: the sun through blinds (the
#: failure mode refinement is for), the glossy room, and the four shared scenes.
REFINEMENT_SCENES = {"sun-blinds": 0.125, "glossy-room": 0.125, "cornell-box": 0.125, "veach-ajar": 0.0625,
                     "staircase2": 0.0625, "living-room": 0.0625}


def refinement_table(scenes: dict[str, float] = REFINEMENT_SCENES, spp: int = 512, reference_spp: int = 8192,
                     seeds: tuple[int, ...] = (0, 1)) -> pd.DataFrame:
    """``ours-plus`` with and without its refined bins (``sub_resolution`` 8 and 1) at equal spp: mean and spread over
    ``seeds`` of the MAE, with the time and the refined entries."""
    import pandas as pd

    from guiding.guides.methods import METHODS

    default = METHODS["ours-plus"].parameters.sub_resolution
    rows = []
    for scene, scale in scenes.items():
        configurations = [({"scene": scene, "sub_resolution": resolution}, "ours-plus",
                           {"sub_resolution": resolution}) for resolution in sorted({1, default})]
        rows += _equal_spp_rows(scene, scale, spp, reference_spp, seeds, configurations)
    frame = pd.DataFrame(rows)
    return frame.groupby(["scene", "sub_resolution"], sort=False).agg(
        mae=("mae", "mean"), mae_std=("mae", "std"), seconds=("seconds", "mean"),
        refined_bins=("refined_bins", "max"), seeds=("seed", "count")).reset_index()
