"""The S-tree of the SD-tree (Müller, Gross, Novák 2017): a binary spatial tree whose leaves own D-trees, and the
doubling schedule of its training iterations.

**Layout** (:class:`STree`): ``child`` (index of the first of two adjacent children, -1 for a leaf), ``axis`` and
``split`` (midpoint) per node, ``tree`` (the D-tree of a leaf). A leaf splits at its midpoint along its axis; its
children split along the next axis (x, y, z, x, …), so the root splits along x and a node's axis is its depth mod 3.
On the device (:meth:`STree.to_device`), one array of two words per node, and a table of where a descent starts:
the nodes of depth ``3·g`` are the cells of a ``2^g`` grid over the root cube, so one read of that grid's table at
a position skips the tree's first ``3·g`` levels (:data:`START_LEVELS`).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from guiding.guides.trees.dtree import padded

#: The flag of a leaf in the device layout's first word (the rest of the word is the leaf's D-tree index).
LEAF = 0x80000000
#: g: :func:`stree_locate` starts its descent at the node of depth ``3·g`` (or the leaf above it) of the position's
#: cell in a ``2^g`` grid over the root cube (32³ cells, a table of 128 KiB), read in one gather; a leaf deeper than
#: ``3·g`` levels is found by descending from there.
START_LEVELS = 5


class STree:
    """Binary spatial tree over a cube around the scene; a leaf's ``tree`` is the index of its D-tree."""

    def __init__(self, bbox_min, bbox_max, max_depth: int = 60):
        lo = np.asarray(bbox_min, dtype=np.float64)
        hi = np.asarray(bbox_max, dtype=np.float64)
        center, half = (lo + hi) / 2, max(float(np.max(hi - lo)) / 2, 1e-6) * (1 + 1e-3)
        self.lo = [center - half]
        self.hi = [center + half]
        self.child = [-1]       # first of two children, -1 for a leaf
        self.axis = [0]         # the axis this node splits along
        self.tree = [0]         # leaves: D-tree index
        self.depth = [0]
        self.max_depth = max_depth

    @property
    def n_nodes(self) -> int:
        return len(self.child)

    def leaves(self) -> list[int]:
        return [n for n in range(self.n_nodes) if self.child[n] < 0]

    @property
    def n_leaves(self) -> int:
        return sum(1 for c in self.child if c < 0)

    def split_value(self, node: int) -> float:
        a = self.axis[node]
        return 0.5 * (self.lo[node][a] + self.hi[node][a])

    def refine(self, counts, threshold: float) -> np.ndarray:
        """Split every leaf whose vertex count (``counts[tree]``) exceeds ``threshold``, at its midpoint; the two
        children inherit the D-tree and half the count each and split again while that half still exceeds it.
        A leaf of at most one vertex never splits, whatever the threshold (its children would hold half a vertex),
        so the tree stays within twice the vertices recorded. Leaves are renumbered in node order; returns, for each
        new leaf, the index of the D-tree it inherits."""
        counts = np.asarray(counts, dtype=np.float64)
        threshold = max(threshold, 1.0)
        work = [(n, counts[self.tree[n]]) for n in self.leaves()]
        while work:
            node, count = work.pop()
            if not (count > threshold) or self.depth[node] >= self.max_depth:
                continue
            a = self.axis[node]
            mid = self.split_value(node)
            first = self.n_nodes
            self.child[node] = first
            for side in range(2):
                lo, hi = self.lo[node].copy(), self.hi[node].copy()
                if side == 0:
                    hi[a] = mid
                else:
                    lo[a] = mid
                self.lo.append(lo)
                self.hi.append(hi)
                self.child.append(-1)
                self.axis.append((a + 1) % 3)
                self.tree.append(self.tree[node])
                self.depth.append(self.depth[node] + 1)
                work.append((first + side, count / 2))
        leaves = self.leaves()
        sources = np.array([self.tree[n] for n in leaves], dtype=np.int64)
        for new, n in enumerate(leaves):
            self.tree[n] = new
        return sources

    def to_device(self, leaf_boxes: bool = False) -> dict:
        """The tree for :func:`stree_locate`: per node a pair of words, ``first`` (the first child of an inner node,
        ``LEAF | D-tree index`` for a leaf) and the bits of ``split`` (float32), read with one packet gather per level
        of the descent; a node's axis follows from its depth. With ``leaf_boxes``, also the size of each D-tree's
        leaf box (``leaf_extent``, four floats per D-tree), for the stochastic spatial filter."""
        first = np.array([LEAF | t if c < 0 else c for c, t in zip(self.child, self.tree)], dtype=np.uint32)
        lo, hi, axis = np.asarray(self.lo), np.asarray(self.hi), np.asarray(self.axis)
        nodes = np.arange(self.n_nodes)
        split = 0.5 * (lo[nodes, axis] + hi[nodes, axis])          # split_value of every node
        words = np.stack([first, split.astype(np.float32).view(np.uint32)], axis=1).ravel()
        cells = 1 << START_LEVELS
        size = hi[0, 0] - lo[0, 0]
        arrays = {"nodes": mi.UInt32(padded(words)), "start": mi.UInt32(self._start_nodes(cells, split)),
                  "lo": dr.opaque(mi.Point3f, [float(x) for x in lo[0]]),
                  "cells_per_unit": dr.opaque(mi.Float, float(cells / size))}
        if leaf_boxes:
            extent = np.zeros((self.n_leaves, 4), dtype=np.float32)
            leaves = np.nonzero(np.asarray(self.child) < 0)[0]
            extent[np.asarray(self.tree)[leaves], :3] = hi[leaves] - lo[leaves]
            arrays["leaf_extent"] = mi.Float(padded(extent.ravel()))
        dr.eval(*arrays.values())
        return arrays

    def _start_nodes(self, cells: int, split: np.ndarray) -> np.ndarray:
        """For each cell ``(z·n + y)·n + x`` of an ``n = cells`` grid over the root cube: the node that contains it
        at depth ``3·log2(n)``, or the leaf above that depth (found with the cell's centre; ``split``: each node's
        split value)."""
        index = np.arange(cells ** 3)
        lo, size = self.lo[0], self.hi[0][0] - self.lo[0][0]
        centre = lo + (np.stack([index % cells, index // cells % cells, index // cells ** 2], axis=1) + 0.5) * (size / cells)
        child, axis = np.asarray(self.child), np.asarray(self.axis)
        node = np.zeros(len(index), dtype=np.int64)
        for _ in range(3 * (cells.bit_length() - 1)):
            above = centre[index, axis[node]] >= split[node]
            node = np.where(child[node] >= 0, child[node] + above, node)
        return node.astype(np.uint32)


@dr.syntax
def stree_locate(arrays: dict, p, active=True):
    """D-tree index of the S-tree leaf containing ``p`` (device); 0 in inactive lanes. The descent starts at the node
    of ``p``'s cell in the start table (:data:`START_LEVELS`): a leaf, or an inner node of depth ``3·g``, which splits
    along x. A point outside the root cube finds the leaf its nearest point of the cube is in (the start cell is
    clamped to the grid, and every split lies inside the cube). (Near a cell's face, float rounding may start it in
    the neighbouring cell: such a point finds a leaf next to its own, the same one wherever it is looked up.)"""
    cells = 1 << START_LEVELS
    c = dr.clip(mi.Vector3i(dr.floor((p - arrays["lo"]) * arrays["cells_per_unit"])), 0, cells - 1)
    node = dr.gather(mi.UInt32, arrays["start"], mi.UInt32((c.z * cells + c.y) * cells + c.x), active)
    axis = mi.UInt32(0)
    first = mi.UInt32(0)
    go = mi.Bool(active)
    while go:
        word = dr.gather(mi.Vector2u, arrays["nodes"], node, go)
        first = word.x
        leaf = first >= LEAF
        coord = dr.select(axis == 0, p.x, dr.select(axis == 1, p.y, p.z))
        above = coord >= dr.reinterpret_array(mi.Float, word.y)
        node = dr.select(leaf, node, first + dr.select(above, mi.UInt32(1), mi.UInt32(0)))
        axis = dr.select(axis == 2, mi.UInt32(0), axis + 1)
        go &= ~leaf
    return first & (LEAF - 1)


# ===================================================================================================================
#  Schedule
# ===================================================================================================================
def iteration_length(base_spp: int, k: int, start_spp: int, budget_spp: int | None = None) -> tuple[int, bool]:
    """Length in spp of training iteration ``k``, which starts at ``start_spp``, and whether it is the last one.

    Iteration ``k`` spans ``base_spp · 2^k`` spp. With a budget of ``budget_spp``, an iteration that the next one
    could not double is extended to the end of the budget, and is the last (Müller's rule: the last iteration has
    at least half the budget to itself); without one, no iteration is the last."""
    length = base_spp * 2 ** k
    if budget_spp is None:
        return length, False
    remaining = budget_spp - start_spp
    length = min(length, remaining)
    if remaining - length < 2 * length:
        return remaining, True
    return length, False
