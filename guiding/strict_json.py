"""Strict JSON for every file the package writes: no ``NaN`` or ``Infinity`` tokens, which strict readers (browsers,
``jq``, most JSON libraries outside Python) reject.

A non-finite number has no JSON spelling, so it becomes ``null``: a reader sees "no value" (e.g. the hit rate of
Mitsuba's own integrator, which reports none) instead of a parse error.
"""

from __future__ import annotations

import json
import math

import numpy as np


def finite(data):
    """``data`` with every non-finite float replaced by None and NumPy scalars and arrays made plain Python (dicts,
    lists and tuples are walked; tuples become lists)."""
    if isinstance(data, dict):
        return {key: finite(value) for key, value in data.items()}
    if isinstance(data, (list, tuple)):
        return [finite(value) for value in data]
    if isinstance(data, np.ndarray):
        return finite(data.tolist())
    if isinstance(data, np.generic):
        data = data.item()
    if isinstance(data, float) and not math.isfinite(data):
        return None
    return data


def dumps(data, indent: int | None = 1) -> str:
    """``data`` as strict JSON text (:func:`finite` first; ``indent`` as for :func:`json.dumps`)."""
    return json.dumps(finite(data), indent=indent, allow_nan=False)
