"""Guides: what the path loop asks for a direction at each vertex, and tells what it learned.

A guide has a host-side life cycle (``prepare`` once per render, ``update`` between passes, ``stats``) and a
device-side part called from inside the Dr.Jit path loop (``new_paths``, ``sample``, ``record``,
``finish_paths``). See :class:`guiding.guides.base.Guide`.
"""

#: Learning rules and samplers of the grid guide (:mod:`guiding.guides.grid`), importable before a variant is set.
RULES = ("mc", "sarsa", "expected_sarsa")
SAMPLERS = ("sphere_inv", "hemi_inv", "hemi_rej", "hemi_rej_plus")
#: How the rejection samplers propose directions (the paper's ``uniform``, or our faster ``policy``).
PROPOSALS = ("policy", "uniform")


def default_proposal(sampler: str) -> str:
    """The proposal a rejection sampler uses unless told otherwise: ``policy`` for hemi_rej_plus, else ``uniform``."""
    return "policy" if sampler == "hemi_rej_plus" else "uniform"


from .base import Guide, NoPathState, UpdateResult  # noqa: E402
from .bsdf import BSDFGuide

__all__ = ["Guide", "NoPathState", "UpdateResult", "BSDFGuide", "RULES", "SAMPLERS", "PROPOSALS", "default_proposal"]
