"""Named methods: a method is a name for a guide and its parameters (a table row, a figure column)."""

from __future__ import annotations

from collections.abc import Callable

from .errors import GuidingError
from .guides import BSDFGuide, Guide


class UnknownMethod(GuidingError):
    pass


_FACTORIES: dict[str, Callable[[], Guide]] = {
    "brdf": BSDFGuide,
}


def method_names() -> list[str]:
    return sorted(_FACTORIES)


def make_guide(name: str) -> Guide:
    """A fresh guide for method ``name``."""
    try:
        factory = _FACTORIES[name]
    except KeyError:
        raise UnknownMethod(f"unknown method '{name}' (known: {', '.join(method_names())})") from None
    return factory()
