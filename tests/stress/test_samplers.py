"""Samplers: densities and weights at extreme samples and at the worst acceptance rate a table can produce.

hemi_inv recomputed the density of a direction from its bin, and a direction drawn at a bin's edge could be looked
up in a neighbour whose probability is below float32 resolution: pdf 0 above the surface (policies with ε → 0). It
now reports the density of the bin it drew in (`GridSampler.pdf(chosen_bin=…, bin_density=…)`). The
rejection loop is capped by construction; the chi-square tests at the worst acceptance rates check that the fallback
share is in the pdf.
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from guiding.experiments.testing import GuideAdapter, chi_square, diffuse_vertex
from arrays import few, unit
from hostile import FixedSampler, extreme_samples, sample_violations, sampler_normals, spiked_guide
from sdtree_parts import DEGENERATE_TREES, TREE_METHODS, sample_from, tree_guide

#: Rejection samplers at the worst acceptance rate a table gives them: (method, spike direction relative to the
#: normal). Uniform proposals are accepted with probability N/(2π·M′): lowest when all of P sits in one bin in front
#: of the surface (≈ 1/D² for hemi_rej). Policy proposals are accepted with the policy's mean cosine on the
#: arrival side: about 0 when all of P sits behind the surface.
WORST_ACCEPTANCE = (("sarsa-hemi_rej", "front"), ("ours-uniform-proposals", "front"), ("ours", "behind"),
                    ("ours", "grazing"))


def sample_at_extremes(guide, normal, position=(0.05, 0.05, 0.05)):
    """What ``guide`` samples at a diffuse vertex for every extreme sample (:func:`~hostile.extreme_samples`)."""
    u, uv = extreme_samples()
    si, bsdf = diffuse_vertex(normal, len(u), position)
    bs, weight = guide.sample(None, FixedSampler(mi.Float(u), mi.Point2f(uv[:, 0], uv[:, 1])), si, bsdf,
                              mi.BSDFContext(), dr.full(mi.Bool, True, len(u)))
    return si, bs, weight


@pytest.mark.parametrize("method", ["sarsa-sphere_inv", "sarsa-hemi_inv"])
def test_grid_samplers_extreme_samples(method, figures):
    """Grid samplers that draw from tables without a loop (sphere_inv, hemi_inv) at u, uv ∈ {0, 0.5, 1 − 2⁻²⁴} on the
    most peaked tables: every direction returned above the surface has a positive, finite pdf, and every weight is
    finite."""
    lanes = 0
    for normal in sampler_normals():
        # The spike in front of the surface, behind it, and at grazing incidence.
        for spike in (normal, -normal, np.cross(normal, (0.6, 0.8, 0.0)) + 1e-3 * normal):
            si, bs, weight = sample_at_extremes(spiked_guide(method, spike, normal), normal)
            problems = sample_violations(si, bs, weight)
            assert not problems, f"normal {tuple(normal)}, spike {tuple(spike)}: {few(problems)}"
            lanes += dr.width(bs.wo)
    figures["lanes_checked"] = lanes


@pytest.mark.parametrize("method, where", WORST_ACCEPTANCE)
def test_rejection_worst_acceptance(method, where, figures):
    """Rejection samplers at the worst acceptance rate a table can produce (all of P in one bin, ε → 0): the loop
    stops after max_proposals, every weight is finite, every direction above the surface has pdf > 0, and the
    fallback is correctly weighted (chi-square on the sampled density)."""
    normal = np.array([0.0, 0.0, 1.0], dtype=np.float32)
    spike = {"front": normal, "behind": -normal,
             "grazing": unit(np.cross(normal, (0.6, 0.8, 0.0)) + 0.05 * normal)[0]}[where]
    guide = spiked_guide(method, spike, normal)
    size = 100_000
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(1, size)
    si, bsdf = diffuse_vertex(normal, size)
    bs, weight = guide.sample(None, sampler, si, bsdf, mi.BSDFContext(), dr.full(mi.Bool, True, size))
    stats = guide.update(spp_done=10_000).stats        # reads (and resets) the sampler's counters
    per_sample = stats["proposals_per_sample"] or 0.0
    figures.update(acceptance_rate=stats["acceptance_rate"], proposals_per_sample=per_sample)
    problems = sample_violations(si, bs, weight)
    assert not problems, few(problems)
    assert stats["guided_samples"] == size, f"{stats['guided_samples']} of {size} samples guided"
    assert per_sample <= guide.parameters.max_proposals, \
        f"{per_sample:.1f} proposals per sample, cap {guide.parameters.max_proposals}"
    adapter = GuideAdapter(guide, normal)
    passed, messages = chi_square(adapter.sample_func, adapter.pdf_func, test_count=len(WORST_ACCEPTANCE),
                                  sample_count=200_000, res=64, ires=32)
    assert passed, f"chi-square test failed: {messages.strip().splitlines()[-1] if messages else ''}"


@pytest.mark.parametrize("method", TREE_METHODS)
def test_sdtree_sampler_extremes(method, figures):
    """SD-tree sampler on degenerate D-trees (all energy in one leaf at depth 20, denormal and 1e30 energies) at
    samples in {0, 0.5, 1 − 2⁻²⁴}: every direction above the surface has pdf > 0, every weight is finite."""
    guide = tree_guide(method)
    lanes = 0
    for name, tree in DEGENERATE_TREES.items():
        sample_from(guide, method, tree)
        for normal in sampler_normals():
            si, bs, weight = sample_at_extremes(guide, normal, position=(0.3, 0.4, 0.0))
            problems = sample_violations(si, bs, weight)
            assert not problems, f"{name}, normal {tuple(normal)}: {few(problems)}"
            lanes += dr.width(bs.wo)
    figures["lanes_checked"] = lanes
