"""Float32 limits, NumPy ↔ Dr.Jit conversions and one-line failure messages, shared by the stress tests."""

import numpy as np

#: float32 machine epsilon: the relative resolution every float32 table and direction has.
EPS32 = float(np.finfo(np.float32).eps)
#: Smallest normal float32. Dr.Jit's CPU backend flushes denormals to zero (FTZ/DAZ) in kernels that run on its
#: worker threads, but not in small ones run on the calling thread: a denormal input is zero or not depending on
#: the array's size, so the checks accept either reading of a denormal component: zero, or its value.
TINY32 = float(np.finfo(np.float32).tiny)
#: The largest float32 below 1: the largest value a Mitsuba sampler returns.
ONE_MINUS_EPS32 = float(np.nextafter(np.float32(1), np.float32(0)))


def vectors(array: np.ndarray):
    """An ``(n, 3)`` NumPy array as a ``mi.Vector3f`` (a memory array, so no value is baked into a kernel)."""
    import mitsuba as mi

    array = np.asarray(array, dtype=np.float32).reshape(-1, 3)
    return mi.Vector3f(*(np.ascontiguousarray(array[:, i]) for i in range(3)))


def to_numpy(vector) -> np.ndarray:
    """A Dr.Jit 3-vector (or 2-point) as an ``(n, 3)`` (or ``(n, 2)``) float64 array."""
    return np.array(vector, dtype=np.float64).T.reshape(-1, len(vector))


def unit(d: np.ndarray, flush: bool = False) -> np.ndarray:
    """Reference normalisation in float64 (scaled by the largest component first; with ``flush``, denormal
    components are zero, see :data:`TINY32`); rows without a direction (zero or non-finite) are NaN."""
    d = np.asarray(d, dtype=np.float64).reshape(-1, 3)
    if flush:
        d = np.where(np.abs(d) < TINY32, 0.0, d)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        largest = np.max(np.abs(d), axis=1, keepdims=True)
        scaled = d / largest
        out = scaled / np.linalg.norm(scaled, axis=1, keepdims=True)
    out[~np.isfinite(out).all(axis=1)] = np.nan
    return out


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit rows (float64, accurate for small angles)."""
    return 2 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=1) / 2, 0, 1))


def few(problems: list[str], limit: int = 3) -> str:
    """The first few problems and how many there were, for a one-line failure message."""
    more = f" (and {len(problems) - limit} more)" if len(problems) > limit else ""
    return "; ".join(problems[:limit]) + more
