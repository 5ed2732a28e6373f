"""The SD-tree baseline's measurements (``python -m guiding sdtree-baseline``): equal-spp errors of the SD-tree in
its previous and its present setup beside BSDF sampling, the quadtree grid and ours, the S-tree threshold rule
at several image sizes, the pieces of Müller 2019's improved preset (the learned BSDF share, ``sdtree-learned``,
and the stochastic spatial filter) on the shared scenes, and the SD-tree at several fixed BSDF shares there.

Every render is the progressive renderer's (:func:`guiding.render.progressive.render`, first passes of 8 spp, max depth 16), with the
seeds of the experiment harness; the error is the paper's tone-mapped MAE against a reference rendered once by
Mitsuba's ``path`` integrator and cached in the harness's layout (``references/{scene}/x{scale}-spp{spp}/``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from guiding.guides.parameters import PAPER_PIXELS, PAPER_SPP_UNIT, SDTreeParameters

#: The reference's seed: the harness's default (config/schema.yaml), apart from the render seeds.
REFERENCE_SEED = 1000003
#: Samples per pixel of the first reference passes (3600 pixels × 1024 spp: 3.7 M paths; later ones may grow).
REFERENCE_PASS_SPP = 1024
#: Max depth of every render and reference (the paper's).
MAX_DEPTH = 16


@dataclass(frozen=True)
class Variant:
    """One row of the equal-spp table.

    Parameters:
      label: what the row shows.
      method: the method name (:mod:`guiding.guides.methods`).
      overrides: parameters changed from the method's defaults (``make_guide`` keywords).
      previous_threshold: the S-tree threshold of the previous setup, 12000·sqrt(spp) whatever the image size
        (``c`` is set so that the present rule gives it at the image's size).
    """

    label: str
    method: str
    overrides: dict = field(default_factory=dict)
    previous_threshold: bool = False

    def guide_overrides(self, pixels: int) -> dict:
        """The ``make_guide`` keywords of this row at an image of ``pixels`` pixels."""
        if not self.previous_threshold:
            return dict(self.overrides)
        # c·sqrt(spp·pixels / (4·PAPER_PIXELS)) = 12000·sqrt(spp), 12000 the default c
        return {**self.overrides, "c": SDTreeParameters().c * math.sqrt(PAPER_SPP_UNIT * PAPER_PIXELS / pixels)}


#: The SD-tree as it was run before (c = 12000 at every image size, its last iteration alone, BSDF sampling alone
#: at D-trees without energy and at BSDFs with a delta lobe).
PREVIOUS_SDTREE = {"combine": "last", "uniform_empty_dtrees": False, "guide_delta_mixtures": False}
#: The rows of the equal-spp table: the baselines, the SD-tree's previous setup, each of its changes taken back
#: alone from the present one, and the present one.
VARIANTS = (
    Variant("brdf", "brdf"),
    Variant("sdtree, previous setup", "sdtree", PREVIOUS_SDTREE, previous_threshold=True),
    Variant("sdtree, threshold unscaled (12000·sqrt(spp))", "sdtree", previous_threshold=True),
    Variant("sdtree, last iteration alone (sdtree-last)", "sdtree-last"),
    Variant("sdtree, BSDF alone at empty D-trees", "sdtree", {"uniform_empty_dtrees": False}),
    Variant("sdtree", "sdtree"),
    Variant("quadtree-grid", "quadtree-grid"),
    Variant("ours", "ours"),
)
#: The rows of the improved-preset table: Müller 2019's learned BSDF share and stochastic spatial filter, alone and
#: together, against Tom94's defaults.
PRESET_VARIANTS = (Variant("brdf", "brdf"), Variant("sdtree", "sdtree"),
                   Variant("sdtree, stochastic spatial filter", "sdtree", {"spatial_filter": "stochastic"}),
                   Variant("sdtree-learned", "sdtree-learned"),
                   Variant("sdtree-learned, stochastic spatial filter", "sdtree-learned",
                           {"spatial_filter": "stochastic"}))
#: The BSDF shares of the share study: Tom94's 0.5 and a range around it.
SHARE_STUDY = (0.3, 0.5, 0.7, 0.9)
#: The rows of the share study: the SD-tree at each fixed share of :data:`SHARE_STUDY`, and the learned share.
SHARE_VARIANTS = (Variant("brdf", "brdf"),
                  *(Variant(f"sdtree, BSDF share {share:g}", "sdtree", {"bsdf_fraction": share})
                    for share in SHARE_STUDY),
                  Variant("sdtree-learned", "sdtree-learned"))
#: Their scenes, at the resolutions of the paper experiments (config/paper.yaml).
PRESET_SCENES = (("cornell-box", 0.125), ("veach-ajar", 0.0625), ("staircase2", 0.0625), ("living-room", 0.0625))


@dataclass(frozen=True)
class SceneStudy:
    """An equal-spp table over several scenes (:func:`scenes_table`; ``sdtree-baseline --part NAME``).

    Parameters:
      variants: its rows, ``brdf`` first.
      output: the stem of its files in the output folder (``.md``, ``.csv``).
      title: what its heading says the rows are.
    """

    variants: tuple[Variant, ...]
    output: str
    title: str


#: The scene studies, by ``--part`` name.
SCENE_STUDIES = {
    "improved-preset": SceneStudy(PRESET_VARIANTS, "sdtree_improved_preset", "The SD-tree with the pieces of Müller "
                                  "2019's improved preset, the BSDF share learned per D-tree (`sdtree-learned`) and "
                                  "the stochastic spatial filter, each and together, against Tom94's defaults "
                                  "(`sdtree`) and `brdf`"),
    "bsdf-share": SceneStudy(SHARE_VARIANTS, "sdtree_bsdf_share", "The SD-tree at fixed BSDF shares (Tom94's 0.5 and "
                             "around it) and with the learned share, against `brdf`"),
}
#: The S-tree constants of the threshold study: the default c = 12000, a quarter of it to four times it.
THRESHOLD_CONSTANTS = (3000.0, 6000.0, 12000.0, 24000.0, 48000.0)


def reference_image(scene_name: str, scale: float, spp: int, cache: Path) -> np.ndarray:
    """Mitsuba ``path``'s image of the scene (``spp`` spp, :data:`REFERENCE_SEED`), read from ``cache`` or rendered
    into it first (``cache/references/{scene}/x{scale}-spp{spp}/image.exr``, the harness's layout)."""
    import mitsuba as mi

    from guiding.imageio import read_exr, write_exr
    from guiding.render.progressive import Budget, render
    from guiding.scenes import load_scene

    path = cache / "references" / scene_name / f"x{scale:g}-spp{spp}" / "image.exr"
    if not path.exists():
        scene = load_scene(scene_name, scale)
        result = render(scene, mi.load_dict({"type": "path", "max_depth": MAX_DEPTH}),
                        Budget(spp=spp, pass_spp=min(REFERENCE_PASS_SPP, spp)), seed=REFERENCE_SEED)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_exr(path, result.image, {"method": "reference-path", "scene": scene_name, "scale": scale, "spp": spp,
                                       "seed": REFERENCE_SEED, "max_depth": MAX_DEPTH})
    return read_exr(path)


def _render(scene, method: str, overrides: dict, spp: int, seed: int) -> dict:
    """One equal-spp render's figures: its image, the final S-tree's leaves (SD-tree), time and hit rate."""
    import mitsuba as mi

    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.guides.methods import make_guide
    from guiding.render.progressive import Budget, render

    props = mi.Properties()
    props["max_depth"] = MAX_DEPTH
    guide = make_guide(method, **overrides)
    result = render(scene, GuidedPathIntegrator(props, guide=guide), Budget(spp=spp), seed=seed, progress=False)
    stats = guide.stats()
    return {"image": result.image, "seconds": result.seconds, "hit_rate": result.hit_rate,
            "spp_in_image": result.spp_in_image, "combine": result.combine,
            "stree_leaves": stats.get("stree_leaves"),
            "stree_threshold": stats.get("last_refine", {}).get("stree_threshold")}


def _describe(overrides: dict) -> str:
    """``make_guide`` keywords as one line (``-`` for none)."""
    return ", ".join(f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}" for k, v in overrides.items()) or "-"


def _pixels(scene) -> int:
    return int(np.prod(scene.sensors()[0].film().crop_size()))


def _runs(scene, reference: np.ndarray, rows: list[tuple[dict, str, dict]], spp: int, seeds: tuple[int, ...]):
    """Render every (row, seed); returns one record per render: the row's fields and the render's figures."""
    from guiding.metrics import evaluate

    records = []
    for fields, method, overrides in rows:
        for seed in seeds:
            run = _render(scene, method, overrides, spp, seed)
            errors = evaluate(run.pop("image"), reference)
            records.append({**fields, "seed": seed, "mae": errors["mae"], "relmse": errors["relmse"], **run})
    return records


def _summary(runs, keys: list[str]):
    """Mean and spread over seeds of each row's errors, with its figures (rows in the order they were run)."""
    import pandas as pd

    frame = pd.DataFrame(runs)
    grouped = frame.groupby(keys, sort=False)
    summary = grouped.agg(mae=("mae", "mean"), mae_std=("mae", "std"), relmse=("relmse", "mean"),
                          hit_rate=("hit_rate", "mean"), seconds=("seconds", "mean"),
                          stree_leaves=("stree_leaves", "mean"), last_threshold=("stree_threshold", "mean"),
                          seeds=("seed", "count")).reset_index()
    return summary, frame


def equal_spp_table(scene_name: str = "veach-ajar", scale: float = 0.0625, spp: int = 1024,
                    seeds: tuple[int, ...] = (0, 1, 2), reference_spp: int = 131072, cache: Path = Path("results"),
                    variants: tuple[Variant, ...] = VARIANTS):
    """MAE (mean and standard deviation over ``seeds``), relMSE, hit rate, seconds, final S-tree leaves and last
    S-tree threshold of each of ``variants`` at ``spp`` spp on the scene, each one's MAE relative to the first
    row's (``mae_vs_first``: −0.25 is 25 % below ``brdf``) and its break-even cost (``break_even_cost``: the cost
    per spp, relative to the first row's, below which it has the lower MAE at equal time, with MAE ∝ 1/sqrt(spp));
    and every run.

    Parameters:
      scene_name, scale: the scene and its resolution scale (default veach-ajar at 1/16: 80 × 45).
      spp: samples per pixel of every render (default 1024).
      seeds: render seeds (default 0, 1, 2, as the harness's Table 2).
      reference_spp: spp of the `path` reference (default 131072).
      cache: folder of the cached references (default results).
      variants: the rows (default :data:`VARIANTS`; the first is the one the others are compared with).
    Returns (summary, runs) as DataFrames.
    """
    from guiding.scenes import load_scene

    scene = load_scene(scene_name, scale)
    reference = reference_image(scene_name, scale, reference_spp, cache)
    pixels = _pixels(scene)
    rows = [({"variant": v.label, "method": v.method, "overrides": _describe(v.guide_overrides(pixels))}, v.method,
             v.guide_overrides(pixels)) for v in variants]
    summary, runs = _summary(_runs(scene, reference, rows, spp, seeds), ["variant", "method", "overrides"])
    summary.insert(summary.columns.get_loc("mae_std") + 1, "mae_vs_first",
                   summary["mae"] / summary["mae"].iloc[0] - 1)
    # With MAE ∝ 1/sqrt(spp), a row costing less than this per spp (relative to the first row) beats it at equal time.
    summary.insert(summary.columns.get_loc("mae_vs_first") + 1, "break_even_cost",
                   (summary["mae"].iloc[0] / summary["mae"]) ** 2)
    return summary, runs


def threshold_table(scales: tuple[float, ...] = (0.0625, 0.125, 0.25), scene_name: str = "veach-ajar",
                    spp: int = 1024, seeds: tuple[int, ...] = (0, 1, 2), reference_spp: int = 131072,
                    cache: Path = Path("results"),
                    constants: tuple[float, ...] = THRESHOLD_CONSTANTS):
    """The S-tree threshold rule at several image sizes: for each scale and S-tree constant ``c`` (with the rule
    ``c·sqrt(paths / (4·1280·720))``), the `sdtree` method's MAE over ``seeds`` (mean, spread), the leaves of its
    final S-tree and its last threshold; and every run.

    Parameters:
      scales: resolution scales of the scene (default 80 × 45, 160 × 90, 320 × 180 for veach-ajar).
      scene_name: the scene (default veach-ajar).
      spp: samples per pixel of every render (default 1024).
      seeds: render seeds (default 0, 1, 2).
      reference_spp: spp of the `path` reference at the first scale (default 131072); the others get the same
        samples per image, ``reference_spp·(scales[0]/scale)²``.
      cache: folder of the cached references (default results).
      constants: the values of ``c`` (default :data:`THRESHOLD_CONSTANTS`).
    Returns (summary, runs) as DataFrames.
    """
    from guiding.scenes import load_scene

    records = []
    for scale in scales:
        ref_spp = max(1, int(round(reference_spp * (scales[0] / scale) ** 2)))
        scene = load_scene(scene_name, scale)
        reference = reference_image(scene_name, scale, ref_spp, cache)
        resolution = "x".join(str(int(v)) for v in scene.sensors()[0].film().crop_size())
        rows = [({"resolution": resolution, "reference_spp": ref_spp, "c": c}, "sdtree", {"c": c}) for c in constants]
        records += _runs(scene, reference, rows, spp, seeds)
    return _summary(records, ["resolution", "reference_spp", "c"])


def scenes_table(scenes=PRESET_SCENES, spp: int = 1024, seeds: tuple[int, ...] = (0, 1, 2),
                 reference_spp: int = 32768, cache: Path = Path("results"), variants=PRESET_VARIANTS):
    """:func:`equal_spp_table` on each of ``scenes`` ((name, scale) pairs, default :data:`PRESET_SCENES`) with
    ``variants`` (default :data:`PRESET_VARIANTS`), one table with a ``scene`` column; and every run."""
    import pandas as pd

    summaries, runs = [], []
    for scene_name, scale in scenes:
        summary, scene_runs = equal_spp_table(scene_name, scale, spp, seeds, reference_spp, cache, variants)
        summaries.append(summary.assign(scene=scene_name, scale=scale))
        runs.append(scene_runs.assign(scene=scene_name, scale=scale))
    first = ["scene", "scale"]
    summary, runs = pd.concat(summaries, ignore_index=True), pd.concat(runs, ignore_index=True)
    return summary[first + [c for c in summary if c not in first]], runs[first + [c for c in runs if c not in first]]
