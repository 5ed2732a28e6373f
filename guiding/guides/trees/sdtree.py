"""Practical path guiding (Müller, Gross, Novák 2017): the SD-tree, and Kim & Kim's simplified "Quadtree" baseline.

Two guides share the D-tree code (:mod:`guiding.guides.trees.dtree`):

* :class:`SDTreeGuide` (method ``sdtree``): one D-tree per leaf of a binary spatial tree (S-tree,
  :mod:`guiding.guides.trees.stree`) over the scene's bounding box (made cubic, as in Müller's code), both refined after
  each iteration of a doubling schedule from the data of that iteration alone. Its defaults are those of Tom94's
  guided_path.cpp, with the S-tree threshold scaled to the image (:class:`~guiding.guides.parameters.SDTreeParameters`).
* :class:`QuadtreeGridGuide` (method ``quadtree-grid``): one D-tree per cell of a uniform ``S³`` grid, split-only,
  energies accumulated over the whole render and the trees refreshed after every pass (the "Quadtree" column of
  Kim & Kim 2021).

**Monte Carlo recording** (:mod:`guiding.guides.grid.vertex_log`). In the path loop, :meth:`record` logs every
vertex of a path in the local memory of its lane: the emitted radiance ``Le`` (RGB), the weight ``w = f·cos/pdf``
including Russian roulette (RGB, 0 where the path ends), and, for vertices whose sampled direction was traced and not
delta-sampled, the leaf slot of that direction in the recording D-tree and its pdf. Once the path is complete, still
in the render kernel (:meth:`finish_paths`), it is walked backwards, ``L ← Le_i + w_i·L``, adding
``mean_rgb(L_{i+1}) / pdf_i`` (the incident radiance along the sampled direction over its pdf) to the leaf, and one
to its count of vertices: one packet scatter of the float64 (energy, count) pair per vertex, without atomics on the
CPU (:mod:`~guiding.guides.pass_sums`), not a scatter per value, each a loop over the packet's lanes with an atomic
per lane. The log takes no device memory; :meth:`update` reads the sums the kernel filled, and counts the vertices
of each D-tree (S-tree leaf) from those of its leaves.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from guiding.guides.base import Guide, NoPathState, UpdateResult, rgb_mean
from guiding.guides.trees.bsdf_fraction import LearnedBsdfFraction
from guiding.guides.trees.dtree import ONE_MINUS_EPS, SPLIT_COPY, SPLIT_GROW, SPLIT_REFINE, DeviceForest, Forest, capacity, padded
from guiding.guides.grid_cells import GridCells
from guiding.guides.parameters import PAPER_SPP_UNIT, QuadtreeGridParameters, SDTreeParameters, TreeParameters, with_overrides
from guiding.guides.pass_sums import add_target, footprint, pass_sums
from guiding.guides.trees.stree import STree, iteration_length, stree_locate
from guiding.guides.grid.vertex_log import NO_RECORD, VertexLog, known_or_found, walk_backward

#: Fewest leaf slots the recorded sums hold (1 MiB of float64 pairs): they are copied per thread
#: (:func:`~guiding.guides.pass_sums.copied_per_thread`), and the floor keeps the trees' growth from recompiling the
#: render kernel at every refinement while they have fewer than 2^14 nodes (beyond, once per doubling).
LEAF_SUMS_MIN_SLOTS = 1 << 16


@dataclass
class TreeVertex:
    """What :meth:`_TreeGuide.locate` hands to ``sample`` and ``record`` at a vertex: its D-tree, and the leaf of
    the sampling D-tree that the direction ``sample`` took lies in, found by the descent that drew it (or found its
    density): its slot (NO_RECORD or None where the mixture was not sampled) and the direction's point in the D-tree's
    square. ``record`` finds the recording leaf from there: the same slot where the sampling and the recording
    D-trees are one (the quadtree grid's), the recording trees' overlay of the leaf elsewhere (the SD-tree's), a
    descent of the recording tree where neither applies."""

    tree: mi.UInt32
    slot: mi.UInt32 = None
    point: mi.Point2f = None
    #: ∂ log m/∂α at the direction the mixture drew ((p_bsdf − p_tree)/m; 1/α at a delta lobe's), 0 where the
    #: mixture was not sampled: what the learned BSDF share needs of the vertex (:mod:`~guiding.guides.trees.bsdf_fraction`;
    #: None unless it is learned).
    score: mi.Float = None
    #: Three uniform numbers that place the vertex's splat in the SD-tree's stochastic spatial filter (None without).
    jitter: mi.Point3f = None


class _TreeGuide(Guide):
    """What the SD-tree and the quadtree grid share: the D-tree mixture sampler and Monte Carlo recording.

    Subclasses provide ``_locate(p, active)`` (the D-tree index of a position), ``self._sampling`` and
    ``self._recording`` (:class:`DeviceForest`), and their update rule; they set ``built`` once their trees
    have been built from recorded data (from then on, with ``uniform_empty_dtrees``, a D-tree without energy is
    sampled, uniformly).
    """

    def __init__(self, parameters: TreeParameters, name: str | None):
        self.parameters = parameters
        self.name = name or type(self).name
        self.bsdf_fraction = parameters.bsdf_fraction
        self.rho = parameters.rho
        self.dtree_max_depth = parameters.dtree_max_depth
        self.max_nodes = parameters.max_nodes
        self.uniform_empty_dtrees = parameters.uniform_empty_dtrees
        self.guide_delta_mixtures = parameters.guide_delta_mixtures
        self.learn_bsdf_fraction = parameters.learn_bsdf_fraction
        self.jump_levels = parameters.jump_levels
        self._fraction: LearnedBsdfFraction | None = None   # the learned shares (made by prepare)
        self.built = False
        self._log: VertexLog | None = None               # how the paths of the pass log their vertices
        self._sampling: DeviceForest | None = None
        self._recording: DeviceForest | None = None
        self._overlay = None      # where each sampling leaf lies in the recording trees (Forest.overlay), if apart
        self._leaf_sums = None                           # (energy, vertices) per recording leaf slot (pass_sums)
        self.sanitised = {"dropped_entries": 0}          # bad accumulator entries of the last update (_pull)

    def records(self) -> bool:
        return True

    @property
    def built(self) -> bool:
        """Whether the trees have been built from recorded data."""
        return self._built

    @built.setter
    def built(self, value: bool) -> None:
        self._built = value
        # A device flag, not a literal of the trace: the kernel reads it as a parameter, so the first build neither
        # recompiles the render nor leaves a frozen pass (guiding.render.frozen_pass) with the flag of its recording.
        self._empty_dtrees_sampled = dr.opaque(mi.Bool, self.uniform_empty_dtrees and value)

    # -------------------------------------------------------------------------------------- device side
    def _locate(self, p, active):
        raise NotImplementedError

    def new_paths(self, size: int, max_depth: int):
        if not self.records():
            return NoPathState()
        # With a learned share, the vertex's D-tree too: a delta lobe's vertex has no recording leaf to find it by.
        learned = {"score": mi.Float, "tree": mi.UInt32} if self._fraction else {}
        self._log = VertexLog(max_depth, {"pdf": mi.Float, **learned})
        return self._log.new_paths(size)

    def _learned_shares(self, n_trees: int) -> LearnedBsdfFraction | None:
        """The learned BSDF shares of ``n_trees`` fresh D-trees, or None where the share is ``bsdf_fraction``."""
        return LearnedBsdfFraction(n_trees, self.bsdf_fraction) if self.learn_bsdf_fraction else None

    def _tree_stats(self) -> dict:
        """The method's name and the parameters the tree guides share (:class:`TreeParameters`), for ``stats()``."""
        return {"method": self.name,
                **{f.name: getattr(self.parameters, f.name) for f in dataclasses.fields(TreeParameters)}}

    def _share(self, tree: mi.UInt32, active: mi.Bool):
        """The BSDF share of the mixture at D-trees ``tree``: learned, or ``bsdf_fraction``."""
        return self._fraction.share(tree, active) if self._fraction else self.bsdf_fraction

    def guided_mask(self, tree, bsdf: mi.BSDFPtr, active):
        """Lanes that mix in the D-tree: a BSDF with a smooth lobe (without ``guide_delta_mixtures``: a BSDF
        without any delta lobe), and a D-tree that has seen energy (with ``uniform_empty_dtrees``, once the trees
        are built, any D-tree: one without energy is uniform, its quadrant probabilities 1/4 each)."""
        guidable = self.guides(bsdf, active)
        return guidable & (dr.gather(mi.Bool, self._sampling.has_energy, tree, guidable) | self._empty_dtrees_sampled)

    def guides(self, bsdf: mi.BSDFPtr, active) -> mi.Bool:
        """Lanes whose BSDF has a lobe the D-tree may guide (the BSDF flags alone)."""
        flags = bsdf.flags()
        if self.guide_delta_mixtures:
            return active & mi.has_flag(flags, mi.BSDFFlags.Smooth)
        return active & ~mi.has_flag(flags, mi.BSDFFlags.Delta)

    def pdf(self, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, bsdf_ctx: mi.BSDFContext, wo, active=True):
        """The density (solid angle) with which :meth:`sample` draws local direction ``wo`` at ``si`` (of its
        smooth part: a delta lobe, which ``bsdf.pdf`` leaves out too, adds a point mass)."""
        active = mi.Bool(active)
        tree = self._locate(si.p, active)
        guided = self.guided_mask(tree, bsdf, active)
        wo_world = si.to_world(wo)
        p_bsdf = bsdf.pdf(bsdf_ctx, si, wo, active)
        p_tree = self._sampling.pdf_dir(tree, wo_world, guided)
        share = self._share(tree, guided)
        return dr.select(guided, share * p_bsdf + (1 - share) * p_tree, p_bsdf)

    def locate(self, si, bsdf, active):
        """The vertex's D-tree (its S-tree leaf, or grid cell), in the lanes sampled from a D-tree or recorded (a
        BSDF it guides, or one with a smooth lobe), found once per vertex (:class:`TreeVertex`)."""
        return TreeVertex(self._locate(si.p, self.guides(bsdf, active)
                                       | (active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth))))

    @dr.syntax
    def sample(self, scene, sampler, si, bsdf, bsdf_ctx, active, vertex=None):
        """The mixture where the BSDF has a lobe to guide, one BSDF sample elsewhere: a branch, not a select, so that
        packets of lanes with nothing to guide (delta BSDFs, emitters, escaped paths) skip the trees' descents."""
        active = mi.Bool(active)
        s1 = sampler.next_1d(active)
        s2 = sampler.next_2d(active)
        guidable = self.guides(bsdf, active)
        tree = None if vertex is None else vertex.tree
        if guidable:
            bs, weight, slot, point, score = self._mixture_sample(si, bsdf, bsdf_ctx, s1, s2, guidable, tree)
        else:
            bs, weight = bsdf.sample(bsdf_ctx, si, s1, s2, active & ~guidable)
            slot, point, score = mi.UInt32(NO_RECORD), mi.Point2f(0), mi.Float(0)
        if dr.hint(vertex is not None and self.records(), mode="scalar"):
            vertex.slot, vertex.point = slot, point
        if dr.hint(vertex is not None and self._fraction is not None, mode="scalar"):
            vertex.score = score
        if dr.hint(vertex is not None and self._splat_jittered() and self.records(), mode="scalar"):
            vertex.jitter = mi.Point3f(sampler.next_1d(active), sampler.next_1d(active), sampler.next_1d(active))
        return bs, weight

    def _mixture_sample(self, si, bsdf, bsdf_ctx, s1, s2, active, tree=None):
        """One sample of the mixture of BSDF sampling and the vertex's D-tree ``tree`` (None: located here) for the
        samples ``s1``, ``s2`` (BSDF sampling alone where the D-tree holds no energy): the sample, its weight, the
        leaf slot of its direction in the sampling D-tree (NO_RECORD where the tree was not descended) and its point
        in the tree's square, and its score (:class:`TreeVertex`)."""
        tree = self._locate(si.p, active) if tree is None else tree
        guided = self.guided_mask(tree, bsdf, active)
        share = self._share(tree, guided)
        frac = dr.select(guided, share, 1.0)
        use_bsdf = s1 < frac
        bs, bsdf_weight = bsdf.sample(bsdf_ctx, si, dr.minimum(s1 / frac, ONE_MINUS_EPS), s2, active & use_bsdf)
        # Only BSDF sampling reaches a delta lobe: its weight is the BSDF's over the BSDF share (Tom94's sampleMat).
        delta = guided & use_bsdf & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        use_tree = guided & ~use_bsdf
        bsdf_dir = si.to_world(bs.wo)
        # One descent of the D-tree: the direction it draws in the lanes that sample it, and the density of the
        # BSDF's direction in the others. The density of a direction the tree drew is the one its descent found:
        # looking the (rounded) direction up again could land in a neighbouring leaf of side ~1e-6 with a very
        # different density.
        d_tree, p_tree, slot, point = self._sampling.sample_or_pdf_dir(tree, s2, bsdf_dir, use_tree, guided)
        wo_world = dr.select(use_tree, d_tree, bsdf_dir)
        wo = si.to_local(wo_world)
        value, p_bsdf = bsdf.eval_pdf(bsdf_ctx, si, wo, guided)
        p_mix = share * p_bsdf + (1 - share) * p_tree
        mix_weight = dr.select(p_mix > 0, value / p_mix, 0)

        bs.wo = dr.select(use_tree, wo, bs.wo)
        bs.pdf = dr.select(delta, share * bs.pdf, dr.select(guided, p_mix, bs.pdf))
        bs.eta = dr.select(use_tree, 1.0, bs.eta)
        bs.sampled_type = dr.select(use_tree, mi.UInt32(+mi.BSDFFlags.DiffuseReflection), bs.sampled_type)
        bs.sampled_component = dr.select(use_tree, mi.UInt32(0), bs.sampled_component)
        weight = dr.select(delta, bsdf_weight / share, dr.select(guided, mix_weight, bsdf_weight))
        score = dr.select(delta, 1 / share, dr.select(guided & (p_mix > 0), (p_bsdf - p_tree) / p_mix, 0))
        return bs, weight, dr.select(guided, slot, NO_RECORD), point, score

    def record(self, state, si, emitted, bs, weight, continues, active, vertex=None):
        # The direction sampled here was traced: record it (delta directions carry no density).
        traced = (mi.Bool(active) & continues & si.is_valid() & (bs.pdf > 0)
                  & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta))
        tree = self._locate(si.p, traced) if vertex is None else vertex.tree
        splat_tree = self._splat_tree(si, vertex, tree, traced)
        slot = known_or_found(self._recording_slot(vertex, traced), traced,
                              lambda lanes: self._recording.slot_of_dir(splat_tree, si.to_world(bs.wo), lanes))
        learned = {}
        if self._fraction:
            score = mi.Float(0) if vertex is None or vertex.score is None else vertex.score
            learned = {"needed": score != 0, "score": score, "tree": tree}
        return self._log.append(state, emitted, weight, continues, dr.select(traced, slot, NO_RECORD), active,
                                pdf=bs.pdf, **learned)

    def _splat_jittered(self) -> bool:
        """Whether vertices splat at a jittered position (the SD-tree's stochastic spatial filter)."""
        return False

    def _recording_slot(self, vertex, active) -> mi.UInt32 | None:
        """The recording leaf of the direction sampled at ``vertex``, from the sampling leaf it lies in
        (:class:`TreeVertex`; NO_RECORD where sampling found none); None where it cannot be told from there."""
        if vertex is None or vertex.slot is None or self._splat_jittered():
            return None
        if self._recording is self._sampling:
            return vertex.slot
        if self._overlay is None:
            return None
        known = active & (vertex.slot != NO_RECORD)
        entry = dr.gather(mi.UInt32, self._overlay, vertex.slot, known)
        return dr.select(known, self._recording.slot_at(entry, vertex.point, known), NO_RECORD)

    def _splat_tree(self, si, vertex, tree, active) -> mi.UInt32:
        """The D-tree a vertex's radiance is splatted into: its own."""
        return tree

    def finish_paths(self, state) -> None:
        walk_backward(state, self._splat)

    # ---------------------------------------------------------------------------------------- host side
    def _reset_accumulators(self) -> None:
        self._leaf_sums = pass_sums(capacity(max(4 * self._recording.n_nodes, LEAF_SUMS_MIN_SLOTS)))

    def _splat(self, entry, L) -> None:
        """One vertex of the backward walk (in the render kernel): ``mean_rgb(L)/pdf`` into its recording D-tree
        leaf, and one to the leaf's count of vertices (a vertex whose estimate is not a finite positive number
        counts, with nothing added)."""
        slot = entry.target
        value = rgb_mean(L) / entry.pdf
        add_target(self._leaf_sums, slot, dr.select((value > 0) & dr.isfinite(value), value, 0), slot != NO_RECORD)
        if self._fraction:
            self._fraction.record(entry.tree, rgb_mean(entry.weight * L), entry.score, entry.score != 0)

    def recorded_sums(self) -> tuple[np.ndarray, np.ndarray]:
        """What the render kernels recorded since the last update, per leaf slot of the recording forest: the sum
        of the vertices' estimates and their number (float64 NumPy arrays of ``4·n_nodes``)."""
        sums = self._leaf_sums.numpy()[: 2 * 4 * self._recording.n_nodes].reshape(-1, 2)
        return sums[:, 0].copy(), sums[:, 1].copy()

    def _pull(self) -> tuple[np.ndarray, np.ndarray]:
        """The recorded leaf energies, and the vertex count of each D-tree. Entries that are NaN, ±Inf or negative
        (memory corruption; float64 sums of finite float32 estimates do not overflow) are set to 0 and counted in
        ``sanitised``: a NaN or infinite energy would make its whole D-tree's probabilities NaN, and an infinite count
        would split the S-tree to its maximum depth (2^60 leaves)."""
        energy, visits = self.recorded_sums()
        bad_energy, bad_visits = ~(np.isfinite(energy) & (energy >= 0)), ~(np.isfinite(visits) & (visits >= 0))
        energy[bad_energy], visits[bad_visits] = 0.0, 0.0
        self.sanitised = {"dropped_entries": int(bad_energy.sum() + bad_visits.sum())}
        counts = np.bincount(np.repeat(self._recording.tree_of_node, 4), weights=visits,
                             minlength=self._recording.n_trees)
        return energy, counts

    def _forest_stats(self, forest: Forest, prefix: str) -> dict:
        nodes = forest.nodes_per_tree()
        return {f"{prefix}_trees": forest.n_trees, f"{prefix}_nodes_total": forest.n_nodes,
                f"{prefix}_nodes_mean": float(nodes.mean()), f"{prefix}_nodes_max": int(nodes.max()),
                f"{prefix}_max_depth": forest.max_depth()}

    def _memory_bytes(self) -> int:
        total = 0
        for f in {id(self._sampling): self._sampling, id(self._recording): self._recording}.values():
            if f is not None:
                total += f.nbytes
        if self._leaf_sums is not None:
            total += footprint(self._leaf_sums)
        if self._overlay is not None:
            total += 4 * dr.width(self._overlay)
        return total


class SDTreeGuide(_TreeGuide):
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
        given spp): README, "SD-tree baseline", for the measurements at three image sizes."""
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


class QuadtreeGridGuide(_TreeGuide):
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
