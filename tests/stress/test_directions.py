"""Directions: the direction ↔ bin maps (the concentric hemisphere pair of `guiding.guides.directions`, its cube map
of normals, and the SD-tree's cylindrical map) at poles, seams and the hemisphere boundary, with degenerate and
unnormalised input, and the solid angle of every bin.

`dr.normalize` alone sent vectors shorter than ~1e-19 or longer than ~1e19 to a wrong bin (|d|² under- or overflows
float32); `directions.safe_normalize` (divide by the largest component first, three divisions because Dr.Jit turns
`d / x` into `d · (1/x)` and 1/x is denormal for |x| > 8.5e37) now serves SphereBins, NormalBins and the SD-tree's
`dir_to_uv`, which also gave NaN for NaN input and read cos θ off unnormalised vectors. Dr.Jit's CPU backend
flushes denormals to zero in kernels run on its worker threads but not in small ones, so denormal components count
as zero. Bin areas are measured as spherical polygons of the maps' own float32 output; 'to float precision' means
within perimeter·ε₃₂ of the exact value. Hypothesis searches arbitrary float32 vectors for counterexamples to the
same checks.
"""

import mitsuba as mi
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arrays import EPS32, angle_between, few, to_numpy, unit, vectors
from direction_maps import (NORMAL_RESOLUTIONS, SCALES, SPHERE_RESOLUTIONS, bin_geometry, containment_violations,
                            degenerate_inputs, equal_area_excess, interior_samples, normal_bins_geometry,
                            round_trip_violations, scale_violations, special_directions, sphere_bins_geometry)
from sdtree_parts import (CYLINDRICAL_DEEP, CYLINDRICAL_DEPTHS, cylindrical_cells, cylindrical_violations,
                          square_edge_directions)


@pytest.mark.parametrize("resolution", SPHERE_RESOLUTIONS)
def test_sphere_bins_round_trip(resolution, figures):
    """SphereBins: every bin's interior maps back to the bin (D = 1, 2, 3, 4, 5, 16, 64)."""
    bins, _ = sphere_bins_geometry(resolution)
    problems = round_trip_violations(bins.index, bins.direction, bins.count)
    figures.update(bins=bins.count, points_per_bin=len(interior_samples()))
    assert not problems, f"D = {resolution}: {few(problems)}"


