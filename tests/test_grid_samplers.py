"""Every grid sampler draws directions with exactly the density it reports (Mitsuba's chi-square test)."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from guiding.guides import PROPOSALS, SAMPLERS
from guiding.guides.grid.guide import GridGuide
from guiding.guides.grid.refinement import REFINE_VISITS
from guiding.experiments.testing import GuideAdapter, chi_square


def _trained_guide(sampler: str, proposal: str, D: int, table: str, normal, visits: float = 1,
                   **overrides) -> GridGuide:
    """A guide whose Q in cell 0 is random: ``peaked`` (a few bright bins) or ``flat`` (within 10 %), each entry
    learned from ``visits`` targets."""
    guide = GridGuide(spatial_resolution=2, directional_resolution=D, rule="sarsa", sampler=sampler,
                      proposal=proposal, **overrides)
    record = guide.record_table
    record.set_bounds(mi.BoundingBox3f(mi.ScalarPoint3f(0), mi.ScalarPoint3f(1)))
    rng = np.random.default_rng(D + len(table) + SAMPLERS.index(sampler))
    B = record.bins.count
    q = np.zeros(record.cells * B)
    if table == "peaked":
        q[rng.choice(B, 3, replace=False)] = rng.uniform(50, 100, 3)
        q[:B] += rng.uniform(0, 0.5, B)
    else:
        q[:B] = 1 + 0.1 * rng.random(B)
    record.acc_sum = mi.Float64(q * visits)
    record.acc_count = mi.Float64(np.full_like(q, visits))
    if record.needs_pairs:
        pair = record.pair(mi.UInt32(0), mi.Vector3f(normal))
        dr.scatter(record.visited, mi.UInt32(1), pair)
    guide.update(spp_done=150)   # ε = 0.1^1.5: the policy follows Q closely
    return guide


#: Samplers with each proposal they take (only the rejection samplers propose).
CONFIGURATIONS = [(sampler, proposal) for sampler in SAMPLERS
                  for proposal in (PROPOSALS if sampler.startswith("hemi_rej") else PROPOSALS[:1])]

#: Number of chi-square tests in this file: the significance level is Šidák-corrected for them, as Mitsuba does.
TEST_COUNT = len(CONFIGURATIONS) * 2 * 2 * 2

#: An axis normal (a normal-bin centre), and a tilted one 12.5° from its normal bin's centre (near a corner of the
#: bin), where the memo tables are used away from the normal they were computed for.
NORMALS = {"tilted": (0.4929, 0.1870, 0.8498), "axis": (0.0, 0.0, 1.0)}


@pytest.mark.parametrize("sampler, proposal", CONFIGURATIONS)
@pytest.mark.parametrize("D", [4, 16])
@pytest.mark.parametrize("table", ["peaked", "flat"])
@pytest.mark.parametrize("normal_name", list(NORMALS))
def test_sampler_pdf_matches_samples(sampler, proposal, D, table, normal_name):
    normal = NORMALS[normal_name]
    guide = _trained_guide(sampler, proposal, D, table, normal)
    adapter = GuideAdapter(guide, normal)
    # 64 integration points per cell side: the densities step along great circles that no cell boundary follows
    # (bin edges, the uniform share's horizon), and 32 integrated them 0.15 % low (a false rejection at p = 3e-5).
    passed, messages = chi_square(adapter.sample_func, adapter.pdf_func, test_count=TEST_COUNT, sample_count=400_000,
                                  res=64, ires=64)
    assert passed, messages


#: Smooth BSDFs that ``guided_bsdfs="smooth"`` guides (ours-plus): the mixture with their own sampling.
SMOOTH_BSDFS = {"roughplastic": {"type": "roughplastic", "alpha": 0.3},
                "roughconductor": {"type": "roughconductor", "alpha": 0.2}}
SMOOTH_CONFIGURATIONS = [("hemi_rej_plus", "bins"), ("hemi_inv", "bins")]


@pytest.mark.parametrize("sampler, proposal", SMOOTH_CONFIGURATIONS)
@pytest.mark.parametrize("bsdf_name", list(SMOOTH_BSDFS))
@pytest.mark.parametrize("normal_name", list(NORMALS))
def test_smooth_bsdf_mixture_pdf_matches_samples(sampler, proposal, bsdf_name, normal_name):
    """At a glossy vertex the guide mixes with the BSDF's own sampling (share ≥ smooth_bsdf_share) and reports
    the exact mixture density."""
    normal = NORMALS[normal_name]
    guide = _trained_guide(sampler, proposal, 16, "peaked", normal, guided_bsdfs="smooth")
    bsdf = mi.load_dict(SMOOTH_BSDFS[bsdf_name])
    adapter = GuideAdapter(guide, normal, bsdf=bsdf)
    si, bsdf_ptr = adapter.vertex(1)
    assert guide._vertex(si, bsdf_ptr, mi.Bool(True), mark_visited=False).guided[0], "the glossy vertex is not guided"
    passed, messages = chi_square(adapter.sample_func, adapter.pdf_func,
                                  test_count=len(SMOOTH_CONFIGURATIONS) * len(SMOOTH_BSDFS) * len(NORMALS),
                                  sample_count=400_000, res=64, ires=64)
    assert passed, messages


@pytest.mark.parametrize("sub_resolution", [2, 8])
@pytest.mark.parametrize("bsdf_name", ["diffuse", "roughplastic"])
@pytest.mark.parametrize("normal_name", list(NORMALS))
def test_refined_bins_pdf_matches_samples(sub_resolution, bsdf_name, normal_name):
    """Bins refined into sub-bins (ours-plus): a sub-bin from its learned distribution, a uniform direction in it,
    and the exact density; the sub-bins' means are random, one bright, and a third unvisited (the bin's Q stands
    in)."""
    normal = NORMALS[normal_name]
    guide = _trained_guide("hemi_rej_plus", "bins", 16, "peaked", normal, guided_bsdfs="smooth",
                           sub_resolution=sub_resolution, visits=REFINE_VISITS * sub_resolution ** 2)
    refinement = guide.record_table.refinement
    assert refinement.used == 3, "the three bright bins of the peaked cell are refined"
    rng = np.random.default_rng(sub_resolution)
    size = refinement.capacity * refinement.sub
    visited = rng.random(size) > 1 / 3
    means = rng.exponential(size=size) ** 4 * 100
    visited[1::refinement.sub] = True
    means[1::refinement.sub] = 2000      # one bright sub-bin each: the refined bins are sampled from their sub-bins
    visits = 64 * visited
    refinement.acc_sum = mi.Float64(means * visits)
    refinement.acc_count = mi.Float64(visits.astype(np.float64))
    guide.update(spp_done=150)
    assert refinement.sampled_count == 3, "far from uniform: all three are sampled"
    bsdf = mi.load_dict(SMOOTH_BSDFS[bsdf_name]) if bsdf_name in SMOOTH_BSDFS else None
    adapter = GuideAdapter(guide, normal, bsdf=bsdf)
    passed, messages = chi_square(adapter.sample_func, adapter.pdf_func, test_count=2 * 2 * len(NORMALS),
                                  sample_count=400_000, res=64, ires=64)
    assert passed, messages
