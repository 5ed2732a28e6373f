"""Named methods: a method is a name for a guide and its parameters (a table row, a figure column)."""

from __future__ import annotations

from collections.abc import Callable

import re

from .errors import GuidingError
from .guides import RULES, SAMPLERS, BSDFGuide, Guide


class UnknownMethod(GuidingError):
    pass


#: The paper's configurations (S = 8, D = 16). Every ``{rule}-{sampler}`` pair is a method too, and any grid
#: method takes resolution overrides as a suffix: ``ours-S4-D32``, ``mc-hemi_inv-S16``. ``ours-uniform-proposals`` is
#: ``ours`` with the paper's rejection loop (same density, about five times the proposals; see GridGuide).
GRID_METHODS = {
    "ours": {"rule": "sarsa", "sampler": "hemi_rej_plus"},
    "ours-uniform-proposals": {"rule": "sarsa", "sampler": "hemi_rej_plus", "proposal": "uniform"},
    "ours-no-rejopt": {"rule": "sarsa", "sampler": "hemi_rej"},
    "ours-expected": {"rule": "expected_sarsa", "sampler": "hemi_rej_plus"},
    **{f"{rule}-{sampler}": {"rule": rule, "sampler": sampler} for rule in RULES for sampler in SAMPLERS},
}
_OVERRIDES = re.compile(r"^(?P<base>.+?)(?:-S(?P<S>\d+))?(?:-D(?P<D>\d+))?$")

def _sdtree(cls_name: str) -> Callable[[], Guide]:
    def build() -> Guide:
        from .guides import sdtree

        return getattr(sdtree, cls_name)()
    return build


_FACTORIES: dict[str, Callable[[], Guide]] = {
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
    return {"spatial_resolution": S, "directional_resolution": D, **GRID_METHODS[match["base"]], "name": name}


def check_method(name: str) -> None:
    """Raise UnknownMethod unless ``name`` names a method (cheap: builds nothing, needs no variant)."""
    if name not in _FACTORIES and grid_parameters(name) is None:
        raise UnknownMethod(f"unknown method '{name}' (known: {', '.join(method_names())}; grid methods take "
                            "-S<n>-D<n> suffixes)")


def make_guide(name: str) -> Guide:
    """A fresh guide for method ``name``."""
    check_method(name)
    if name in _FACTORIES:
        return _FACTORIES[name]()
    from .guides.grid import GridGuide

    return GridGuide(**grid_parameters(name))
