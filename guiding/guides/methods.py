"""Methods as typed values: a :class:`Method` is a guide class and its typed parameters (a table row, a figure column).

``ours`` is ``GridGuide`` with ``GridParameters(rule="sarsa", sampler="hemi_rej_plus")``; every ``{rule}-{sampler}``
pair is a method too. A name is resolved once, where it comes in (the command line, the harness's configuration,
the plugin's ``method`` property), into a :class:`Method`, with any parameter set to a typed value
(``resolve("ours", {"spatial_resolution": 16})``); from then on the value is passed on, never the name. The suffix
``-S<n>`` (and, for the grid guide, ``-D<n>``) is shorthand for people that resolves into the same value:
``ours-S4-D32`` is ``ours`` with S = 4 and D = 32. A method's :attr:`~Method.label` is a readable name
(``ours-S4-D32``), never read back. ``make_guide(name, **overrides)`` resolves and builds in one call.
"""

from __future__ import annotations

import numbers
import os
import re
import typing
from dataclasses import dataclass, fields, replace
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING

from guiding.errors import GuidingError
from guiding.guides.parameters import RULES, SAMPLERS, GridParameters, QuadtreeGridParameters, SDTreeParameters

if TYPE_CHECKING:
    from guiding.guides import Guide


class UnknownMethod(GuidingError):
    pass


class BadSetting(GuidingError, ValueError):
    """A parameter setting a method does not take: an unknown field, a value of the wrong type or out of range."""


# The guide classes need a Mitsuba variant to be defined, so each factory imports its class when it builds.

def _bsdf_guide(parameters, label: str) -> Guide:
    from guiding.guides.bsdf import BSDFGuide

    return BSDFGuide()


def _grid_guide(parameters, label: str) -> Guide:
    from guiding.guides.grid.guide import GridGuide

    return GridGuide(parameters, name=label)


def _sdtree_guide(parameters, label: str) -> Guide:
    from guiding.guides.trees.sdtree import SDTreeGuide

    return SDTreeGuide(parameters, name=label)


def _quadtree_grid_guide(parameters, label: str) -> Guide:
    from guiding.guides.trees.quadtree_grid import QuadtreeGridGuide

    return QuadtreeGridGuide(parameters, name=label)


#: The resolution fields that the name shorthand and the labels write as suffixes: ``-S<n>``, ``-D<n>``.
RESOLUTION_SUFFIXES = {"spatial_resolution": "S", "directional_resolution": "D"}


