"""Measuring the direction ↔ bin maps of :mod:`guiding.guides.directions` (the concentric hemisphere pair ``SphereBins``
and the cube map of normals ``NormalBins``): float64 references computed from the maps' own float32 output, the
inputs that are hard for them, and finders of the directions a map gets wrong."""

import functools
from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from guiding.guides.directions import NormalBins, SphereBins
from arrays import EPS32, TINY32, angle_between, to_numpy, unit, vectors

#: Directional resolutions D checked: 1 and 2 (one and four bins per hemisphere), odd ones (a bin centred on the
#: pole), the paper's 16, and 64.
SPHERE_RESOLUTIONS = (1, 2, 3, 4, 5, 16, 64)
#: Odd cube-map resolutions of the memo tables' normal bins (5 is the default).
NORMAL_RESOLUTIONS = (1, 3, 5, 7)


def readings(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two unit vectors a float32 input may stand for: denormal components kept, and flushed to zero. An input
    whose flushed reading has no direction (only denormal components) may land in any valid bin."""
    return unit(directions), unit(directions, flush=True)


def smallest_angle(candidates: tuple[np.ndarray, ...], target: np.ndarray) -> np.ndarray:
    """Per row, the smallest angle between ``target`` and the candidates that have a direction (NaN if none)."""
    angles = np.stack([angle_between(c, target) for c in candidates])
    return np.where(np.isnan(angles).all(axis=0), np.nan, np.nanmin(np.where(np.isnan(angles), np.inf, angles),
                                                                          axis=0))


def boundary_samples(steps: int) -> np.ndarray:
    """``4·steps`` positions walking once around the unit square (the boundary of a bin in its own coordinates)."""
    t = np.arange(steps) / steps
    zero, one = np.zeros(steps), np.ones(steps)
    return np.concatenate([np.stack([t, zero], 1), np.stack([one, t], 1), np.stack([1 - t, one], 1),
                           np.stack([zero, 1 - t], 1)])


@dataclass
class BinGeometry:
    """Float64 measurements of the bins of a direction map, from the float32 directions the map produces.

    ``solid_angle``: the area of each bin (spherical polygon through ``4·steps`` boundary points, Richardson-
    extrapolated from ``steps/2`` to remove the chords' O(1/steps²) error); ``perimeter``: its boundary length;
    ``centre``: the unit direction at the bin's centre; ``radius``: the largest angle from the centre to the
    boundary; ``spacing``: the largest angle between neighbouring boundary points (how far the true boundary can
    lie beyond ``radius``).
    """

    solid_angle: np.ndarray
    perimeter: np.ndarray
    centre: np.ndarray
    radius: np.ndarray
    spacing: np.ndarray

    def reach(self, k) -> np.ndarray:
        """How far from its centre a direction can lie and still be in bin(s) ``k``: the radius at the sampled
        boundary points, plus their spacing (the true boundary may bulge that far beyond them), plus rounding."""
        return self.radius[k] + self.spacing[k] + 8 * EPS32


def _polygon(direction_of, bins: np.ndarray, steps: int):
    """Fan areas and boundary of the spherical polygons of ``bins`` with ``4·steps`` boundary points."""
    samples = boundary_samples(steps)
    m = len(samples)
    k = np.repeat(bins, m).astype(np.uint32)
    s = np.tile(samples, (len(bins), 1))
    points = unit(to_numpy(direction_of(mi.UInt32(k), mi.Point2f(s[:, 0], s[:, 1])))).reshape(len(bins), m, 3)
    centre = unit(to_numpy(direction_of(mi.UInt32(bins.astype(np.uint32)), mi.Point2f(0.5, 0.5))))
    a, b, c = points, np.roll(points, -1, axis=1), centre[:, None, :]
    # Van Oosterom & Strackee: the solid angle of the triangle (c, a, b).
    triple = np.einsum("kmi,kmi->km", c, np.cross(a, b))
    denominator = 1 + np.einsum("kmi,kmi->km", a, b) + np.einsum("kmi,kmi->km", b, c) + np.einsum("kmi,kmi->km", c, a)
    area = np.abs(2 * np.arctan2(triple, denominator).sum(axis=1))
    edges = angle_between(a.reshape(-1, 3), b.reshape(-1, 3)).reshape(len(bins), m)
    radius = angle_between(points.reshape(-1, 3), np.repeat(centre, m, axis=0)).reshape(len(bins), m).max(axis=1)
    return area, edges.sum(axis=1), centre, radius, edges.max(axis=1)


def bin_geometry(direction_of, bins, steps: int = 32, chunk_points: int = 1 << 20) -> BinGeometry:
    """Measure the bins ``bins`` (indices) of ``direction_of(k, sample ∈ [0,1]²) → direction``, in chunks of at
    most ``chunk_points`` boundary points (memory stays near 100 MB whatever the bin count)."""
    bins = np.asarray(bins, dtype=np.int64)
    per_chunk = max(1, chunk_points // (4 * steps))
    parts = []
    for start in range(0, len(bins), per_chunk):
        chunk = bins[start:start + per_chunk]
        coarse = _polygon(direction_of, chunk, steps // 2)[0]
        fine, perimeter, centre, radius, spacing = _polygon(direction_of, chunk, steps)
        parts.append(((4 * fine - coarse) / 3, perimeter, centre, radius, spacing))
    return BinGeometry(*(np.concatenate(column) for column in zip(*parts)))


def equal_area_excess(geometry: BinGeometry, expected: float) -> np.ndarray:
    """Each bin's |solid angle − expected| in units of ``perimeter·ε₃₂``: the area a shift of the boundary by the
    float32 resolution of a unit vector sweeps. Values ≤ 1 mean "equal to float precision"."""
    return np.abs(geometry.solid_angle - expected) / (geometry.perimeter * EPS32)


def containment_violations(index_of, count: int, geometry: BinGeometry, directions: np.ndarray,
                           lower_from: int | None = None) -> list[str]:
    """Directions that a map sends to an invalid bin or to a bin that does not contain them.

    Parameters:
      index_of: the map, ``mi.Vector3f → mi.UInt32``.
      count: the number of bins.
      geometry: :func:`bin_geometry` of all bins.
      directions: ``(n, 3)`` float32-representable inputs; rows without a direction (zero, NaN, Inf) must only
        land in a valid bin.
      lower_from: for the sphere bins, the first bin of the z < 0 hemisphere (``D²``): a direction with z < 0 must
        land at or above it, one with z ≥ 0 below it (a denormal z may land on either side: it can be flushed).
    """
    directions = np.asarray(directions, dtype=np.float32).reshape(-1, 3)
    k = np.array(index_of(vectors(directions)), dtype=np.int64)
    problems = []
    invalid = (k < 0) | (k >= count)
    problems += [f"{tuple(d)} -> bin {b} (of {count})" for d, b in zip(directions[invalid], k[invalid])]
    if lower_from is not None:
        wrong_side = ~invalid & ((directions[:, 2] < 0) != (k >= lower_from)) & (np.abs(directions[:, 2]) >= TINY32)
        problems += [f"{tuple(d)} -> bin {b} on the other hemisphere" for d, b in
                     zip(directions[wrong_side], k[wrong_side])]
    kept, flushed = readings(directions)
    has_direction = np.isfinite(kept).all(axis=1) & np.isfinite(flushed).all(axis=1) & ~invalid
    kk = k[has_direction]
    angle = smallest_angle((kept[has_direction], flushed[has_direction]), geometry.centre[kk])
    reach = geometry.reach(kk)
    outside = angle > reach
    problems += [f"{tuple(x)} -> bin {b}: {a:.3g} rad from its centre, bin radius {r:.3g}" for x, b, a, r in
                 zip(directions[has_direction][outside], kk[outside], angle[outside], reach[outside])]
    return problems


def special_directions() -> np.ndarray:
    """Poles, both seams of the maps, the hemisphere boundary and its neighbours, in float32.

    The concentric map's pieces meet on the square's diagonals (azimuths π/4 + k·π/2) and axes; the cylindrical
    map's seam is azimuth 0 (y = ±0 with x > 0); the hemispheres meet at z = 0 (both signed zeros)."""
    rows = [(0, 0, 1), (0, 0, -1)]
    tiny = [0.0, -0.0, 1e-7, -1e-7, 1e-30, -1e-30, 1e-40, -1e-40, 1e-45, -1e-45]
    elevations = [*tiny, 0.5, -0.5, 0.999, -0.999, 1 - 1e-7, -(1 - 1e-7)]
    for azimuth in np.arange(16) * np.pi / 8:
        for z in elevations:
            r = np.sqrt(max(0.0, 1 - z * z))
            rows.append((r * np.cos(azimuth), r * np.sin(azimuth), z))
    for x in (1.0, -1.0):         # the cylindrical seam and its mirror, approached from both sides
        for y in (0.0, -0.0, 1e-7, -1e-7, 1e-30, -1e-30, 1e-45, -1e-45):
            for z in (0.0, -0.0, 0.5, -0.5):
                rows.append((x, y, z))
    return np.array(rows, dtype=np.float32)


def degenerate_inputs() -> np.ndarray:
    """Vectors without a direction (zero, NaN, ±Inf in any component) and extreme but valid ones."""
    nan, inf = float("nan"), float("inf")
    rows = [(0, 0, 0), (-0.0, -0.0, -0.0)]
    for bad in (nan, inf, -inf):
        rows += [(bad, 0, 0), (0, bad, 0), (0, 0, bad), (bad, bad, bad), (bad, 1, -1)]
    rows += [(1e-45, 0, 0), (0, -1e-45, 0), (1e-40, 1e-40, -1e-40), (3e38, 3e38, 3e38), (-3e38, 1, 1e-30)]
    return np.array(rows, dtype=np.float32)


#: Scales applied to unit directions: tiny (|d|² underflows float32 below about 1e-19), huge (|d|² overflows
#: above about 1.8e19) and near the ends of the float32 range. (Denormal vectors have no direction: TINY32.)
SCALES = (1e-30, 1e-20, 1e-5, 1e5, 1e20, 1e30, 1e38)


def scale_violations(index_of, directions: np.ndarray) -> list[str]:
    """Directions whose bin changes when the vector is scaled by one of :data:`SCALES` (unnormalised input).
    Use directions away from bin boundaries (bin centres), where a scaled copy cannot round across one."""
    directions = np.asarray(directions, dtype=np.float32)
    reference = np.array(index_of(vectors(directions)))
    problems = []
    for scale in SCALES:
        scaled = (directions.astype(np.float64) * scale).astype(np.float32)
        k = np.array(index_of(vectors(scaled)))
        problems += [f"{tuple(d)} x {scale:g}: bin {b} instead of {r}" for d, b, r in
                     zip(directions[k != reference], k[k != reference], reference[k != reference])]
    return problems


def interior_samples(margin: float = 1e-3) -> np.ndarray:
    """Nine positions inside a bin's square, ``margin`` away from its boundary (a round trip must keep them)."""
    t = np.array([margin, 0.5, 1 - margin])
    return np.stack(np.meshgrid(t, t), -1).reshape(-1, 2)


def round_trip_violations(index_of, direction_of, count: int) -> list[str]:
    """Bins ``k`` with ``index_of(direction_of(k, s)) != k`` for a sample ``s`` inside the bin."""
    samples = interior_samples()
    k = np.repeat(np.arange(count), len(samples)).astype(np.uint32)
    s = np.tile(samples, (count, 1))
    back = np.array(index_of(direction_of(mi.UInt32(k), mi.Point2f(s[:, 0], s[:, 1]))))
    wrong = back != k
    return [f"bin {a} at {tuple(p)} -> bin {b}" for a, p, b in zip(k[wrong], s[wrong], back[wrong])]


@functools.lru_cache(maxsize=None)
def sphere_bins_geometry(resolution: int) -> tuple:
    """(:class:`~guiding.guides.directions.SphereBins`, its :class:`BinGeometry`) for ``D = resolution`` (cached)."""
    bins = SphereBins(resolution)
    return bins, bin_geometry(bins.direction, np.arange(bins.count))


@functools.lru_cache(maxsize=None)
def normal_bins_geometry(resolution: int) -> tuple:
    """(:class:`~guiding.guides.directions.NormalBins`, its :class:`BinGeometry`) for ``R = resolution`` (cached)."""
    bins = NormalBins(resolution)
    return bins, bin_geometry(bins.normal, np.arange(bins.count))

