"""The BSDF share of the tree guides' mixture, learned per D-tree (Müller 2019, "Practical Path Guiding in
Production"; Tom94's guided_path.cpp with ``bsdfSamplingFractionLoss = "kl"``).

A vertex samples the one-sample mixture ``m_α = α·p_bsdf + (1 − α)·p_tree``. The share α of each D-tree is the one
that minimises the KL divergence from the normalised product ``f·cos·L`` to ``m_α``; up to a constant, the loss
estimated from the recorded vertices ``i`` is

    ``ℒ(α) = −Σ c_i·log m_α(ω_i)``,  ``c_i = mean(f·cos·L)(ω_i) / m_{α₀}(ω_i) = mean(w_i·L_i)``,

with ``α₀`` the share the pass sampled with and ``w_i`` the vertex's logged weight (Russian roulette's ``1/q``
included, and 0 where roulette ended the path, which keeps the sum unbiased). ℒ is convex in α: with
``s_i = ∂ log m_α/∂α = (p_bsdf − p_tree)/m_{α₀}`` at the sampled direction (``1/α₀`` at a direction of a BSDF's
delta lobe, which only the BSDF share reaches: there ``m_α`` is α times the lobe's probability), its derivative at
α₀ is ``−G = −Σ c_i·s_i`` and its second derivative ``H = Σ c_i·s_i²``. Vertices with ``c = 0`` add nothing, and
count for nothing (Tom94's ``product > 0``). Each D-tree sums G and H over a pass (in the render kernel, during the
backward walk) and, after the pass, takes one Newton step ``α ← α₀ + G/H``.

Tom94 takes an Adam step per recorded vertex, one vertex after another under a lock; a SIMD path loop records
thousands of vertices at once, and the Newton step uses them all at once. A tree steps only with at least
:data:`MIN_VERTICES` vertices recorded since its last step, by at most :data:`MAX_STEP`, and α stays within
[:data:`MIN_SHARE`, :data:`MAX_SHARE`]: Tom94 lets α reach 2·10⁻⁹, where a direction the D-tree does not cover gets
a weight of 10⁹·ρ; the floor bounds every weight by ρ/MIN_SHARE, as the grid guide's ``min_bsdf_share`` does.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from guiding.guides.trees.dtree import capacity, padded
from guiding.guides.parameters import LEARNED_SHARE_RANGE
from guiding.guides.pass_sums import copied_per_thread

MIN_SHARE, MAX_SHARE = LEARNED_SHARE_RANGE
#: Most a share moves in one step.
MAX_STEP = 0.25
#: Least vertices a tree must have recorded since its last step to step again: c is heavy-tailed (a path that finds
#: a light through a direction of low density), and the ratio G/H of a few vertices follows their largest c.
MIN_VERTICES = 1024
#: Fewest trees the sums hold (64 KiB): they are copied per thread
#: (:func:`~guiding.guides.pass_sums.copied_per_thread`), and the floor keeps the S-tree's growth from recompiling the
#: render kernel until it has more leaves.
SUMS_MIN_TREES = 1 << 12


class LearnedBsdfFraction:
    """The BSDF share of each of ``n_trees`` D-trees, starting at ``initial``, and the sums of its pass.

    Life cycle: the render kernel reads :meth:`share` when it samples and calls :meth:`record` in its backward walk;
    after the pass, :meth:`step` moves the shares and clears the sums; when the trees are rebuilt from ``sources``
    (new tree i from old tree ``sources[i]``), :meth:`remap` gives each new tree its source's share."""

    def __init__(self, n_trees: int, initial: float):
        self.host = np.full(n_trees, initial, dtype=np.float64)
        self._upload()

    def _upload(self, sums: np.ndarray | None = None) -> None:
        """The shares to the device, with ``sums`` (None: cleared): count, G and H per tree, and a fourth float
        that keeps a tree's three in one packet scatter per vertex."""
        self.shares = mi.Float(padded(self.host.astype(np.float32)))
        table = np.zeros(capacity(4 * max(len(self.host), SUMS_MIN_TREES)), dtype=np.float32)
        if sums is not None:
            table[: len(sums)] = sums
        self._sums = mi.Float(padded(table))
        dr.eval(self.shares, self._sums)

    # ------------------------------------------------------------------------------------- device side
    def share(self, tree: mi.UInt32, active: mi.Bool) -> mi.Float:
        """The BSDF share of D-trees ``tree``."""
        return dr.gather(mi.Float, self.shares, tree, active)

    def record(self, tree: mi.UInt32, c: mi.Float, s: mi.Float, active: mi.Bool) -> None:
        """Add a recorded vertex of D-tree ``tree`` to its sums: ``c`` = mean(w·L) and ``s`` = (p_bsdf − p_tree)/m
        at its sampled direction (see the module docstring)."""
        cs = c * s
        usable = active & (c > 0) & dr.isfinite(cs * s)
        dr.scatter_reduce(dr.ReduceOp.Add, self._sums, mi.Vector4f(1, cs, cs * s, 0), tree, usable,
                          mode=copied_per_thread(self._sums))

    # --------------------------------------------------------------------------------------- host side
    def step(self) -> dict:
        """One Newton step of every tree whose sums hold at least :data:`MIN_VERTICES` vertices (and are finite);
        their sums are cleared, the others' kept for the next pass: their share, which the sums were taken at, has
        not changed (nor, in the SD-tree, their D-tree until the next refinement, which clears every sum; the
        quadtree grid's D-trees grow after every pass, and its kept sums mix the densities of a few passes).
        Returns the shares' mean and range and the number of trees that stepped."""
        n = len(self.host)
        sums = self._sums.numpy()[: 4 * n].reshape(n, 4).astype(np.float64)
        count, g, h = sums[:, 0], sums[:, 1], sums[:, 2]
        full = count >= MIN_VERTICES
        steps = full & (h > 0) & np.isfinite(g) & np.isfinite(h)
        move = np.clip(np.divide(g, h, out=np.zeros_like(g), where=steps), -MAX_STEP, MAX_STEP)
        self.host = np.clip(self.host + np.where(steps, move, 0), MIN_SHARE, MAX_SHARE)
        sums[full] = 0
        self._upload(sums.ravel())
        return {"bsdf_fraction_mean": float(self.host.mean()), "bsdf_fraction_min": float(self.host.min()),
                "bsdf_fraction_max": float(self.host.max()), "bsdf_fraction_steps": int(steps.sum())}

    def remap(self, sources: np.ndarray) -> None:
        """New trees from old ones (tree i from ``sources[i]``): each keeps its source's share; the sums are
        cleared."""
        self.host = self.host[np.asarray(sources, dtype=np.int64)]
        self._upload()
