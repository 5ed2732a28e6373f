"""Stress cases: numerical stability and bad input (the grid guide and the SD-tree).

A guided estimator divides by learned densities, so one zero, denormal or NaN in a table could poison a whole
sweep unnoticed. Each case here drives one part of the system with hostile input and checks that what comes out is
finite, valid and correctly weighted:

- ``directions``: the direction ↔ bin maps (the concentric hemisphere pair of :mod:`guiding.directions`, its cube
  map of normals, and the SD-tree's cylindrical map) at poles, seams and the hemisphere boundary, with degenerate
  and unnormalised input, and the solid angle of every bin;
- ``tables``: table updates of both guides with all-zero, huge, denormal, NaN and infinite accumulators;
- ``samplers``: densities and weights at extreme samples and at the worst acceptance rate a table can produce;
- ``targets``: learning targets from extreme radiance, zero or tiny densities, and paths ending at every depth;
- ``scenes``: whole renders of hostile scenes built with ``mi.load_dict``;
- ``memory``, ``drift``, ``determinism`` and ``bad-input``: the refusal of oversized tables, float32 accumulation
  drift, run-to-run differences, and the command line's answers to bad input.

A case is a function registered with :func:`case`: it raises :class:`StressFailure` when a check fails and returns
the figures it measured. ``tests/test_stress_*.py`` run the cases under pytest and ``python -m guiding stress``
runs them all and writes ``results/stress.md`` (:func:`run_cases`, :func:`write_report`), so no check is written
twice. A Mitsuba variant must be set before a case runs.
"""

from __future__ import annotations

import contextlib
import functools
import io
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .cli import EXIT_BAD_INPUT, EXIT_INTERRUPTED
from .metrics import nonfinite_pixels

#: float32 machine epsilon: the relative resolution every float32 table and direction has.
EPS32 = float(np.finfo(np.float32).eps)
#: Smallest normal float32. Dr.Jit's CPU backend flushes denormals to zero (FTZ/DAZ) in kernels that run on its
#: worker threads, but not in small ones run on the calling thread: a denormal input is zero or not depending on
#: the array's size, so the checks accept either reading of a denormal component: zero, or its value.
TINY32 = float(np.finfo(np.float32).tiny)

GROUPS = ("directions", "tables", "samplers", "targets", "scenes", "memory", "drift", "determinism", "bad-input")


# =====================================================================================================================
#  Registry
# =====================================================================================================================
class StressFailure(AssertionError):
    """A stress check failed; the message says what was measured and what was expected."""