@dataclass(frozen=True)
class Method:
    """A method: its registered ``name``, the ``guide`` factory that builds its guide from (parameters, label), the
    guide's typed ``parameters`` (None for BSDF sampling), and the ``settings`` changed from the registered ones
    ((field, value) pairs in the parameters' field order). A method that is another Mitsuba integrator (``path``)
    names it in ``mitsuba_integrator`` and has no guide. ``guide`` is None for a name this checkout does not know
    (:func:`unknown_method`): it has a label, and refuses to build."""

    name: str
    guide: Callable[[object, str], Guide] | None
    parameters: object = None
    settings: tuple[tuple[str, object], ...] = ()
    mitsuba_integrator: str | None = None

    @property
    def known(self) -> bool:
        """Whether this checkout can render the method."""
        return self.guide is not None or self.mitsuba_integrator is not None

    @property
    def label(self) -> str:
        """A readable name: the registered name, S and D set as the shorthand suffixes, other settings in
        parentheses (``ours-S4-D8``, ``sarsa-hemi_inv (bsdf_fraction=0.0)``)."""
        settings = dict(self.settings)
        suffixes = "".join(f"-{letter}{settings.pop(field)}" for field, letter in RESOLUTION_SUFFIXES.items()
                           if field in settings)
        others = ", ".join(f"{field}={value}" for field, value in settings.items())
        return self.name + suffixes + (f" ({others})" if others else "")

    def field_types(self) -> dict[str, object]:
        """The parameters' fields and their types (empty for a method without parameters)."""
        return typing.get_type_hints(type(self.parameters)) if self.parameters is not None else {}

    def with_settings(self, settings: Mapping[str, object]) -> Method:
        """This method with the fields in ``settings`` set; BadSetting (one line naming the field) for an unknown
        field or a value of the wrong type, or one the parameters refuse."""
        if not settings:
            return self
        types = self.field_types()
        settings = {field: _typed_setting(self, types, field, value) for field, value in settings.items()}
        merged = {**dict(self.settings), **settings}
        try:
            parameters = replace(self.parameters, **settings)
        except ValueError as error:
            given = ", ".join(f"{field}={value}" for field, value in settings.items())
            raise BadSetting(f"method '{self.label}' with {given}: {error}") from None
        order = [f.name for f in fields(self.parameters)]
        return replace(self, parameters=parameters, settings=tuple(sorted(merged.items(),
                                                                           key=lambda item: order.index(item[0]))))

    @property
    def grid_parameters(self) -> GridParameters | None:
        """The grid guide's parameters (None for the other methods)."""
        return self.parameters if isinstance(self.parameters, GridParameters) else None

    def table_bytes(self) -> int | None:
        """Bytes the guide's tables take once built (grid methods; None for the others, whose tables grow while they
        learn). Needs no variant and allocates nothing."""
        parameters = self.grid_parameters
        if parameters is None:
            return None
        from guiding.guides.grid.record import RadianceRecord
        from guiding.guides.grid.strategy import grid_strategy

        needs = grid_strategy(parameters).table_needs()
        return RadianceRecord.planned_bytes(parameters.spatial_resolution, parameters.directional_resolution,
                                            parameters.normal_resolution, **needs,
                                            sub_resolution=parameters.sub_resolution,
                                            refine_capacity=parameters.refine_capacity)

    def check_memory(self, limit: int | str | None = None) -> int:
        """Raise GuidingError if the guide's fixed tables would exceed the memory limit (:func:`memory_limit`), with
        the size they would need: before anything is allocated, rather than failing (or swapping) in the middle.
        Returns what the tables leave of the limit, in bytes (the whole limit for a method without fixed tables)."""
        size, allowed = self.table_bytes(), memory_limit(limit)
        if size is not None and size > allowed:
            S, D = self.parameters.spatial_resolution, self.parameters.directional_resolution
            raise GuidingError(f"method '{self.label}' needs {format_size(size)} for its tables (S = {S}, D = {D}: "
                               f"{S ** 3} cells x {2 * D * D} direction bins), over the memory limit of "
                               f"{format_size(allowed)}; lower S or D, or raise the limit (--memory-limit or "
                               f"${MEMORY_LIMIT_VARIABLE})")
        return allowed - (size or 0)

    def build(self, memory_limit: int | str | None = None) -> Guide:
        """A fresh guide; refused (GuidingError) if its tables would exceed ``memory_limit`` (default:
        :func:`memory_limit`)."""
        if self.guide is None:
            raise UnknownMethod(_unknown_message(self.name) if not self.known else
                                f"method '{self.name}' is Mitsuba's {self.mitsuba_integrator} integrator: it has no guide")
        left = self.check_memory(memory_limit)
        guide = self.guide(self.parameters, self.label)
        if getattr(guide, "record_table", None) is not None:     # a grid guide (as guide_state tells them apart)
            # What the fixed tables leave of the limit is what the visited pairs' rows may grow into.
            guide.record_table.row_memory_limit = left
        return guide


def _check_field(method: Method, types: dict, field: str) -> None:
    """BadSetting unless ``field`` is a parameter of ``method`` (whose fields have the types ``types``)."""
    if not types:
        raise BadSetting(f"method '{method.name}' takes no parameters, got {field}")
    if field not in types:
        raise BadSetting(f"method '{method.name}' has no parameter '{field}' (its parameters: {', '.join(types)})")


def _typed_setting(method: Method, types: dict, field: str, value):
    """``value`` as a setting of ``field`` of ``method``: BadSetting unless the field exists and the value is of its
    type; an integer for a number field is that number (``bsdf_fraction: 0`` is 0.0)."""
    _check_field(method, types, field)
    kinds = _alternatives(types[field])
    if not any(_is_instance(value, kind) for kind in kinds):
        raise BadSetting(f"method '{method.name}': {field}={value!r} is not {_type_name(types[field])}")
    return float(value) if float in kinds and not isinstance(value, float) and value is not None else value


