"""Discretisations of the sphere of directions.

:class:`SphereBins` is the radiance record's directional axis (method.md §2): the sphere split at the world
z = 0 plane, each hemisphere mapped to the unit square by the concentric (Shirley–Chiu) map with the equal-area
lift ``cos θ = 1 − r²`` (Mitsuba's ``square_to_uniform_hemisphere``), each square cut into ``D × D`` cells. All
``2·D²`` bins have the solid angle ``2π/D²``, and a uniform point of a bin's square is a uniform direction in it.

:class:`NormalBins` groups surface normals for the memo tables (N, M and the Expected SARSA value per
(cell, normal bin)). It is a cube map with an odd resolution, so the axis directions — the normals of walls,
floors and boxes — are bin centres, where the memoised values are exact.

Both accept any vector: :func:`safe_normalize` rescales by the largest component before normalising, so tiny
(even denormal) and huge vectors keep their direction, and the zero vector or a non-finite one falls back to +z
(the cube map needs no normalising at all: its face and position are ratios of the components). The path loop's
directions are unit vectors already, and skip the rescaling (``unit=True``): the bounce's lookups are a good part of
its instructions (results/bench/README.md).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


def safe_normalize(d: mi.Vector3f) -> mi.Vector3f:
    """``d / |d|`` for any finite non-zero ``d``, and +z for the zero vector or a non-finite one.

    ``dr.normalize`` alone fails at both ends of the float range: ``|d|²`` underflows to 0 for ``|d| < 1e-19``
    (the result is then NaN or a wrong direction) and overflows to infinity for ``|d| > 1e19``. Dividing by the
    largest component first brings ``|d|`` into [1, √3].
    """
    d = mi.Vector3f(d)
    largest = dr.maximum(dr.maximum(dr.abs(d.x), dr.abs(d.y)), dr.abs(d.z))
    # Three divisions, not ``d / largest``: Dr.Jit computes that as ``d · (1/largest)``, and 1/largest is denormal
    # for |d| > 8.5e37, which the CPU backend flushes to zero.
    unit = dr.normalize(mi.Vector3f(d.x / largest, d.y / largest, d.z / largest))
    usable = (largest > 0) & dr.isfinite(largest) & dr.isfinite(unit.x) & dr.isfinite(unit.y) & dr.isfinite(unit.z)
    return dr.select(usable, unit, mi.Vector3f(0, 0, 1))


#: How far inside its bin's square (in the unit square's coordinates) :meth:`SphereBins.direction` keeps a point. The
#: map to the sphere and back moves points by float32 rounding: of 4 M points on bin edges (D = 1 … 256) about half
#: were looked up in the neighbour, none once kept 1e-6 inside. A sampler drew such directions with its bin's density
#: and the density lookup (``pdf``) reported the neighbour's, 0 where that bin cannot be drawn.
EDGE_MARGIN = 1e-5


class SphereBins:
    """``2·D²`` equal-area direction bins; bin ``k = h·D² + row·D + column`` (h = 1 for the z < 0 hemisphere)."""

    def __init__(self, resolution: int):
        if resolution < 1:
            raise ValueError(f"directional resolution must be >= 1, got {resolution}")
        self.resolution = resolution
        self.count = 2 * resolution * resolution
        self.solid_angle = 2 * dr.pi / (resolution * resolution)

    def index(self, d: mi.Vector3f, unit: bool = False) -> mi.UInt32:
        """Bin of world direction ``d`` (any length; the zero vector and non-finite input land in a pole bin;
        ``unit``: the caller's ``d`` is a unit vector, used as it is)."""
        return self.fine_index(d, 1, unit)

    def fine_index(self, d: mi.Vector3f, sub_resolution: int, unit: bool = False) -> mi.UInt32:
        """``k·R² + j`` for world direction ``d`` in bin k and sub-bin j of the bin's square cut ``R × R``
        (``R = sub_resolution``; sub-bin ``j = row·R + column``); with R = 1, the bin. ``unit`` as :meth:`index`'s."""
        lower = d.z < 0
        local = mi.Vector3f(d.x, d.y, dr.abs(d.z))
        if not unit:
            local = safe_normalize(local)
        uv = mi.warp.uniform_hemisphere_to_square(local)
        n, R = self.resolution, sub_resolution
        fine = dr.clip(mi.Vector2i(dr.floor(uv * (n * R))), 0, n * R - 1)
        cell = fine // R if R > 1 else fine
        k = dr.select(lower, n * n, 0) + mi.UInt32(cell.y * n + cell.x)
        if R == 1:
            return k
        return k * (R * R) + mi.UInt32((fine.y % R) * R + fine.x % R)

    def sample(self, k: mi.UInt32, sample: mi.Point2f) -> mi.Vector3f:
        """A direction drawn uniformly in bin ``k`` for ``sample`` ∈ [0,1)²: :meth:`direction`, kept
        :data:`EDGE_MARGIN` inside the bin's square so that :meth:`index` gives ``k`` back."""
        margin = min(EDGE_MARGIN * self.resolution, 0.5)
        return self.direction(k, dr.clip(sample, margin, 1 - margin))

    def sample_sub(self, k: mi.UInt32, j: mi.UInt32, sub_resolution: int, sample: mi.Point2f) -> mi.Vector3f:
        """A direction drawn uniformly in sub-bin ``j`` of bin ``k`` (:meth:`fine_index`) for ``sample`` ∈ [0,1)²,
        kept :data:`EDGE_MARGIN` inside the sub-bin's square so that :meth:`fine_index` gives ``(k, j)`` back."""
        R = sub_resolution
        margin = min(EDGE_MARGIN * self.resolution * R, 0.5)
        inner = dr.clip(sample, margin, 1 - margin)
        return self.direction(k, (mi.Point2f(mi.Float(j % R), mi.Float(j // R)) + inner) / R)

    def direction(self, k: mi.UInt32, sample: mi.Point2f) -> mi.Vector3f:
        """The direction at position ``sample`` ∈ [0,1]² of bin ``k``'s square (uniform in solid angle)."""
        n = self.resolution
        lower = k >= n * n
        local_index = k - dr.select(lower, n * n, 0)
        uv = (mi.Point2f(mi.Float(local_index % n), mi.Float(local_index // n)) + sample) / n
        d = mi.warp.square_to_uniform_hemisphere(uv)
        return mi.Vector3f(d.x, d.y, dr.select(lower, -d.z, d.z))

    def centres(self) -> mi.Vector3f:
        return self.direction(dr.arange(mi.UInt32, self.count), mi.Point2f(0.5, 0.5))


class NormalBins:
    """``6·R²`` cube-map bins of unit normals (R odd, so ±x, ±y, ±z are bin centres)."""

    def __init__(self, resolution: int):
        if resolution < 1 or resolution % 2 == 0:
            raise ValueError(f"normal-bin resolution must be odd and >= 1, got {resolution}")
        self.resolution = resolution
        self.count = 6 * resolution * resolution

    def index(self, n: mi.Vector3f) -> mi.UInt32:
        """Bin of normal ``n`` (any length; the zero vector and non-finite input land in the +z face's centre).

        Not normalised: the face is the largest component's, and the position on it the two others' ratios to it,
        divided (not multiplied by a reciprocal, which is denormal, and flushed to zero, for components over
        8.5e37)."""
        a = dr.abs(n)
        axis = dr.select((a.x >= a.y) & (a.x >= a.z), 0, dr.select(a.y >= a.z, 1, 2))
        major = dr.select(axis == 0, n.x, dr.select(axis == 1, n.y, n.z))
        u = dr.select(axis == 0, n.y, n.x) / dr.abs(major)
        v = dr.select(axis == 2, n.y, n.z) / dr.abs(major)
        face = mi.UInt32(axis) * 2 + dr.select(major < 0, 1, 0)
        r = self.resolution
        i = dr.clip(mi.Int32(dr.floor((u * 0.5 + 0.5) * r)), 0, r - 1)
        j = dr.clip(mi.Int32(dr.floor((v * 0.5 + 0.5) * r)), 0, r - 1)
        usable = dr.isfinite(major) & dr.isfinite(u) & dr.isfinite(v)      # 0/0 and ∞/∞ are NaN
        plus_z_centre = 4 * r * r + (r // 2) * r + r // 2
        return dr.select(usable, face * (r * r) + mi.UInt32(j * r + i), plus_z_centre)

    def normal(self, k: mi.UInt32, sample: mi.Point2f | None = None) -> mi.Vector3f:
        """The unit normal at position ``sample`` ∈ [0,1]² of bin ``k`` (its centre by default)."""
        sample = mi.Point2f(0.5, 0.5) if sample is None else sample
        r = self.resolution
        face, local_index = k // (r * r), k % (r * r)
        u = (mi.Float(local_index % r) + sample.x) / r * 2 - 1
        v = (mi.Float(local_index // r) + sample.y) / r * 2 - 1
        sign = dr.select((face & 1) == 1, -1.0, 1.0)
        axis = face // 2
        x = dr.select(axis == 0, sign, u)
        y = dr.select(axis == 0, u, dr.select(axis == 1, sign, v))
        z = dr.select(axis == 2, sign, v)
        return dr.normalize(mi.Vector3f(x, y, z))
