"""Comparing image means of two estimators with a tolerance derived from their measured variance."""

from __future__ import annotations

import numpy as np

import mitsuba as mi

from guiding.render import pass_seed

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
