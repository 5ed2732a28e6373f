"""What the grid guide knows about a path vertex: which BSDFs it guides, what it hands from ``locate`` to ``sample``
and ``record`` (:class:`GridVertex`), and what its sampler reads at a vertex (:class:`SamplerVertex`)."""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from guiding.guides.grid.lambertian import LambertianVertex
from guiding.guides.grid.record import PairMemo


def guidable(bsdf: mi.BSDFPtr, smooth: bool = False) -> mi.Bool:
    """Purely diffuse reflection: the BSDFs the paper guides (glossy, delta and transmissive lobes are not). With
    ``smooth``, every reflecting BSDF without a delta, null or transmissive lobe (rough plastic and conductors too)."""
    flags, F = bsdf.flags(), mi.BSDFFlags
    reflects = F.DiffuseReflection | (F.GlossyReflection if smooth else 0)
    excluded = F.Delta | F.DiffuseTransmission | F.GlossyTransmission | (F.Null if smooth else F.Glossy)
    return ((flags & int(reflects)) != 0) & ((flags & int(excluded)) == 0)


def arrival_side(si: mi.SurfaceInteraction3f) -> mi.Float:
    """+1 or −1: the side of the surface the path arrived on, where guided directions must leave."""
    return dr.select(si.wi.z < 0, -1.0, 1.0)


@dataclass
class GridVertex:
    """What the path loop hands from :meth:`GridGuide.locate` to ``sample`` and ``record`` at a vertex: the lanes
    the guide may guide (the BSDF flags), and the record index of the direction ``sample`` took (left None by an
    untrained guide and by refined bins, whose record index ``record`` computes: the sampler's bin of a refined
    entry's unrefined neighbour does not say the sub-bin), and, for Expected SARSA's record and next-event
    estimation, the albedo of Lambertian BSDFs read at the ``guidable`` lanes (sampling computes their BSDF from it;
    None: not read yet)."""

    guidable: mi.Bool
    index: mi.UInt32 = None
    lambertian: LambertianVertex = None


@dataclass
class SamplerVertex:
    """Per-lane facts about a vertex that a sampler reads: the guide finds the cell, the side and (where the record
    keeps pair tables) the (cell, normal bin) pair, its memo and the alias row it draws from; the sampler's
    ``classify`` narrows ``guided`` to the lanes it guides and sets the rest."""

    guided: mi.Bool
    cell: mi.UInt32
    side: mi.Float
    pair: mi.UInt32 = None
    memo: PairMemo = None          # the pair's N, alias row, M and in-bin miss share
    row: mi.UInt32 = None          # the row of ``hemi_alias`` it draws from and reads densities in
    centre: mi.Vector3f = None     # n_c, the normal bin's centre on the arrival side (world; rejection samplers)
    bsdf_share: mi.Float = None    # α of the mixture; ≥ smooth_bsdf_share where the BSDF is not purely diffuse