def check(condition, message: str) -> None:
    """Raise :class:`StressFailure` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise StressFailure(message)


@dataclass(frozen=True)
class Case:
    """One stress case.

    Parameters:
      name: the case's name (the function name with dashes).
      group: one of :data:`GROUPS`.
      checks: one line saying what the case checks (the report's description).
      run: the function; returns the measured figures, raises :class:`StressFailure` on a failed check.
      also_tested: tests elsewhere that check related input (not repeated here), named in the report.
    """

    name: str
    group: str
    checks: str
    run: Callable[[], dict]
    also_tested: str | None = None


#: Every case, in registration order (the report's order).
CASES: dict[str, Case] = {}


def case(group: str, checks: str, also_tested: str | None = None):
    """Register the decorated function as a case of ``group`` (see :class:`Case` for the parameters)."""
    if group not in GROUPS:
        raise ValueError(f"unknown stress group '{group}'")

    def register(function: Callable[[], dict]) -> Callable[[], dict]:
        name = function.__name__.replace("_", "-")
        CASES[name] = Case(name, group, checks, function, also_tested)
        return function

    return register


@dataclass
class Outcome:
    """What running a case gave: ``status`` is ``pass``, ``FAIL`` (a check failed) or ``ERROR`` (an exception)."""

    case: Case
    status: str
    seconds: float
    figures: dict = field(default_factory=dict)
    message: str = ""


def run_case(name: str) -> Outcome:
    """Run case ``name`` and catch what it raises."""
    stress_case = CASES[name]
    start = time.perf_counter()
    try:
        figures = stress_case.run() or {}
        status, message = "pass", ""
    except StressFailure as failure:
        figures, status, message = {}, "FAIL", str(failure)
    except Exception as error:  # a crash is an outcome too: the report must still list the case
        figures, status = {}, "ERROR"
        message = f"{type(error).__name__}: {error} ({traceback.extract_tb(error.__traceback__)[-1].name})"
    return Outcome(stress_case, status, time.perf_counter() - start, figures, message)


def run_cases(names: list[str] | None = None, progress: Callable[[Outcome], None] | None = None) -> list[Outcome]:
    """Run the named cases in the order given (by default all, in registration order); ``progress`` sees each
    outcome as it comes."""
    outcomes = []
    for name in names or list(CASES):
        outcome = run_case(name)
        if progress is not None:
            progress(outcome)
        outcomes.append(outcome)
    return outcomes


# =====================================================================================================================
#  Directions: geometry helpers (float64 references computed from the maps' float32 output)
# =====================================================================================================================
def _vectors(array: np.ndarray):
    """An ``(n, 3)`` NumPy array as a ``mi.Vector3f`` (a memory array, so no value is baked into a kernel)."""
    import mitsuba as mi

    array = np.asarray(array, dtype=np.float32).reshape(-1, 3)
    return mi.Vector3f(*(np.ascontiguousarray(array[:, i]) for i in range(3)))


def to_numpy(vector) -> np.ndarray:
    """A Dr.Jit 3-vector (or 2-point) as an ``(n, 3)`` (or ``(n, 2)``) float64 array."""
    return np.array(vector, dtype=np.float64).T.reshape(-1, len(vector))


def unit(d: np.ndarray, flush: bool = False) -> np.ndarray:
    """Reference normalisation in float64 (scaled by the largest component first; with ``flush``, denormal
    components are zero, see :data:`TINY32`); rows without a direction (zero or non-finite) are NaN."""
    d = np.asarray(d, dtype=np.float64).reshape(-1, 3)
    if flush:
        d = np.where(np.abs(d) < TINY32, 0.0, d)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        largest = np.max(np.abs(d), axis=1, keepdims=True)
        scaled = d / largest
        out = scaled / np.linalg.norm(scaled, axis=1, keepdims=True)
    out[~np.isfinite(out).all(axis=1)] = np.nan
    return out


def readings(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two unit vectors a float32 input may stand for: denormal components kept, and flushed to zero. An input
    whose flushed reading has no direction (only denormal components) may land in any valid bin."""
    return unit(directions), unit(directions, flush=True)


def smallest_angle(candidates: tuple[np.ndarray, ...], target: np.ndarray) -> np.ndarray:
    """Per row, the smallest angle between ``target`` and the candidates that have a direction (NaN if none)."""
    angles = np.stack([angle_between(c, target) for c in candidates])
    return np.where(np.isnan(angles).all(axis=0), np.nan, np.nanmin(np.where(np.isnan(angles), np.inf, angles),
                                                                          axis=0))


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit rows (float64, accurate for small angles)."""
    return 2 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=1) / 2, 0, 1))


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
    import mitsuba as mi

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
    k = np.array(index_of(_vectors(directions)), dtype=np.int64)
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
    reference = np.array(index_of(_vectors(directions)))
    problems = []
    for scale in SCALES:
        scaled = (directions.astype(np.float64) * scale).astype(np.float32)
        k = np.array(index_of(_vectors(scaled)))
        problems += [f"{tuple(d)} x {scale:g}: bin {b} instead of {r}" for d, b, r in
                     zip(directions[k != reference], k[k != reference], reference[k != reference])]
    return problems


def interior_samples(margin: float = 1e-3) -> np.ndarray:
    """Nine positions inside a bin's square, ``margin`` away from its boundary (a round trip must keep them)."""
    t = np.array([margin, 0.5, 1 - margin])
    return np.stack(np.meshgrid(t, t), -1).reshape(-1, 2)


def round_trip_violations(index_of, direction_of, count: int) -> list[str]:
    """Bins ``k`` with ``index_of(direction_of(k, s)) != k`` for a sample ``s`` inside the bin."""
    import mitsuba as mi

    samples = interior_samples()
    k = np.repeat(np.arange(count), len(samples)).astype(np.uint32)
    s = np.tile(samples, (count, 1))
    back = np.array(index_of(direction_of(mi.UInt32(k), mi.Point2f(s[:, 0], s[:, 1]))))
    wrong = back != k
    return [f"bin {a} at {tuple(p)} -> bin {b}" for a, p, b in zip(k[wrong], s[wrong], back[wrong])]


@functools.lru_cache(maxsize=None)
def sphere_bins_geometry(resolution: int) -> tuple:
    """(:class:`~guiding.directions.SphereBins`, its :class:`BinGeometry`) for ``D = resolution`` (cached)."""
    from .directions import SphereBins

    bins = SphereBins(resolution)
    return bins, bin_geometry(bins.direction, np.arange(bins.count))


@functools.lru_cache(maxsize=None)
def normal_bins_geometry(resolution: int) -> tuple:
    """(:class:`~guiding.directions.NormalBins`, its :class:`BinGeometry`) for ``R = resolution`` (cached)."""
    from .directions import NormalBins

    bins = NormalBins(resolution)
    return bins, bin_geometry(bins.normal, np.arange(bins.count))


class CylindricalCells:
    """The SD-tree's directional square cut into ``2^depth × 2^depth`` cells: every D-tree leaf at that depth is
    one of them. ``cells`` (an ``(n, 2)`` array of (column, row)) selects which; all by default."""

    def __init__(self, depth: int, cells: np.ndarray | None = None):
        self.n = 1 << depth
        if cells is None:
            column, row = np.meshgrid(np.arange(self.n), np.arange(self.n))
            cells = np.stack([column.ravel(), row.ravel()], 1)
        self.cells = np.asarray(cells, dtype=np.int64)
        self.count = len(self.cells)
        self.solid_angle = 4 * np.pi / (self.n * self.n)

    def uv(self, k, sample):
        """The point at ``sample`` ∈ [0,1]² of cell ``k`` (float64 positions rounded once to float32)."""
        import mitsuba as mi

        k = np.array(k, dtype=np.int64)
        s = np.broadcast_to(to_numpy(sample), (len(k), 2))
        return mi.Point2f((self.cells[k, 0] + s[:, 0]) / self.n, (self.cells[k, 1] + s[:, 1]) / self.n)

    def direction(self, k, sample):
        from .guides.sdtree import uv_to_dir

        return uv_to_dir(self.uv(k, sample))

    def index(self, d) -> np.ndarray:
        """The position in ``cells`` of the cell of ``d`` (by :func:`~guiding.guides.sdtree.dir_to_uv`), or
        ``count`` when that cell is not among them."""
        from .guides.sdtree import dir_to_uv

        uv = to_numpy(dir_to_uv(d))
        key = np.floor(uv[:, 1] * self.n).astype(np.int64) * self.n + np.floor(uv[:, 0] * self.n).astype(np.int64)
        keys = self.cells[:, 1] * self.n + self.cells[:, 0]
        order = np.argsort(keys)
        position = np.clip(np.searchsorted(keys[order], key), 0, self.count - 1)
        found = keys[order][position] == key
        return np.where(found, order[position], self.count)


def _first(problems: list[str], limit: int = 3) -> str:
    """The first few problems and how many there were, for a one-line failure message."""
    more = f" (and {len(problems) - limit} more)" if len(problems) > limit else ""
    return "; ".join(problems[:limit]) + more


# =====================================================================================================================
#  Directions
# =====================================================================================================================
#: Directional resolutions D checked: 1 and 2 (one and four bins per hemisphere), odd ones (a bin centred on the
#: pole), the paper's 16, and 64.
SPHERE_RESOLUTIONS = (1, 2, 3, 4, 5, 16, 64)
#: Odd cube-map resolutions of the memo tables' normal bins (5 is the default).
NORMAL_RESOLUTIONS = (1, 3, 5, 7)
#: D-tree depths whose every leaf is checked, and deeper ones (to the default maximum 20) checked on random leaves.
CYLINDRICAL_DEPTHS = (1, 2, 3, 4, 6, 8)
CYLINDRICAL_DEEP = (12, 16, 20)


def cylindrical_cells(depth: int, count: int = 4096, seed: int = 0) -> CylindricalCells:
    """All cells at ``depth`` up to depth 8, else ``count`` random ones plus the cells at the poles and seams."""
    if depth <= 8:
        return CylindricalCells(depth)
    n = 1 << depth
    rng = np.random.default_rng(seed + depth)
    edges = [0, 1, n // 2 - 1, n // 2, n - 2, n - 1]
    special = np.array([(c, r) for c in edges for r in edges])
    return CylindricalCells(depth, np.unique(np.concatenate([special, rng.integers(0, n, size=(count, 2))]), axis=0))


@case("directions", "SphereBins: every bin's interior maps back to the bin (D = 1, 2, 3, 4, 5, 16, 64)")
def sphere_bins_round_trip() -> dict:
    for resolution in SPHERE_RESOLUTIONS:
        bins, _ = sphere_bins_geometry(resolution)
        problems = round_trip_violations(bins.index, bins.direction, bins.count)
        check(not problems, f"D = {resolution}: {_first(problems)}")
    return {"resolutions": list(SPHERE_RESOLUTIONS), "points_per_bin": len(interior_samples())}


@case("directions", "SphereBins: poles, the concentric map's seams and the hemisphere boundary (z = ±0, ±1e-45, "
                    "…) land in a valid bin that contains them, on the right hemisphere")
def sphere_bins_poles_seams_boundary() -> dict:
    directions = special_directions()
    for resolution in SPHERE_RESOLUTIONS:
        bins, geometry = sphere_bins_geometry(resolution)
        problems = containment_violations(bins.index, bins.count, geometry, directions, lower_from=bins.count // 2)
        check(not problems, f"D = {resolution}: {_first(problems)}")
    return {"directions": len(directions)}


@case("directions", "SphereBins: zero, NaN, Inf and extreme vectors give a valid bin; scaling a direction by "
                    "1e-30 … 1e38 (unnormalised, |d|² under- or overflowing) keeps its bin")
def sphere_bins_any_input() -> dict:
    for resolution in SPHERE_RESOLUTIONS:
        bins, geometry = sphere_bins_geometry(resolution)
        problems = containment_violations(bins.index, bins.count, geometry, degenerate_inputs(),
                                          lower_from=bins.count // 2)
        problems += scale_violations(bins.index, geometry.centre)
        check(not problems, f"D = {resolution}: {_first(problems)}")
    return {"inputs": len(degenerate_inputs()), "scales": list(SCALES)}


@case("directions", "SphereBins: every bin has solid angle 2π/D² to float precision (|error| ≤ perimeter·ε₃₂)")
def sphere_bins_equal_solid_angle() -> dict:
    figures = {}
    for resolution in SPHERE_RESOLUTIONS:
        bins, geometry = sphere_bins_geometry(resolution)
        excess = equal_area_excess(geometry, bins.solid_angle)
        worst = int(np.argmax(excess))
        relative = np.abs(geometry.solid_angle / bins.solid_angle - 1)
        check(excess[worst] <= 1, f"D = {resolution}: bin {worst} has solid angle {geometry.solid_angle[worst]:.9g}"
                                  f" instead of {bins.solid_angle:.9g} ({excess[worst]:.2f} x perimeter·ε₃₂)")
        figures[f"D{resolution}_max_relative_error"] = float(relative.max())
    return figures


@case("directions", "NormalBins: interiors map back to their bin, the six axes are bin centres, zero/NaN/Inf "
                    "normals give a valid bin, scaled normals keep theirs (R = 1, 3, 5, 7)")
def normal_bins_maps() -> dict:
    import mitsuba as mi

    axes = np.array([(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)], dtype=np.float32)
    for resolution in NORMAL_RESOLUTIONS:
        bins, geometry = normal_bins_geometry(resolution)
        problems = round_trip_violations(bins.index, bins.normal, bins.count)
        problems += containment_violations(bins.index, bins.count, geometry,
                                           np.concatenate([special_directions(), degenerate_inputs()]))
        problems += scale_violations(bins.index, geometry.centre)
        # The memo tables are exact only at bin centres: an axis normal must be the centre of its bin.
        k = np.array(bins.index(_vectors(axes)))
        centres = to_numpy(bins.normal(mi.UInt32(k.astype(np.uint32))))
        off = angle_between(unit(axes), unit(centres)) > 2 * EPS32
        problems += [f"axis {tuple(a)} is not the centre of bin {b}" for a, b in zip(axes[off], k[off])]
        check(not problems, f"R = {resolution}: {_first(problems)}")
    return {"resolutions": list(NORMAL_RESOLUTIONS)}


#: Largest angle between a direction and its round trip through the cylindrical square: at a pole, a z error of
#: 2 ulps (u = (z + 1)/2 is rounded, then 2u − 1) moves the direction by √(2·Δz) = √(4·ε₃₂) ≈ 7e-4 rad.
CYLINDRICAL_ROUND_TRIP = float(np.sqrt(4 * EPS32)) * 1.5


def cylindrical_violations(directions: np.ndarray) -> list[str]:
    """Directions whose point on the SD-tree's square is outside [0, 1)² or NaN, or, for directions that have
    one, whose round trip through the square moves them more than :data:`CYLINDRICAL_ROUND_TRIP`."""
    from .guides.sdtree import dir_to_uv, uv_to_dir

    directions = np.asarray(directions, dtype=np.float32).reshape(-1, 3)
    uv = dir_to_uv(_vectors(directions))
    square = to_numpy(uv)
    outside = ~((square >= 0) & (square < 1)).all(axis=1)
    problems = [f"{tuple(d)} -> uv {tuple(p)}" for d, p in zip(directions[outside], square[outside])]
    kept, flushed = readings(directions)
    has_direction = np.isfinite(kept).all(axis=1) & np.isfinite(flushed).all(axis=1) & ~outside
    back = unit(to_numpy(uv_to_dir(uv)))[has_direction]
    angle = smallest_angle((kept[has_direction], flushed[has_direction]), back)
    moved = angle > CYLINDRICAL_ROUND_TRIP
    problems += [f"{tuple(x)} comes back {a:.3g} rad away" for x, a in zip(directions[has_direction][moved],
                                                                            angle[moved])]
    return problems


@case("directions", "SD-tree cylindrical map: poles, the azimuth seam, the equator, zero/NaN/Inf and scaled "
                    "directions give a point of [0,1)² and come back; every leaf centre down to depth 20 maps back "
                    "to its leaf")
def cylindrical_map_round_trip() -> dict:
    import mitsuba as mi

    problems = cylindrical_violations(np.concatenate([special_directions(), degenerate_inputs()]))
    centres = unit(special_directions())
    for scale in SCALES:
        problems += cylindrical_violations((centres * scale).astype(np.float32))
    # The square's own corners and edges, as float32 points (1 − 2⁻²⁴ is the largest coordinate below 1).
    edge = np.array([0, 2.0 ** -24, 0.5, ONE_MINUS_EPS32], dtype=np.float32)
    corners = np.stack(np.meshgrid(edge, edge), -1).reshape(-1, 2)
    from .guides.sdtree import uv_to_dir

    problems += cylindrical_violations(to_numpy(uv_to_dir(mi.Point2f(corners[:, 0], corners[:, 1]))))
    checked = 0
    for depth in (*CYLINDRICAL_DEPTHS, *CYLINDRICAL_DEEP):
        cells = cylindrical_cells(depth)
        back = cells.index(cells.direction(np.arange(cells.count), mi.Point2f(0.5, 0.5)))
        wrong = np.flatnonzero(back != np.arange(cells.count))
        problems += [f"depth {depth}: leaf {tuple(cells.cells[i])} -> {back[i]}" for i in wrong]
        checked += cells.count
    check(not problems, _first(problems))
    return {"leaves_checked": checked, "max_depth": max(CYLINDRICAL_DEEP)}


@case("directions", "SD-tree cylindrical map: every leaf has solid angle 4π/4^depth to float precision (all "
                    "leaves to depth 8, random ones at 12, 16, 20)")
def cylindrical_map_equal_solid_angle() -> dict:
    figures = {}
    for depth in (*CYLINDRICAL_DEPTHS, *CYLINDRICAL_DEEP):
        cells = cylindrical_cells(depth)
        # Large leaves have long curved edges: more boundary points keep the chords' error below float precision.
        geometry = bin_geometry(cells.direction, np.arange(cells.count), steps=max(16, 256 >> depth))
        excess = equal_area_excess(geometry, cells.solid_angle)
        worst = int(np.argmax(excess))
        check(excess[worst] <= 1, f"depth {depth}: leaf {tuple(cells.cells[worst])} has solid angle "
                                  f"{geometry.solid_angle[worst]:.9g} instead of {cells.solid_angle:.9g} "
                                  f"({excess[worst]:.2f} x perimeter·ε₃₂)")
        figures[f"depth{depth}_max_relative_error"] = float(np.abs(geometry.solid_angle / cells.solid_angle - 1).max())
    return figures


# =====================================================================================================================
#  Tables: updates from hostile accumulators
# =====================================================================================================================
#: Contents injected into one accumulator entry (``sum`` or ``count``), and what the update must make of it:
#: ``dropped`` entries lose their history (counted), ``clamped`` ones keep it with Q clamped to Q_LIMIT (counted).
HOSTILE_ENTRIES = {
    "all-zero": dict(),
    "1e30": dict(sum=1e30),
    "1e39 (beyond float32)": dict(sum=1e39, clamped=True),
    "float32 denormal": dict(sum=1e-40),
    "float64 denormal": dict(sum=1e-310),
    "NaN": dict(sum=float("nan"), dropped=True),
    "+Inf": dict(sum=float("inf"), dropped=True),
    "-Inf": dict(sum=float("-inf"), dropped=True),
    "negative": dict(sum=-5.0, dropped=True),
    "NaN count": dict(count=float("nan"), dropped=True),
    "Inf count": dict(count=float("inf"), dropped=True),
}

#: The grid guides whose tables cover every array an update builds: the sphere CDF (sphere_inv, and the policy
#: proposal of hemi_rej_plus), the per-pair N, M and hemi_inv CDF, and Expected SARSA's V.
TABLE_METHODS = ("expected_sarsa-sphere_inv", "expected_sarsa-hemi_inv", "expected_sarsa-hemi_rej_plus",
                 "sarsa-hemi_rej")


def _grid_guide(method: str, S: int = 2, D: int = 4, min_exploration: float | None = None):
    """A grid guide of ``method`` at resolution S, D over the unit cube (its bounds set, nothing learnt)."""
    import mitsuba as mi

    from .guides.grid import GridGuide
    from .methods import grid_parameters

    overrides = {"spatial_resolution": S, "directional_resolution": D}
    if min_exploration is not None:
        overrides["min_exploration"] = min_exploration
    guide = GridGuide(grid_parameters(method), **overrides)
    guide.record_table.set_bounds(mi.BoundingBox3f(mi.ScalarPoint3f(0), mi.ScalarPoint3f(1)))
    return guide


def _fill_record(record, sums: np.ndarray, counts: np.ndarray) -> None:
    """Give a record accumulators (float64, as the device holds them) and mark every (cell, normal bin) visited."""
    import drjit as dr
    import mitsuba as mi

    record.acc_sum, record.acc_count = mi.Float64(sums), mi.Float64(counts)
    if record.needs_pairs:
        record.visited = dr.full(mi.UInt32, 1, record.cells * record.normal_bins.count)


def _record_arrays(record) -> dict:
    """Every table an update builds, as NumPy arrays."""
    names = ["q", "policy", "cdf", "norm", "bound", "value", "hemi_cdf"]
    return {name: np.array(getattr(record, name, None)) for name in names if getattr(record, name, None) is not None}


def record_violations(record) -> list[str]:
    """What is wrong with a record's tables after an update: anything non-finite, a policy entry that is not a
    positive normal float or a cell whose policy does not sum to 1, a CDF that decreases or does not end at exactly
    1, a memo with N ≤ 0 or a bound M below the mean ū = N/2π of P·cos, or Q outside [0, Q_LIMIT]."""
    from .guides.grid_record import Q_LIMIT

    B = record.bins.count
    tables = _record_arrays(record)
    problems = [f"{name} has {np.count_nonzero(~np.isfinite(a))} non-finite entries" for name, a in tables.items()
                if not np.isfinite(a).all()]
    q, policy = tables["q"], tables["policy"].reshape(-1, B)
    if not ((q >= 0) & (q <= Q_LIMIT)).all():
        problems.append(f"Q outside [0, {Q_LIMIT:g}]: {q[(q < 0) | (q > Q_LIMIT)][:3]}")
    if not (policy >= TINY32).all():
        problems.append(f"policy entries below the smallest normal float: {policy[policy < TINY32][:3]}")
    sums = policy.astype(np.float64).sum(axis=1)
    if not (np.abs(sums - 1) <= B * EPS32).all():
        problems.append(f"cell policies sum to {sums[np.abs(sums - 1) > B * EPS32][:3]}")
    rows = [("cdf", tables.get("cdf"))]
    if record.needs_pairs and record.hemi_cdf is not None:
        rows.append(("hemi_cdf", tables["hemi_cdf"].reshape(-1, B)[np.array(record.visited) != 0]))
    for name, cdf in rows:
        if cdf is None:
            continue
        cdf = cdf.reshape(-1, B)
        if not (np.diff(cdf, axis=1) >= 0).all():
            problems.append(f"{name} decreases in {np.count_nonzero((np.diff(cdf, axis=1) < 0).any(axis=1))} rows")
        if not (cdf[:, -1] == 1).all():
            problems.append(f"{name} rows end at {cdf[cdf[:, -1] != 1, -1][:3]} instead of 1")
    if record.needs_pairs:
        visited = np.array(record.visited) != 0
        norm, bound, value = tables["norm"][visited], tables["bound"][visited], tables["value"][visited]
        if not (norm >= TINY32).all():
            problems.append(f"N not a positive normal float: {norm[norm < TINY32][:3]}")
        if not (bound >= norm / (2 * np.pi) * (1 - 1e-5)).all():
            problems.append("bound M below the mean of P·cos")
        if not (value >= 0).all():
            problems.append(f"V negative: {value[value < 0][:3]}")
    return problems


def _hostile_grid(method: str, kind: str, min_exploration: float | None) -> tuple:
    """Two guides of ``method``: one whose accumulators hold ``HOSTILE_ENTRIES[kind]`` in one entry of cell 0,
    and one holding what the update should turn that entry into (zeros if dropped, Q_LIMIT if clamped)."""
    from .guides.grid_record import Q_LIMIT

    spec = HOSTILE_ENTRIES[kind]
    hostile, expected = (_grid_guide(method, min_exploration=min_exploration) for _ in range(2))
    record = hostile.record_table
    size, entry = record.cells * record.bins.count, 3
    rng = np.random.default_rng(len(kind))
    if spec:
        sums, counts = rng.uniform(0, 2, size) * 4, np.full(size, 4.0)
    else:
        sums, counts = np.zeros(size), np.zeros(size)
    bad_sums, bad_counts = sums.copy(), counts.copy()
    bad_sums[entry] = spec.get("sum", sums[entry])
    bad_counts[entry] = spec.get("count", counts[entry])
    if spec.get("dropped"):
        sums[entry] = counts[entry] = 0.0
    elif spec.get("clamped"):
        sums[entry], counts[entry] = Q_LIMIT, 1.0
    else:
        sums, counts = bad_sums, bad_counts
    _fill_record(record, bad_sums, bad_counts)
    _fill_record(expected.record_table, sums, counts)
    return hostile, expected


@case("tables", "grid record: an update from all-zero, 1e30, 1e39, denormal, NaN, ±Inf or negative accumulators "
                "gives finite tables (policy > 0 summing to 1, CDFs ending at 1, N > 0, M ≥ ū), counts what it "
                "dropped or clamped, and equals the update of the sanitised table (nothing propagates)")
def grid_table_updates() -> dict:
    updates = 0
    for method in TABLE_METHODS:
        for min_exploration in (None, 0.0):      # the default floor, and the paper's schedule (ε → 1e-10)
            for kind, spec in HOSTILE_ENTRIES.items():
                hostile, expected = _hostile_grid(method, kind, min_exploration)
                where = f"{method}, min_exploration={min_exploration}, {kind}"
                for spp_done in (8, 1000):       # first update, and a late one with a small ε
                    stats = hostile.update(spp_done).stats
                    expected.update(spp_done)
                    problems = record_violations(hostile.record_table)
                    check(not problems, f"{where}, {spp_done} spp: {_first(problems)}")
                    want = {"dropped_entries": int(bool(spec.get("dropped"))) if spp_done == 8 else 0,
                            "clamped_entries": int(bool(spec.get("clamped")))}
                    got = {key: stats.get(key) for key in want}
                    check(got == want, f"{where}, {spp_done} spp: counted {got}, expected {want}")
                    for name, array in _record_arrays(hostile.record_table).items():
                        reference = _record_arrays(expected.record_table)[name]
                        differ = np.count_nonzero(array != reference)
                        check(differ == 0, f"{where}, {spp_done} spp: {name} differs from the sanitised table's "
                                           f"in {differ} entries")
                    updates += 1
    return {"methods": list(TABLE_METHODS), "kinds": list(HOSTILE_ENTRIES), "updates_checked": updates}


#: Largest relative error allowed in the memo tables' cosine integrals. A rejection sampler reports the density
#: P·cos/N, so N's relative error is its relative bias: 1e-3 keeps that an order of magnitude below the ~1 %
#: standard errors of the unbiasedness checks (results/grid_unbiasedness.md), which could not see it.
COSINE_INTEGRAL_TOLERANCE = 1e-3


@case("tables", "memo tables: for every normal bin and D = 1 … 64, the cosine integrals of all bins sum to "
                "∫_H cos dω = π within 1e-3 (N's relative error is the rejection samplers' relative bias)")
def memo_cosine_integrals() -> dict:
    from .guides.grid_record import RadianceRecord

    figures = {}
    for resolution in (1, 2, 3, 4, 8, 16, 32, 64):
        record = RadianceRecord(1, resolution, needs_memo=True)
        integrals = np.array(record.cos_integral, dtype=np.float64).reshape(record.normal_bins.count, -1)
        error = np.abs(integrals.sum(axis=1) / np.pi - 1)
        worst = int(np.argmax(error))
        check(error[worst] <= COSINE_INTEGRAL_TOLERANCE,
              f"D = {resolution}: the cosine integrals of normal bin {worst} sum to {integrals[worst].sum():.6g} "
              f"instead of π (relative error {error[worst]:.3g})")
        figures[f"D{resolution}_max_relative_error"] = float(error.max())
    return figures


@functools.lru_cache(maxsize=None)
def floor_scene():
    """A diffuse unit square at z = 0 (no sensor, no emitter): enough to prepare a guide on."""
    import mitsuba as mi

    return mi.load_dict({"type": "scene", "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"}}})


#: The SD-tree guides: Müller's SD-tree and Kim & Kim's uniform grid of split-only quadtrees.
TREE_METHODS = ("sdtree", "quadtree-grid")


def _tree_guide(method: str):
    from .methods import make_guide

    guide = make_guide(method)
    guide.prepare(floor_scene())
    return guide


def _recording_forest(guide):
    """The host forest whose leaves the guide's energy accumulator addresses."""
    return guide._recording_host if hasattr(guide, "_recording_host") else guide._forest


def forest_violations(forest) -> list[str]:
    """What is wrong with a device forest: probabilities non-finite or outside [0, 1], or a node whose four
    probabilities do not sum to 1."""
    prob = np.array(forest.prob, dtype=np.float64)[: 4 * forest.n_nodes].reshape(-1, 4)
    problems = []
    if not np.isfinite(prob).all():
        problems.append(f"{np.count_nonzero(~np.isfinite(prob))} non-finite probabilities")
    elif not ((prob >= 0) & (prob <= 1)).all():
        problems.append("probabilities outside [0, 1]")
    elif not (np.abs(prob.sum(axis=1) - 1) <= 4 * EPS32).all():
        problems.append(f"node probabilities sum to {prob.sum(axis=1)[np.abs(prob.sum(axis=1) - 1) > 4 * EPS32][:3]}")
    return problems


def _hostile_tree(method: str, kind: str) -> tuple:
    """Two prepared guides of ``method`` with recorded energies and counts: one holding ``HOSTILE_ENTRIES[kind]``
    in a leaf of tree 0 (as a float32 accumulator holds it: 1e39 is +Inf there), one holding it sanitised."""
    import mitsuba as mi

    spec = HOSTILE_ENTRIES[kind]
    hostile, expected = _tree_guide(method), _tree_guide(method)
    slots = _recording_forest(hostile).leaf_table()[1]
    energy = np.zeros(hostile._energy_acc.shape[0], dtype=np.float32)
    counts = np.zeros(hostile._count_acc.shape[0], dtype=np.float32)
    if spec:
        energy[slots] = np.random.default_rng(len(kind)).uniform(0.5, 2, len(slots))
        counts[: _recording_forest(hostile).n_trees] = 100
    bad_energy, bad_counts = energy.copy(), counts.copy()
    with np.errstate(over="ignore"):
        bad_energy[slots[5]] = np.float32(spec.get("sum", energy[slots[5]]))
        bad_counts[0] = np.float32(spec.get("count", counts[0]))
    clean_energy = np.where(np.isfinite(bad_energy) & (bad_energy >= 0), bad_energy, 0)
    clean_counts = np.where(np.isfinite(bad_counts) & (bad_counts >= 0), bad_counts, 0)
    hostile._energy_acc, hostile._count_acc = mi.Float(bad_energy), mi.Float(bad_counts)
    expected._energy_acc, expected._count_acc = mi.Float(clean_energy), mi.Float(clean_counts)
    dropped = int(np.count_nonzero(bad_energy != clean_energy) + np.count_nonzero(bad_counts != clean_counts))
    return hostile, expected, dropped


@case("tables", "SD-tree and quadtree grid: an update from all-zero, huge, denormal, NaN, ±Inf or negative "
                "energies and vertex counts gives finite D-tree probabilities (summing to 1 per node), counts what "
                "it dropped, keeps the S-tree bounded, and equals the update of the sanitised input")
def sdtree_table_updates() -> dict:
    checked = 0
    for method in TREE_METHODS:
        for kind in HOSTILE_ENTRIES:
            hostile, expected, dropped = _hostile_tree(method, kind)
            spp_done = getattr(hostile, "iteration_end_spp", 8)    # the SD-tree refines at an iteration's end
            stats, _ = hostile.update(spp_done).stats, expected.update(spp_done)
            where = f"{method}, {kind}"
            problems = forest_violations(hostile._sampling)
            check(not problems, f"{where}: {_first(problems)}")
            check(stats.get("dropped_entries") == dropped,
                  f"{where}: counted {stats.get('dropped_entries')} dropped entries, expected {dropped}")
            same = np.array_equal(np.array(hostile._sampling.prob), np.array(expected._sampling.prob))
            check(same, f"{where}: the D-trees differ from those of the sanitised input")
            if hasattr(hostile, "stree"):
                check(hostile.stree.n_nodes == expected.stree.n_nodes,
                      f"{where}: S-tree of {hostile.stree.n_nodes} nodes, {expected.stree.n_nodes} expected")
            if not HOSTILE_ENTRIES[kind]:
                check(not np.array(hostile._sampling.has_energy).any(), f"{where}: a tree without energy is guided")
            checked += 1
    return {"methods": list(TREE_METHODS), "kinds": list(HOSTILE_ENTRIES), "updates_checked": checked}


# =====================================================================================================================
#  Samplers
# =====================================================================================================================
class FixedSampler:
    """A stand-in for ``mi.Sampler`` that returns the same chosen values at every call: ``next_1d`` gives ``u``,
    ``next_2d`` gives ``uv`` (per lane). It drives samplers to the extremes of their inputs (0 and 1 − 2⁻²⁴); only
    for code without a symbolic loop over the sampler's state."""

    def __init__(self, u, uv):
        self.u, self.uv = u, uv

    def next_1d(self, active=True):
        return self.u

    def next_2d(self, active=True):
        return self.uv


#: The largest float32 below 1: the largest value a Mitsuba sampler returns.
ONE_MINUS_EPS32 = float(np.nextafter(np.float32(1), np.float32(0)))


def extreme_samples(size_per_value: int = 1) -> tuple:
    """All combinations of u, and both coordinates of uv, in {0, 0.5, 1 − 2⁻²⁴}: ``(u, uv)`` as NumPy arrays."""
    values = np.array([0.0, 0.5, ONE_MINUS_EPS32], dtype=np.float32)
    grid = np.stack(np.meshgrid(values, values, values), -1).reshape(-1, 3)
    grid = np.repeat(grid, size_per_value, axis=0)
    return grid[:, 0], grid[:, 1:]


def diffuse_vertex(normal, size: int, position=(0.05, 0.05, 0.05)):
    """A surface interaction on a diffuse surface with ``normal`` at ``position``, ``size`` lanes wide (the path
    arrives from the normal's side), and its BSDF."""
    import drjit as dr
    import mitsuba as mi

    si = dr.zeros(mi.SurfaceInteraction3f, size)
    si.p = mi.Point3f(*position)
    si.n = mi.Normal3f(*(float(c) for c in normal))
    si.sh_frame = mi.Frame3f(si.n)
    si.wi = mi.Vector3f(0, 0, 1)
    return si, mi.BSDFPtr(diffuse_bsdf())


@functools.lru_cache(maxsize=None)
def diffuse_bsdf():
    """A diffuse BSDF of albedo 0.5, kept alive here: a ``BSDFPtr`` does not own the object it points to."""
    import mitsuba as mi

    return mi.load_dict({"type": "diffuse", "reflectance": 0.5})


def spiked_guide(method: str, spike, normal, D: int = 16, min_exploration: float = 0.0):
    """A trained grid guide (cell 0 of S = 2) whose Q is Q_LIMIT in the bin of direction ``spike`` and 0 elsewhere,
    with the paper's exploration schedule after 10 000 spp (ε = 1e-100): the most peaked policy a table can hold.
    The (cell, normal bin) pair of ``normal`` is memoised."""
    import drjit as dr
    import mitsuba as mi

    from .guides.grid_record import Q_LIMIT

    guide = _grid_guide(method, S=2, D=D, min_exploration=min_exploration)
    record = guide.record_table
    size = record.cells * record.bins.count
    sums, counts = np.zeros(size), np.zeros(size)
    k = int(np.array(record.bins.index(_vectors(np.array([spike]))))[0])
    sums[k], counts[k] = Q_LIMIT, 1.0
    _fill_record(record, sums, counts)
    record.visited = dr.zeros(mi.UInt32, record.cells * record.normal_bins.count)
    dr.scatter(record.visited, mi.UInt32(1), record.pair(mi.UInt32(0), _vectors(np.array([normal]))))
    guide.update(spp_done=10_000)
    return guide


def sample_violations(si, bs, weight) -> list[str]:
    """Lanes whose direction leaves on the side the path arrived from (f·cos > 0 for a diffuse BSDF) with a
    density that is not positive and finite, and lanes whose weight is not finite."""
    pdf, w = np.array(bs.pdf), np.array(weight).reshape(3, -1)
    usable = to_numpy(bs.wo)[:, 2] * np.sign(np.array(si.wi.z)) > 0
    problems = [f"lane {i}: direction {tuple(to_numpy(bs.wo)[i])} with pdf {pdf[i]}"
                for i in np.flatnonzero(usable & ~(np.isfinite(pdf) & (pdf > 0)))]
    problems += [f"lane {i}: weight {w[:, i]}" for i in np.flatnonzero(~np.isfinite(w).all(axis=0))]
    return problems


#: Normals at which the samplers are driven: the axes (walls) and an oblique normal-bin centre, both sides.
def sampler_normals() -> np.ndarray:
    import mitsuba as mi

    from .directions import NormalBins

    oblique = to_numpy(NormalBins(5).normal(mi.UInt32([7])))[0]
    return np.array([(0, 0, 1), (0, 0, -1), (1, 0, 0), oblique, -oblique], dtype=np.float32)


@case("samplers", "grid samplers that invert CDFs without a loop (sphere_inv, hemi_inv) at "
                  "u, uv ∈ {0, 0.5, 1 − 2⁻²⁴} on the most peaked tables: every direction returned above the surface "
                  "has a positive, finite pdf, and every weight is finite")
def grid_samplers_extreme_samples() -> dict:
    import drjit as dr
    import mitsuba as mi

    u, uv = extreme_samples()
    lanes = 0
    for method in ("sarsa-sphere_inv", "sarsa-hemi_inv"):
        for normal in sampler_normals():
            # The spike in front of the surface, behind it, and at grazing incidence.
            for spike in (normal, -normal, np.cross(normal, (0.6, 0.8, 0.0)) + 1e-3 * normal):
                guide = spiked_guide(method, spike, normal)
                si, bsdf = diffuse_vertex(normal, len(u))
                active = dr.full(mi.Bool, True, len(u))
                bs, weight = guide.sample(None, FixedSampler(mi.Float(u), mi.Point2f(uv[:, 0], uv[:, 1])), si,
                                          bsdf, mi.BSDFContext(), active)
                problems = sample_violations(si, bs, weight)
                check(not problems, f"{method}, normal {tuple(normal)}, spike {tuple(spike)}: {_first(problems)}")
                lanes += len(u)
    return {"lanes_checked": lanes}


#: Rejection samplers at the worst acceptance rate a table gives them: (method, spike direction relative to the
#: normal). Uniform proposals are accepted with probability N/(2π·M′): lowest when all of P sits in one bin in front
#: of the surface (≈ 1/D² for hemi_rej). Policy proposals are accepted with the policy's mean cosine on the
#: arrival side: about 0 when all of P sits behind the surface.
WORST_ACCEPTANCE = (("sarsa-hemi_rej", "front"), ("ours-uniform-proposals", "front"), ("ours", "behind"),
                    ("ours", "grazing"))


def _worst_case_guide(method: str, where: str, normal: np.ndarray):
    spike = {"front": normal, "behind": -normal,
             "grazing": unit(np.cross(normal, (0.6, 0.8, 0.0)) + 0.05 * normal)[0]}[where]
    return spiked_guide(method, spike, normal)


def chi_square_guide(guide, normal, sample_count: int = 200_000, test_count: int = 1) -> tuple[bool, str]:
    """Mitsuba's chi-square test of ``guide``'s sampler at a diffuse vertex with ``normal``: do the directions it
    draws follow the density it reports? (It also fails a density that does not integrate to 1.)"""
    import drjit as dr
    import mitsuba as mi
    from mitsuba.chi2 import ChiSquareTest, SphericalDomain

    def sample_func(sample):
        size = dr.width(sample)
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(7, size)
        si, bsdf = diffuse_vertex(normal, size)
        bs, _ = guide.sample(None, sampler, si, bsdf, mi.BSDFContext(), dr.full(mi.Bool, True, size))
        return si.to_world(bs.wo)

    def pdf_func(wo):
        size = dr.width(wo)
        si, bsdf = diffuse_vertex(normal, size)
        return guide.pdf(si, bsdf, mi.BSDFContext(), si.to_local(wo), dr.full(mi.Bool, True, size))

    test = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func, sample_dim=2,
                         sample_count=sample_count, res=64, ires=32)
    with contextlib.redirect_stdout(io.StringIO()):    # the test prints its statistics; they are in `messages`
        passed = test.run(test_count=test_count)
    return passed, test.messages


@case("samplers", "rejection samplers at the worst acceptance rate a table can produce (all of P in one bin, "
                  "ε → 0): the loop stops after max_proposals, every weight is finite, every direction above the "
                  "surface has pdf > 0, and the fallback is correctly weighted (chi-square on the sampled density)")
def rejection_worst_acceptance() -> dict:
    import drjit as dr
    import mitsuba as mi

    normal = np.array([0.0, 0.0, 1.0], dtype=np.float32)
    figures = {}
    for method, where in WORST_ACCEPTANCE:
        guide = _worst_case_guide(method, where, normal)
        size = 100_000
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(1, size)
        si, bsdf = diffuse_vertex(normal, size)
        bs, weight = guide.sample(None, sampler, si, bsdf, mi.BSDFContext(), dr.full(mi.Bool, True, size))
        stats = guide.update(spp_done=10_000).stats        # reads (and resets) the sampler's counters
        label = f"{method}, spike {where}"
        problems = sample_violations(si, bs, weight)
        check(not problems, f"{label}: {_first(problems)}")
        check(stats["guided_samples"] == size, f"{label}: {stats['guided_samples']} of {size} samples guided")
        per_sample = stats["proposals_per_sample"] or 0.0
        check(per_sample <= guide.max_proposals,
              f"{label}: {per_sample:.1f} proposals per sample, cap {guide.max_proposals}")
        passed, messages = chi_square_guide(guide, normal, test_count=len(WORST_ACCEPTANCE))
        check(passed, f"{label}: chi-square test failed: {messages.strip().splitlines()[-1] if messages else ''}")
        figures[f"{method}/{where}"] = {"acceptance_rate": stats["acceptance_rate"],
                                        "proposals_per_sample": per_sample}
    return figures


@case("samplers", "SD-tree sampler on degenerate D-trees (all energy in one leaf at depth 20, denormal and 1e30 "
                  "energies) at samples in {0, 0.5, 1 − 2⁻²⁴}: every direction above the surface has pdf > 0, "
                  "every weight is finite")
def sdtree_sampler_extremes() -> dict:
    import drjit as dr
    import mitsuba as mi

    from .guides.sdtree import DeviceForest, Forest

    def chain(depth: int, energy: float, quadrant: int = 3):
        """A tree whose energy sits in one quadrant ``quadrant`` at every level down to ``depth``."""
        node: object = energy
        for _ in range(depth - 1):
            node = [0.0] * quadrant + [node] + [0.0] * (3 - quadrant)
        return [0.0] * quadrant + [node] + [0.0] * (3 - quadrant)

    trees = {"one leaf at depth 20": chain(20, 1.0), "one leaf at depth 20, corner 0": chain(20, 1.0, 0),
             "denormal energies": [1e-40, 1e-45, [1e-40] * 4, 0.0], "1e30 beside 1e-30": [1e30, 1e-30, 0.0, 1e-30]}
    u, uv = extreme_samples()
    lanes = 0
    for method in TREE_METHODS:
        guide = _tree_guide(method)
        for name, tree in trees.items():
            forest = Forest.from_nested([tree])
            if method == "quadtree-grid":       # every cell of the grid gets the same tree
                forest = forest.rebuild(np.zeros(guide.S ** 3, dtype=np.int64), "copy")
            guide._sampling = DeviceForest(forest)
            for normal in sampler_normals():
                si, bsdf = diffuse_vertex(normal, len(u), position=(0.3, 0.4, 0.0))
                bs, weight = guide.sample(None, FixedSampler(mi.Float(u), mi.Point2f(uv[:, 0], uv[:, 1])), si, bsdf,
                                          mi.BSDFContext(), dr.full(mi.Bool, True, len(u)))
                problems = sample_violations(si, bs, weight)
                check(not problems, f"{method}, {name}, normal {tuple(normal)}: {_first(problems)}")
                lanes += len(u)
    return {"lanes_checked": lanes}


# =====================================================================================================================
#  Learning targets
# =====================================================================================================================
#: Longest path of the synthetic batches (the renderer's default max_depth).
TARGET_DEPTH = 16
#: Emitted radiance at hostile vertices: none, ordinary, extreme and the largest float32.
HOSTILE_EMISSION = (0.0, 1.0, 1e30, 3e38)
#: Densities of the directions sampled at hostile vertices (the weight is 0.5/pdf): ordinary, tiny, and the
#: smallest normal float32 (weights 0.5, 5e29, 2.5e37). The last vertex of every path has pdf 0 and weight 0.
HOSTILE_PDF = (1.0, 1e-30, 2e-38)


@dataclass
class SyntheticPaths:
    """A batch of paths on :func:`floor_scene` fed to a guide's ``record`` vertex by vertex.

    ``length[l]`` vertices for lane ``l`` (every length 1 … TARGET_DEPTH occurs); at depth ``j`` all lanes leave
    in the direction of sphere bin ``j`` (D = 4: one bin per depth). ``emitted``, ``pdf`` and ``weight`` are
    ``(lanes, depth)`` arrays; a path's last vertex has pdf 0 and weight 0. ``position`` is the lanes' (x, y).
    """

    length: np.ndarray
    emitted: np.ndarray
    pdf: np.ndarray
    weight: np.ndarray
    position: tuple

    @classmethod
    def benign(cls, position=(-0.5, -0.5)) -> "SyntheticPaths":
        """Emission 1 and weight 0.5 everywhere: targets with closed forms."""
        length = np.arange(1, TARGET_DEPTH + 1)
        shape = (len(length), TARGET_DEPTH)
        return cls(length, np.ones(shape), np.ones(shape), np.full(shape, 0.5), position)._end_paths()

    @classmethod
    def hostile(cls, position=(0.5, 0.5)) -> "SyntheticPaths":
        """Every length four times, with every combination of HOSTILE_EMISSION and HOSTILE_PDF along the paths."""
        length = np.tile(np.arange(1, TARGET_DEPTH + 1), 4)
        lane, depth = np.meshgrid(np.arange(len(length)), np.arange(TARGET_DEPTH), indexing="ij")
        emitted = np.array(HOSTILE_EMISSION)[(lane + depth) % len(HOSTILE_EMISSION)]
        pdf = np.array(HOSTILE_PDF)[(lane // TARGET_DEPTH + 2 * depth) % len(HOSTILE_PDF)]
        weight = (np.float32(0.5) / pdf.astype(np.float32)).astype(np.float64)
        return cls(length, emitted, pdf, weight, position)._end_paths()

    def _end_paths(self) -> "SyntheticPaths":
        depth = np.arange(TARGET_DEPTH)[None, :]
        last = depth == self.length[:, None] - 1
        self.pdf, self.weight = np.where(last, 0.0, self.pdf), np.where(last, 0.0, self.weight)
        return self

    @property
    def lanes(self) -> int:
        return len(self.length)

    def continues(self, depth: int) -> np.ndarray:
        return depth < self.length - 1

    def records(self) -> int:
        """Targets a grid guide records: one per segment after the camera's, ``Σ (length − 1)``."""
        return int(np.sum(self.length - 1))

    def run(self, guide) -> None:
        """Feed the batch to ``guide`` (``new_paths``, ``record`` at every depth, ``finish_paths``)."""
        import drjit as dr
        import mitsuba as mi

        from .directions import SphereBins

        scene = floor_scene()
        origin = mi.Point3f(self.position[0], self.position[1], 1)
        si = scene.ray_intersect(mi.Ray3f(origin, mi.Vector3f(0, 0, -1)))
        si = dr.gather(type(si), si, dr.zeros(mi.UInt32, self.lanes))      # the same vertex in every lane
        directions = SphereBins(4).centres()
        state = guide.new_paths(self.lanes, TARGET_DEPTH)
        for depth in range(TARGET_DEPTH):
            bs = dr.zeros(mi.BSDFSample3f, self.lanes)
            bs.wo = si.to_local(dr.gather(mi.Vector3f, directions, mi.UInt32(depth)))
            bs.pdf = mi.Float(self.pdf[:, depth].astype(np.float32))
            with np.errstate(over="ignore"):
                emitted = mi.Color3f(mi.Float(self.emitted[:, depth].astype(np.float32)))
                weight = mi.Color3f(mi.Float(self.weight[:, depth].astype(np.float32)))
            active = mi.Bool(depth < self.length)
            state = guide.record(state, si, emitted, bs, weight, mi.Bool(self.continues(depth)), active)
        guide.finish_paths(state)

    def expected_grid_targets(self, rule: str) -> dict[int, tuple[float, int]]:
        """{depth i: (sum of targets, count)} recorded into the bin of depth i's direction by a guide with all-zero
        tables: MC records ``L_{i+1} = Σ_m Le_m Π w`` at every vertex that continues; SARSA and Expected SARSA
        (no memo yet) record ``Le_{i+1}`` for the segment i → i+1."""
        out = {}
        for i in range(TARGET_DEPTH - 1):
            lanes = np.flatnonzero(self.continues(i))
            if not len(lanes):
                continue
            if rule == "mc":
                radiance = np.zeros(len(lanes))
                for m in range(TARGET_DEPTH - 1, i, -1):
                    alive = m < self.length[lanes]
                    radiance = np.where(alive, self.emitted[lanes, m] + self.weight[lanes, m] * radiance, radiance)
                targets = radiance
            else:
                targets = self.emitted[lanes, i + 1]
            out[i] = (float(np.sum(targets)), len(lanes))
        return out


@case("targets", "learning targets of MC, SARSA and Expected SARSA for paths ending at every depth 1-16: benign "
                 "paths record exactly the hand-computed targets and counts; paths with emission up to 3e38 and "
                 "pdfs down to 2e-38 (weights to 2.5e37) record the right number of targets and the update leaves "
                 "every table finite")
def grid_learning_targets() -> dict:
    from .directions import SphereBins

    figures = {}
    for rule in ("mc", "sarsa", "expected_sarsa"):
        guide = _grid_guide(f"{rule}-hemi_rej_plus", S=2, D=4)
        record = guide.record_table
        record.set_bounds(floor_scene().bbox())
        benign, hostile = SyntheticPaths.benign(), SyntheticPaths.hostile()
        benign.run(guide)
        hostile.run(guide)
        sums, counts = np.array(record.acc_sum), np.array(record.acc_count)
        B = record.bins.count
        cell = {name: int(np.array(record.cell(_vectors(np.array([[*paths.position, 0.0]]))))[0])
                for name, paths in (("benign", benign), ("hostile", hostile))}
        check(cell["benign"] != cell["hostile"], "the benign and hostile paths share a grid cell")
        bins = np.array(SphereBins(4).index(SphereBins(4).centres()))
        for depth, (total, count) in benign.expected_grid_targets(rule).items():
            entry = cell["benign"] * B + bins[depth]
            check(counts[entry] == count and abs(sums[entry] - total) <= 1e-6 * total,
                  f"{rule}, depth {depth + 1}: recorded (sum {sums[entry]}, count {counts[entry]}), expected "
                  f"({total}, {count})")
        recorded = counts.reshape(-1, B)[cell["hostile"]].sum()
        check(recorded == hostile.records(), f"{rule}: hostile paths recorded {recorded} targets, expected "
                                             f"{hostile.records()}")
        stats = guide.update(spp_done=8).stats
        problems = record_violations(record)
        check(not problems, f"{rule}: {_first(problems)}")
        figures[rule] = {"dropped_entries": stats["dropped_entries"], "clamped_entries": stats["clamped_entries"]}
    return figures


@case("targets", "SD-tree recording (L/pdf into the leaves) for paths ending at every depth 1-16 with emission "
                 "up to 3e38 and pdfs down to 2e-38 or 0: the vertex counts are exact and the D-trees built from "
                 "them are finite")
def sdtree_learning_targets() -> dict:
    figures = {}
    for method in TREE_METHODS:
        guide = _tree_guide(method)
        paths = SyntheticPaths.hostile()
        paths.run(guide)
        guide._splat_logs()
        counts = np.array(guide._count_acc)
        recorded_vertices = paths.records()     # every vertex that continues has pdf > 0
        check(counts.sum() == recorded_vertices,
              f"{method}: {counts.sum()} vertices recorded, expected {recorded_vertices}")
        stats = guide.update(getattr(guide, "iteration_end_spp", 8)).stats
        problems = forest_violations(guide._sampling)
        check(not problems, f"{method}: {_first(problems)}")
        figures[method] = {"dropped_entries": stats.get("dropped_entries")}
    return figures


# =====================================================================================================================
#  Scenes
# =====================================================================================================================
#: Methods every scene is rendered with: the baseline, the paper's method, and the SD-tree.
SCENE_METHODS = ("brdf", "ours", "sdtree")
#: Film side (pixels), passes and spp per pass of the scene cases: small, so the suite stays fast.
SCENE_PIXELS, SCENE_PASSES, SCENE_PASS_SPP = 16, 8, 4
ALBEDO = 0.5


def _transform(offset: float = 0.0, scale: float = 1.0):
    """``x ↦ scale·x + offset`` (on every axis), applied to a whole scene: shapes and camera."""
    import mitsuba as mi

    return mi.ScalarTransform4f().translate([offset] * 3) @ mi.ScalarTransform4f().scale(scale)


def _sensor(origin, target, up=(0, 0, 1), fov: float = 50, scale: float = 1.0, transform=None) -> dict:
    """A perspective camera; with the scene scaled by ``scale``, its clip planes scale too (Mitsuba's default far
    plane, 1e4, would cut a scene of size 1e5 out of the picture)."""
    import mitsuba as mi

    transform = transform or _transform()
    return {"type": "perspective", "fov": fov, "near_clip": 1e-2 * scale, "far_clip": 1e4 * scale,
            "to_world": mi.ScalarTransform4f().look_at(transform @ mi.ScalarPoint3f(origin),
                                                       transform @ mi.ScalarPoint3f(target), up),
            "film": {"type": "hdrfilm", "width": SCENE_PIXELS, "height": SCENE_PIXELS, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent"}}


def _diffuse(albedo: float = ALBEDO) -> dict:
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": albedo}}


def closed_room(light_radius: float | None = 0.25, light_radiance: float = 10.0) -> dict:
    """A closed diffuse box [-1, 1]³ seen from inside, with a spherical light near the ceiling (or none)."""
    import mitsuba as mi

    scene = {"type": "scene", "sensor": _sensor((0, -0.9, 0), (0, 1, 0), fov=80),
             "room": {"type": "cube", "flip_normals": True, "bsdf": _diffuse()},
             "box": {"type": "cube", "to_world": mi.ScalarTransform4f().translate([0.3, 0.3, -0.7]).scale(0.3),
                     "bsdf": _diffuse(0.8)}}
    if light_radius is not None:
        scene["light"] = {"type": "sphere", "center": [0, 0.2, 0.6], "radius": light_radius,
                          "emitter": {"type": "area", "radiance": {"type": "rgb", "value": light_radiance}}}
    return scene


def open_plane(with_cube: bool = True, offset: float = 0.0, scale: float = 1.0) -> dict:
    """A diffuse plane (z = 0, side 8), optionally a cube standing on it, under a uniform sky of radiance 1, seen
    from above; moved to ``offset`` and scaled by ``scale`` (geometry and camera)."""
    import mitsuba as mi

    transform = _transform(offset, scale)
    scene = {"type": "scene", "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
             "plane": {"type": "rectangle", "to_world": transform @ mi.ScalarTransform4f().scale(4),
                       "bsdf": _diffuse()}}
    if with_cube:
        scene["sensor"] = _sensor((0, -3, 2.5), (0, 0, 0.3), scale=scale, transform=transform)
        scene["cube"] = {"type": "cube", "bsdf": _diffuse(0.8), "to_world": transform @ mi.ScalarTransform4f()
                         .translate([0, 0, 0.5]).scale(0.5)}
    else:
        scene["sensor"] = _sensor((0, 0, 2), (0, 0, 0), up=(0, 1, 0), fov=40, scale=scale, transform=transform)
    return scene


@dataclass
class SceneRun:
    """One progressive render of a stress scene: per-pass images ``(passes, H, W, 3)`` and their means
    ``(passes, 3)``, the final image, the per-pass statistics (:class:`~guiding.render.PassStats`) and the guide."""

    method: str
    pass_images: np.ndarray
    image: np.ndarray
    passes: list
    guide: object

    @property
    def means(self) -> np.ndarray:
        return self.pass_images.mean(axis=(1, 2))


def render_scene(scene_dict: dict, method: str, max_depth: int = 16, seed: int = 0,
                 passes: int = SCENE_PASSES) -> SceneRun:
    """Render a scene (a ``mi.load_dict`` dictionary) with ``method``: ``passes`` passes of SCENE_PASS_SPP spp."""
    import mitsuba as mi

    from .integrator import GuidedPathIntegrator
    from .methods import make_guide
    from .render import Budget, render

    props = mi.Properties()
    props["max_depth"] = max_depth
    integrator = GuidedPathIntegrator(props, guide=make_guide(method))
    images = []
    result = render(mi.load_dict(scene_dict), integrator, Budget(spp=passes * SCENE_PASS_SPP,
                                                                 pass_spp=SCENE_PASS_SPP),
                    seed=seed, progress=False, on_pass=lambda stats, image: images.append(image))
    return SceneRun(method, np.array(images), result.image, result.passes, integrator.guide)


def _nonfinite_numbers(value, path: str = "") -> list[str]:
    """Paths of the non-finite numbers in a nested statistics dictionary."""
    if isinstance(value, dict):
        return [p for key, item in value.items() for p in _nonfinite_numbers(item, f"{path}.{key}")]
    if isinstance(value, (list, tuple)):
        return [p for i, item in enumerate(value) for p in _nonfinite_numbers(item, f"{path}[{i}]")]
    if isinstance(value, (int, float)) and not isinstance(value, bool) and not np.isfinite(value):
        return [f"{path} = {value}"]
    return []


def scene_run_violations(run: SceneRun) -> list[str]:
    """What is not sane about a render: a non-finite pixel or pass mean, a hit rate outside [0, 1], a non-finite
    statistic, an invalid share or acceptance rate outside [0, 1], proposals per sample above the cap, accumulator
    entries dropped or clamped (a physical scene has no bad input), or invalid guide tables."""
    problems = []
    if nonfinite_pixels(run.image):
        problems.append(f"{nonfinite_pixels(run.image)} non-finite pixels")
    if not np.isfinite(run.means).all():
        problems.append("a non-finite pass mean")
    for p in run.passes:
        if not 0 <= p.hit_rate <= 1:
            problems.append(f"pass {p.index}: hit rate {p.hit_rate}")
        problems += [f"pass {p.index}: {item}" for item in _nonfinite_numbers(p.guide, "guide")]
        for key in ("invalid_share", "acceptance_rate"):
            if p.guide.get(key) is not None and not 0 <= p.guide[key] <= 1:
                problems.append(f"pass {p.index}: {key} = {p.guide[key]}")
        if (p.guide.get("proposals_per_sample") or 0) > getattr(run.guide, "max_proposals", np.inf):
            problems.append(f"pass {p.index}: {p.guide['proposals_per_sample']} proposals per sample")
        for key in ("dropped_entries", "clamped_entries"):
            if p.guide.get(key):
                problems.append(f"pass {p.index}: {p.guide[key]} accumulator entries {key.split('_')[0]}")
    if hasattr(run.guide, "record_table"):
        problems += record_violations(run.guide.record_table)
    elif getattr(run.guide, "_sampling", None) is not None:
        problems += forest_violations(run.guide._sampling)
    return problems


def mean_difference_excess(means, expected) -> float:
    """How far the mean of per-pass means is from ``expected`` (a number, or another run's per-pass means), in
    units of the allowed difference: Z_LIMIT standard errors of the difference plus float32 rounding of the
    values (8 ε₃₂, for estimators without variance). ≤ 1 means they agree."""
    from .validation import Z_LIMIT

    means = np.asarray(means, dtype=np.float64)
    variance = means.var(axis=0, ddof=1) / len(means)
    if isinstance(expected, np.ndarray):
        variance = variance + expected.var(axis=0, ddof=1) / len(expected)
        expected = expected.mean(axis=0)
    allowed = Z_LIMIT * np.sqrt(variance) + 8 * EPS32 * np.abs(expected)
    return float(np.max(np.abs(means.mean(axis=0) - expected) / np.maximum(allowed, TINY32)))


def _check_runs(scene_name: str, runs: dict) -> dict:
    """Check every run of a scene with :func:`scene_run_violations`; returns each method's image mean."""
    for method, run in runs.items():
        problems = scene_run_violations(run)
        check(not problems, f"{scene_name}, {method}: {_first(problems)}")
    return {method: float(run.means.mean()) for method, run in runs.items()}


@case("scenes", "a scene without an emitter renders a black image (exactly 0), hit rate 0, finite statistics and "
                "all-zero finite guide tables")
def scene_without_emitter() -> dict:
    runs = {method: render_scene(closed_room(light_radius=None), method) for method in SCENE_METHODS}
    figures = _check_runs("no emitter", runs)
    for method, run in runs.items():
        check(not run.image.any(), f"{method}: {np.count_nonzero(run.image)} non-zero pixel values")
        check(all(p.hit_rate == 0 for p in run.passes), f"{method}: hit rates {[p.hit_rate for p in run.passes]}")
        if hasattr(run.guide, "record_table"):
            check(not np.array(run.guide.record_table.q).any(), f"{method}: Q is not all zero")
    return figures


@case("scenes", "a flat bounding box (a single plane: zero extent along z) under a uniform sky: finite, sane, and "
                "every method's mean equals the exact albedo × sky radiance within 4 standard errors")
def scene_with_flat_bounding_box() -> dict:
    import mitsuba as mi

    scene = open_plane(with_cube=False)
    extent = np.array(mi.load_dict(scene).bbox().extents())
    check(extent[2] == 0, f"the test scene's bounding box is not flat: extent {extent}")
    runs = {method: render_scene(scene, method) for method in SCENE_METHODS}
    figures = _check_runs("flat bounding box", runs)
    for method, run in runs.items():
        excess = mean_difference_excess(run.means, ALBEDO * 1.0)
        check(excess <= 1, f"{method}: mean {run.means.mean():.6g} vs exact {ALBEDO} ({excess:.2f} x allowed)")
    return figures


@case("scenes", "the same scene at the origin, scaled by 1e5 and moved to coordinates 1e5: finite and sane; the "
                "scaled scene's image mean agrees with the origin's within 4 standard errors, the moved scene's "
                "difference is measured (float32 geometry and Mitsuba's ray offsets grow with |p|)")
def scene_at_1e5_coordinates() -> dict:
    figures = {}
    for method in SCENE_METHODS:
        runs = {"origin": render_scene(open_plane(), method, seed=1),
                "scale 1e5": render_scene(open_plane(scale=1e5), method, seed=2),
                "offset 1e5": render_scene(open_plane(offset=1e5), method, seed=3)}
        means = _check_runs(f"1e5 coordinates ({method})", runs)
        excess = mean_difference_excess(runs["scale 1e5"].means, runs["origin"].means)
        check(excess <= 1, f"{method}, scale 1e5: mean {means['scale 1e5']:.6g} vs {means['origin']:.6g} at the "
                           f"origin ({excess:.2f} x allowed)")
        figures[method] = {**means, "offset_relative_difference": means["offset 1e5"] / means["origin"] - 1,
                           "offset_difference_in_allowed": mean_difference_excess(runs["offset 1e5"].means,
                                                                                  runs["origin"].means)}
    return figures


@case("scenes", "a tiny (radius 0.02 in a room of side 2), extremely bright (radiance 1e20) emitter, found by a "
                "few paths: fireflies stay finite, statistics and guide tables stay finite, nothing is sanitised, "
                "and the metrics of the image are finite")
def scene_with_tiny_bright_emitter() -> dict:
    from .metrics import evaluate

    runs = {method: render_scene(closed_room(light_radius=0.02, light_radiance=1e20), method)
            for method in SCENE_METHODS}
    figures = _check_runs("tiny bright emitter", runs)
    for method, run in runs.items():
        check(any(p.hit_rate > 0 for p in run.passes), f"{method}: no path found the emitter (no fireflies)")
        metrics = evaluate(run.image, np.zeros_like(run.image))
        check(all(metrics[key] is not None for key in ("mae", "mae_hdr", "relmse")), f"{method}: metrics {metrics}")
        figures[f"{method}_max_pixel"] = float(run.image.max())
    return figures


@case("scenes", "max depth 1 (only directly visible emitters): every method gives the same image, the emitter's "
                "radiance where it is seen and 0 elsewhere, and learns nothing")
def scene_with_max_depth_1() -> dict:
    radiance = 10.0
    runs = {method: render_scene(closed_room(light_radius=0.6, light_radiance=radiance), method, max_depth=1)
            for method in SCENE_METHODS}
    figures = _check_runs("max depth 1", runs)
    reference = runs["brdf"].pass_images
    check(reference.max() > 0, "the emitter is not in view")
    for method, run in runs.items():
        # Pass by pass (the SD-tree's final image holds its last iteration only).
        if method != "brdf":
            check(np.array_equal(run.pass_images, reference), f"{method}: pass images differ from brdf's")
        check(((run.image >= 0) & (run.image <= radiance * (1 + 4 * EPS32))).all(),
              f"{method}: pixel values outside [0, {radiance}]")
        if hasattr(run.guide, "record_table"):
            check(not np.array(run.guide.record_table.acc_count).any(), f"{method}: recorded targets")
    return figures


@case("scenes", "S = D = 1 (one cell, two direction bins) for every sampler: finite, sane, and agreeing with brdf "
                "within 4 standard errors")
def scene_with_one_cell_and_one_bin() -> dict:
    from .guides import SAMPLERS

    methods = ["brdf", *(f"sarsa-{sampler}-S1-D1" for sampler in SAMPLERS), "ours-expected-S1-D1"]
    runs = {method: render_scene(open_plane(), method, seed=i) for i, method in enumerate(methods)}
    figures = _check_runs("S = D = 1", runs)
    for method, run in runs.items():
        if method == "brdf":
            continue
        excess = mean_difference_excess(run.means, runs["brdf"].means)
        check(excess <= 1, f"{method}: mean {figures[method]:.6g} vs brdf {figures['brdf']:.6g} "
                           f"({excess:.2f} x allowed)")
    return figures


# =====================================================================================================================
#  Memory
# =====================================================================================================================
@dataclass
class CliRun:
    """What a command line run gave: exit code, stderr lines, stdout text."""

    code: int
    errors: list[str]
    output: str


def run_cli(argv: list[str]) -> CliRun:
    """Run ``python -m guiding ARGV`` in this process (``guiding.cli.main``), capturing its output."""
    from .cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return CliRun(code, err.getvalue().strip().splitlines(), out.getvalue())


def one_error_line(run: CliRun, fragment: str, code: int = EXIT_BAD_INPUT) -> list[str]:
    """Problems with a run that should have failed with exit ``code`` and one stderr line containing
    ``fragment``."""
    problems = []
    if run.code != code:
        problems.append(f"exit code {run.code} instead of {code}")
    if len(run.errors) != 1:
        problems.append(f"{len(run.errors)} stderr lines: {run.errors[:3]}")
    elif fragment not in run.errors[0]:
        problems.append(f"'{fragment}' not in: {run.errors[0]}")
    return problems


def files_in(folder) -> list[str]:
    """Files below ``folder`` (none when it does not exist)."""
    from pathlib import Path

    folder = Path(folder)
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()) if folder.is_dir() else []


#: A table far beyond any memory limit: 64³ cells × 2·64² bins (the issue's example).
OVERSIZED_METHOD = "ours-S64-D64"


@case("memory", f"a table over the memory limit ({OVERSIZED_METHOD}: 56.6 GiB) is refused up front with one line "
                "giving the size it needs (exit 2 from the CLI, no output folder); the limit is configurable "
                "(--memory-limit, $GUIDING_MEMORY_LIMIT) and the planned size equals what built tables report")
def memory_limit_refusal() -> dict:
    import os
    import tempfile

    from .errors import GuidingError
    from .guides import PROPOSALS, RULES, SAMPLERS
    from .guides.grid import GridGuide
    from .guides.grid_record import RadianceRecord, table_needs
    from .methods import MEMORY_LIMIT_VARIABLE, check_method, format_size, make_guide, table_bytes

    # The planned size is what a built record reports, for every rule, sampler and proposal.
    for rule in RULES:
        for sampler in SAMPLERS:
            for proposal in PROPOSALS:
                built = GridGuide(spatial_resolution=2, directional_resolution=3, rule=rule, sampler=sampler, proposal=proposal).record_table.memory_bytes()
                planned = RadianceRecord.planned_bytes(2, 3, **table_needs(rule, sampler, proposal))
                check(planned == built, f"{rule}-{sampler} ({proposal}): planned {planned} bytes, built {built}")

    size = table_bytes(OVERSIZED_METHOD)
    try:
        check_method(OVERSIZED_METHOD)
        raise StressFailure(f"{OVERSIZED_METHOD} ({format_size(size)}) was accepted")
    except GuidingError as error:
        message = str(error)
    check("\n" not in message and format_size(size) in message, f"refusal message: {message!r}")
    for refused in (lambda: make_guide(OVERSIZED_METHOD), lambda: check_method("ours", table_bytes("ours") - 1)):
        try:
            refused()
            raise StressFailure("a table over the limit was accepted")
        except GuidingError:
            pass
    check_method("ours", table_bytes("ours"))           # exactly at the limit: allowed
    check_method(OVERSIZED_METHOD, 2 * size)            # a raised limit lets it through
    previous = os.environ.get(MEMORY_LIMIT_VARIABLE)
    try:
        os.environ[MEMORY_LIMIT_VARIABLE] = "1M"
        try:
            check_method("ours")
            raise StressFailure(f"${MEMORY_LIMIT_VARIABLE}=1M did not refuse 'ours' "
                                f"({format_size(table_bytes('ours'))})")
        except GuidingError:
            pass
    finally:
        if previous is None:
            os.environ.pop(MEMORY_LIMIT_VARIABLE, None)
        else:
            os.environ[MEMORY_LIMIT_VARIABLE] = previous

    with tempfile.TemporaryDirectory() as folder:
        out = os.path.join(folder, "out")
        start = time.perf_counter()
        run = run_cli(["render", "--scene", "cornell", "--method", OVERSIZED_METHOD, "--spp", "1", "--out", out])
        seconds = time.perf_counter() - start
        problems = one_error_line(run, f"needs {format_size(size)}")
        check(not problems, f"CLI: {_first(problems)}")
        check(not os.path.exists(out), "CLI: the output folder was created")
        run = run_cli(["render", "--scene", "cornell", "--method", "ours", "--spp", "1", "--out", out,
                       "--memory-limit", "1M"])
        check(not one_error_line(run, "over the memory limit of 1.0 MiB"), f"CLI --memory-limit 1M: {run.errors}")
    return {"oversized_table": format_size(size), "ours_table": format_size(table_bytes("ours")),
            "cli_refusal_seconds": round(seconds, 3)}


# =====================================================================================================================
#  Bad input on the command line
# =====================================================================================================================
def _render_args(out: str, *extra: str, scene: str = "cornell") -> list[str]:
    """A valid, tiny ``render`` command line plus ``extra`` options (a later option overrides an earlier one)."""
    return ["render", "--scene", scene, "--scale", "0.05", "--method", "brdf", "--spp", "1", "--out", out,
            "--quiet", *extra]


def _bad_input_violations(runs: list[tuple[str, list[str], str]], folder) -> list[str]:
    """Run each ``(label, argv, fragment)`` and collect what is wrong: not exit 2 with one line containing
    ``fragment``, or a new file below ``folder``."""
    problems = []
    for label, argv, fragment in runs:
        before = set(files_in(folder))
        run = run_cli(argv)
        problems += [f"{label}: {p}" for p in one_error_line(run, fragment)]
        problems += [f"{label}: wrote {f}" for f in sorted(set(files_in(folder)) - before)]
    return problems


@case("bad-input", "bad option values (scale 0, NaN or Inf; an infinite time budget; 0 threads, spp per pass or "
                   "depth; a seed that is not a number; negative excluded passes; an unknown variant; a bad memory "
                   "limit): one line, exit 2, nothing written",
      also_tested="tests/test_cli.py::test_bad_render_input (unknown method, spp 0, negative seconds, no budget)")
def bad_option_values() -> dict:
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        out = f"{folder}/out"
        runs = [(f"{option} {value}", _render_args(out, option, value), fragment) for option, value, fragment in (
            ("--scale", "0", "must be > 0 and finite"), ("--scale", "nan", "must be > 0 and finite"),
            ("--scale", "inf", "must be > 0 and finite"), ("--scale", "-1", "must be > 0 and finite"),
            ("--threads", "0", "must be > 0"), ("--pass-spp", "0", "must be > 0"), ("--max-depth", "0", "must be > 0"),
            ("--seed", "abc", "invalid int value"), ("--exclude-passes", "-1", "excluded passes must be >= 0"),
            ("--variant", "bogus", "unknown variant 'bogus'"), ("--memory-limit", "lots", "bad memory size"),
            ("--memory-limit", "0", "must be > 0"))]
        runs.append(("--seconds inf", [a for a in _render_args(out) if a not in ("--spp", "1")] + ["--seconds", "inf"],
                     "must be > 0 and finite"))
        problems = _bad_input_violations(runs, folder)
    check(not problems, _first(problems))
    return {"inputs": len(runs)}


@case("bad-input", "missing or broken scenes (an XML path that does not exist, malformed XML, XML Mitsuba cannot "
                   "load, no resx/resy defaults): one line, exit 2, nothing written",
      also_tested="tests/test_cli.py::test_bad_render_input and test_real_process_prints_no_traceback (unknown "
                  "scene name)")
def bad_scenes() -> dict:
    import tempfile
    from pathlib import Path

    defaults = '<default name="resx" value="8"/><default name="resy" value="8"/>'
    files = {"malformed.xml": f'<scene version="3.0.0">{defaults}',
             "unloadable.xml": f'<scene version="3.0.0">{defaults}<shape type="no_such_plugin"/></scene>',
             "no_defaults.xml": '<scene version="3.0.0"><shape type="sphere"/></scene>'}
    with tempfile.TemporaryDirectory() as folder, tempfile.TemporaryDirectory() as scenes:
        for name, text in files.items():
            (Path(scenes) / name).write_text(text)
        out = f"{folder}/out"
        runs = [("missing file", _render_args(out, scene=f"{scenes}/absent.xml"), "does not exist"),
                ("malformed", _render_args(out, scene=f"{scenes}/malformed.xml"), "cannot read scene"),
                ("unloadable", _render_args(out, scene=f"{scenes}/unloadable.xml"), "cannot load scene"),
                ("no defaults", _render_args(out, scene=f"{scenes}/no_defaults.xml"), "does not declare")]
        problems = _bad_input_violations(runs, folder)
    check(not problems, _first(problems))
    return {"inputs": len(runs)}


@case("bad-input", "corrupt EXR input to `evaluate` (random bytes, an empty file, a folder, an EXR without RGB "
                   "channels) and a reference of another resolution (transposed): one line, exit 2",
      also_tested="tests/test_cli.py::test_evaluate_bad_files (truncated EXR, missing file, different size)")
def bad_images() -> dict:
    import tempfile
    from pathlib import Path

    import OpenEXR

    from . import imageio

    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        good = folder / "good.exr"
        imageio.write_exr(good, np.ones((3, 2, 3)))
        imageio.write_exr(folder / "transposed.exr", np.ones((2, 3, 3)))
        (folder / "random.exr").write_bytes(np.random.default_rng(0).bytes(4096))
        (folder / "empty.exr").write_bytes(b"")
        (folder / "folder.exr").mkdir()
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        with OpenEXR.File(header, {"Y": np.ones((3, 2), dtype=np.float32)}) as exr:
            exr.write(str(folder / "grey.exr"))
        runs = [("random bytes", ["evaluate", str(folder / "random.exr"), str(good)], "not a readable EXR"),
                ("empty file", ["evaluate", str(good), str(folder / "empty.exr")], "not a readable EXR"),
                ("a folder", ["evaluate", str(folder / "folder.exr"), str(good)], "it is a folder"),
                ("no RGB channels", ["evaluate", str(folder / "grey.exr"), str(good)], "no RGB channels"),
                ("transposed reference", ["evaluate", str(good), str(folder / "transposed.exr")], "differ in size")]
        problems = []
        for label, argv, fragment in runs:
            problems += [f"{label}: {p}" for p in one_error_line(run_cli(argv), fragment)]
    check(not problems, _first(problems))
    return {"inputs": len(runs)}


@case("bad-input", "unwritable output folders (below a file, below /proc): one line, exit 2",
      also_tested="tests/test_cli.py::test_unwritable_output (the output path is a file)")
def unwritable_output() -> dict:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        blocker = Path(folder) / "file"
        blocker.write_text("x")
        runs = [("below a file", _render_args(str(blocker / "out")), "cannot create output folder"),
                ("below /proc", _render_args("/proc/guiding-stress/out"), "cannot create output folder")]
        problems = _bad_input_violations(runs, folder)
    check(not problems, _first(problems))
    return {"inputs": len(runs)}


@case("bad-input", "Ctrl-C (SIGINT) in the middle of a render, after its first snapshot was written, and Ctrl-C "
                   "while Dr.Jit traces the path loop (which wraps it in a RuntimeError): exit 130, one line, no "
                   "traceback, and no file left in the output folder (snapshots removed)")
def ctrl_c_mid_render() -> dict:
    import os
    import signal
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    from .scenes import PROJECT_ROOT

    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "out"
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(PROJECT_ROOT), os.environ.get("PYTHONPATH", "")])}
        argv = _render_args(str(out), "--spp", "1000000", "--variant", "llvm_ad_rgb", "--snapshots")
        # A process started in the background inherits SIGINT ignored; Ctrl-C needs its default disposition back.
        process = subprocess.Popen([sys.executable, "-m", "guiding", *argv], stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE, text=True, env=env,
                                   preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        start = time.perf_counter()
        try:
            while not list(out.glob("image_snap*.exr")) and process.poll() is None:
                check(time.perf_counter() - start < 120, "no snapshot after 120 s")
                time.sleep(0.05)
            check(process.poll() is None, "the render ended before it was interrupted")
            interrupted_after = time.perf_counter() - start
            process.send_signal(signal.SIGINT)
            stdout, stderr = process.communicate(timeout=120)
        finally:
            if process.poll() is None:
                process.kill()
                process.communicate()
        lines = stderr.strip().splitlines()
        check(process.returncode == EXIT_INTERRUPTED, f"exit code {process.returncode}: {stderr[-500:]}")
        check(len(lines) == 1 and lines[0].startswith("interrupted"), f"stderr: {lines[-3:]}")
        left = files_in(out)
        check(not left, f"files left: {left}")

        from .guides.bsdf import BSDFGuide

        def interrupt(*args, **kwargs):
            raise KeyboardInterrupt

        own = BSDFGuide.__dict__.get("sample")  # None while BSDFGuide inherits Guide.sample
        BSDFGuide.sample = interrupt            # brdf's sample() runs inside the traced path loop
        try:
            run = run_cli(_render_args(str(out)))
        finally:
            if own is None:
                del BSDFGuide.sample
            else:
                BSDFGuide.sample = own
        problems = one_error_line(run, "interrupted", code=EXIT_INTERRUPTED)
        check(not problems, f"Ctrl-C while tracing: {_first(problems)}")
        check(not files_in(out), f"Ctrl-C while tracing: files left: {files_in(out)}")
    return {"interrupted_after_seconds": round(interrupted_after, 2)}


# =====================================================================================================================
#  Accumulation drift
# =====================================================================================================================
#: The long run of the drift case: 1250 passes of 8 spp (the renderer's default pass) = 10 000 spp.
DRIFT_PASSES, DRIFT_PASS_SPP = 1250, 8
#: Relative error above which float32 accumulation would need fixing (the issue's threshold).
DRIFT_LIMIT = 1e-4


@case("drift", f"a {DRIFT_PASSES * DRIFT_PASS_SPP} spp run ({DRIFT_PASSES} passes of {DRIFT_PASS_SPP} spp, "
               "cornell at 16x16): the renderer's image equals the float64 sum of its passes to float32 rounding, "
               "and the drift a float32 accumulator would have had is measured against it")
def accumulation_drift() -> dict:
    from .integrator import GuidedPathIntegrator
    from .render import Budget, render
    from .scenes import load_scene

    scene = load_scene("cornell", scale=16 / 256)
    sum64 = sum32 = None

    def accumulate(stats, image) -> None:
        nonlocal sum64, sum32
        weighted64 = image * stats.spp                                   # what the renderer adds (float64)
        weighted32 = image.astype(np.float32) * np.float32(stats.spp)    # what a float32 accumulator would add
        sum64 = weighted64 if sum64 is None else sum64 + weighted64
        sum32 = weighted32 if sum32 is None else sum32 + weighted32

    result = render(scene, GuidedPathIntegrator(), Budget(spp=DRIFT_PASSES * DRIFT_PASS_SPP,
                                                          pass_spp=DRIFT_PASS_SPP), progress=False,
                    on_pass=accumulate)
    spp = result.spp_in_image
    check(spp == DRIFT_PASSES * DRIFT_PASS_SPP and len(result.passes) == DRIFT_PASSES,
          f"{len(result.passes)} passes, {spp} spp in the image")
    mean64, mean32 = sum64 / spp, sum32 / np.float32(spp)
    lit = mean64 > 0
    renderer_error = np.abs(result.image - mean64)[lit] / mean64[lit]
    float32_drift = np.abs(mean32 - mean64)[lit] / mean64[lit]
    check(renderer_error.max() <= EPS32, f"the renderer's image differs from the float64 sum of its passes by "
                                         f"{renderer_error.max():.3g} (relative)")
    return {"spp": spp, "passes": DRIFT_PASSES, "renderer_max_relative_error": float(renderer_error.max()),
            "float32_max_relative_drift": float(float32_drift.max()),
            "float32_mean_relative_drift": float(float32_drift.mean()),
            "float32_would_need_a_fix": bool(float32_drift.max() > DRIFT_LIMIT)}


# =====================================================================================================================
#  Determinism
# =====================================================================================================================
#: Methods whose determinism is measured: the baseline (no learning), grid guides learning through float64
#: atomics (SARSA with rejection sampling, MC with hemi_inv) and the SD-tree guides (float32 atomics).
DETERMINISM_METHODS = ("brdf", "ours", "mc-hemi_inv", "sdtree", "quadtree-grid")
DETERMINISM_SCALE, DETERMINISM_SPP = 32 / 256, 32


def _render_cornell(method: str, seed: int) -> np.ndarray:
    from .integrator import GuidedPathIntegrator
    from .methods import make_guide
    from .render import Budget, render
    from .scenes import load_scene

    scene = load_scene("cornell", scale=DETERMINISM_SCALE)
    return render(scene, GuidedPathIntegrator(guide=make_guide(method)), Budget(spp=DETERMINISM_SPP, pass_spp=8),
                  seed=seed, progress=False).image


@case("determinism", "the same seed gives the same image: bit-identical for every method on one thread and for "
                     "brdf on two; where guides learn through atomics on two threads, the largest difference is "
                     "measured and must stay below 1e-3 of the difference between two seeds")
def same_seed_same_image() -> dict:
    import drjit as dr

    threads = dr.thread_count()
    figures = {}
    try:
        for count in (1, threads):
            dr.set_thread_count(count)
            for method in DETERMINISM_METHODS:
                first, second = _render_cornell(method, seed=5), _render_cornell(method, seed=5)
                difference = float(np.abs(first - second).max())
                label = f"{method}, {count} thread{'s' if count > 1 else ''}"
                figures[label] = {"max_abs_difference": difference,
                                  "pixels_differing": int(np.count_nonzero((first != second).any(axis=-1)))}
                if count == 1 or method == "brdf":
                    check(difference == 0, f"{label}: the same seed differs by up to {difference:.3g}")
                else:
                    noise = float(np.abs(first - _render_cornell(method, seed=6)).max())
                    figures[label]["max_abs_difference_between_seeds"] = noise
                    check(difference <= 1e-3 * noise, f"{label}: the same seed differs by up to {difference:.3g}, "
                                                      f"two seeds by {noise:.3g}")
    finally:
        dr.set_thread_count(threads)
    return figures


# =====================================================================================================================
#  Report
# =====================================================================================================================
#: What each group found and what was done about it (the report's notes); the figures are in the table.
NOTES = {
    "directions": "`dr.normalize` alone sent vectors shorter than ~1e-19 or longer than ~1e19 to a wrong bin (|d|² "
                  "under- or overflows float32); `directions.safe_normalize` (divide by the largest component "
                  "first, three divisions because Dr.Jit turns `d / x` into `d · (1/x)` and 1/x is denormal for "
                  "|x| > 8.5e37) now serves SphereBins, NormalBins and the SD-tree's `dir_to_uv`, which also gave "
                  "NaN for NaN input and read cos θ off unnormalised vectors. Dr.Jit's CPU backend flushes "
                  "denormals to zero in kernels run on its worker threads but not in small ones, so denormal "
                  "components count as zero. Bin areas are measured as spherical polygons of the maps' own float32 "
                  "output; 'to float precision' means within perimeter·ε₃₂ of the exact value.",
    "tables": "A NaN, ±Inf or negative accumulator entry made a whole cell's policy NaN for the rest of the run "
              "(the grid's accumulators are never cleared) and an SD-tree's probabilities NaN; an infinite vertex "
              "count would have split the S-tree to depth 60. `RadianceRecord.update` (via `_sanitise`) now drops "
              "such entries and clamps Q to 1e30 (`Q_LIMIT`), the SD-tree's `_pull` zeroes bad energies and "
              "counts; both report `dropped_entries` (and the grid `clamped_entries`) in each pass's statistics. "
              "The CDF rows (`_normalised_cdf`) now end at exactly 1.",
    "samplers": "hemi_inv recomputed the density of a direction from its bin, and a direction drawn at a bin's edge "
                "could be looked up in a neighbour whose CDF step is below float32 resolution: pdf 0 above the "
                "surface (policies with ε → 0). It now reports the density of the bin it drew in "
                "(`GridGuide._eval_pdf(chosen_bin=…)`). The rejection loop is capped by construction; the "
                "chi-square tests at the worst acceptance rates check that the fallback share is in the pdf.",
    "targets": "Emission above ~1.1e38 overflows float32 in `dr.mean` over RGB and reaches the grid's accumulators "
               "as Inf; such entries are now dropped and counted (see `dropped_entries` in the figures), never "
               "propagated. The SD-tree already skipped non-finite L/pdf values when splatting.",
    "scenes": "The S = D = 1 scene found a 3 % bias of the rejection samplers: the memo tables' cosine integrals "
              "used 8×8 quadrature points per bin whatever D, too few when one bin spans a hemisphere. They now "
              "use at least 128 points per hemisphere side (`grid_record.quadrature_points`), and the case "
              "`memo-cosine-integrals` checks them directly. A scene moved to "
              "coordinates 1e5 renders a few percent brighter than at the origin with every method, Mitsuba's "
              "own `path` integrator included: float32 positions there are 0.008 apart and Mitsuba offsets "
              "spawned rays by about 1e-4·|p|. That is measured (`offset_relative_difference`), not fixed; a "
              "scene scaled by 1e5 agrees with the original.",
    "memory": "A grid method whose tables would exceed the limit (default 8 GiB, `--memory-limit`, "
              "`$GUIDING_MEMORY_LIMIT`) is refused by `methods.check_method` before anything is allocated; "
              "`ours-S64-D64` used to start allocating 57 GiB. The SD-tree's tables grow while it learns and are "
              "not checked up front.",
    "drift": "The renderer accumulates passes in float64; the figures show what a float32 accumulator would have "
             "cost over the long run, compared with the 1e-4 threshold.",
    "determinism": "On one thread every method is bit-identical from run to run. On two threads the grid guides' "
                   "float64 atomics have so far given identical images (their sums are rounded to float32 Q), while "
                   "the SD-tree guides' float32 atomics (energies splatted per pass) can change images in the last "
                   "bits; the figures give the largest difference.",
    "bad-input": "New: a scale or time budget of Inf or NaN (a traceback, or a render that never ends), a bad "
                 "variant (checked before the output folder is made), an EXR path that is a folder, Ctrl-C "
                 "during the tracing of a Dr.Jit loop (it reaches the command line as a RuntimeError whose cause is "
                 "the KeyboardInterrupt: a traceback and exit 1 before), outputs written one by one (now all "
                 "together or none) and snapshots left behind by an interrupted render.",
}


def _format_value(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_format_value(v) for v in value) + "]"
    return str(value)


def format_figures(figures: dict, prefix: str = "") -> str:
    """Measured figures as ``key=value`` pairs (nested keys joined with ``/``)."""
    parts = []
    for key, value in figures.items():
        if isinstance(value, dict):
            parts.append(format_figures(value, f"{prefix}{key}/"))
        else:
            parts.append(f"{prefix}{key}={_format_value(value)}")
    return "; ".join(p for p in parts if p)


def report_markdown(outcomes: list[Outcome], device: str = "", command: str = "python -m guiding stress") -> str:
    """The Markdown report of ``outcomes``: one table row per case, then the notes of the groups that ran."""
    import drjit as dr
    import mitsuba as mi

    passed = sum(o.status == "pass" for o in outcomes)

    def cell(text: str) -> str:
        return text.replace("|", "\\|").replace("\n", " ")

    lines = ["# Stress cases: numerical stability and bad input", "",
             f"Generated by `{command}` on {device or 'this machine'} ({mi.variant()}, {dr.thread_count()} threads), "
             f"{time.strftime('%Y-%m-%d')}: **{passed} of {len(outcomes)} cases pass** in "
             f"{sum(o.seconds for o in outcomes):.0f} s. The same cases run in CI as `tests/test_stress_cases.py`; "
             "hypothesis searches arbitrary float32 vectors for counterexamples to the direction maps' checks in "
             "`tests/test_stress_properties.py`.", "",
             "| group | case | checks | outcome | measured |", "|---|---|---|---|---|"]
    for o in outcomes:
        checks = o.case.checks + (f" (related input: {o.case.also_tested})" if o.case.also_tested else "")
        outcome = f"{o.status} ({o.seconds:.1f} s)" + (f": {o.message}" if o.message else "")
        lines.append(f"| {o.case.group} | `{o.case.name}` | {cell(checks)} | {cell(outcome)} | "
                     f"{cell(format_figures(o.figures))} |")
    groups = [g for g in GROUPS if any(o.case.group == g for o in outcomes)]
    lines += ["", "## Notes", ""] + [f"- **{g}**: {NOTES[g]}" for g in groups]
    return "\n".join(lines) + "\n"


def write_report(outcomes: list[Outcome], path, device: str = "", command: str = "python -m guiding stress"):
    """Write :func:`report_markdown` to ``path`` atomically; returns the path."""
    from pathlib import Path

    from .imageio import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(report_markdown(outcomes, device, command))
    return path
