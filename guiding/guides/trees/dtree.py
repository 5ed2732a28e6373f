"""D-trees (Müller, Gross, Novák 2017): quadtrees over the sphere of directions, on the host and on the device.

Directional distributions are quadtrees ("D-trees") over the equal-area cylindrical square of world directions,
``(u, v) ∈ [0, 1)²`` with ``cos θ = 2u − 1`` and ``φ = 2πv`` (θ from the world z axis): equal areas in ``(u, v)``
are equal solid angles, so a density ``p_uv`` on the square is ``p_uv / (4π)`` per steradian.

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
``4n + q`` in an energy accumulator of the same size. The first levels are skipped: per tree, a table of its cells of
side ``2^-jump_levels`` says where a descent stands below them, and an alias row draws a cell with its probability
(:meth:`Forest.cells`, :class:`DeviceForest`).
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from guiding.guides.directions import safe_normalize
from guiding.guides import alias_rows
from guiding.guides.alias_rows import ONE_MINUS_EPS     # samples and coordinates are clamped to [0, ONE_MINUS_EPS]

#: How far inside a leaf's edges a drawn point stays (at most a quarter of the leaf's side): four float32 steps of
#: [0.5, 1). Points within it of an edge are pressed onto it, so inside the smallest leaves (side 2^-20, 16 floats)
#: the points are not uniform; the leaf's probability, and its density, are unchanged.
EDGE_OFFSET = 2.0 ** -22
#: A cell's entry with this bit is a leaf slot (the descent ended within the first levels), without it a node.
LEAF_BIT = 0x80000000
#: An :meth:`Forest.overlay` entry without LEAF_BIT: the node in its low bits, the level of its square (side
#: 2^-level) from this bit on.
LEVEL_SHIFT = 26
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

    def overlay(self, other: "Forest") -> np.ndarray | None:
        """Where each leaf quadrant of this forest lies in ``other``, a forest of the same trees and squares in
        another structure (the SD-tree's sampling and recording trees): per slot ``4·node + q`` (uint32; inner
        quadrants' entries mean nothing), ``LEAF_BIT | slot`` of ``other``'s leaf holding the quadrant (the same
        square, or a larger one where ``other`` is coarser), or, where ``other`` divides it further, the node of
        ``other`` whose square it is, with the square's level (:data:`LEVEL_SHIFT`). None where ``other`` has too
        many nodes for the entries' bits."""
        if other.n_nodes >= 1 << LEVEL_SHIFT or self.max_depth() >= 1 << (31 - LEVEL_SHIFT):
            return None
        entry = np.zeros((self.n_nodes, 4), dtype=np.uint32)
        mine = theirs = np.arange(self.n_trees)
        held = np.full(self.n_trees, -1, dtype=np.int64)     # other's leaf entry holding the whole node, or -1
        quadrant = np.arange(4)
        while len(mine):
            coarser = held[:, None] >= 0
            their_child = np.where(coarser, -1, other.child[np.maximum(theirs, 0)])
            their_leaf = np.where(coarser, held[:, None], LEAF_BIT | (4 * theirs[:, None] + quadrant))
            level = self.depth[mine].astype(np.int64)[:, None]
            entry[mine] = np.where(their_child >= 0, their_child | (level << LEVEL_SHIFT), their_leaf)
            rows, quads = np.nonzero(self.child[mine] >= 0)
            mine = self.child[mine[rows], quads]
            theirs = their_child[rows, quads]
            held = np.where(theirs >= 0, -1, their_leaf[rows, quads])
        return entry.ravel()

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

    def probabilities(self, nodes: np.ndarray | None = None) -> np.ndarray:
        """Each quadrant's share of its node's energy (1/4 each for a node without energy), shape (N, 4), or of the
        nodes ``nodes`` (shape ``nodes.shape + (4,)``)."""
        energy = self.energy if nodes is None else self.energy[nodes]
        tot = energy.sum(axis=-1, keepdims=True)
        return np.where(tot > 0, energy / np.where(tot > 0, tot, 1), 0.25)

    def cells(self, levels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where a descent stands after ``levels`` levels, in each cell of side ``2^-levels`` of each tree's square
        (cell ``row·2^levels + column``, the column along ``u``): the node it reached (-1 where it ended in a leaf
        before), the slot of that leaf (-1 where it did not), and the cell's probability under the trees' float32
        probabilities; each of shape (trees, 4^levels)."""
        trees = self.n_trees
        node, slot, mass = np.arange(trees)[:, None], np.full((trees, 1), -1), np.ones((trees, 1))
        side = 1
        for _ in range(levels):
            inner = (node >= 0)[..., None]
            at = np.maximum(node, 0)
            child = np.where(inner, self.child[at], -1)
            # The device's probabilities (float32) of the nodes reached, and their shares as a descent takes them.
            prob = self.probabilities(at).astype(np.float32)
            share = np.where(inner, prob / prob.sum(axis=-1, keepdims=True, dtype=np.float64), 0.25)

            def grid(a):      # quadrant q = qx + 2·qy of cell (row, column): cell (2·row + qy, 2·column + qx) below
                return a.reshape(trees, side, side, 2, 2).transpose(0, 1, 3, 2, 4).reshape(trees, 4 * side * side)

            slot = grid(np.where(inner, np.where(child < 0, 4 * at[..., None] + np.arange(4), -1), slot[..., None]))
            mass = grid(mass[..., None] * share)
            node = grid(child)
            side *= 2
        return node, slot, mass


# ===================================================================================================================
#  D-trees on the device
# ===================================================================================================================
def capacity(n: int) -> int:
    """The smallest power of two ≥ ``n``, at least 2: the size of a device accumulator for ``n`` entries (a kernel
    that scatters into it is compiled for its size, and this keeps small changes of ``n`` from recompiling it)."""
    return 1 << max(int(n) - 1, 1).bit_length()


def padded(a: np.ndarray, minimum: int = 2) -> np.ndarray:
    """``a`` with zeros appended up to ``minimum`` entries, in 64-byte aligned memory, for uploading as a device
    table (D-trees, S-tree). Arrays of one element may be traced differently from larger ones, so every table keeps
    >= 2 entries; and the CPU backend uses a NumPy array's memory in place, where a table that is not 64-byte aligned
    gets scalar instead of packet gathers: a different kernel, compiled again."""
    a = a if len(a) >= minimum else np.concatenate([a, np.zeros(minimum - len(a), dtype=a.dtype)])
    buffer = np.empty(a.nbytes + 64, dtype=np.uint8)
    offset = -buffer.ctypes.data % 64
    out = buffer[offset:offset + a.nbytes].view(a.dtype)
    out[:] = a
    return out


def _node_probabilities(prob: mi.Float, node: mi.UInt32, active: mi.Bool):
    """The four quadrant probabilities of nodes ``node``, and their sum: one packet gather (the four are neighbours;
    on the CPU each gather is a loop over the lanes, so four of one float cost about four times one of four)."""
    p = dr.gather(mi.Vector4f, prob, node, active)
    return p.x, p.y, p.z, p.w, p.x + p.y + p.z + p.w


def _per_lane(draw, drawn, looked):
    """``drawn`` in the lanes of mask ``draw``, ``looked`` in the others; a Python bool ``draw`` takes one of them
    whole (the other is None: :meth:`DeviceForest.descend` did not trace it)."""
    if draw is True or draw is False:
        return drawn if draw else looked
    return dr.select(draw, drawn, looked)


def _quadrant(right: mi.Bool, up: mi.Bool) -> mi.UInt32:
    """Quadrant ``q = qx + 2·qy`` of the upper halves in ``u`` (``right``) and in ``v`` (``up``)."""
    return dr.select(right, mi.UInt32(1), mi.UInt32(0)) + dr.select(up, mi.UInt32(2), mi.UInt32(0))


class DeviceForest:
    """A :class:`Forest` uploaded for sampling, density evaluation and leaf lookup inside kernels."""

    def __init__(self, forest: Forest, jump_levels: int = 3, densities: bool = True):
        """``jump_levels``: the levels a descent skips. Each tree's square is cut into ``4^jump_levels`` cells of
        side ``2^-jump_levels``, and a table per cell holds where a descent stands after these levels
        (:meth:`Forest.cells`) and, as alias rows, each cell's probability: a descent starts there with one read of
        its cell instead of two per level. 0: every descent starts at the root (Müller's). ``densities=False``: a
        forest whose lookups find leaves only (the SD-tree's recording trees), without the cells' alias rows."""
        self.jump_levels = jump_levels
        self.n_nodes = forest.n_nodes
        self.n_trees = forest.n_trees
        child = np.where(forest.child < 0, 0, forest.child).astype(np.uint32).ravel()
        self.child = mi.UInt32(padded(child))
        self.prob = mi.Float(padded(forest.probabilities().astype(np.float32).ravel()))
        self.tree_of_node = forest.tree       # host side: where the recorded sums of a node's leaves are counted
        self.has_energy = mi.Bool(padded(forest.totals() > 0))
        dr.eval(self.child, self.prob, self.has_energy)
        self.n_cells = 4 ** jump_levels
        self.cell_alias = None
        if jump_levels > 0:
            node, slot, mass = forest.cells(jump_levels)
            self.cell_entry = mi.UInt32(padded(np.where(node >= 0, node, slot | LEAF_BIT).astype(np.uint32).ravel()))
            # The cells' alias rows give a cell's density (per unit area of the square) to draws and lookups alike.
            if densities:
                self.cell_alias = alias_rows.build(mi.Float(mass.astype(np.float32).ravel()), self.n_cells,
                                                   scale=self.n_cells)
            dr.eval(self.cell_entry)

    @property
    def nbytes(self) -> int:
        cells = 0
        if self.jump_levels:
            cells = self.n_trees * self.n_cells * (4 + (alias_rows.SLOT_BYTES if self.cell_alias is not None else 0))
        return 4 * 2 * 4 * self.n_nodes + self.n_trees + cells

    # ----------------------------------------------------------------------------------------- device code
    @dr.syntax
    def descend(self, tree, point, draw, active=True, with_pdf=True, start=None):
        """Descend tree ``tree`` to a leaf: (its slot ``4·node + q``, the point drawn, the density there, and the
        lane's point: the one drawn, or the one looked up).

        Lanes with ``draw`` sample: ``point`` is a 2D sample, the cell below the first ``jump_levels`` levels is drawn
        with its probability (:meth:`_start`), then quadrants with theirs (first the ``u`` half, then the ``v`` half,
        reusing the rescaled random number as in Müller's code), and the point drawn is uniform in the leaf (up to
        :data:`EDGE_OFFSET`). The other lanes look a point up: ``point`` lies in the square, the leaf is the one that
        contains it, and the point returned means nothing. ``draw`` is a Python bool (every lane alike; only that
        half of the loop is traced) or a mask, with which the mixture sampler draws from the tree in some lanes and
        finds the density of the BSDF's direction in the others in one descent instead of two. ``with_pdf=False``
        (lookups only) skips the probabilities. ``start`` (lookups only): nodes to descend from instead of the trees'
        roots, ``point`` the place within a start node's square (``tree`` is not read)."""
        child, prob = self.child, self.prob
        if dr.hint(start is not None, mode="scalar"):
            node, slot, x, origin, pdf = mi.UInt32(start), mi.UInt32(0), mi.Point2f(point), mi.Point2f(0), mi.Float(1)
            go = mi.Bool(active)
        elif dr.hint(self.jump_levels > 0, mode="scalar"):
            node, slot, x, origin, pdf = self._start(tree, point, draw, active, with_pdf)
            go = mi.Bool(active) & (node != 0)
        else:
            node, slot, x, origin, pdf = mi.UInt32(tree), mi.UInt32(0), mi.Point2f(point), mi.Point2f(0), mi.Float(1)
            go = mi.Bool(active)
        size = mi.Float(2.0 ** -self.jump_levels)
        while go:
            base = node * 4
            if dr.hint(with_pdf or draw is not False, mode="scalar"):
                p0, p1, p2, p3, total = _node_probabilities(prob, node, go)
            if dr.hint(draw is not False, mode="scalar"):
                # A drawn quadrant depends on the probabilities just read: reading its four children along with them,
                # rather than the chosen one after the choice, makes one round of memory accesses per level, not two.
                children = dr.gather(mi.Vector4u, child, node, go)
            if dr.hint(draw is not False, mode="scalar"):
                px = dr.select(total > 0, (p0 + p2) / total, 0.5)
                drawn_right = x.x >= px
                a = dr.select(drawn_right, p1, p0)
                b = dr.select(drawn_right, p3, p2)
                py = dr.select((a + b) > 0, a / (a + b), 0.5)
                drawn_up = x.y >= py
                drawn = mi.Point2f(dr.clip(dr.select(drawn_right, (x.x - px) / (1 - px), x.x / px), 0, ONE_MINUS_EPS),
                                   dr.clip(dr.select(drawn_up, (x.y - py) / (1 - py), x.y / py), 0, ONE_MINUS_EPS))
            else:
                drawn_right = drawn_up = drawn = None
            if dr.hint(draw is not True, mode="scalar"):
                x2 = x * 2
                looked_right, looked_up = x2.x >= 1, x2.y >= 1
                looked = mi.Point2f(dr.select(looked_right, x2.x - 1, x2.x), dr.select(looked_up, x2.y - 1, x2.y))
            else:
                looked_right = looked_up = looked = None
            right = _per_lane(draw, drawn_right, looked_right)
            up = _per_lane(draw, drawn_up, looked_up)
            x = _per_lane(draw, drawn, looked)
            if dr.hint(with_pdf, mode="scalar"):
                chosen = dr.select(up, dr.select(right, p3, p2), dr.select(right, p1, p0))
                pdf *= dr.select(total > 0, 4 * chosen / total, 1)
            size *= 0.5
            origin += mi.Point2f(dr.select(right, size, 0), dr.select(up, size, 0))
            slot = base + _quadrant(right, up)
            if dr.hint(draw is not False, mode="scalar"):
                node = dr.select(up, dr.select(right, children.w, children.z), dr.select(right, children.y, children.x))
            else:
                node = dr.gather(mi.UInt32, child, slot, go)
            go &= node != 0
        # Keep the point inside the leaf it came from, off its edges (see EDGE_OFFSET), so that the direction made of
        # it (whose φ is rounded in sincos) lies in the leaf too, and none is the pole u = 0, whose φ is lost.
        margin = dr.minimum(size * 0.25, EDGE_OFFSET)
        uv = dr.clip(origin + size * x, origin + margin, origin + size - margin)
        return slot, uv, pdf, _per_lane(draw, uv, point)

    def _start(self, tree, point, draw, active, with_pdf):
        """Where the descent of :meth:`descend` stands after ``jump_levels`` levels, from its cell's tables: the
        node (0 where it ended in a leaf), the leaf's slot there, the point within the cell, the cell's corner and
        its density. Looking lanes take the cell ``point`` lies in; drawing lanes take that cell's slot of the tree's
        alias row (uniform over the cells, the bits of both coordinates alike), its threshold against the point's
        place within the cell in ``v``, and go on with the point's place in ``u`` and what is left of it in ``v``."""
        side, n_cells, row = 2 ** self.jump_levels, self.n_cells, mi.UInt32(tree)
        scaled = mi.Point2f(point) * side
        column, cell_row = dr.minimum(mi.UInt32(scaled.x), side - 1), dr.minimum(mi.UInt32(scaled.y), side - 1)
        cell = cell_row * side + column
        within = dr.clip(scaled - mi.Point2f(mi.Float(column), mi.Float(cell_row)), 0, ONE_MINUS_EPS)
        drawn_cell = drawn_density = drawn = looked_density = None
        if dr.hint(draw is not False, mode="scalar"):
            drawn_cell, drawn_density, rest = alias_rows.pick(self.cell_alias, row, n_cells, cell, within.y,
                                                              mi.Bool(active) & draw)
            drawn = mi.Point2f(within.x, rest)
        if dr.hint(draw is not True, mode="scalar"):
            looking = mi.Bool(active) if draw is False else mi.Bool(active) & ~draw
            looked_density = (alias_rows.density(self.cell_alias, row, n_cells, cell, looking) if with_pdf
                              else mi.Float(1))
        cell = _per_lane(draw, drawn_cell, cell)
        entry = dr.gather(mi.UInt32, self.cell_entry, row * n_cells + cell, active)
        leaf = (entry & LEAF_BIT) != 0
        corner = mi.Point2f(mi.Float(cell % side), mi.Float(cell // side)) / side
        return (dr.select(leaf, 0, entry), dr.select(leaf, entry & (LEAF_BIT - 1), 0), _per_lane(draw, drawn, within),
                corner, _per_lane(draw, drawn_density, looked_density))

    def sample_uv(self, tree, sample, active=True):
        """Descend tree ``tree`` with the 2D ``sample``: a point of the square and its density there."""
        _, uv, pdf, _ = self.descend(tree, sample, True, active)
        return uv, pdf

    def lookup_uv(self, tree, uv, active=True, with_pdf=True):
        """Leaf slot (``4·node + q``) containing ``uv`` in tree ``tree``, and the density there."""
        slot, _, pdf, _ = self.descend(tree, uv, False, active, with_pdf)
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

    def sample_or_pdf_dir(self, tree, sample, d, draw, active=True):
        """In one descent of tree ``tree``: lanes with ``draw`` draw a world direction with the 2D ``sample``, the
        others look world direction ``d`` up; returns (the direction drawn, meaningless where not ``draw``; the
        solid-angle density of the lane's direction; the slot of the leaf it lies in; its point in the square)."""
        slot, uv, pdf, point = self.descend(tree, dr.select(draw, mi.Point2f(sample), dir_to_uv(d)), draw, active)
        return uv_to_dir(uv), pdf * INV_4PI, slot, point

    @dr.syntax
    def slot_at(self, entry, point, active=True):
        """The leaf slot of this forest that holds ``point`` (in the tree's square), from the :meth:`Forest.overlay`
        entry of another forest's leaf that holds it: the slot the entry names, or the leaf a descent from the node it
        names finds (a branch: packets whose every lane's entry names a leaf skip it)."""
        slot = entry & (LEAF_BIT - 1)
        deeper = mi.Bool(active) & ((entry & LEAF_BIT) == 0)
        if deeper:
            # The point's place in the node's square: exact in float32 (a product by a power of two, its fraction).
            scaled = point * dr.reinterpret_array(mi.Float, ((entry >> LEVEL_SHIFT) + 127) << 23)
            below, _, _, _ = self.descend(None, scaled - dr.floor(scaled), False, deeper, with_pdf=False,
                                          start=entry & ((1 << LEVEL_SHIFT) - 1))
            slot = dr.select(deeper, below, slot)
        return slot
