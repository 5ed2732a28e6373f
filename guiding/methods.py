"""Named methods: a method is a name for a guide class and its typed parameters (a table row, a figure column).

``ours`` is ``GridGuide`` with ``GridParameters(rule="sarsa", sampler="hemi_rej_plus")``; every ``{rule}-{sampler}``
pair is a method too. The suffix ``-S<n>`` (and, for the grid guide, ``-D<n>``) is shorthand for the resolution:
``ours-S4-D32``, ``mc-hemi_inv-S16``, ``quadtree-grid-S16``. ``make_guide(name, **overrides)`` builds a fresh guide,
with any parameter changed (``make_guide("sarsa-hemi_inv", bsdf_fraction=0)``).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

from .errors import GuidingError
from .guides.parameters import (RULES, SAMPLERS, GridParameters, QuadtreeGridParameters, SDTreeParameters,
                                with_overrides)

if TYPE_CHECKING:
    from .guides import Guide


class UnknownMethod(GuidingError):
    pass


@dataclass(frozen=True)
class Method:
    """A named guide configuration: which guide class (by module and name, imported when built) and its
    parameters."""

    module: str
    guide_class: str
    parameters: object = None     # the guide's parameter dataclass; None for BSDF sampling

    def build(self, name: str, overrides: dict):
        from importlib import import_module

        guide_class = getattr(import_module(self.module, __package__), self.guide_class)
        if self.parameters is None:
            if overrides:
                raise ValueError(f"method '{name}' takes no parameters, got {', '.join(sorted(overrides))}")
            return guide_class()
        return guide_class(with_overrides(self.parameters, overrides), name=name)


def _grid(**parameters) -> Method:
    return Method(".guides.grid", "GridGuide", GridParameters(**parameters))


#: The paper's configurations (S = 8, D = 16), the baselines, and every rule × sampler. ``sdtree`` is Tom94's
#: SD-tree with its last iterations combined (Müller 2019), ``sdtree-last`` the same with the 2017 paper's final image
#: (its last iteration alone), ``sdtree-learned`` the same with a BSDF share learned per D-tree (Müller 2019's
#: improved preset; :mod:`guiding.guides.bsdf_fraction`). ``ours-uniform-proposals`` is ``ours`` with the paper's
#: rejection loop (the same target, about five times the proposals; see GridGuide).
#: ``{rule}-hemi_inv-pure`` is the paper's hemi_inv without the BSDF share of ours (heavy-tailed; not in the tables).
#: ``ours-plus`` (beyond the paper, in progress): ``ours`` guiding every smooth reflecting BSDF, with a BSDF share of
#: at least ``smooth_bsdf_share`` where the BSDF is not purely diffuse, and its brightest bins refined into 8 × 8
#: sub-bins (:mod:`guiding.guides.grid_refinement`).
METHODS: dict[str, Method] = {
    "brdf": Method(".guides.bsdf", "BSDFGuide"),
    "sdtree": Method(".guides.sdtree", "SDTreeGuide", SDTreeParameters()),
    "sdtree-last": Method(".guides.sdtree", "SDTreeGuide", SDTreeParameters(combine="last")),
    "sdtree-learned": Method(".guides.sdtree", "SDTreeGuide", SDTreeParameters(learn_bsdf_fraction=True)),
    "quadtree-grid": Method(".guides.sdtree", "QuadtreeGridGuide", QuadtreeGridParameters()),
    "ours": _grid(rule="sarsa", sampler="hemi_rej_plus"),
    "ours-uniform-proposals": _grid(rule="sarsa", sampler="hemi_rej_plus", proposal="uniform"),
    "ours-no-rejopt": _grid(rule="sarsa", sampler="hemi_rej"),
    "ours-expected": _grid(rule="expected_sarsa", sampler="hemi_rej_plus"),
    "ours-plus": _grid(rule="sarsa", sampler="hemi_rej_plus", guided_bsdfs="smooth", sub_resolution=8,
                       rebuild_growth=0.25),
    **{f"{rule}-{sampler}": _grid(rule=rule, sampler=sampler) for rule in RULES for sampler in SAMPLERS},
    **{f"{rule}-hemi_inv-pure": _grid(rule=rule, sampler="hemi_inv", bsdf_fraction=0.0) for rule in RULES},
}
_SHORTHAND = re.compile(r"^(?P<base>.+?)(?:-S(?P<S>\d+))?(?:-D(?P<D>\d+))?$")


def method_names() -> list[str]:
    return sorted(METHODS)


def resolve(name: str) -> Method:
    """The :class:`Method` that ``name`` stands for, resolution shorthand applied (UnknownMethod if none)."""
    if name in METHODS:
        return METHODS[name]
    match = _SHORTHAND.match(name)
    base = METHODS.get(match["base"]) if match and (match["S"] or match["D"]) else None
    resolution = {}
    if isinstance(base.parameters if base else None, GridParameters):
        resolution = {"spatial_resolution": match["S"], "directional_resolution": match["D"]}
    elif isinstance(base.parameters if base else None, QuadtreeGridParameters) and not match["D"]:
        resolution = {"spatial_resolution": match["S"]}
    if not resolution:
        raise UnknownMethod(f"unknown method '{name}' (known: {', '.join(method_names())}; grid methods take "
                            "-S<n>-D<n> suffixes, quadtree-grid -S<n>)")
    try:
        parameters = replace(base.parameters, **{k: int(v) for k, v in resolution.items() if v is not None})
    except ValueError as error:
        raise UnknownMethod(f"method '{name}': {error}") from None
    return replace(base, parameters=parameters)


def grid_parameters(name: str) -> GridParameters | None:
    """The grid guide's parameters for a grid method name (None for other methods); no variant needed."""
    parameters = resolve(name).parameters
    return parameters if isinstance(parameters, GridParameters) else None


