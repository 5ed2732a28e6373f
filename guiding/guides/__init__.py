"""Guides: what the path loop asks for a direction at each vertex, and tells what it learned.

A guide has a host-side life cycle (``prepare`` once per render, ``update`` between passes, ``stats``) and a
device-side part called from inside the Dr.Jit path loop (``new_paths``, ``sample``, ``record``,
``finish_paths``). See :class:`guiding.guides.base.Guide`.
"""

from guiding.guides.base import Guide, NoPathState, UpdateResult
from guiding.guides.parameters import PROPOSALS, RULES, SAMPLERS
from guiding.guides.bsdf import BSDFGuide

__all__ = ["Guide", "NoPathState", "UpdateResult", "BSDFGuide", "RULES", "SAMPLERS", "PROPOSALS"]
