"""The path-vertex log of Monte Carlo learning, and its backward walk.

A guide that learns from the radiance its paths actually brought back (the grid guide's ``mc`` rule, the SD-tree
and the quadtree grid) logs every vertex of every path in the path loop, and walks each path backwards once the
path is complete, ``L ← Le_i + w_i·L``: at vertex ``i`` the walk holds ``L_{i+1}``, the radiance that arrived at
``i`` along the direction sampled there (Russian roulette included), which the guide records.

**Where the log lives.** Each path keeps its own vertices in the local memory of its lane (``dr.alloc_local``:
the stack of the CPU worker running the lane's packet, a thread's local memory on the GPU), and the walk runs in
the render kernel itself, right after the path loop (:meth:`~guiding.guides.base.Guide.finish_paths`). Nothing is
written to device memory: a log in device memory had to hold ``paths × max_depth`` entries of 32 bytes for the
pass (260 MiB at 1/4 resolution of the shared scenes, 8 spp, depth 16), although paths average 3–8 vertices, and a
compact pool sized from earlier passes would still have needed about 100 MiB in the first pass (paths run to the
Russian-roulette depth before the guide has learned anything) and a fallback for paths that find it full. Local
memory needs neither: it is sized by ``max_depth`` per lane in flight, and no vertex is ever dropped.

**Entry** (:class:`VertexLog`), ``max_depth`` per path, one per iteration of the path loop from the path's first
vertex with a target (the vertices before it have nothing to learn and nothing the walk needs): ``emitted`` (RGB, the
radiance ``Le`` emitted at the vertex towards the previous one), ``weight`` (RGB, ``w = f·cos/pdf`` including
Russian roulette, 0 where the path ends), ``target`` (UInt32: where the guide records the vertex's estimate, an
accumulator index of its own; :data:`NO_RECORD` for none) and the values a guide asks for by name (the SD-tree's
``pdf``, the density of the sampled direction, and ``score`` and ``tree`` for its learned BSDF share). The path's loop state
(:meth:`VertexLog.new_paths`) carries the buffer, the iteration, and the first and number of vertices logged.

**Why by iteration.** The CPU backend reads and writes local memory with one vector load or store where every lane
of a packet names the same entry, and with a gather or a scatter of one load or store per lane where they differ
(it tests which, at each access). Every lane still in the path loop is at the same iteration, so a vertex stored at
its iteration is one store per field; and the walk goes down the iterations from ``max_depth`` for every lane alike,
each lane taking in its own vertices only, so that its reads are one load per field too (indexed by the lanes' own
counts, which differ between paths that start logging at different vertices and end at different lengths, they were
per lane).

:func:`known_or_found` is how a guide finds where a vertex's estimate goes (this log's ``target``, or a SARSA
record index) when its sampler may have handed it over.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import field, make_dataclass

import drjit as dr
import mitsuba as mi

#: An accumulator index that names none: the ``target`` of a vertex whose estimate is recorded nowhere.
NO_RECORD = 0xFFFFFFFF


@dr.syntax
def known_or_found(known: mi.UInt32 | None, needed: mi.Bool, find: Callable[[mi.Bool], mi.UInt32]) -> mi.UInt32:
    """Where a vertex's estimate goes: ``known`` (what sampling handed over), and ``find(lanes)`` in the ``needed``
    lanes where it is :data:`NO_RECORD` (everywhere when ``known`` is None). A branch: packets whose every needed
    index was handed over skip ``find``."""
    if dr.hint(known is None, mode="scalar"):
        index = find(needed)
    else:
        index = mi.UInt32(known)
        missing = needed & (known == NO_RECORD)
        if missing:
            index = dr.select(missing, find(missing), index)
    return index

_TYPES: dict = {}


def _pytree(name: str, doc: str, fields: dict) -> type:
    """A dataclass that Dr.Jit traverses as a PyTree, with ``fields`` (name → type) defaulting to None."""
    return make_dataclass(name, [(key, kind, field(default=None)) for key, kind in fields.items()],
                          namespace={"DRJIT_STRUCT": fields, "__doc__": doc})


def _types(extra: tuple[tuple[str, type], ...]) -> tuple[type, type]:
    """The entry and loop-state classes of a log, built per variant (their fields are the variant's types, and this
    module may be imported before a variant is set) and per set of ``extra`` fields (name, type)."""
    key = (mi.variant(), extra)
    if key not in _TYPES:
        fields = {"emitted": mi.Color3f, "weight": mi.Color3f, "target": mi.UInt32, **dict(extra)}
        entry = _pytree("VertexEntry", "One logged vertex (see the module docstring).", fields)
        cursor = _pytree("PathCursor", "A path's log: its vertices (local memory, by iteration), the iteration, and "
                         "the first and number of vertices logged.",
                         {"entries": dr.Local, "step": mi.UInt32, "first": mi.UInt32, "n": mi.UInt32})
        _TYPES[key] = entry, cursor
    return _TYPES[key]


class VertexLog:
    """How a guide logs the vertices of its paths (see the module docstring).

    Parameters:
      max_depth: most vertices logged per path (the integrator's ``max_depth``).
      extra: further values logged per vertex, by name and Dr.Jit type (``{"pdf": mi.Float}``: the density of
        its sampled direction).
    """

    def __init__(self, max_depth: int, extra: dict[str, type] | None = None):
        self.max_depth, self.extra = max_depth, dict(extra or {})
        self._entry, self._cursor = _types(tuple(self.extra.items()))

    def new_paths(self, size: int):
        """The loop state of ``size`` paths, none of their vertices logged yet: one value per lane of each field.

        Only the iteration indexes local memory: Dr.Jit 1.5's CPU backend takes an index of width 1 for the packet's
        largest in its active lanes, so a per-lane count would write every lane's vertex at the largest count; every
        lane still in the loop is at the same iteration."""
        return self._cursor(entries=dr.alloc_local(self._entry, self.max_depth), step=dr.zeros(mi.UInt32, size),
                            first=dr.zeros(mi.UInt32, size), n=dr.zeros(mi.UInt32, size))

    def append(self, cursor, emitted: mi.Spectrum, weight: mi.Spectrum, continues: mi.Bool, target: mi.UInt32,
               active: mi.Bool, needed: mi.Bool | bool = False, **extra):
        """Log the vertex the active paths are at (arguments as :meth:`Guide.record`'s; ``target`` where its
        estimate goes, and a value for each of the log's ``extra`` fields, by name); returns ``cursor``
        moved on. A path's log starts at its first vertex with a target, or that the guide marks ``needed`` for
        something else its walk does: the walk needs no vertex before it (a path through delta lobes only logs
        nothing and walks nothing). Called once per iteration of the loop (its entries are by iteration): from the
        ``max_depth``-th iteration on a path logs nothing (local memory is not bounds-checked)."""
        starts = (target != NO_RECORD) | needed
        written = mi.Bool(active) & (cursor.step < self.max_depth) & ((cursor.n > 0) | starts)
        # The walk starts at a path's last vertex with L = 0: a weight there other than 0 (non-finite) would
        # make w·L NaN, so a vertex the path does not continue from logs w = 0.
        entry = self._entry(emitted=mi.Color3f(emitted), weight=mi.Color3f(dr.select(continues, weight, 0)),
                            target=mi.UInt32(target))
        for name, kind in self.extra.items():
            setattr(entry, name, kind(extra[name]))
        cursor.entries.write(entry, cursor.step, written)
        cursor.first = dr.select(written & (cursor.n == 0), cursor.step, cursor.first)
        cursor.n = dr.select(written, cursor.n + 1, cursor.n)
        cursor.step += 1
        return cursor


@dr.syntax
def walk_backward(cursor, visit: Callable[[object, mi.Color3f], None]) -> None:
    """Walk the paths of ``cursor`` from their last logged vertex to their first, ``L ← Le_i + w_i·L``.

    ``visit(entry, L)`` is called at every vertex before ``L`` takes in the vertex's own ``Le`` and ``w``:
    ``entry`` is the vertex's :class:`VertexLog` entry (``entry.target``: where its estimate goes, :data:`NO_RECORD`
    for none), ``L`` (RGB) the radiance that arrived at it along its sampled direction."""
    L = mi.Color3f(0)
    j = dr.full(mi.UInt32, len(cursor.entries), dr.width(cursor.n))     # the same in every lane (module docstring)
    end = cursor.first + cursor.n
    while j > 0:
        j -= 1
        if (j >= cursor.first) & (j < end):
            entry = cursor.entries.read(j)
            visit(entry, L)
            L = entry.emitted + entry.weight * L