@pytest.mark.parametrize("resolution", SPHERE_RESOLUTIONS)
def test_sphere_bins_poles_seams_boundary(resolution, figures):
    """SphereBins: poles, the concentric map's seams and the hemisphere boundary (z = ±0, ±1e-45, …) land in a
    valid bin that contains them, on the right hemisphere."""
    bins, geometry = sphere_bins_geometry(resolution)
    directions = special_directions()
    problems = containment_violations(bins.index, bins.count, geometry, directions, lower_from=bins.count // 2)
    figures["directions"] = len(directions)
    assert not problems, f"D = {resolution}: {few(problems)}"


@pytest.mark.parametrize("resolution", SPHERE_RESOLUTIONS)
def test_sphere_bins_any_input(resolution, figures):
    """SphereBins: zero, NaN, Inf and extreme vectors give a valid bin; scaling a direction by 1e-30 … 1e38
    (unnormalised, |d|² under- or overflowing) keeps its bin."""
    bins, geometry = sphere_bins_geometry(resolution)
    problems = containment_violations(bins.index, bins.count, geometry, degenerate_inputs(),
                                      lower_from=bins.count // 2)
    problems += scale_violations(bins.index, geometry.centre)
    figures.update(inputs=len(degenerate_inputs()), scales=list(SCALES))
    assert not problems, f"D = {resolution}: {few(problems)}"


@pytest.mark.parametrize("resolution", SPHERE_RESOLUTIONS)
def test_sphere_bins_equal_solid_angle(resolution, figures):
    """SphereBins: every bin has solid angle 2π/D² to float precision (|error| ≤ perimeter·ε₃₂)."""
    bins, geometry = sphere_bins_geometry(resolution)
    excess = equal_area_excess(geometry, bins.solid_angle)
    worst = int(np.argmax(excess))
    figures["max_relative_error"] = float(np.abs(geometry.solid_angle / bins.solid_angle - 1).max())
    assert excess[worst] <= 1, (f"D = {resolution}: bin {worst} has solid angle {geometry.solid_angle[worst]:.9g} "
                                f"instead of {bins.solid_angle:.9g} ({excess[worst]:.2f} x perimeter·ε₃₂)")


@pytest.mark.parametrize("resolution", NORMAL_RESOLUTIONS)
def test_normal_bins_maps(resolution, figures):
    """NormalBins: interiors map back to their bin, the six axes are bin centres, zero/NaN/Inf normals land in the +z
    face's centre bin, scaled normals keep theirs (R = 1, 3, 5, 7)."""
    bins, geometry = normal_bins_geometry(resolution)
    problems = round_trip_violations(bins.index, bins.normal, bins.count)
    problems += containment_violations(bins.index, bins.count, geometry,
                                       np.concatenate([special_directions(), degenerate_inputs()]))
    problems += scale_violations(bins.index, geometry.centre)
    # The memo tables are exact only at bin centres: an axis normal must be the centre of its bin.
    axes = np.array([(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)], dtype=np.float32)
    k = np.array(bins.index(vectors(axes)))
    centres = to_numpy(bins.normal(mi.UInt32(k.astype(np.uint32))))
    off = angle_between(unit(axes), unit(centres)) > 2 * EPS32
    problems += [f"axis {tuple(a)} is not the centre of bin {b}" for a, b in zip(axes[off], k[off])]
    # A normal without a direction (zero, NaN, ±Inf in any component) lands in the +z face's centre bin.
    degenerate = degenerate_inputs()
    degenerate = degenerate[np.isnan(unit(degenerate, flush=True)).any(axis=1)]
    landed = np.array(bins.index(vectors(degenerate)))
    plus_z = int(np.array(bins.index(vectors(np.array([(0, 0, 1)], dtype=np.float32))))[0])
    problems += [f"{tuple(d)} lands in bin {b}, not the +z centre {plus_z}"
                 for d, b in zip(degenerate, landed) if b != plus_z]
    figures["bins"] = bins.count
    assert not problems, f"R = {resolution}: {few(problems)}"


def test_cylindrical_map_round_trip(figures):
    """SD-tree cylindrical map: poles, the azimuth seam, the equator, the square's corners and edges, zero/NaN/Inf
    and scaled directions give a point of [0,1)² and come back; every leaf centre down to depth 20 maps back to
    its leaf."""
    problems = cylindrical_violations(np.concatenate([special_directions(), degenerate_inputs()]))
    centres = unit(special_directions())
    for scale in SCALES:
        problems += cylindrical_violations((centres * scale).astype(np.float32))
    problems += cylindrical_violations(square_edge_directions())
    checked = 0
    for depth in (*CYLINDRICAL_DEPTHS, *CYLINDRICAL_DEEP):
        cells = cylindrical_cells(depth)
        back = cells.index(cells.direction(np.arange(cells.count), mi.Point2f(0.5, 0.5)))
        wrong = np.flatnonzero(back != np.arange(cells.count))
        problems += [f"depth {depth}: leaf {tuple(cells.cells[i])} -> {back[i]}" for i in wrong]
        checked += cells.count
    figures.update(leaves_checked=checked, max_depth=max(CYLINDRICAL_DEEP))
    assert not problems, few(problems)


@pytest.mark.parametrize("depth", (*CYLINDRICAL_DEPTHS, *CYLINDRICAL_DEEP))
def test_cylindrical_map_equal_solid_angle(depth, figures):
    """SD-tree cylindrical map: every leaf has solid angle 4π/4^depth to float precision (all leaves to depth 8,
    random ones at 12, 16, 20)."""
    cells = cylindrical_cells(depth)
    # Large leaves have long curved edges: more boundary points keep the chords' error below float precision.
    geometry = bin_geometry(cells.direction, np.arange(cells.count), steps=max(16, 256 >> depth))
    excess = equal_area_excess(geometry, cells.solid_angle)
    worst = int(np.argmax(excess))
    figures.update(leaves=cells.count,
                   max_relative_error=float(np.abs(geometry.solid_angle / cells.solid_angle - 1).max()))
    assert excess[worst] <= 1, (f"depth {depth}: leaf {tuple(cells.cells[worst])} has solid angle "
                                f"{geometry.solid_angle[worst]:.9g} instead of {cells.solid_angle:.9g} "
                                f"({excess[worst]:.2f} x perimeter·ε₃₂)")


# Hypothesis: arbitrary float32 vectors, NaN, ±Inf, signed zeros, denormals and the largest values included, in
# batches (one kernel launch checks a whole batch).
ANY_FLOAT32 = st.floats(width=32)
VECTOR_BATCHES = st.lists(st.tuples(ANY_FLOAT32, ANY_FLOAT32, ANY_FLOAT32), min_size=1, max_size=32).map(
    lambda rows: np.array(rows, dtype=np.float32))
PROPERTY_SETTINGS = settings(max_examples=150, deadline=None)


@PROPERTY_SETTINGS
@given(resolution=st.sampled_from(SPHERE_RESOLUTIONS), batch=VECTOR_BATCHES)
def test_sphere_bins_send_any_vector_to_a_bin_that_contains_it(resolution, batch):
    """SphereBins, any float32 vectors (hypothesis): a valid bin that contains the direction, on its hemisphere."""
    bins, geometry = sphere_bins_geometry(resolution)
    assert containment_violations(bins.index, bins.count, geometry, batch, lower_from=bins.count // 2) == []


@PROPERTY_SETTINGS
@given(resolution=st.sampled_from(NORMAL_RESOLUTIONS), batch=VECTOR_BATCHES)
def test_normal_bins_send_any_vector_to_a_bin_that_contains_it(resolution, batch):
    """NormalBins, any float32 vectors (hypothesis): a valid bin that contains the direction."""
    bins, geometry = normal_bins_geometry(resolution)
    assert containment_violations(bins.index, bins.count, geometry, batch) == []


@PROPERTY_SETTINGS
@given(batch=VECTOR_BATCHES)
def test_cylindrical_map_keeps_any_vector_in_the_square_and_round_trips(batch):
    """SD-tree cylindrical map, any float32 vectors (hypothesis): a point of [0,1)² that maps back to the
    direction."""
    assert cylindrical_violations(batch) == []


@PROPERTY_SETTINGS
@given(resolution=st.sampled_from(SPHERE_RESOLUTIONS),
       bin_and_sample=st.tuples(st.integers(0, 2 * 64 * 64 - 1), st.floats(0, 1), st.floats(0, 1)))
def test_sphere_bin_directions_lie_in_their_bin(resolution, bin_and_sample):
    """SphereBins (hypothesis): `direction(k, s)` for any s ∈ [0,1]² (boundary included) lies in bin k (within
    its measured radius)."""
    bins, geometry = sphere_bins_geometry(resolution)
    k, u, v = bin_and_sample
    k %= bins.count
    d = unit(to_numpy(bins.direction(mi.UInt32([k]), mi.Point2f([u], [v]))))
    assert angle_between(d, geometry.centre[[k]])[0] <= geometry.reach(k)
