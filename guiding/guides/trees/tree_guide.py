"""What the tree guides share (:class:`TreeGuide`): the one-sample mixture of BSDF sampling and a D-tree, and
Monte Carlo recording into D-trees. The SD-tree (:mod:`~guiding.guides.trees.sdtree`) and Kim & Kim's "Quadtree"
(:mod:`~guiding.guides.trees.quadtree_grid`) differ only in how a position finds its D-tree and when the trees are
refined.

**Monte Carlo recording** (:mod:`guiding.guides.vertex_log`). In the path loop, :meth:`record` logs every
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
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from guiding.guides.base import Guide, NoPathState, rgb_mean
from guiding.guides.trees.bsdf_fraction import LearnedBsdfFraction
from guiding.guides.trees.dtree import ONE_MINUS_EPS, DeviceForest, Forest, capacity
from guiding.guides.parameters import TreeParameters
from guiding.guides.pass_sums import add_target, footprint, pass_sums
from guiding.guides.vertex_log import NO_RECORD, VertexLog, known_or_found, walk_backward

#: Fewest leaf slots the recorded sums hold (1 MiB of float64 pairs): they are copied per thread
#: (:func:`~guiding.guides.pass_sums.copied_per_thread`), and the floor keeps the trees' growth from recompiling the
#: render kernel at every refinement while they have fewer than 2^14 nodes (beyond, once per doubling).
LEAF_SUMS_MIN_SLOTS = 1 << 16


@dataclass
class TreeVertex:
    """What :meth:`TreeGuide.locate` hands to ``sample`` and ``record`` at a vertex: its D-tree, and the leaf of
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


class TreeGuide(Guide):
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

    def pdf(self, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, bsdf_ctx: mi.BSDFContext, wo, active=True,
            bsdf_pdf=None, vertex=None):
        """The density (solid angle) with which :meth:`sample` draws local direction ``wo`` at ``si`` (of its
        smooth part: a delta lobe, which ``bsdf.pdf`` leaves out too, adds a point mass)."""
        active = mi.Bool(active)
        tree = self._locate(si.p, active) if vertex is None else vertex.tree   # locate's lanes hold ``active``'s
        guided = self.guided_mask(tree, bsdf, active)
        wo_world = si.to_world(wo)
        p_bsdf = bsdf.pdf(bsdf_ctx, si, wo, active) if bsdf_pdf is None else bsdf_pdf
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
