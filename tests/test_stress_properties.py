"""Property tests (hypothesis) for the direction ↔ bin maps: arbitrary float32 vectors, NaN and Inf included.

The checks are the stress module's (:mod:`guiding.stress`), which its registered cases also run on fixed sets of
poles, seams and degenerate inputs; here hypothesis searches the whole float32 range for a counterexample.
"""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from guiding import stress

#: Any float32: NaN, ±Inf, signed zeros, denormals and the largest values included.
ANY_FLOAT32 = st.floats(width=32)
#: A batch of vectors (one kernel launch checks them all).
VECTORS = st.lists(st.tuples(ANY_FLOAT32, ANY_FLOAT32, ANY_FLOAT32), min_size=1, max_size=32).map(
    lambda rows: np.array(rows, dtype=np.float32))
PROPERTY_SETTINGS = settings(max_examples=150, deadline=None)


@PROPERTY_SETTINGS
@given(resolution=st.sampled_from(stress.SPHERE_RESOLUTIONS), vectors=VECTORS)
def test_sphere_bins_send_any_vector_to_a_bin_that_contains_it(resolution, vectors):
    bins, geometry = stress.sphere_bins_geometry(resolution)
    assert stress.containment_violations(bins.index, bins.count, geometry, vectors,
                                         lower_from=bins.count // 2) == []


@PROPERTY_SETTINGS
@given(resolution=st.sampled_from(stress.NORMAL_RESOLUTIONS), vectors=VECTORS)
def test_normal_bins_send_any_vector_to_a_bin_that_contains_it(resolution, vectors):
    bins, geometry = stress.normal_bins_geometry(resolution)
    assert stress.containment_violations(bins.index, bins.count, geometry, vectors) == []


@PROPERTY_SETTINGS
@given(vectors=VECTORS)
def test_cylindrical_map_keeps_any_vector_in_the_square_and_round_trips(vectors):
    assert stress.cylindrical_violations(vectors) == []


@PROPERTY_SETTINGS
@given(resolution=st.sampled_from(stress.SPHERE_RESOLUTIONS),
       bin_and_sample=st.tuples(st.integers(0, 2 * 64 * 64 - 1), st.floats(0, 1), st.floats(0, 1)))
def test_sphere_bin_directions_lie_in_their_bin(resolution, bin_and_sample):
    """``direction(k, s)`` for any s ∈ [0,1]² (boundary included) lies in bin k (within its measured radius)."""
    import mitsuba as mi

    bins, geometry = stress.sphere_bins_geometry(resolution)
    k, u, v = bin_and_sample
    k %= bins.count
    d = stress.unit(stress.to_numpy(bins.direction(mi.UInt32([k]), mi.Point2f([u], [v]))))
    assert stress.angle_between(d, geometry.centre[[k]])[0] <= geometry.reach(k)
