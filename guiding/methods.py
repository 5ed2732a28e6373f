"""Named methods: a method is a name for a guide and its parameters (a table row, a figure column)."""

from __future__ import annotations

import os
import re
from collections.abc import Callable

from .errors import GuidingError
from .guides import RULES, SAMPLERS, BSDFGuide, Guide, default_proposal


class UnknownMethod(GuidingError):
    pass


#: The paper's configurations (S = 8, D = 16). Every ``{rule}-{sampler}`` pair is a method too, and any grid
#: method takes resolution overrides as a suffix: ``ours-S4-D32``, ``mc-hemi_inv-S16``. ``ours-uniform-proposals`` is
#: ``ours`` with the paper's rejection loop (the same target, about five times the proposals; see GridGuide).
#: ``{rule}-hemi_inv-pure`` is the paper's hemi_inv without the BSDF share of ours (heavy-tailed; not in the tables).
GRID_METHODS = {
    "ours": {"rule": "sarsa", "sampler": "hemi_rej_plus"},
    "ours-uniform-proposals": {"rule": "sarsa", "sampler": "hemi_rej_plus", "proposal": "uniform"},
    "ours-no-rejopt": {"rule": "sarsa", "sampler": "hemi_rej"},
    "ours-expected": {"rule": "expected_sarsa", "sampler": "hemi_rej_plus"},
    **{f"{rule}-{sampler}": {"rule": rule, "sampler": sampler} for rule in RULES for sampler in SAMPLERS},
    **{f"{rule}-hemi_inv-pure": {"rule": rule, "sampler": "hemi_inv", "bsdf_fraction": 0.0} for rule in RULES},
}
_OVERRIDES = re.compile(r"^(?P<base>.+?)(?:-S(?P<S>\d+))?(?:-D(?P<D>\d+))?$")

def _sdtree(cls_name: str) -> Callable[..., Guide]:
    def build(**parameters) -> Guide:
        from .guides import sdtree

        return getattr(sdtree, cls_name)(**parameters)
    return build


_FACTORIES: dict[str, Callable[..., Guide]] = {
    "brdf": BSDFGuide,
    "sdtree": _sdtree("SDTreeGuide"),
    "quadtree-grid": _sdtree("QuadtreeGridGuide"),
}


def method_names() -> list[str]:
    return sorted([*_FACTORIES, *GRID_METHODS])


def grid_parameters(name: str) -> dict | None:
    """The grid guide's parameters for a grid method name (None for other names); no variant needed."""
    match = _OVERRIDES.match(name)
    if not match or match["base"] not in GRID_METHODS:
        return None
    S, D = int(match["S"] or 8), int(match["D"] or 16)
    if not (1 <= S <= 256 and 1 <= D <= 256):
        raise UnknownMethod(f"method '{name}': S and D must be in 1..256")
    method = GRID_METHODS[match["base"]]
    return {"spatial_resolution": S, "directional_resolution": D,
            "proposal": default_proposal(method["sampler"]), **method, "name": name}


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

    needs = table_needs(parameters["rule"], parameters["sampler"], parameters["proposal"])
    return RadianceRecord.planned_bytes(parameters["spatial_resolution"], parameters["directional_resolution"],
                                        **needs)


def check_memory(name: str, limit: int | str | None = None) -> None:
    """Raise GuidingError if the tables of method ``name`` would exceed the memory limit (:func:`memory_limit`),
    with the size they would need: before anything is allocated, rather than failing (or swapping) in the middle."""
    size, allowed = table_bytes(name), memory_limit(limit)
    if size is not None and size > allowed:
        parameters = grid_parameters(name)
        S, D = parameters["spatial_resolution"], parameters["directional_resolution"]
        raise GuidingError(f"method '{name}' needs {format_size(size)} for its tables (S = {S}, D = {D}: {S ** 3} "
                           f"cells x {2 * D * D} direction bins), over the memory limit of {format_size(allowed)}; "
                           f"lower S or D, or raise the limit (--memory-limit or ${MEMORY_LIMIT_VARIABLE})")


def check_method(name: str, memory_limit: int | str | None = None) -> None:
    """Raise UnknownMethod unless ``name`` names a method, and GuidingError if its tables would exceed the memory
    limit (:func:`check_memory`). Cheap: builds nothing, needs no variant."""
    if name not in _FACTORIES and grid_parameters(name) is None:
        raise UnknownMethod(f"unknown method '{name}' (known: {', '.join(method_names())}; grid methods take "
                            "-S<n>-D<n> suffixes)")
    check_memory(name, memory_limit)


def make_guide(name: str, memory_limit: int | str | None = None, **overrides) -> Guide:
    """A fresh guide for method ``name``, with its constructor's parameters ``overrides`` changed (for example
    ``make_guide("sarsa-hemi_inv", bsdf_fraction=0)``); refused (GuidingError) if its tables would exceed
    ``memory_limit`` (default: :func:`memory_limit`)."""
    check_method(name, memory_limit)
    if name in _FACTORIES:
        return _FACTORIES[name](**overrides)
    from .guides.grid import GridGuide

    return GridGuide(**{**grid_parameters(name), **overrides})
