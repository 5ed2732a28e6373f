"""Practical path guiding (Müller, Gross, Novák 2017): the SD-tree.

Two guides share the D-tree code (:mod:`guiding.guides.trees.dtree`):

* :class:`SDTreeGuide` (method ``sdtree``): one D-tree per leaf of a binary spatial tree (S-tree,
  :mod:`guiding.guides.trees.stree`) over the scene's bounding box (made cubic, as in Müller's code), both refined after
  each iteration of a doubling schedule from the data of that iteration alone. Its defaults are those of Tom94's
  guided_path.cpp, with the S-tree threshold scaled to the image (:class:`~guiding.guides.parameters.SDTreeParameters`).
* :class:`QuadtreeGridGuide` (method ``quadtree-grid``): one D-tree per cell of a uniform ``S³`` grid, split-only,
  energies accumulated over the whole render and the trees refreshed after every pass (the "Quadtree" column of
  Kim & Kim 2021).
"""

from __future__ import annotations

import math
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from guiding.guides.base import UpdateResult
from guiding.guides.trees.dtree import SPLIT_COPY, SPLIT_REFINE, DeviceForest, Forest, padded
from guiding.guides.parameters import PAPER_SPP_UNIT, SDTreeParameters, with_overrides
from guiding.guides.trees.stree import STree, iteration_length, stree_locate
from guiding.guides.trees.tree_guide import TreeGuide


