"""Practical path guiding (Müller, Gross, Novák 2017): the SD-tree, and Kim & Kim's simplified "Quadtree" baseline.

Directional distributions are quadtrees ("D-trees") over the equal-area cylindrical square of world directions,
``(u, v) ∈ [0, 1)²`` with ``cos θ = 2u − 1`` and ``φ = 2πv`` (θ from the world z axis): equal areas in ``(u, v)``
are equal solid angles, so a density ``p_uv`` on the square is ``p_uv / (4π)`` per steradian.

Two guides share the D-tree code:

* :class:`SDTreeGuide` (method ``sdtree``): one D-tree per leaf of a binary spatial tree (S-tree) over the scene's
  bounding box (made cubic, as in Müller's code), both refined after each iteration of a doubling schedule from the
  data of that iteration alone.
* :class:`QuadtreeGridGuide` (method ``quadtree-grid``): one D-tree per cell of a uniform ``S³`` grid, split-only,
  energies accumulated over the whole render and the trees refreshed after every pass (the "Quadtree" column of
  Kim & Kim 2021).

**Host layout** (:class:`Forest`, NumPy): all D-trees of a guide in one node table, nodes in breadth-first order
(level by level over all trees), so tree ``t``'s root is node ``t`` and every child comes after its parent. A node
has four quadrants ``q = qx + 2·qy`` (``qx``: upper half in ``u``, ``qy``: upper half in ``v``), each with a child
node index (``-1`` where the quadrant is a leaf) and an energy (the energy recorded in the quadrant's region).
A root node has depth 1; a quadrant of a node at depth ``d`` has side ``2^-d``.

**Device layout** (:class:`DeviceForest`): ``child[4n + q]`` (UInt32, 0 for a leaf: a root is never a child) and
``prob[4n + q]`` (Float, the quadrant's share of its node's energy; a node without energy gets 1/4 each). Sampling
descends from the root choosing quadrants with these probabilities (first the ``u`` half, then the ``v`` half,
reusing the rescaled random number as in Müller's code), then picks a uniform point inside the leaf; the density is
``Π 4·prob`` over the descent (= leaf energy share / leaf area). Recording addresses a leaf by its slot
``4n + q`` in an energy accumulator of the same size.

**S-tree** (:class:`STree`): ``child`` (index of the first of two adjacent children, 0 for a leaf), ``axis`` and
``split`` (midpoint) per node, ``tree`` (the D-tree of a leaf). A leaf splits at its midpoint along its axis; its
children split along the next axis (x, y, z, x, …).

**Monte Carlo recording.** In the path loop, :meth:`record` writes one record per (path, vertex) into per-pass
buffers of ``n_paths × max_depth`` entries: the emitted radiance ``Le`` (RGB), the weight ``w = f·cos/pdf``
including Russian roulette (RGB, 0 where the path ends), and, for vertices whose sampled direction was traced and
not delta-sampled, the leaf slot of that direction in the recording D-tree and its pdf. After the pass, a second
kernel (started by :meth:`update`, once the render kernel has run: Dr.Jit would otherwise have to evaluate the
buffers in the middle of the render) walks every path backwards, ``L ← Le_i + w_i·L``, and adds
``mean_rgb(L_{i+1}) / pdf_i`` (the incident radiance along the sampled direction over its pdf) to the leaf, and
one to the vertex count of the vertex's D-tree (S-tree leaf). The buffers take 32 bytes per (path, vertex):
``pixels × pass_spp × max_depth × 32`` bytes per pass (314 MB at 320 × 240, 8 spp, depth 16).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..directions import safe_normalize
from .base import Guide, NoPathState, UpdateResult

#: Largest float32 below one: samples and coordinates are clamped to [0, ONE_MINUS_EPS].
ONE_MINUS_EPS = float(np.nextafter(np.float32(1), np.float32(0)))
INV_4PI = 1.0 / (4.0 * math.pi)

SPLIT_COPY = "copy"        # keep the structure as it is
SPLIT_REFINE = "refine"    # Müller: subdivide while the share exceeds rho (up to max_depth), merge below
SPLIT_GROW = "grow"        # split-only: keep every existing node, subdivide leaves whose share exceeds rho


# ===================================================================================================================
#  Direction <-> equal-area cylindrical square
# ===================================================================================================================
def dir_to_uv(d):
    """World direction → ``(u, v) ∈ [0, 1)²`` with ``u = (cos θ + 1)/2``, ``v = φ / 2π``.

    ``d`` may have any length: ``u`` reads ``cos θ`` off the unit vector (the zero vector and non-finite input,
    which have no direction, map to +z), so no input gives a point outside the square or NaN."""
    d = safe_normalize(d)
    u = dr.clip((d.z + 1) * 0.5, 0, ONE_MINUS_EPS)
    v = dr.atan2(d.y, d.x) * (0.5 / dr.pi)
    v = dr.clip(dr.select(v < 0, v + 1, v), 0, ONE_MINUS_EPS)
    return mi.Point2f(u, v)


def uv_to_dir(uv):
    """Inverse of :func:`dir_to_uv`."""
    cos_theta = 2 * uv.x - 1
    sin_theta = dr.safe_sqrt(dr.fma(-cos_theta, cos_theta, 1))
    sin_phi, cos_phi = dr.sincos(2 * dr.pi * uv.y)
    return mi.Vector3f(cos_phi * sin_theta, sin_phi * sin_theta, cos_theta)


# ===================================================================================================================
#  D-trees on the host: a forest in one breadth-first node table
# ===================================================================================================================
class Forest:
    """All D-trees of a guide (NumPy): ``child`` (N, 4) int32 (-1: leaf quadrant), ``energy`` (N, 4) float64,
    ``depth`` (N,) int16 (roots: 1), ``tree`` (N,) int32; tree ``t``'s root is node ``t``."""

    def __init__(self, child: np.ndarray, energy: np.ndarray, depth: np.ndarray, tree: np.ndarray, n_trees: int):
        self.child = np.asarray(child, dtype=np.int32).reshape(-1, 4)
        self.energy = np.asarray(energy, dtype=np.float64).reshape(-1, 4)
        self.depth = np.asarray(depth, dtype=np.int16)
        self.tree = np.asarray(tree, dtype=np.int32)
        self.n_trees = int(n_trees)
        assert len(self.child) == len(self.energy) == len(self.depth) == len(self.tree) >= self.n_trees

    # ------------------------------------------------------------------------------------------------ builders
    @classmethod
    def empty(cls, n_trees: int) -> "Forest":
        """``n_trees`` trees of one node each (four leaf quadrants), without energy."""
        return cls(np.full((n_trees, 4), -1), np.zeros((n_trees, 4)), np.ones(n_trees), np.arange(n_trees),
                   n_trees)

    @classmethod
    def from_nested(cls, trees: list) -> "Forest":
        """Trees written as nested lists, for tests: a quadrant is a number (a leaf's energy) or a list of four
        quadrants (a child node). ``[1, 0, [1, 1, 1, 1], 2]`` is a root whose quadrant 2 is subdivided."""
        level = [(t, q) for t, q in enumerate(trees)]
        child, energy, depth, tree = [], [], [], []
        d = 1
        while level:
            nxt = []
            base = len(child) + len(level)
            for t, quads in level:
                assert len(quads) == 4, "a node has four quadrants"
                row_c, row_e = [], []
                for q in quads:
                    if isinstance(q, (list, tuple)):
                        row_c.append(base + len(nxt))
                        row_e.append(0.0)
                        nxt.append((t, q))
                    else:
                        row_c.append(-1)
                        row_e.append(float(q))
                child.append(row_c)
                energy.append(row_e)
                depth.append(d)
                tree.append(t)
            level, d = nxt, d + 1
        forest = cls(np.array(child).reshape(-1, 4), np.array(energy).reshape(-1, 4), depth, tree, len(trees))
        forest.propagate()
        return forest

    # ---------------------------------------------------------------------------------------------- queries
    @property
    def n_nodes(self) -> int:
        return len(self.child)

    def totals(self) -> np.ndarray:
        """Energy of each tree."""
        return self.energy[: self.n_trees].sum(axis=1)

    def nodes_per_tree(self) -> np.ndarray:
        return np.bincount(self.tree, minlength=self.n_trees)

    def max_depth(self) -> int:
        return int(self.depth.max())

    def leaf_table(self):
        """Every leaf quadrant: (tree, slot = 4·node + q, u0, v0, side, energy), in node order (NumPy arrays)."""
        n = self.n_nodes
        origin = np.zeros((n, 2))
        side = np.ones(n)
        q_off = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=np.float64)
        for node in range(n):  # parents come first
            half = side[node] * 0.5
            for q in range(4):
                c = self.child[node, q]
                if c >= 0:
                    origin[c] = origin[node] + half * q_off[q]
                    side[c] = half
        nodes, quads = np.nonzero(self.child < 0)
        half = side[nodes] * 0.5
        corner = origin[nodes] + half[:, None] * q_off[quads]
        return (self.tree[nodes], 4 * nodes + quads, corner[:, 0], corner[:, 1], half, self.energy[nodes, quads])

    def lookup_np(self, trees: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reference lookup (NumPy, float64): leaf slot and density on the square of points ``uv`` in ``trees``."""
        node = np.asarray(trees, dtype=np.int64).copy()
        x = np.array(uv, dtype=np.float64)
        pdf = np.ones(len(node))
        slot = np.zeros(len(node), dtype=np.int64)
        go = np.ones(len(node), dtype=bool)
        while go.any():
            idx = np.nonzero(go)[0]
            x2 = x[idx] * 2
            qx = (x2[:, 0] >= 1).astype(np.int64)
            qy = (x2[:, 1] >= 1).astype(np.int64)
            x[idx] = x2 - np.stack([qx, qy], axis=1)
            q = qx + 2 * qy
            e = self.energy[node[idx]]
            tot = e.sum(axis=1)
            share = np.where(tot > 0, e[np.arange(len(idx)), q] / np.where(tot > 0, tot, 1), 0.25)
            pdf[idx] *= 4 * share
            slot[idx] = 4 * node[idx] + q
            nxt = self.child[node[idx], q]
            go[idx] = nxt >= 0
            node[idx] = np.where(nxt >= 0, nxt, node[idx])
        return slot, pdf

    # -------------------------------------------------------------------------------------------- updates
    def propagate(self) -> None:
        """Make every interior quadrant's energy the sum of its child node's quadrants (bottom-up)."""
        for d in range(int(self.depth.max()), 0, -1):
            nodes = np.nonzero(self.depth == d)[0]
            sub = self.child[nodes]
            inner = sub >= 0
            if inner.any():
                rows, quads = np.nonzero(inner)
                self.energy[nodes[rows], quads] = self.energy[sub[rows, quads]].sum(axis=1)

    def deposit(self, leaf_energy: np.ndarray, accumulate: bool = False) -> None:
        """Set (or add) leaf quadrant energies from a flat per-slot array (4·N values), then propagate."""
        flat = np.asarray(leaf_energy, dtype=np.float64).reshape(-1, 4)[: self.n_nodes]
        leaves = self.child < 0
        if accumulate:
            self.energy[leaves] += flat[leaves]
        else:
            self.energy[leaves] = flat[leaves]
        self.propagate()

    def rebuild(self, sources, mode: str, rho: float = 0.01, max_depth: int = 20,
                keep_energy: bool = True, max_nodes: int | None = None) -> "Forest":
        """A new forest whose tree ``i`` is derived from tree ``sources[i]`` of this one (sources may repeat).

        ``mode``: :data:`SPLIT_COPY` keeps the structure; :data:`SPLIT_REFINE` (Müller's D-tree rebuild) subdivides
        a quadrant while its share of the tree's energy exceeds ``rho`` and its node is shallower than
        ``max_depth``, and makes every other quadrant a leaf (merging the subtree below it); :data:`SPLIT_GROW`
        keeps every existing node and also subdivides leaves under the same rule (split-only). A new child below a
        former leaf gets a quarter of the leaf's energy in each quadrant; an existing child keeps its energies. A
        tree without energy uses the share ``4^-depth`` (uniform refinement). ``keep_energy=False`` zeroes the
        energies of the result (the tree that records the next iteration). ``max_nodes`` caps the nodes of a tree
        (further subdivisions are dropped, breadth-first).
        """
        sources = np.asarray(sources, dtype=np.int64)
        n_new = len(sources)
        totals = self.totals()[sources]
        # frontier: the nodes of one level of the new forest
        f_old = sources.copy()                     # node of this forest it copies (-1: below a former leaf)
        f_energy = self.energy[sources].copy()     # (k, 4)
        f_tree = np.arange(n_new)
        depth = 1
        levels_child, levels_energy, levels_depth, levels_tree = [], [], [], []
        count = np.zeros(n_new, dtype=np.int64) + 1
        next_id = n_new
        while len(f_old):
            has_old = f_old >= 0
            old_child = np.where(has_old[:, None], self.child[np.maximum(f_old, 0)], -1)
            tot = totals[f_tree][:, None]
            share = np.where(tot > 0, f_energy / np.where(tot > 0, tot, 1), 0.25 ** depth)
            can = (share > rho) & (depth < max_depth)
            if mode == SPLIT_COPY:
                split = old_child >= 0
            elif mode == SPLIT_REFINE:
                split = can
            elif mode == SPLIT_GROW:
                split = (old_child >= 0) | can
            else:
                raise ValueError(f"unknown rebuild mode {mode!r}")
            if max_nodes is not None:
                # keep the first subdivisions of each tree (row-major order) while the tree has room
                rows, quads = np.nonzero(split)
                order = np.argsort(f_tree[rows], kind="stable")
                t_sorted = f_tree[rows][order]
                rank = np.arange(len(order)) - np.searchsorted(t_sorted, t_sorted, side="left")
                allowed = count[t_sorted] + rank < max_nodes
                keep = np.zeros(len(rows), dtype=bool)
                keep[order] = allowed
                split = np.zeros_like(split)
                split[rows[keep], quads[keep]] = True
                np.add.at(count, f_tree[rows[keep]], 1)
            rows, quads = np.nonzero(split)
            ids = np.full(split.shape, -1, dtype=np.int64)
            ids[rows, quads] = next_id + np.arange(len(rows))
            next_id += len(rows)
            levels_child.append(ids)
            levels_energy.append(f_energy)
            levels_depth.append(np.full(len(f_old), depth))
            levels_tree.append(f_tree)
            # next level
            nxt_old = old_child[rows, quads]
            from_old = nxt_old >= 0
            nxt_energy = np.repeat(f_energy[rows, quads][:, None] / 4.0, 4, axis=1)
            if from_old.any():
                nxt_energy[from_old] = self.energy[nxt_old[from_old]]
            f_old, f_energy, f_tree = nxt_old, nxt_energy, f_tree[rows]
            depth += 1
        child = np.concatenate(levels_child)
        energy = np.concatenate(levels_energy)
        if not keep_energy:
            energy = np.zeros_like(energy)
        return Forest(child, energy, np.concatenate(levels_depth), np.concatenate(levels_tree), n_new)

    def probabilities(self) -> np.ndarray:
        """Each quadrant's share of its node's energy (1/4 each for a node without energy), shape (N, 4)."""
        tot = self.energy.sum(axis=1, keepdims=True)
        return np.where(tot > 0, self.energy / np.where(tot > 0, tot, 1), 0.25)


# ===================================================================================================================
#  D-trees on the device
# ===================================================================================================================
def _pad(a: np.ndarray, minimum: int = 2) -> np.ndarray:
    """Arrays of one element may be traced differently from larger ones: keep every table at >= 2 entries."""
    return a if len(a) >= minimum else np.concatenate([a, np.zeros(minimum - len(a), dtype=a.dtype)])


def _prev_float(x):
    """The largest float below ``x`` (``x`` > 0)."""
    return mi.Point2f(dr.reinterpret_array(mi.Float, dr.reinterpret_array(mi.UInt32, x.x) - 1),
                      dr.reinterpret_array(mi.Float, dr.reinterpret_array(mi.UInt32, x.y) - 1))


def _capacity(n: int) -> int:
    return 1 << max(int(n) - 1, 1).bit_length()


class DeviceForest:
    """A :class:`Forest` uploaded for sampling, density evaluation and leaf lookup inside kernels."""

    def __init__(self, forest: Forest):
        self.n_nodes = forest.n_nodes
        self.n_trees = forest.n_trees
        child = np.where(forest.child < 0, 0, forest.child).astype(np.uint32).ravel()
        self.child = mi.UInt32(_pad(child))
        self.prob = mi.Float(_pad(forest.probabilities().astype(np.float32).ravel()))
        self.tree_of_node = mi.UInt32(_pad(forest.tree.astype(np.uint32)))
        self.has_energy = mi.Bool(_pad(forest.totals() > 0))
        dr.eval(self.child, self.prob, self.tree_of_node, self.has_energy)

    @property
    def nbytes(self) -> int:
        return 4 * (2 * 4 * self.n_nodes + self.n_nodes) + self.n_trees

    # ----------------------------------------------------------------------------------------- device code
    @dr.syntax
    def sample_uv(self, tree, sample, active=True):
        """Descend tree ``tree`` with the 2D ``sample``: a point of the square and its density there."""
        child, prob = self.child, self.prob
        node = mi.UInt32(tree)
        s = mi.Point2f(sample)
        origin = mi.Point2f(0)
        size = mi.Float(1)
        pdf = mi.Float(1)
        go = mi.Bool(active)
        while go:
            base = node * 4
            p0 = dr.gather(mi.Float, prob, base, go)
            p1 = dr.gather(mi.Float, prob, base + 1, go)
            p2 = dr.gather(mi.Float, prob, base + 2, go)
            p3 = dr.gather(mi.Float, prob, base + 3, go)
            total = p0 + p1 + p2 + p3
            valid = total > 0
            px = dr.select(valid, (p0 + p2) / total, 0.5)
            right = s.x >= px
            sx = dr.select(right, (s.x - px) / (1 - px), s.x / px)
            a = dr.select(right, p1, p0)
            b = dr.select(right, p3, p2)
            ab_valid = (a + b) > 0
            py = dr.select(ab_valid, a / (a + b), 0.5)
            up = s.y >= py
            sy = dr.select(up, (s.y - py) / (1 - py), s.y / py)
            s = mi.Point2f(dr.clip(sx, 0, ONE_MINUS_EPS), dr.clip(sy, 0, ONE_MINUS_EPS))
            chosen = dr.select(up, b, a)
            pdf *= dr.select(valid, 4 * chosen / total, 1)
            size *= 0.5
            origin += mi.Point2f(dr.select(right, size, 0), dr.select(up, size, 0))
            q = dr.select(right, mi.UInt32(1), mi.UInt32(0)) + dr.select(up, mi.UInt32(2), mi.UInt32(0))
            node = dr.gather(mi.UInt32, child, base + q, go)
            go &= node != 0
        # A leaf of side 2^-20 spans only a few dozen floats: keep the rounded point inside the leaf it came from.
        upper = _prev_float(origin + size)
        uv = mi.Point2f(dr.minimum(origin.x + size * s.x, upper.x), dr.minimum(origin.y + size * s.y, upper.y))
        return uv, pdf

    @dr.syntax
    def lookup_uv(self, tree, uv, active=True, with_pdf=True):
        """Leaf slot (``4·node + q``) containing ``uv`` in tree ``tree``, and the density there."""
        child, prob = self.child, self.prob
        node = mi.UInt32(tree)
        x = mi.Point2f(uv)
        pdf = mi.Float(1)
        slot = mi.UInt32(0)
        go = mi.Bool(active)
        while go:
            base = node * 4
            x2 = x * 2
            right = x2.x >= 1
            up = x2.y >= 1
            x = mi.Point2f(dr.select(right, x2.x - 1, x2.x), dr.select(up, x2.y - 1, x2.y))
            q = dr.select(right, mi.UInt32(1), mi.UInt32(0)) + dr.select(up, mi.UInt32(2), mi.UInt32(0))
            if dr.hint(with_pdf, mode="scalar"):
                p0 = dr.gather(mi.Float, prob, base, go)
                p1 = dr.gather(mi.Float, prob, base + 1, go)
                p2 = dr.gather(mi.Float, prob, base + 2, go)
                p3 = dr.gather(mi.Float, prob, base + 3, go)
                total = p0 + p1 + p2 + p3
                chosen = dr.select(right, dr.select(up, p3, p1), dr.select(up, p2, p0))
                pdf *= dr.select(total > 0, 4 * chosen / total, 1)
            slot = base + q
            node = dr.gather(mi.UInt32, child, slot, go)
            go &= node != 0
        return slot, pdf

    def sample_dir(self, tree, sample, active=True):
        """A world direction drawn from tree ``tree`` and its solid-angle density."""
        uv, pdf = self.sample_uv(tree, sample, active)
        return uv_to_dir(uv), pdf * INV_4PI

    def pdf_dir(self, tree, d, active=True):
        """Solid-angle density of world direction ``d`` under tree ``tree``."""
        _, pdf = self.lookup_uv(tree, dir_to_uv(d), active)
        return pdf * INV_4PI

    def slot_of_dir(self, tree, d, active=True):
        slot, _ = self.lookup_uv(tree, dir_to_uv(d), active, with_pdf=False)
        return slot


# ===================================================================================================================
#  S-tree
# ===================================================================================================================
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
        Leaves are renumbered in node order; returns, for each new leaf, the index of the D-tree it inherits."""
        counts = np.asarray(counts, dtype=np.float64)
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

    def to_device(self) -> dict:
        child = np.array([max(c, 0) for c in self.child], dtype=np.uint32)
        axis = np.array(self.axis, dtype=np.uint32)
        split = np.array([self.split_value(n) for n in range(self.n_nodes)], dtype=np.float32)
        tree = np.array([t if c < 0 else 0 for t, c in zip(self.tree, self.child)], dtype=np.uint32)
        arrays = {"child": mi.UInt32(_pad(child)), "axis": mi.UInt32(_pad(axis)), "split": mi.Float(_pad(split)),
                  "tree": mi.UInt32(_pad(tree))}
        dr.eval(*arrays.values())
        return arrays


@dr.syntax
def stree_locate(arrays: dict, p, active=True):
    """D-tree index of the S-tree leaf containing ``p`` (device)."""
    child, axis, split = arrays["child"], arrays["axis"], arrays["split"]
    node = mi.UInt32(0)
    go = mi.Bool(active)
    while go:
        first = dr.gather(mi.UInt32, child, node, go)
        leaf = first == 0
        a = dr.gather(mi.UInt32, axis, node, go)
        mid = dr.gather(mi.Float, split, node, go)
        coord = dr.select(a == 0, p.x, dr.select(a == 1, p.y, p.z))
        node = dr.select(leaf, node, first + dr.select(coord >= mid, mi.UInt32(1), mi.UInt32(0)))
        go &= ~leaf
    return dr.gather(mi.UInt32, arrays["tree"], node, active)


# ===================================================================================================================
#  Schedule
# ===================================================================================================================
def doubling_schedule(base_spp: int, budget_spp: int | None = None, iterations: int = 40) -> list[tuple[int, int]]:
    """``[(start, end)]`` in spp of each training iteration: iteration ``k`` spans ``base_spp · 2^k`` spp. With a
    budget, an iteration that the next one could not double is extended to the end of the budget (Müller's rule:
    the last iteration has at least half the budget to itself)."""
    bounds, start, k = [], 0, 0
    while (budget_spp is None and k < iterations) or (budget_spp is not None and start < budget_spp):
        length = base_spp * 2 ** k
        if budget_spp is not None:
            remaining = budget_spp - start
            length = min(length, remaining)
            if remaining - length < 2 * length:
                length = remaining
        bounds.append((start, start + length))
        start, k = start + length, k + 1
    return bounds


# ===================================================================================================================
#  The guides
# ===================================================================================================================
_STATE_TYPES: dict = {}


def _vertex_log_type():
    """The per-path loop state (a Dr.Jit PyTree): path index and number of vertices logged so far."""
    key = mi.variant()
    if key not in _STATE_TYPES:
        @dataclass
        class VertexLog:
            path: mi.UInt32 = None
            n: mi.UInt32 = None
            DRJIT_STRUCT = {"path": mi.UInt32, "n": mi.UInt32}

        _STATE_TYPES[key] = VertexLog
    return _STATE_TYPES[key]


class _PassLog:
    """Per-pass vertex records, ``n_paths × max_depth`` entries, written by the render kernel."""

    def __init__(self, n_paths: int, max_depth: int):
        size = n_paths * max_depth
        self.n_paths, self.max_depth = n_paths, max_depth
        self.emitted = dr.zeros(mi.Color3f, size)
        self.weight = dr.zeros(mi.Color3f, size)
        self.slot = dr.zeros(mi.UInt32, size)      # leaf slot + 1; 0: nothing to record at this vertex
        self.pdf = dr.zeros(mi.Float, size)
        self.count = dr.zeros(mi.UInt32, n_paths)

    @property
    def nbytes(self) -> int:
        return 4 * (self.n_paths * self.max_depth * 8 + self.n_paths)


class _TreeGuide(Guide):
    """What the SD-tree and the quadtree grid share: the D-tree mixture sampler and Monte Carlo recording.

    Subclasses provide ``_locate(p, active)`` (the D-tree index of a position), ``self._sampling`` and
    ``self._recording`` (:class:`DeviceForest`), and their update rule.
    """

    def __init__(self, bsdf_fraction: float = 0.5, rho: float = 0.01, dtree_max_depth: int = 20,
                 max_nodes: int | None = None):
        if not 0 <= bsdf_fraction < 1:
            raise ValueError(f"bsdf_fraction must be in [0, 1), got {bsdf_fraction}")
        self.bsdf_fraction = float(bsdf_fraction)
        self.rho = float(rho)
        self.dtree_max_depth = int(dtree_max_depth)
        self.max_nodes = max_nodes
        self._logs: list[_PassLog] = []
        self._log_bytes = 0
        self._sampling: DeviceForest | None = None
        self._recording: DeviceForest | None = None
        self._energy_acc = None
        self._count_acc = None
        self.sanitised = {"dropped_entries": 0}          # bad accumulator entries of the last update (_pull)

    def records(self) -> bool:
        return True

    # -------------------------------------------------------------------------------------- device side
    def _locate(self, p, active):
        raise NotImplementedError

    def new_paths(self, size: int, max_depth: int):
        if not self.records():
            return NoPathState()
        log = _PassLog(size, max_depth)
        self._logs.append(log)
        self._log_bytes = log.nbytes
        return _vertex_log_type()(path=dr.arange(mi.UInt32, size), n=mi.UInt32(0))

    def guided_mask(self, tree, bsdf: mi.BSDFPtr, active):
        """Lanes that mix in the D-tree: not a delta BSDF, and a D-tree that has seen energy."""
        delta = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Delta)
        return active & ~delta & dr.gather(mi.Bool, self._sampling.has_energy, tree, active)

    def pdf(self, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, bsdf_ctx: mi.BSDFContext, wo, active=True):
        """The density (solid angle) with which :meth:`sample` draws local direction ``wo`` at ``si``."""
        active = mi.Bool(active)
        tree = self._locate(si.p, active)
        guided = self.guided_mask(tree, bsdf, active)
        wo_world = si.to_world(wo)
        p_bsdf = bsdf.pdf(bsdf_ctx, si, wo, active)
        p_tree = self._sampling.pdf_dir(tree, wo_world, guided)
        return dr.select(guided, self.bsdf_fraction * p_bsdf + (1 - self.bsdf_fraction) * p_tree, p_bsdf)

    def sample(self, scene, sampler, si, bsdf, bsdf_ctx, active):
        active = mi.Bool(active)
        tree = self._locate(si.p, active)
        guided = self.guided_mask(tree, bsdf, active)
        frac = dr.select(guided, self.bsdf_fraction, 1.0)
        s1 = sampler.next_1d(active)
        s2 = sampler.next_2d(active)
        use_bsdf = s1 < frac
        bs, bsdf_weight = bsdf.sample(bsdf_ctx, si, dr.minimum(s1 / frac, ONE_MINUS_EPS), s2, active & use_bsdf)
        use_tree = guided & ~use_bsdf
        d_tree, p_tree_sampled = self._sampling.sample_dir(tree, s2, use_tree)
        wo_world = dr.select(use_tree, d_tree, si.to_world(bs.wo))
        wo = si.to_local(wo_world)
        value, p_bsdf = bsdf.eval_pdf(bsdf_ctx, si, wo, guided)
        # The D-tree density of a direction it drew is the one its descent found: looking the (rounded) direction
        # up again could land in a neighbouring leaf of side ~1e-6 with a very different density.
        p_tree = dr.select(use_tree, p_tree_sampled, self._sampling.pdf_dir(tree, wo_world, guided & use_bsdf))
        p_mix = self.bsdf_fraction * p_bsdf + (1 - self.bsdf_fraction) * p_tree
        mix_weight = dr.select(p_mix > 0, value / p_mix, 0)

        bs.wo = dr.select(use_tree, wo, bs.wo)
        bs.pdf = dr.select(guided, p_mix, bs.pdf)
        bs.eta = dr.select(use_tree, 1.0, bs.eta)
        bs.sampled_type = dr.select(use_tree, mi.UInt32(+mi.BSDFFlags.DiffuseReflection), bs.sampled_type)
        bs.sampled_component = dr.select(use_tree, mi.UInt32(0), bs.sampled_component)
        weight = dr.select(guided, mix_weight, bsdf_weight)
        return bs, weight

    def record(self, state, si, emitted, bs, weight, continues, active):
        log = self._logs[-1]
        ok = mi.Bool(active) & (state.n < log.max_depth)
        index = state.path * log.max_depth + state.n
        dr.scatter(log.emitted, emitted, index, ok)
        dr.scatter(log.weight, dr.select(continues, weight, 0), index, ok)
        # The direction sampled here was traced: record it (delta directions carry no density).
        rec = ok & continues & si.is_valid() & (bs.pdf > 0) & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        tree = self._locate(si.p, rec)
        slot = self._recording.slot_of_dir(tree, si.to_world(bs.wo), rec)
        dr.scatter(log.slot, slot + 1, index, rec)
        dr.scatter(log.pdf, bs.pdf, index, rec)
        state.n = dr.select(ok, state.n + 1, state.n)
        return state

    def finish_paths(self, state) -> None:
        log = self._logs[-1]
        dr.scatter(log.count, state.n, state.path)

    # ---------------------------------------------------------------------------------------- host side
    def _reset_accumulators(self) -> None:
        # Capacities rounded up to powers of two: the splat kernel's atomics depend on the target size, so this
        # keeps it from being recompiled whenever the trees change a little.
        self._energy_acc = dr.zeros(mi.Float, _capacity(4 * self._recording.n_nodes))
        self._count_acc = dr.zeros(mi.Float, _capacity(self._recording.n_trees))
        dr.eval(self._energy_acc, self._count_acc)

    @dr.syntax
    def _splat(self, log: _PassLog) -> None:
        """Backward walk over one pass's vertex records: ``mean_rgb(L)/pdf`` into the recording D-tree leaves."""
        md = log.max_depth
        path = dr.arange(mi.UInt32, log.n_paths)
        j = dr.gather(mi.UInt32, log.count, path)
        L = mi.Color3f(0)
        while j > 0:
            j -= 1
            index = path * md + j
            slot = dr.gather(mi.UInt32, log.slot, index)
            pdf = dr.gather(mi.Float, log.pdf, index)
            rec = slot > 0
            value = (L.x + L.y + L.z) * (1.0 / 3.0) / pdf
            dr.scatter_reduce(dr.ReduceOp.Add, self._energy_acc, value, slot - 1,
                              rec & (value > 0) & dr.isfinite(value))
            tree = dr.gather(mi.UInt32, self._recording.tree_of_node, (slot - 1) // 4, rec)
            dr.scatter_reduce(dr.ReduceOp.Add, self._count_acc, mi.Float(1), tree, rec)
            L = dr.gather(mi.Color3f, log.emitted, index) + dr.gather(mi.Color3f, log.weight, index) * L

    def _splat_logs(self) -> float:
        """Process the vertex records of every pass rendered since the last call; returns its seconds."""
        start = time.perf_counter()
        for log in self._logs:
            self._splat(log)
        self._logs.clear()
        dr.eval(self._energy_acc, self._count_acc)
        dr.sync_thread()
        return time.perf_counter() - start

    def _pull(self) -> tuple[np.ndarray, np.ndarray]:
        """The recorded leaf energies and vertex counts. Entries that are NaN, ±Inf or negative (a float32 sum
        that overflowed, or memory corruption) are set to 0 and counted in ``sanitised``: a NaN or infinite energy
        would make its whole D-tree's probabilities NaN, and an infinite count would split the S-tree to its maximum
        depth (2^60 leaves)."""
        energy = self._energy_acc.numpy()[: 4 * self._recording.n_nodes].astype(np.float64)
        counts = self._count_acc.numpy()[: self._recording.n_trees].astype(np.float64)
        bad_energy, bad_counts = ~(np.isfinite(energy) & (energy >= 0)), ~(np.isfinite(counts) & (counts >= 0))
        energy[bad_energy], counts[bad_counts] = 0.0, 0.0
        self.sanitised = {"dropped_entries": int(bad_energy.sum() + bad_counts.sum())}
        return energy, counts

    def _forest_stats(self, forest: Forest, prefix: str) -> dict:
        nodes = forest.nodes_per_tree()
        return {f"{prefix}_trees": forest.n_trees, f"{prefix}_nodes_total": forest.n_nodes,
                f"{prefix}_nodes_mean": float(nodes.mean()), f"{prefix}_nodes_max": int(nodes.max()),
                f"{prefix}_max_depth": forest.max_depth()}

    def _memory_bytes(self) -> int:
        total = self._log_bytes
        for f in {id(self._sampling): self._sampling, id(self._recording): self._recording}.values():
            if f is not None:
                total += f.nbytes
        if self._energy_acc is not None:
            total += 4 * (dr.width(self._energy_acc) + dr.width(self._count_acc))
        return total


class SDTreeGuide(_TreeGuide):
    """Müller et al. 2017's SD-tree (see the module docstring).

    Parameters: ``c`` (S-tree split constant, 12000), ``rho`` (D-tree subdivision share, 0.01),
    ``dtree_max_depth`` (20), ``bsdf_fraction`` (0.5), ``max_nodes`` (cap on the nodes of one D-tree; none),
    ``base_spp`` (spp of iteration 0, 8 = one default pass; iteration ``k`` spans ``base_spp·2^k`` spp),
    ``budget_spp`` (optional: the last iteration then runs to the end of the budget and records nothing).

    S-tree threshold: a leaf splits when the vertices recorded in it during iteration ``k`` exceed
    ``c·sqrt(spp_k)``, ``spp_k = base_spp·2^k`` the spp of that iteration. This is the paper's ``c·sqrt(2^k)``
    with its iterations of ``2^k`` spp; here iteration 0 already has ``base_spp`` spp.

    Schedule: :meth:`update` is called after every pass; it refines when the spp done reach the end of the
    current iteration. ``update`` reports ``iteration_done`` for the pass that closed an iteration: a renderer that
    keeps only the last iteration (Müller's final image) restarts its accumulation there. Under a seconds budget
    the guide has no end: the renderer asks :meth:`iteration_spp` at each boundary and calls :meth:`stop_training`
    when the next iteration would not fit (:mod:`guiding.render`).
    """

    name = "sdtree"

    def __init__(self, c: float = 12000.0, rho: float = 0.01, dtree_max_depth: int = 20, bsdf_fraction: float = 0.5,
                 base_spp: int = 8, budget_spp: int | None = None, max_nodes: int | None = None):
        super().__init__(bsdf_fraction, rho, dtree_max_depth, max_nodes)
        if base_spp < 1:
            raise ValueError(f"base_spp must be >= 1, got {base_spp}")
        self.c = float(c)
        self.base_spp = int(base_spp)
        self.budget_spp = budget_spp
        self._recording_on = True

    # ------------------------------------------------------------------------------------ schedule
    def set_budget(self, spp: int | None) -> None:
        """Tell the guide the total spp budget (before the first pass), so the last iteration runs to its end."""
        self.budget_spp = spp

    def iteration_bounds(self) -> list[tuple[int, int]]:
        """``[(start, end)]`` spp of the iterations of this guide's schedule (finite with a budget)."""
        return doubling_schedule(self.base_spp, self.budget_spp)

    def _start_iteration(self, spp_start: int) -> None:
        length = self.base_spp * 2 ** self.iteration
        self.is_final_iteration = False
        if self.budget_spp is not None:
            remaining = self.budget_spp - spp_start
            length = min(length, remaining)
            if remaining - length < 2 * length:
                length, self.is_final_iteration = remaining, True
        self.iteration_start_spp = spp_start
        self.iteration_end_spp = spp_start + max(length, 1)

    def iteration_spp(self) -> int:
        """Length in spp of the iteration the next pass belongs to (a renderer under a seconds budget checks
        that it fits before letting it run)."""
        return self.iteration_end_spp - self.iteration_start_spp

    def stop_training(self) -> None:
        """Freeze the distributions (e.g. when a time budget leaves no room for another iteration): no more
        refinement and no more recording (the next pass traces a kernel without the recording code). The
        current iteration becomes the final one and runs to the end of the budget, so it has no end spp."""
        self.is_final_iteration = True
        self._recording_on = False
        self._logs.clear()
        self.iteration_end_spp = None

    # ------------------------------------------------------------------------------------ host side
    def prepare(self, scene: mi.Scene) -> None:
        bbox = scene.bbox()
        self.stree = STree(np.array(bbox.min), np.array(bbox.max))
        self._s_device = self.stree.to_device()
        self._sampling_host = Forest.empty(1)
        self._recording_host = Forest.empty(1).rebuild([0], SPLIT_REFINE, self.rho, self.dtree_max_depth,
                                                       keep_energy=False, max_nodes=self.max_nodes)
        self._sampling = DeviceForest(self._sampling_host)
        self._recording = DeviceForest(self._recording_host)
        self._reset_accumulators()
        self._logs.clear()
        self._recording_on = True
        self.iteration = 0
        self._start_iteration(0)
        self._last_refine = {}

    def _locate(self, p, active):
        return stree_locate(self._s_device, p, active)

    def records(self) -> bool:
        return self._recording_on

    def update(self, spp_done: int) -> UpdateResult:
        """Splat the pass's records; at the end of an iteration, refine. ``iteration`` in the returned statistics
        is the iteration the pass belonged to; ``iteration_done`` marks the pass that ended it (the distributions
        change after it; a renderer keeping only the last iteration restarts its accumulation there)."""
        pass_iteration = self.iteration
        recorded = self.records()
        splat_seconds = self._splat_logs() if recorded else 0.0
        stats = {"splat_seconds": splat_seconds, "refine_seconds": 0.0}
        iteration_done = recorded and not self.is_final_iteration and spp_done >= self.iteration_end_spp
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
        spp_k = self.iteration_end_spp - self.iteration_start_spp
        threshold = self.c * math.sqrt(spp_k)
        sources = self.stree.refine(counts, threshold)
        self._sampling_host = built.rebuild(sources, SPLIT_COPY)
        self._recording_host = built.rebuild(sources, SPLIT_REFINE, self.rho, self.dtree_max_depth,
                                             keep_energy=False, max_nodes=self.max_nodes)
        host_seconds = time.perf_counter() - start
        self._s_device = self.stree.to_device()
        self._sampling = DeviceForest(self._sampling_host)
        self._recording = DeviceForest(self._recording_host)
        self._reset_accumulators()
        dr.sync_thread()
        self._last_refine = {"refine_seconds": time.perf_counter() - start, "refine_host_seconds": host_seconds,
                             "stree_threshold": threshold, "vertices_recorded": float(counts.sum()),
                             "energy_recorded": float(energy.sum()), **self.sanitised}
        return dict(self._last_refine)

    def _structure_stats(self) -> dict:
        stats = {"iteration": self.iteration, "stree_nodes": self.stree.n_nodes, "stree_leaves": self.stree.n_leaves,
                 "stree_max_depth": max(self.stree.depth),
                 "memory_bytes": self._memory_bytes() + 16 * self.stree.n_nodes,
                 "iteration_start_spp": self.iteration_start_spp, "iteration_end_spp": self.iteration_end_spp,
                 "final_iteration": self.is_final_iteration}
        stats.update(self._forest_stats(self._sampling_host, "dtree"))
        stats.update(self._forest_stats(self._recording_host, "dtree_recording"))
        return stats

    def stats(self) -> dict:
        out = {"method": self.name, "c": self.c, "rho": self.rho, "dtree_max_depth": self.dtree_max_depth,
               "bsdf_fraction": self.bsdf_fraction, "base_spp": self.base_spp, "budget_spp": self.budget_spp}
        if hasattr(self, "stree"):
            out.update(self._structure_stats())
            out["last_refine"] = self._last_refine
        return out


class QuadtreeGridGuide(_TreeGuide):
    """One D-tree per cell of a uniform ``S³`` grid over the scene's bounding box (Kim & Kim's "Quadtree").

    Split-only: a leaf whose share of its tree's energy exceeds ``rho`` is subdivided (its energy spread evenly over
    the new quadrants); nothing is merged. Energies accumulate over the whole render and the trees are refreshed
    after every pass (the same structure records and samples).
    """

    name = "quadtree-grid"

    def __init__(self, S: int = 8, rho: float = 0.01, dtree_max_depth: int = 20, bsdf_fraction: float = 0.5,
                 max_nodes: int | None = None):
        super().__init__(bsdf_fraction, rho, dtree_max_depth, max_nodes)
        self.S = int(S)

    def prepare(self, scene: mi.Scene) -> None:
        bbox = scene.bbox()
        self._bbox_min = np.array(bbox.min, dtype=np.float64)
        extent = np.array(bbox.max, dtype=np.float64) - self._bbox_min
        self._inv_extent = 1.0 / np.maximum(extent, 1e-6)
        n = self.S ** 3
        self._forest = Forest.empty(n).rebuild(np.arange(n), SPLIT_GROW, self.rho, self.dtree_max_depth,
                                               keep_energy=True, max_nodes=self.max_nodes)
        self._sampling = self._recording = DeviceForest(self._forest)
        self._reset_accumulators()
        self._logs.clear()

    def _locate(self, p, active):
        S = self.S
        lo, inv = [float(x) for x in self._bbox_min], [float(x) for x in self._inv_extent]
        rel = (p - mi.Point3f(*lo)) * mi.Vector3f(*inv)
        cell = mi.Vector3u(dr.clip(mi.Vector3i(dr.floor(rel * S)), 0, S - 1))
        return (cell.z * S + cell.y) * S + cell.x

    def update(self, spp_done: int) -> UpdateResult:
        splat_seconds = self._splat_logs()
        start = time.perf_counter()
        energy, _ = self._pull()
        self._forest.deposit(energy, accumulate=True)
        self._forest = self._forest.rebuild(np.arange(self._forest.n_trees), SPLIT_GROW, self.rho,
                                            self.dtree_max_depth, keep_energy=True, max_nodes=self.max_nodes)
        host_seconds = time.perf_counter() - start
        self._sampling = self._recording = DeviceForest(self._forest)
        self._reset_accumulators()
        dr.sync_thread()
        stats = {"splat_seconds": splat_seconds, "refine_seconds": time.perf_counter() - start,
                 "refine_host_seconds": host_seconds, "energy_recorded": float(energy.sum()), **self.sanitised}
        stats.update(self._structure_stats())
        return UpdateResult(stats)

    def _structure_stats(self) -> dict:
        stats = {"grid_cells": self.S ** 3, "memory_bytes": self._memory_bytes()}
        stats.update(self._forest_stats(self._forest, "dtree"))
        return stats

    def stats(self) -> dict:
        out = {"method": self.name, "S": self.S, "rho": self.rho, "dtree_max_depth": self.dtree_max_depth,
               "bsdf_fraction": self.bsdf_fraction}
        if hasattr(self, "_forest"):
            out.update(self._structure_stats())
        return out