def _alternatives(kind) -> tuple:
    """The types a field accepts: ``int | None`` accepts int and None."""
    return typing.get_args(kind) or (kind,)


def _is_instance(value, kind) -> bool:
    if kind is type(None):
        return value is None
    if kind is bool:
        return isinstance(value, bool)
    if kind is int:
        return isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if kind is float:
        return isinstance(value, numbers.Real) and not isinstance(value, bool)
    return isinstance(value, kind)


def _type_name(kind) -> str:
    names = {bool: "true or false", int: "an integer", float: "a number", str: "a string", type(None): "none"}
    return " or ".join(names.get(k, getattr(k, "__name__", str(k))) for k in _alternatives(kind))


_BOOLEANS = {"true": True, "false": False, "yes": True, "no": False, "on": True, "off": False, "1": True, "0": False}


def _parsed(text: str, kind):
    """``text`` as a value of type ``kind`` (ValueError if it is none)."""
    alternatives, lowered = _alternatives(kind), text.lower()
    if type(None) in alternatives and lowered in ("none", "null"):
        return None
    if bool in alternatives and lowered in _BOOLEANS:
        return _BOOLEANS[lowered]
    for alternative in (int, float, str):
        if alternative in alternatives:
            try:
                return alternative(text)
            except ValueError:
                continue
    raise ValueError(text)


def parse_settings(method: Method, texts: Iterable[str]) -> dict[str, object]:
    """``KEY=VALUE`` texts (the command line's ``--set``) as typed settings of ``method``: each value parsed as its
    field's type (``true``/``false`` for a flag, ``none`` for an unset optional). BadSetting (one line naming the
    field) for a text without ``=``, an unknown field or a value that is not of its type."""
    types, settings = method.field_types(), {}
    for text in texts:
        field, equals, value = text.partition("=")
        field = field.strip()
        if not equals or not field:
            raise BadSetting(f"--set expects FIELD=VALUE, got '{text}'")
        _check_field(method, types, field)
        try:
            settings[field] = _parsed(value.strip(), types[field])
        except ValueError:
            raise BadSetting(f"method '{method.name}': {field}={value!r} is not {_type_name(types[field])}") from None
    return settings


