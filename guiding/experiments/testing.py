"""Checks of a guide's sampler, for this project's tests and for a user's own guide: at the vertices of a real
scene, and its density at one synthetic vertex.

A sampler that passes its chi-square test can still be heavy-tailed in a render: the density is right, but where
it is far below ``f·cos`` the weight ``f·cos/p`` of a rare direction is huge, and a few paths carry the image.
:func:`single_bounce_weights` measures that weight where it matters, at diffuse vertices that camera paths reach,
after the guide has trained on the scene (:func:`train`).

    vertices = scene_vertices(scene, count=1000)
    weights = single_bounce_weights(guide, vertices, samples=4096)
    weights.mean / weights.albedo      # ≈ 1 for an unbiased sampler
    weights.maximum / weights.albedo   # the single-bounce bound

Before that, a sampler's density is checked where it is drawn: :class:`GuideAdapter` puts a guide at one synthetic
vertex (:func:`diffuse_vertex`) and hands its sampler to Mitsuba's chi-square test, as ``mitsuba.chi2.BSDFAdapter``
does for a BSDF:

    adapter = GuideAdapter(guide, normal=(0, 0, 1))
    passed, messages = chi_square(adapter.sample_func, adapter.pdf_func, sample_count=400_000, res=64, ires=32)
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from guiding.guides.base import Guide


def train(scene: mi.Scene, guide: Guide, spp: int, seed: int = 0, max_depth: int = 16) -> Guide:
    """Train ``guide`` on ``scene`` as a progressive render of ``spp`` samples per pixel would; returns it."""
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.render.progressive import Budget, render

    props = mi.Properties()
    props["max_depth"] = max_depth
    render(scene, GuidedPathIntegrator(props, guide=guide), Budget(spp=spp), seed=seed, progress=False)
    return guide


def scene_vertices(scene: mi.Scene, count: int, seed: int = 0, max_bounces: int = 3) -> mi.SurfaceInteraction3f:
    """``count`` surface interactions with a purely diffuse BSDF of non-zero albedo that camera paths reach.

    Camera rays through uniformly random film positions are followed by BSDF sampling for up to ``max_bounces``
    bounces; every diffuse vertex met is a candidate, and ``count`` of them are drawn at random (so vertices deep in
    the scene, away from the camera's first hits, are included)."""
    from guiding.guides.grid.guide import guidable

    lanes = max(4 * count, 1 << 14)
    sensor = scene.sensors()[0]
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, lanes)
    ray, _ = sensor.sample_ray(0.0, 0.5, sampler.next_2d(), sampler.next_2d())
    found = []
    active = mi.Bool(True)
    for _ in range(max_bounces):
        si = scene.ray_intersect(ray, active)
        bsdf = si.bsdf(ray)
        keep = active & si.is_valid() & guidable(bsdf) & (dr.mean(bsdf.eval_diffuse_reflectance(si, active)) > 0)
        index = dr.compress(keep)
        if dr.width(index):
            found.append(dr.gather(mi.SurfaceInteraction3f, si, index))
        bs, weight = bsdf.sample(mi.BSDFContext(), si, sampler.next_1d(), sampler.next_2d(), active & si.is_valid())
        active &= si.is_valid() & dr.any(weight != 0)
        ray = si.spawn_ray(si.to_world(bs.wo))
    candidates = _concatenate(found)
    total = dr.width(candidates.p)
    if total < count:
        raise ValueError(f"only {total} diffuse vertices found in the scene, {count} asked for")
    pick = np.sort(np.random.default_rng(seed).choice(total, count, replace=False))
    return dr.gather(mi.SurfaceInteraction3f, candidates, mi.UInt32(pick))


def _concatenate(parts: list[mi.SurfaceInteraction3f]) -> mi.SurfaceInteraction3f:
    widths = [dr.width(p.p) for p in parts]
    result = dr.zeros(mi.SurfaceInteraction3f, sum(widths))
    start = 0
    for part, width in zip(parts, widths):
        dr.scatter(result, part, dr.arange(mi.UInt32, start, start + width))
        start += width
    return result