#: Memory a guide's tables may take unless told otherwise: ``GUIDING_MEMORY_LIMIT`` (bytes, or a size such as
#: ``512M`` or ``16G``) or ``--memory-limit`` on the command line set another.
DEFAULT_MEMORY_LIMIT = 8 * 2 ** 30
MEMORY_LIMIT_VARIABLE = "GUIDING_MEMORY_LIMIT"
_SIZE = re.compile(r"^\s*(?P<number>[0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*(?P<unit>[kKmMgGtT]?)(?:i?[bB])?\s*$")


def parse_size(text: str) -> int:
    """Bytes in ``text``: a number of bytes, or one with a binary unit (``512M``, ``16G``, ``1.5GiB``)."""
    match = _SIZE.match(str(text))
    if not match:
        raise GuidingError(f"bad memory size '{text}': expected bytes or a size such as 512M or 16G")
    return int(float(match["number"]) * 1024 ** " KMGT".index(match["unit"].upper() or " "))


def format_size(size: int) -> str:
    """``size`` bytes in the largest binary unit that keeps it at least 1 (``56.6 GiB``)."""
    for unit, power in (("TiB", 4), ("GiB", 3), ("MiB", 2), ("KiB", 1)):
        if size >= 1024 ** power:
            return f"{size / 1024 ** power:.1f} {unit}"
    return f"{size} bytes"


def memory_limit(limit: int | str | None = None) -> int:
    """The memory limit in bytes: ``limit`` when given, else ``$GUIDING_MEMORY_LIMIT``, else the default."""
    if limit is None:
        limit = os.environ.get(MEMORY_LIMIT_VARIABLE) or DEFAULT_MEMORY_LIMIT
    return limit if isinstance(limit, int) else parse_size(limit)


def table_bytes(name: str) -> int | None:
    """Bytes the tables of method ``name`` take once built (grid methods; None for the others, whose tables grow
    while they learn). Needs no variant and allocates nothing."""
    parameters = grid_parameters(name)
    if parameters is None:
        return None
    from .guides.grid_record import RadianceRecord, table_needs

    needs = table_needs(parameters.rule, parameters.sampler, parameters.proposal)
    return RadianceRecord.planned_bytes(parameters.spatial_resolution, parameters.directional_resolution,
                                        parameters.normal_resolution, **needs,
                                        sub_resolution=parameters.sub_resolution,
                                        refine_capacity=parameters.refine_capacity)


def check_memory(name: str, limit: int | str | None = None) -> int:
    """Raise GuidingError if the fixed tables of method ``name`` would exceed the memory limit
    (:func:`memory_limit`), with the size they would need: before anything is allocated, rather than failing (or
    swapping) in the middle. Returns the limit in bytes."""
    size, allowed = table_bytes(name), memory_limit(limit)
    if size is not None and size > allowed:
        parameters = grid_parameters(name)
        S, D = parameters.spatial_resolution, parameters.directional_resolution
        raise GuidingError(f"method '{name}' needs {format_size(size)} for its tables (S = {S}, D = {D}: {S ** 3} "
                           f"cells x {2 * D * D} direction bins), over the memory limit of {format_size(allowed)}; "
                           f"lower S or D, or raise the limit (--memory-limit or ${MEMORY_LIMIT_VARIABLE})")
    return allowed


def check_method(name: str, memory_limit: int | str | None = None) -> None:
    """Raise UnknownMethod unless ``name`` names a method, and GuidingError if its tables would exceed the memory
    limit (:func:`check_memory`). Cheap: builds nothing, needs no variant."""
    resolve(name)
    check_memory(name, memory_limit)


def make_guide(name: str, memory_limit: int | str | None = None, **overrides) -> Guide:
    """A fresh guide for method ``name``, with its parameters ``overrides`` changed (for example
    ``make_guide("sarsa-hemi_inv", bsdf_fraction=0)``); refused (GuidingError) if its tables would exceed
    ``memory_limit`` (default: :func:`memory_limit`)."""
    method = resolve(name)
    allowed = check_memory(name, memory_limit)
    guide = method.build(name, overrides)
    if getattr(guide, "record_table", None) is not None:     # a grid guide (as guide_state tells them apart)
        # What the fixed tables leave of the limit is what the visited pairs' rows may grow into.
        guide.record_table.row_memory_limit = allowed - table_bytes(name)
    return guide