def setting_text(value) -> str:
    """A setting's value as :func:`parse_settings` reads it back (``true``, ``none``, ``0.5``)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return "none" if value is None else str(value)


def _grid(**parameters) -> tuple:
    return _grid_guide, GridParameters(**parameters)


def grid_method_name(rule: str, sampler: str) -> str:
    """The name of the grid method with learning rule ``rule`` and sampler ``sampler`` (``sarsa-hemi_inv``)."""
    return f"{rule}-{sampler}"


#: The paper's configurations (S = 8, D = 16), the baselines, and every rule × sampler. ``sdtree`` is Tom94's
#: SD-tree with its last iterations combined (Müller 2019), ``sdtree-last`` the same with the 2017 paper's final image
#: (its last iteration alone), ``sdtree-learned`` the same with a BSDF share learned per D-tree (Müller 2019's
#: improved preset; :mod:`guiding.guides.trees.bsdf_fraction`). ``ours-uniform-proposals`` is ``ours`` with the paper's
#: rejection loop (the same target, about five times the proposals; see GridGuide).
#: ``{rule}-hemi_inv-pure`` is the paper's hemi_inv without the BSDF share of ours (heavy-tailed; not in the tables).
#: ``ours-plus`` (beyond the paper, in progress): ``ours`` guiding every smooth reflecting BSDF, with a BSDF share of
#: at least ``smooth_bsdf_share`` where the BSDF is not purely diffuse, and its brightest bins refined into 8 × 8
#: sub-bins (:mod:`guiding.guides.grid.refinement`).
_REGISTERED = {
    "brdf": (_bsdf_guide, None),
    "sdtree": (_sdtree_guide, SDTreeParameters()),
    "sdtree-last": (_sdtree_guide, SDTreeParameters(combine="last")),
    "sdtree-learned": (_sdtree_guide, SDTreeParameters(learn_bsdf_fraction=True)),
    "quadtree-grid": (_quadtree_grid_guide, QuadtreeGridParameters()),
    "ours": _grid(rule="sarsa", sampler="hemi_rej_plus"),
    "ours-uniform-proposals": _grid(rule="sarsa", sampler="hemi_rej_plus", proposal="uniform"),
    "ours-no-rejopt": _grid(rule="sarsa", sampler="hemi_rej"),
    "ours-expected": _grid(rule="expected_sarsa", sampler="hemi_rej_plus"),
    "ours-plus": _grid(rule="sarsa", sampler="hemi_rej_plus", guided_bsdfs="smooth", sub_resolution=8,
                       rebuild_growth=0.25),
    **{grid_method_name(rule, sampler): _grid(rule=rule, sampler=sampler) for rule in RULES for sampler in SAMPLERS},
    **{f"{rule}-hemi_inv-pure": _grid(rule=rule, sampler="hemi_inv", bsdf_fraction=0.0) for rule in RULES},
}
METHODS: dict[str, Method] = {name: Method(name, guide, parameters)
                              for name, (guide, parameters) in _REGISTERED.items()}
#: Mitsuba's own path tracer (next-event estimation and MIS), the renderer a Mitsuba user has: rendered by it, not
#: by ``guided_path``, with the same budgets, so that tables compare with it directly.
METHODS["path"] = Method("path", None, mitsuba_integrator="path")
_SUFFIXED_NAME = re.compile(r"^(?P<base>.+?)(?:-S(?P<S>\d+))?(?:-D(?P<D>\d+))?$")


def method_names() -> list[str]:
    return sorted(METHODS)


def _unknown_message(name: str) -> str:
    return (f"unknown method '{name}' (known: {', '.join(method_names())}; grid methods take -S<n>-D<n> suffixes, "
            "quadtree-grid -S<n>)")


def resolve(name: str, settings: Mapping[str, object] | None = None) -> Method:
    """The :class:`Method` that ``name`` stands for, resolution shorthand applied, with ``settings`` set
    (UnknownMethod if no method has that name, BadSetting if it does not take the settings)."""
    method = METHODS.get(name)
    if method is None:
        match = _SUFFIXED_NAME.match(name)
        base = METHODS.get(match["base"]) if match and (match["S"] or match["D"]) else None
        types = base.field_types() if base is not None else {}
        suffixes = {field: int(match[letter]) for field, letter in RESOLUTION_SUFFIXES.items()
                    if base is not None and match[letter]}
        if base is None or not set(suffixes) <= set(types):
            raise UnknownMethod(_unknown_message(name))
        method = base.with_settings(suffixes)
    return method.with_settings(settings or {})


def unknown_method(name: str, settings: Mapping[str, object] | None = None) -> Method:
    """A method of a name this checkout does not know, with ``settings`` as given: it has a label and refuses to
    build (a configuration written for another checkout)."""
    return Method(name, None, settings=tuple((settings or {}).items()))


def grid_parameters(name: str) -> GridParameters | None:
    """The grid guide's parameters for a grid method name (None for other methods); no variant needed."""
    return resolve(name).grid_parameters


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
    """:meth:`Method.table_bytes` of method ``name``."""
    return resolve(name).table_bytes()


def check_method(name: str, memory_limit: int | str | None = None) -> None:
    """Raise UnknownMethod unless ``name`` names a method, and GuidingError if its tables would exceed the memory
    limit (:meth:`Method.check_memory`). Cheap: builds nothing, needs no variant."""
    resolve(name).check_memory(memory_limit)


def make_guide(name: str, memory_limit: int | str | None = None, **overrides) -> Guide:
    """A fresh guide for method ``name``, with its parameters ``overrides`` set (for example
    ``make_guide("sarsa-hemi_inv", bsdf_fraction=0)``); refused (GuidingError) if its tables would exceed
    ``memory_limit`` (default: :func:`memory_limit`)."""
    return resolve(name, overrides).build(memory_limit)