@dataclass
class BounceWeights:
    """Per vertex, over the samples drawn there (each averaged over RGB): the albedo ρ, and the mean, second
    moment and maximum of the single-bounce weight ``f·cos/p``."""

    albedo: np.ndarray
    mean: np.ndarray
    second_moment: np.ndarray
    maximum: np.ndarray
    samples: int

    def mean_ratio(self) -> tuple[float, float]:
        """Σ mean / Σ albedo and its standard error: 1 for an unbiased sampler."""
        variance = np.maximum(self.second_moment - self.mean ** 2, 0) / self.samples
        return float(self.mean.sum() / self.albedo.sum()), float(np.sqrt(variance.sum()) / self.albedo.sum())

    def largest_ratio(self) -> float:
        """The largest weight relative to its vertex's albedo."""
        return float(np.max(self.maximum / self.albedo))

    def second_moment_ratio(self) -> float:
        """Σ second moment / Σ albedo²: 1 for cosine sampling of a diffuse BSDF, the variance a bounce adds."""
        return float(self.second_moment.sum() / (self.albedo ** 2).sum())


def single_bounce_weights(guide: Guide, vertices: mi.SurfaceInteraction3f, samples: int = 4096,
                          seed: int = 0, scene: mi.Scene | None = None, batch: int = 1 << 22) -> BounceWeights:
    """Draw ``samples`` directions with ``guide`` at each of ``vertices`` and summarise their weights."""
    count = dr.width(vertices.p)
    per_batch = max(1, batch // samples)
    sums, squares, maxima = (np.zeros(count) for _ in range(3))
    ctx = mi.BSDFContext()
    for first in range(0, count, per_batch):
        lanes = min(per_batch, count - first) * samples
        owner = mi.UInt32(first) + dr.arange(mi.UInt32, lanes) // samples
        si = dr.gather(mi.SurfaceInteraction3f, vertices, owner)
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(seed + first, lanes)
        _, weight = guide.sample(scene, sampler, si, si.bsdf(), ctx, dr.full(mi.Bool, True, lanes))
        w = np.array(dr.mean(weight), dtype=np.float64).reshape(-1, samples)
        rows = slice(first, first + w.shape[0])
        sums[rows], squares[rows], maxima[rows] = w.mean(1), (w ** 2).mean(1), w.max(1)
    albedo = np.array(dr.mean(vertices.bsdf().eval_diffuse_reflectance(vertices)), dtype=np.float64)
    return BounceWeights(albedo, sums, squares, maxima, samples)


# =====================================================================================================================
#  A guide's sampler at one synthetic vertex
# =====================================================================================================================
def diffuse_vertex(normal, size: int, position=(0.05, 0.05, 0.05)) -> tuple[mi.SurfaceInteraction3f, mi.BSDFPtr]:
    """``size`` lanes of one surface interaction at ``position`` with shading ``normal`` (normalised: a frame built
    on a longer vector is not orthonormal, and ``to_world(to_local(ω))`` then misses ω by ~1e-4), reached from the
    normal's side (``wi`` is the local +z), and a diffuse BSDF of albedo 0.5 for it."""
    si = dr.zeros(mi.SurfaceInteraction3f, size)
    si.p = mi.Point3f(*position)
    si.n = dr.normalize(mi.Normal3f(*(float(c) for c in normal)))
    si.sh_frame = mi.Frame3f(si.n)
    si.wi = mi.Vector3f(0, 0, 1)
    return si, mi.BSDFPtr(_diffuse_bsdf())


@functools.lru_cache(maxsize=None)
def _diffuse_bsdf() -> mi.BSDF:
    # Kept alive here: a BSDFPtr does not own the object it points to.
    return mi.load_dict({"type": "diffuse", "reflectance": 0.5})


class ReplaySampler:
    """A stand-in for ``mi.Sampler`` that hands out the dimensions of a chi-square test's sample, in order."""

    def __init__(self, sample):
        self.dims = [sample[i] for i in range(len(sample))]

    def next_1d(self, active=True):
        return self.dims.pop(0)

    def next_2d(self, active=True):
        return mi.Point2f(self.dims.pop(0), self.dims.pop(0))


class GuideAdapter:
    """``guide``'s sampler at a vertex made by :func:`diffuse_vertex`, in the form ``mitsuba.chi2.ChiSquareTest``
    takes: ``sample_func`` maps the test's samples to the world directions ``guide.sample`` draws, ``pdf_func``
    gives ``guide.pdf`` of world directions.

    Parameters:
      normal, position: the vertex (see :func:`diffuse_vertex`).
      bsdf: the vertex's BSDF (a ``mi.BSDF``); the diffuse one of :func:`diffuse_vertex` by default.
      replay: the guide draws the test's own sample dimensions, in order (:class:`ReplaySampler`; give the test the
        ``sample_dim`` the guide consumes). By default every call draws from an independent sampler seeded with
        ``seed`` and the test's sample only sets the number of lanes: a rejection sampler consumes a number of
        dimensions no test can know in advance.
    """

    def __init__(self, guide: Guide, normal=(0, 0, 1), position=(0.05, 0.05, 0.05), bsdf: mi.BSDF | None = None,
                 replay: bool = False, seed: int = 7):
        self.guide, self.normal, self.position, self.bsdf = guide, normal, position, bsdf
        self.replay, self.seed = replay, seed

    def vertex(self, size: int) -> tuple[mi.SurfaceInteraction3f, mi.BSDFPtr]:
        """The vertex, ``size`` lanes wide, and its BSDF."""
        si, diffuse = diffuse_vertex(self.normal, size, self.position)
        return si, diffuse if self.bsdf is None else mi.BSDFPtr(self.bsdf)

    def draw(self, sample) -> tuple[mi.SurfaceInteraction3f, mi.BSDFSample3f, mi.Spectrum]:
        """The vertex, and what ``guide.sample`` returns there for the test's ``sample``."""
        size = dr.width(sample)
        if self.replay:
            sampler = ReplaySampler(sample)
        else:
            sampler = mi.load_dict({"type": "independent"})
            sampler.seed(self.seed, size)
        si, bsdf = self.vertex(size)
        bs, weight = self.guide.sample(None, sampler, si, bsdf, mi.BSDFContext(), dr.full(mi.Bool, True, size))
        return si, bs, weight

    def sample_func(self, sample) -> mi.Vector3f:
        si, bs, _ = self.draw(sample)
        return si.to_world(bs.wo)

    def pdf_func(self, wo: mi.Vector3f) -> mi.Float:
        size = dr.width(wo)
        si, bsdf = self.vertex(size)
        return self.guide.pdf(si, bsdf, mi.BSDFContext(), si.to_local(wo), dr.full(mi.Bool, True, size))


def chi_square(sample_func, pdf_func, domain=None, test_count: int = 1, **options) -> tuple[bool, str]:
    """Mitsuba's chi-square test: do the samples of ``sample_func`` follow the density ``pdf_func`` reports? (It
    also fails a density that does not integrate to 1.) ``domain`` is the sphere by default (:func:`sphere_domain`),
    ``test_count`` the number of tests the caller runs (the significance level is Šidák-corrected for them) and
    ``options`` go to ``ChiSquareTest`` (``sample_dim``, ``sample_count``, ``res``, ``ires``). Returns the verdict
    and the test's messages, printing nothing."""
    from mitsuba.chi2 import ChiSquareTest

    domain = domain or sphere_domain(options.get("res", 101))
    test = ChiSquareTest(domain=domain, sample_func=sample_func, pdf_func=pdf_func, **options)
    return test.run(test_count=test_count, quiet=True), test.messages


def sphere_domain(res: int, margin: float = 1e-3):
    """Mitsuba's sphere of (φ, −cos θ) for a histogram of resolution ``res``, whose density evaluations stay
    ``margin`` of a cell inside their cell. Mitsuba's trapezoid rule puts a cell's end nodes 1e-4 of a step (3e-7
    rad at ``res`` 64) inside it; a direction made of such a node came back on the other side of the edge at some
    edges (φ = −π/2, in float32), and a density with a jump there (a D-tree's leaf edges, which fall on the
    histogram's) was integrated with the neighbour's value, which the test reads as the sampler's error."""
    from mitsuba.chi2 import SphericalDomain

    class CellInterior(SphericalDomain):
        cells = mi.ScalarVector2u(max(int(res / SphericalDomain().aspect()), 1), res)   # as ChiSquareTest lays out

        def map_forward(self, p):
            low, high = self.bounds().min, self.bounds().max
            inside = []
            for axis in range(2):
                size = (high[axis] - low[axis]) / self.cells[axis]
                t = (mi.Float64(p[axis]) - low[axis]) / size      # float64: a node 1e-4 of a step in keeps its side
                cell = dr.floor(t)
                inside.append(mi.Float(low[axis] + (cell + dr.clip(t - cell, margin, 1 - margin)) * size))
            return super().map_forward(mi.Point2f(*inside))

    return CellInterior()
