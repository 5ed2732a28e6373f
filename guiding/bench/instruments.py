"""The benchmark's instruments (``python -m guiding bench``, its cost breakdown): guides with parts of their work
switched off or changed, so that the breakdown times each part apart. Their images are not meant to be correct.

Grid guides (subclasses of :class:`~guiding.guides.grid.guide.GridGuide` that override its bounce's protected steps):
  :class:`ClassifyStage`   ``[classify]``: the vertex looked up and the guided mask computed (and used), then the
                           BSDF's sample;
  :class:`SampleStage`     ``[+sample]``: the guided directions drawn too (with the BSDF's weights; the mixture's
                           density is not evaluated);
  :class:`PdfStage`        ``[+pdf]``: the exact mixture density too (the full sampler, nothing recorded);
  :class:`BsdfPathsStage`  ``[bsdf paths]``: the whole bounce computed and recorded, but the path continues along the
                           BSDF's own sample, so that its cost is the guide's work at ``brdf``'s paths, apart from what
                           the guided paths themselves cost (they differ in length and in where they go);
  :class:`HotRowsStage`    ``[hot rows]`` (the rejection samplers' ``bins`` proposal): the whole bounce computed and
                           recorded, but every vertex draws from and looks densities up in the first pair's alias row,
                           a few KiB that stay in the core's cache, instead of its own pair's: what the rows' cache
                           misses cost the bounce, and what drawing every vertex's directions from one distribution
                           changes (a part of its gain, README). Its paths are about as long as the method's, since a
                           bin of the other pair's row that lies below the vertex's normal bin is rejected, and the
                           BSDF's direction taken (``hemi_inv`` would take it: its paths were a third shorter).
The three partial stages record in their first :data:`TRAINING_PASSES` passes only (so that their tables are learnt),
then stop.

Tree guides: :class:`SamplingOnly` (``[no record]``), the method's own trees sampled by a kernel that records nothing.
"""

from __future__ import annotations

from dataclasses import replace

import drjit as dr
import mitsuba as mi

from guiding.guides.base import NoPathState, UpdateResult
from guiding.guides.grid.guide import GridGuide
from guiding.guides.grid.strategy import grid_strategy
from guiding.guides.methods import resolve
from guiding.guides.parameters import GridParameters, with_overrides

#: Passes a partial stage records before it stops (the benchmark's warm-up passes).
TRAINING_PASSES = 2


class GridInstrument(GridGuide):
    """A grid guide instrumented for the cost breakdown."""

    @staticmethod
    def applies_to(parameters: GridParameters) -> bool:
        """Whether the instrument measures something for a guide of ``parameters`` (the breakdown leaves it out
        where not)."""
        return True


class _PartialBounce(GridInstrument):
    """A grid guide whose bounce stops short of the whole: it learns its tables in its first
    :data:`TRAINING_PASSES` passes, then records nothing."""

    def __init__(self, parameters: GridParameters | None = None, name: str | None = None, **overrides):
        super().__init__(parameters, name, **overrides)
        self._updates = 0

    def update(self, spp_done: int) -> UpdateResult:
        result = super().update(spp_done)
        self._updates += 1
        return result

    def records(self) -> bool:
        return self._updates < TRAINING_PASSES


class ClassifyStage(_PartialBounce):
    """``[classify]``: the guided mask is computed (and used), the BSDF samples."""

    def _guided_sample(self, sampler, si, bsdf, bsdf_ctx, vertex, lambertian=None):
        guided = vertex.guided
        bs, weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(guided), sampler.next_2d(guided), guided)
        return bs, weight * 0.5, self._index_taken(si, si.to_world(bs.wo))


class SampleStage(_PartialBounce):
    """``[+sample]``: the guided directions, the BSDF's weights."""

    def _guided_sample(self, sampler, si, bsdf, bsdf_ctx, vertex, lambertian=None):
        mixture = self._draw_both(sampler, si, bsdf, bsdf_ctx, vertex, lambertian)
        bs = mixture.bs
        bs.wo = dr.select(mixture.guide.taken, mixture.guide_wo, bs.wo)
        return bs, mixture.bsdf_weight, self._index_taken(si, si.to_world(bs.wo))


class PdfStage(_PartialBounce):
    """``[+pdf]``: the full sampler, nothing recorded after the training passes."""


class BsdfPathsStage(GridInstrument):
    """``[bsdf paths]``: the whole bounce, the path continuing along the BSDF's sample."""

    def _guided_sample(self, sampler, si, bsdf, bsdf_ctx, vertex, lambertian=None):
        mixture = self._draw_both(sampler, si, bsdf, bsdf_ctx, vertex, lambertian)
        self._weigh(si, vertex, mixture)
        # Everything above is kept alive by an opaque zero; the path follows the BSDF.
        keep = dr.opaque(mi.Float, 0) * (mixture.weight + mi.Float(mixture.guide_wo.x))
        bs = mixture.bs
        return bs, mixture.bsdf_weight + keep, self._index_taken(si, si.to_world(bs.wo))


class HotRowsStage(GridInstrument):
    """``[hot rows]``: every vertex on the first pair's alias row; only for samplers that draw a bin, then a
    direction in it by rejection (a ValueError for the others, whose paths would take another row's bins below the
    surface)."""

    def __init__(self, parameters: GridParameters | None = None, name: str | None = None, **overrides):
        parameters = with_overrides(parameters or GridParameters(), overrides)
        if not self.applies_to(parameters):
            raise ValueError(f"the hot rows instrument is for the rejection samplers' bins proposal, not "
                             f"{parameters.sampler} ({grid_strategy(parameters).proposal_name or 'no proposal'})")
        super().__init__(parameters, name)

    @staticmethod
    def applies_to(parameters: GridParameters) -> bool:
        return grid_strategy(parameters).draws_bins_by_rejection

    def _pair_row(self, vertex):
        return mi.UInt32(0)


def instrumented_guide(method: str, instrument: type[GridInstrument]) -> GridInstrument:
    """A fresh guide of grid method ``method`` (a name of :mod:`guiding.guides.methods`) with ``instrument``, one of
    this module's stages; refused, as ``make_guide`` refuses it, if its tables would exceed the memory limit."""
    return replace(resolve(method), guide=lambda parameters, label: instrument(parameters, name=label)).build()


class SamplingOnly:
    """The guide of another integrator, sampled as it stands, recording and learning nothing (the benchmark's tree
    ``[no record]`` stage): the same trees as the method's own passes at every pass (a guide of its own that stopped
    recording would keep the coarse trees of the warm-up passes, and the increment of recording would include the
    cost of the finer trees). Its passes must follow the method's (prepared after it, interleaved after it)."""

    def __init__(self, guide):
        self._guide = guide

    def __getattr__(self, name):
        return getattr(self._guide, name)

    def records(self) -> bool:
        return False

    def trace_key(self) -> tuple:
        return ("sampling only", *self._guide.trace_key())

    def prepare(self, scene: mi.Scene) -> None:
        """Nothing: the method's integrator prepared the guide."""

    def new_paths(self, size: int, max_depth: int):
        return NoPathState()

    def update_due(self, spp_done: int) -> None:
        return None

    def update(self, spp_done: int) -> UpdateResult:
        return UpdateResult({})
