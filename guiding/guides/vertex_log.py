"""The path-vertex log of Monte Carlo learning, and its backward walk.

A guide that learns from the radiance its paths actually brought back (the grid guide's ``mc`` rule, the SD-tree
and the quadtree grid) logs every vertex of every path of a pass in the path loop, and walks each path backwards
once the path is complete, ``L ← Le_i + w_i·L``: at vertex ``i`` the walk holds ``L_{i+1}``, the radiance that
arrived at ``i`` along the direction sampled there (Russian roulette included), which the guide records.

**Layout** (:class:`VertexLog`): ``n_paths × max_depth`` entries, entry ``path·max_depth + i`` for vertex ``i`` of
a path: ``emitted`` (RGB, the radiance ``Le`` emitted at the vertex towards the previous one), ``weight`` (RGB,
``w = f·cos/pdf`` including Russian roulette, 0 where the path ends), ``target`` (UInt32: where the guide records
the vertex's estimate, an accumulator index of its own; :data:`NO_RECORD` for none) and, if asked for, ``pdf``
(the density of the sampled direction). Per path, ``count`` holds the number of vertices logged, for a walk in a
later kernel. The walk runs where the guide calls it: the grid guide right after the path loop
(:meth:`~guiding.guides.base.Guide.finish_paths`), where reading the log makes Dr.Jit launch the render kernel and
walk in a second kernel of the pass; the tree guides in a kernel of their own in ``update``, after the pass.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

#: An accumulator index that names none: the ``target`` of a vertex whose estimate is recorded nowhere.
NO_RECORD = 0xFFFFFFFF

_CURSOR_TYPES: dict = {}


def _cursor_type():
    """The per-path loop state of a log (a Dr.Jit PyTree), one class per variant (its fields are the variant's
    types, and this module may be imported before a variant is set)."""
    key = mi.variant()
    if key not in _CURSOR_TYPES:
        @dataclass
        class PathCursor:
            """Path index and number of vertices logged so far."""

            path: mi.UInt32 = None
            n: mi.UInt32 = None
            DRJIT_STRUCT = {"path": mi.UInt32, "n": mi.UInt32}

        _CURSOR_TYPES[key] = PathCursor
    return _CURSOR_TYPES[key]


class VertexLog:
    """The vertices of ``n_paths`` paths of at most ``max_depth`` vertices (see the module docstring).

    Parameters:
      n_paths: paths of the pass (lanes of the render kernel).
      max_depth: most vertices logged per path (the integrator's ``max_depth``).
      with_pdf: log the density of each vertex's sampled direction too.
    """

    def __init__(self, n_paths: int, max_depth: int, with_pdf: bool = False):
        size = n_paths * max_depth
        self.n_paths, self.max_depth = n_paths, max_depth
        self.emitted = dr.zeros(mi.Color3f, size)
        self.weight = dr.zeros(mi.Color3f, size)
        self.target = dr.full(mi.UInt32, NO_RECORD, size)
        self.pdf = dr.zeros(mi.Float, size) if with_pdf else None
        self.count = dr.zeros(mi.UInt32, n_paths)

    @property
    def nbytes(self) -> int:
        per_vertex = 3 + 3 + 1 + (1 if self.pdf is not None else 0)
        return 4 * (self.n_paths * self.max_depth * per_vertex + self.n_paths)

    def new_paths(self):
        """The loop state of the log's paths, none logged yet."""
        return _cursor_type()(path=dr.arange(mi.UInt32, self.n_paths), n=mi.UInt32(0))

    def append(self, cursor, emitted: mi.Spectrum, weight: mi.Spectrum, continues: mi.Bool, target: mi.UInt32,
               active: mi.Bool, pdf: mi.Float = None):
        """Log the vertex the active paths are at (arguments as :meth:`Guide.record`'s; ``target`` where its
        estimate goes, ``pdf`` the density of its sampled direction when the log keeps them); returns ``cursor``
        moved on. Beyond ``max_depth`` vertices a path logs nothing."""
        written = mi.Bool(active) & (cursor.n < self.max_depth)
        entry = cursor.path * self.max_depth + cursor.n
        dr.scatter(self.emitted, emitted, entry, written)
        # The walk starts at a path's last vertex with L = 0: a weight there other than 0 (non-finite) would
        # make w·L NaN, so a vertex the path does not continue from logs w = 0.
        dr.scatter(self.weight, dr.select(continues, weight, 0), entry, written)
        dr.scatter(self.target, target, entry, written)
        if self.pdf is not None:
            dr.scatter(self.pdf, pdf, entry, written)
        cursor.n = dr.select(written, cursor.n + 1, cursor.n)
        return cursor

    def keep(self, cursor) -> None:
        """Store the paths' vertex counts (after the path loop), for a walk in a later kernel (:meth:`kept`)."""
        dr.scatter(self.count, cursor.n, cursor.path)

    def kept(self):
        """The loop state of the paths as :meth:`keep` stored it."""
        path = dr.arange(mi.UInt32, self.n_paths)
        return _cursor_type()(path=path, n=dr.gather(mi.UInt32, self.count, path))


@dr.syntax
def walk_backward(log: VertexLog, cursor, visit: Callable[[mi.UInt32, mi.UInt32, mi.Color3f], None]) -> None:
    """Walk the paths of ``cursor`` from their last logged vertex to their first, ``L ← Le_i + w_i·L``.

    ``visit(entry, target, L)`` is called at every vertex before ``L`` takes in the vertex's own ``Le`` and
    ``w``: ``entry`` is the vertex's entry in ``log``, ``target`` where its estimate goes (:data:`NO_RECORD`: none),
    ``L`` (RGB) the radiance that arrived at it along its sampled direction."""
    L = mi.Color3f(0)
    j = mi.UInt32(cursor.n)
    while j > 0:
        j -= 1
        entry = cursor.path * log.max_depth + j
        visit(entry, dr.gather(mi.UInt32, log.target, entry), L)
        L = dr.gather(mi.Color3f, log.emitted, entry) + dr.gather(mi.Color3f, log.weight, entry) * L
