"""Image error metrics: the paper's tone-mapped MAE (method.md §7), HDR MAE and relMSE.

Non-finite pixels are never averaged away: they are counted, and any metric they touch is NaN.
"""

from __future__ import annotations

import numpy as np

from .errors import GuidingError

#: relMSE's denominator offset, so black reference pixels do not dominate.
RELMSE_EPSILON = 0.01


def tone_map(image: np.ndarray) -> np.ndarray:
    """The paper's tone map ``T(c) = (c / (1 + L/1.5))^(1/2.2)`` with per-pixel ``L = 0.3R + 0.6G + 0.1B``.

    Negative values (impossible for our estimators, possible for denoised inputs) are clamped to zero first.
    """
    rgb = np.maximum(np.asarray(image, dtype=np.float64)[..., :3], 0.0)
    luminance = rgb @ np.array([0.3, 0.6, 0.1])
    with np.errstate(invalid="ignore"):  # NaN/Inf pixels stay NaN and are counted by `evaluate`
        return np.power(rgb / (1.0 + luminance[..., None] / 1.5), 1.0 / 2.2)


def _check_shapes(test: np.ndarray, ref: np.ndarray) -> None:
    if test.shape != ref.shape:
        raise GuidingError(f"images differ in size: {test.shape[1]}x{test.shape[0]} vs reference "
                           f"{ref.shape[1]}x{ref.shape[0]}")


def mae_tonemapped(test: np.ndarray, ref: np.ndarray) -> float:
    """Mean over pixels and channels of ``|T(test) − T(ref)|`` (the paper's MAE, on a float reference)."""
    _check_shapes(test, ref)
    return float(np.mean(np.abs(tone_map(test) - tone_map(ref))))


def mae_hdr(test: np.ndarray, ref: np.ndarray) -> float:
    """Mean absolute error on linear values."""
    _check_shapes(test, ref)
    return float(np.mean(np.abs(np.asarray(test, np.float64) - ref)))


def relmse(test: np.ndarray, ref: np.ndarray) -> float:
    """Mean of ``(x − r)² / (r² + 0.01)`` over pixels and channels."""
    _check_shapes(test, ref)
    test, ref = np.asarray(test, np.float64), np.asarray(ref, np.float64)
    return float(np.mean((test - ref) ** 2 / (ref ** 2 + RELMSE_EPSILON)))


def nonfinite_pixels(image: np.ndarray) -> int:
    """Number of pixels with a NaN or infinite channel."""
    return int(np.count_nonzero(~np.isfinite(image[..., :3]).all(axis=-1)))


def evaluate(test: np.ndarray, ref: np.ndarray) -> dict:
    """All metrics of ``test`` against ``ref``; a metric that a non-finite pixel touches is ``None`` (JSON null)."""
    _check_shapes(test, ref)
    result = {"mae": mae_tonemapped(test, ref), "mae_hdr": mae_hdr(test, ref), "relmse": relmse(test, ref)}
    result = {key: (value if np.isfinite(value) else None) for key, value in result.items()}
    result["nonfinite_pixels"] = nonfinite_pixels(test)
    result["reference_nonfinite_pixels"] = nonfinite_pixels(ref)
    result["pixels"] = int(test.shape[0] * test.shape[1])
    return result
