"""Kim & Kim's "Quadtree" baseline (method ``quadtree-grid``): one D-tree per cell of a uniform ``S³`` grid,
split-only, energies accumulated over the whole render and the trees refreshed after every pass. It shares the
D-tree mixture and Monte Carlo recording of :class:`~guiding.guides.trees.tree_guide.TreeGuide`.
"""

from __future__ import annotations

import time

import drjit as dr
import mitsuba as mi
import numpy as np

from guiding.guides.base import UpdateResult
from guiding.guides.trees.dtree import SPLIT_GROW, DeviceForest, Forest
from guiding.guides.grid_cells import GridCells
from guiding.guides.parameters import QuadtreeGridParameters, with_overrides
from guiding.guides.trees.tree_guide import TreeGuide


class QuadtreeGridGuide(TreeGuide):
    """One D-tree per cell of a uniform ``S³`` grid over the scene's bounding box (Kim & Kim's "Quadtree").

    Split-only: a leaf whose share of its tree's energy exceeds ``rho`` is subdivided (its energy spread evenly over
    the new quadrants); nothing is merged. Energies accumulate over the whole render and the trees are refreshed
    after every pass (the same structure records and samples).

    Parameters:
      parameters: :class:`~guiding.guides.parameters.QuadtreeGridParameters` (``spatial_resolution`` S, ``rho``,
        ``dtree_max_depth``, ``bsdf_fraction``, ``max_nodes``, ``learn_bsdf_fraction``), default
        ``QuadtreeGridParameters()``.
      name: the method name shown in tables (default ``quadtree-grid``).
      overrides: parameters changed from ``parameters`` (``QuadtreeGridGuide(spatial_resolution=4)``).
    """

    name = "quadtree-grid"

    def __init__(self, parameters: QuadtreeGridParameters | None = None, name: str | None = None, **overrides):
        super().__init__(with_overrides(parameters or QuadtreeGridParameters(), overrides), name)
        self.S = self.parameters.spatial_resolution
        self._cells = GridCells(self.S)

    def prepare(self, scene: mi.Scene) -> None:
        self._cells.set_bounds(scene.bbox())
        n = self._cells.count
        self._forest = Forest.empty(n).rebuild(np.arange(n), SPLIT_GROW, self.rho, self.dtree_max_depth,
                                               keep_energy=True, max_nodes=self.max_nodes)
        self._sampling = self._recording = DeviceForest(self._forest, self.jump_levels)
        self._fraction = self._learned_shares(n)
        self._reset_accumulators()
        self.built = False

    def _locate(self, p, active):
        return self._cells.cell(p)

    def update_due(self, spp_done: int) -> int:
        return spp_done      # its D-trees grow after every pass

    def update(self, spp_done: int) -> UpdateResult:
        start = time.perf_counter()
        energy, _ = self._pull()
        self._forest.deposit(energy, accumulate=True)
        self._forest = self._forest.rebuild(np.arange(self._forest.n_trees), SPLIT_GROW, self.rho,
                                            self.dtree_max_depth, keep_energy=True, max_nodes=self.max_nodes)
        host_seconds = time.perf_counter() - start
        self._sampling = self._recording = DeviceForest(self._forest, self.jump_levels)
        self._reset_accumulators()
        self.built = True
        dr.sync_thread()
        stats = {"refine_seconds": time.perf_counter() - start,
                 "refine_host_seconds": host_seconds, "energy_recorded": float(energy.sum()), **self.sanitised}
        if self._fraction:
            stats.update(self._fraction.step())
        stats.update(self._structure_stats())
        return UpdateResult(stats)

    def _structure_stats(self) -> dict:
        stats = {"grid_cells": self._cells.count, "memory_bytes": self._memory_bytes()}
        stats.update(self._forest_stats(self._forest, "dtree"))
        return stats

    def stats(self) -> dict:
        out = {**self._tree_stats(), "S": self.S}
        if hasattr(self, "_forest"):
            out.update(self._structure_stats())
        return out
