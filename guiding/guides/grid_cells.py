"""The cells of a uniform ``S³`` grid over the scene's bounding box: where the grid guide's radiance record
(:mod:`guiding.guides.grid.record`) and the quadtree grid (:class:`~guiding.guides.trees.quadtree_grid.QuadtreeGridGuide`) keep
what they learn about a position.

Cell ``(x, y, z)`` is flat index ``(z·S + y)·S + x``; a point outside the box belongs to the nearest cell.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


class GridCells:
    """The cell index of a uniform grid of ``resolution³`` cells.

    Parameters:
      resolution: S, cells per axis of the bounding box (at least 1).
    """

    def __init__(self, resolution: int):
        if resolution < 1:
            raise ValueError(f"spatial resolution must be >= 1, got {resolution}")
        self.S = resolution
        self.count = resolution ** 3
        self.bbox_min = mi.Point3f(0)
        self.inv_extent = mi.Vector3f(1)

    def set_bounds(self, bbox: mi.BoundingBox3f) -> None:
        """Span the grid over ``bbox`` (before any :meth:`cell`); an axis along which the box is flat gets a
        millionth of the box's largest extent, so the grid never divides by zero."""
        extent = dr.maximum(bbox.max - bbox.min, 1e-6 * dr.maximum(dr.max(bbox.max - bbox.min), 1e-3))
        self.bbox_min = mi.Point3f(bbox.min)
        self.inv_extent = mi.Vector3f(dr.rcp(extent))

    def cell(self, p: mi.Point3f) -> mi.UInt32:
        """``clamp(floor(S·(p − bbox.min)/extent), 0, S − 1)``, flattened."""
        c = dr.clip(mi.Vector3i(dr.floor((p - self.bbox_min) * self.inv_extent * self.S)), 0, self.S - 1)
        return mi.UInt32((c.z * self.S + c.y) * self.S + c.x)
