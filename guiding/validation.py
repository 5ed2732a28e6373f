"""Statistical checks shared by the tests and the result tables: image means of two estimators compared with a
tolerance derived from their measured variance."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

import mitsuba as mi

from .render import pass_seed

if TYPE_CHECKING:
    import pandas as pd

#: Allowed difference in standard errors. With three channels, an unbiased pair fails with probability < 1e-3.
Z_LIMIT = 4.0


def pass_means(scene: mi.Scene, integrator, passes: int, spp: int, seed: int = 0) -> np.ndarray:
    """Per-channel image mean of each of ``passes`` passes, shape (passes, 3).

    A guide attached to the integrator is prepared and updated between passes, as the progressive renderer does:
    every pass is an unbiased estimate given the tables the previous passes built.
    """
    guide = getattr(integrator, "guide", None)
    if guide is not None:
        guide.prepare(scene)
    means = []
    for index in range(passes):
        image = mi.render(scene, integrator=integrator, spp=spp, seed=pass_seed(seed, index))
        means.append(np.asarray(image, dtype=np.float64)[..., :3].mean(axis=(0, 1)))
        if guide is not None:
            guide.update((index + 1) * spp)
    return np.array(means)


def z_scores(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-channel |mean(a) − mean(b)| in units of the standard error of that difference."""
    se2 = a.var(axis=0, ddof=1) / len(a) + b.var(axis=0, ddof=1) / len(b)
    return np.abs(a.mean(axis=0) - b.mean(axis=0)) / np.sqrt(se2)


def unbiasedness_table(scene_name: str = "door-ajar", scale: float = 0.1, passes: int = 24, spp: int = 32,
                       methods: list[str] | None = None) -> pd.DataFrame:
    """Image mean of each grid method against Mitsuba's ``path`` integrator, with z-scores and relative bias."""
    import pandas as pd

    from .guides import RULES, SAMPLERS
    from .integrator import GuidedPathIntegrator
    from .methods import make_guide
    from .scenes import load_scene

    scene = load_scene(scene_name, scale)
    methods = methods or [f"{rule}-{sampler}" for rule in RULES for sampler in SAMPLERS] + ["ours-uniform-proposals"]
    reference = pass_means(scene, mi.load_dict({"type": "path", "max_depth": 16}), passes, spp, seed=1000)
    rows = []
    for method in methods:
        means = pass_means(scene, GuidedPathIntegrator(guide=make_guide(method)), passes, spp, seed=1)
        z = z_scores(means, reference)
        relative = means.mean(axis=0) / reference.mean(axis=0) - 1
        rows.append({"method": method, "mean": means.mean(), "reference_mean": reference.mean(),
                     "relative_difference": float(relative.mean()), "max_z": float(z.max()),
                     "relative_standard_error": float((means.std(axis=0, ddof=1) / np.sqrt(passes)
                                                       / reference.mean(axis=0)).mean()),
                     "agrees": bool((z < Z_LIMIT).all())})
    return pd.DataFrame(rows)


def learning_table(scene_name: str = "door-ajar", scale: float = 0.25, spp: int = 256, reference_spp: int = 4096,
                   methods: tuple[str, ...] = ("brdf", "ours", "ours-uniform-proposals", "ours-no-rejopt",
                                               "ours-expected", "sdtree", "quadtree-grid")) -> pd.DataFrame:
    """MAE, relMSE, hit rate and time of each method at equal spp against a `path` reference."""
    import pandas as pd

    from .integrator import GuidedPathIntegrator
    from .methods import make_guide
    from .metrics import evaluate
    from .render import Budget, render
    from .scenes import load_scene

    scene = load_scene(scene_name, scale)
    reference = render(scene, mi.load_dict({"type": "path", "max_depth": 16}),
                       Budget(spp=reference_spp, pass_spp=64), seed=1000, progress=False)
    rows = []
    for method in methods:
        result = render(scene, GuidedPathIntegrator(guide=make_guide(method)), Budget(spp=spp), seed=1,
                        progress=False)
        errors = evaluate(result.image, reference.image)
        rows.append({"method": method, "spp": result.spp, "mae": errors["mae"], "relmse": errors["relmse"],
                     "hit_rate": result.hit_rate, "seconds": result.seconds,
                     "update_seconds": sum(p.update_seconds for p in result.passes)})
    return pd.DataFrame(rows)
