"""Test helpers for the D-trees and the SD-tree's schedule: trees written by hand, a NumPy reference lookup and the
whole schedule of an SD-tree guide."""

from __future__ import annotations

import numpy as np

from guiding.guides.trees.dtree import Forest
from guiding.guides.trees.stree import iteration_length


def nested_forest(trees: list) -> Forest:
    """A forest of trees written as nested lists: a quadrant is a number (a leaf's energy) or a list of four
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
    forest = Forest(np.array(child).reshape(-1, 4), np.array(energy).reshape(-1, 4), depth, tree, len(trees))
    forest.propagate()
    return forest


def lookup_np(forest: Forest, trees: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference lookup (NumPy, float64) of :meth:`DeviceForest.lookup_uv`: the leaf slot and the density on the
    square of points ``uv`` (shape (n, 2)) in trees ``trees`` of ``forest``."""
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
        e = forest.energy[node[idx]]
        tot = e.sum(axis=1)
        share = np.where(tot > 0, e[np.arange(len(idx)), q] / np.where(tot > 0, tot, 1), 0.25)
        pdf[idx] *= 4 * share
        slot[idx] = 4 * node[idx] + q
        nxt = forest.child[node[idx], q]
        go[idx] = nxt >= 0
        node[idx] = np.where(nxt >= 0, nxt, node[idx])
    return slot, pdf


def doubling_schedule(base_spp: int, budget_spp: int | None = None, iterations: int = 40) -> list[tuple[int, int]]:
    """``[(start, end)]`` in spp of the training iterations of an SD-tree guide with ``base_spp`` and
    ``budget_spp`` (:func:`~guiding.guides.trees.stree.iteration_length`): the first ``iterations`` without a budget,
    all of them up to its end with one."""
    bounds, start, k = [], 0, 0
    while (budget_spp is None and k < iterations) or (budget_spp is not None and start < budget_spp):
        length, _ = iteration_length(base_spp, k, start, budget_spp)
        bounds.append((start, start + length))
        start, k = start + length, k + 1
    return bounds