class SDTreeGuide(TreeGuide):
    """Müller et al. 2017's SD-tree (see the module docstring).

    Parameters:
      parameters: :class:`~guiding.guides.parameters.SDTreeParameters` (``c``, ``c_pixels``, ``rho``,
        ``dtree_max_depth``, ``bsdf_fraction``, ``max_nodes``, ``uniform_empty_dtrees``, ``guide_delta_mixtures``,
        ``learn_bsdf_fraction``, ``base_spp``, ``budget_spp``, ``combine``, ``spatial_filter``; each documented
        there), default ``SDTreeParameters()``.
      name: the method name shown in tables (default ``sdtree``).
      overrides: parameters changed from ``parameters`` (``SDTreeGuide(c=1000)``).

    S-tree threshold (:meth:`stree_threshold`): a leaf splits when the vertices recorded in it during an iteration
    exceed ``c·sqrt(paths / (4·c_pixels))``, ``paths`` the paths that iteration traced (counted from its vertex
    logs: pixels × spp). At 1280 × 720 this is Tom94's ``c·sqrt(spp/4)``; the paper's ``c·sqrt(2^k)`` had
    iterations of 2^k of his 4-spp passes. Here iteration 0 already has ``base_spp`` spp.

    Schedule: :meth:`update` is called after every pass; it refines when the spp done reach the end of the
    current iteration. ``update`` reports ``iteration_done`` for the pass that closed an iteration: a renderer that
    keeps only the last iteration (Müller's final image) restarts its accumulation there. Under a seconds budget
    the guide has no end: the renderer asks :meth:`iteration_spp` at each boundary and calls :meth:`stop_training`
    when the next iteration would not fit (:mod:`guiding.render.progressive`).
    """

    name = "sdtree"

    def __init__(self, parameters: SDTreeParameters | None = None, name: str | None = None, **overrides):
        super().__init__(with_overrides(parameters or SDTreeParameters(), overrides), name)
        self.c = self.parameters.c
        self.c_pixels = self.parameters.c_pixels
        self.base_spp = self.parameters.base_spp
        self.budget_spp = self.parameters.budget_spp
        self.combine = self.parameters.combine
        self.spatial_filter = self.parameters.spatial_filter
        self._recording_on = True
        self._pass_paths = mi.UInt32(0)  # paths recorded since the last update (counted in the kernel)

    # ------------------------------------------------------------------------------------ schedule
    def set_budget(self, spp: int | None) -> None:
        """Tell the guide the total spp budget (before the first pass), so the last iteration runs to its end."""
        self.budget_spp = spp

    def _start_iteration(self, spp_start: int) -> None:
        length, self.is_final_iteration = iteration_length(self.base_spp, self.iteration, spp_start,
                                                           self.budget_spp)
        self.iteration_start_spp = spp_start
        self.iteration_end_spp = spp_start + max(length, 1)
        self._iteration_paths = 0      # paths traced in the iteration's recording passes (the S-tree threshold)

    def stree_threshold(self, paths: int) -> float:
        """Vertices an S-tree leaf must have recorded, in an iteration that traced ``paths`` paths, to split:
        ``c·sqrt(paths / (PAPER_SPP_UNIT·c_pixels))``. Growing as the square root of the samples, it lets the
        number of leaves and the vertices per leaf grow alike, whatever the image size (c ∝ sqrt(pixels) at a
        given spp; results/README.md, "The SD-tree baseline studies", measures it at three image sizes)."""
        return self.c * math.sqrt(paths / (PAPER_SPP_UNIT * self.c_pixels))

    def iteration_spp(self) -> int | None:
        """Length in spp of the iteration the next pass belongs to (a renderer under a seconds budget checks
        that it fits before letting it run); None once training stopped, when it runs to the end of the budget."""
        return None if self.iteration_end_spp is None else self.iteration_end_spp - self.iteration_start_spp

    def update_due(self, spp_done: int) -> int | None:
        """The end of the current iteration while it records; None once the distributions are final."""
        return self.iteration_end_spp if self.records() and not self.is_final_iteration else None

    def stop_training(self) -> None:
        """Freeze the distributions (e.g. when a time budget leaves no room for another iteration): no more
        refinement and no more recording (the next pass traces a kernel without the recording code). The
        current iteration becomes the final one and runs to the end of the budget, so it has no end spp."""
        self.is_final_iteration = True
        self._recording_on = False
        self.iteration_end_spp = None

    # ------------------------------------------------------------------------------------ host side
    def prepare(self, scene: mi.Scene) -> None:
        bbox = scene.bbox()
        self.stree = STree(np.array(bbox.min), np.array(bbox.max))
        self._s_device = self.stree.to_device(leaf_boxes=self._splat_jittered())
        self._sampling_host = Forest.empty(1)
        self._recording_host = Forest.empty(1).rebuild([0], SPLIT_REFINE, self.rho, self.dtree_max_depth,
                                                       keep_energy=False, max_nodes=self.max_nodes)
        self._upload_forests()
        self._fraction = self._learned_shares(1)
        self._reset_accumulators()
        self._recording_on = True
        self.built = False
        self.iteration = 0
        self._start_iteration(0)
        self._last_refine = {}

    def _upload_forests(self) -> None:
        """The sampling and recording forests on the device, and where each sampling leaf lies in the recording
        trees (:meth:`Forest.overlay`)."""
        self._sampling = DeviceForest(self._sampling_host, self.jump_levels)
        self._recording = DeviceForest(self._recording_host, self.jump_levels, densities=False)
        overlay = self._sampling_host.overlay(self._recording_host)
        self._overlay = None if overlay is None else mi.UInt32(padded(overlay))

    def _locate(self, p, active):
        return stree_locate(self._s_device, p, active)

    def _splat_jittered(self) -> bool:
        return self.spatial_filter == "stochastic"

    def _splat_tree(self, si, vertex, tree, active) -> mi.UInt32:
        """With the stochastic spatial filter, the D-tree at a point drawn uniformly in a box of the vertex's leaf
        size around it (Tom94's ``EStochasticBox``; he clips the point to the root box, and :func:`stree_locate`
        finds the same leaf for a point outside it); else the vertex's own. (A vertex located without ``sample``'s
        jitter splats at its own.)"""
        if not self._splat_jittered() or vertex is None or vertex.jitter is None:
            return tree
        extent = dr.gather(mi.Vector4f, self._s_device["leaf_extent"], tree, active)
        offset = (vertex.jitter - 0.5) * mi.Vector3f(extent.x, extent.y, extent.z)
        return self._locate(si.p + offset, active)

    def new_paths(self, size: int, max_depth: int):
        if self.records():
            # Counted on the device, not here: a frozen pass (guiding.render.frozen_pass) does not run this method.
            dr.scatter_reduce(dr.ReduceOp.Add, self._pass_paths, 1, dr.zeros(mi.UInt32, size))
        return super().new_paths(size, max_depth)

    def records(self) -> bool:
        return self._recording_on

    def update(self, spp_done: int) -> UpdateResult:
        """At the end of an iteration, refine from what its passes recorded (their render kernels filled the
        accumulators). ``iteration`` in the returned statistics is the iteration the pass belonged to;
        ``iteration_done`` marks the pass that ended it (the distributions change after it; a renderer keeping only
        the last iteration restarts its accumulation there)."""
        pass_iteration = self.iteration
        recorded = self.records()
        self._iteration_paths += int(self._pass_paths[0])
        self._pass_paths = mi.UInt32(0)
        stats = {"refine_seconds": 0.0}
        iteration_done = recorded and not self.is_final_iteration and spp_done >= self.iteration_end_spp
        if recorded and self._fraction:
            stats.update(self._fraction.step())
        if iteration_done:
            stats.update(self._refine())
            self.iteration += 1
            self._start_iteration(spp_done)
            if self.is_final_iteration and self.budget_spp is not None:
                self._recording_on = False   # Müller: the last iteration does not record
        stats.update(self._structure_stats())
        stats["iteration"] = pass_iteration
        return UpdateResult(stats, iteration_done)

    def _refine(self) -> dict:
        start = time.perf_counter()
        energy, counts = self._pull()
        built = self._recording_host
        built.deposit(energy)
        threshold = self.stree_threshold(self._iteration_paths)
        sources = self.stree.refine(counts, threshold)
        if self._fraction:
            self._fraction.remap(sources)
        self._sampling_host = built.rebuild(sources, SPLIT_COPY)
        self._recording_host = built.rebuild(sources, SPLIT_REFINE, self.rho, self.dtree_max_depth,
                                             keep_energy=False, max_nodes=self.max_nodes)
        host_seconds = time.perf_counter() - start
        self._s_device = self.stree.to_device(leaf_boxes=self._splat_jittered())
        self._upload_forests()
        self._reset_accumulators()
        self.built = True
        dr.sync_thread()
        self._last_refine = {"refine_seconds": time.perf_counter() - start, "refine_host_seconds": host_seconds,
                             "stree_threshold": threshold, "paths_recorded": self._iteration_paths,
                             "vertices_recorded": float(counts.sum()),
                             "energy_recorded": float(energy.sum()), **self.sanitised}
        return dict(self._last_refine)

    def _structure_stats(self) -> dict:
        stats = {"iteration": self.iteration, "stree_nodes": self.stree.n_nodes, "stree_leaves": self.stree.n_leaves,
                 "stree_max_depth": max(self.stree.depth),
                 "memory_bytes": self._memory_bytes() + sum(4 * dr.width(a) for a in self._s_device.values()),
                 "iteration_start_spp": self.iteration_start_spp, "iteration_end_spp": self.iteration_end_spp,
                 "final_iteration": self.is_final_iteration}
        stats.update(self._forest_stats(self._sampling_host, "dtree"))
        stats.update(self._forest_stats(self._recording_host, "dtree_recording"))
        return stats

    def stats(self) -> dict:
        out = {**self._tree_stats(), "c": self.c, "c_pixels": self.c_pixels, "base_spp": self.base_spp,
               "budget_spp": self.budget_spp, "combine": self.combine, "spatial_filter": self.spatial_filter}
        if hasattr(self, "stree"):
            out.update(self._structure_stats())
            out["last_refine"] = self._last_refine
        return out
