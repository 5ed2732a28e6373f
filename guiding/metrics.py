"""Image error metrics: the paper's tone-mapped MAE (method.md §7), HDR MAE, MSE, relMSE (also with its outliers
trimmed), SMAPE and HDR-FLIP (through NVIDIA's ``flip-evaluator``).

Non-finite pixels are never averaged away: they are counted, and any metric they touch is NaN (None in
:func:`evaluate`).
"""

from __future__ import annotations

import math

import numpy as np

from guiding.errors import GuidingError

#: relMSE's denominator offset, so black reference pixels do not dominate.
RELMSE_EPSILON = 0.01
#: Share of the pixels with the largest relMSE that the trimmed relMSE leaves out (fireflies).
TRIM_FRACTION = 0.001
#: SMAPE's denominator offset, so pixels black in both images count as no error.
SMAPE_EPSILON = 0.01
#: Everything :func:`evaluate` reports per image pair that a non-finite pixel can touch (None then).
METRICS = ("mae", "mae_hdr", "mse", "relmse", "relmse_trimmed", "smape", "flip")


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


def mse(test: np.ndarray, ref: np.ndarray) -> float:
    """Mean of ``(x − r)²`` over pixels and channels (linear values)."""
    _check_shapes(test, ref)
    return float(np.mean((np.asarray(test, np.float64) - ref) ** 2))


def _relative_squared_errors(test: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``(x − r)² / (r² + 0.01)`` per pixel and channel."""
    _check_shapes(test, ref)
    test, ref = np.asarray(test, np.float64), np.asarray(ref, np.float64)
    return (test - ref) ** 2 / (ref ** 2 + RELMSE_EPSILON)


def relmse(test: np.ndarray, ref: np.ndarray) -> float:
    """Mean of ``(x − r)² / (r² + 0.01)`` over pixels and channels."""
    return float(np.mean(_relative_squared_errors(test, ref)))


def relmse_trimmed(test: np.ndarray, ref: np.ndarray, fraction: float = TRIM_FRACTION) -> float:
    """relMSE without its outliers: the mean over pixels of each pixel's relMSE (mean over channels), leaving out
    the ``⌊fraction · pixels⌋`` largest (``fraction`` 0.1 % by default: a few fireflies no longer decide it)."""
    per_pixel = _relative_squared_errors(test, ref)[..., :3].mean(axis=-1).ravel()
    if not np.isfinite(per_pixel).all():   # a non-finite pixel is never trimmed away
        return math.nan
    keep = per_pixel.size - int(fraction * per_pixel.size)
    return float(np.mean(np.partition(per_pixel, keep - 1)[:keep]))


def smape(test: np.ndarray, ref: np.ndarray) -> float:
    """Symmetric mean absolute percentage error: the mean of ``|x − r| / (|x| + |r| + 0.01)`` over pixels and
    channels, in [0, 1)."""
    _check_shapes(test, ref)
    test, ref = np.asarray(test, np.float64), np.asarray(ref, np.float64)
    with np.errstate(invalid="ignore"):  # inf/inf: NaN, as for every metric a non-finite pixel touches
        return float(np.mean(np.abs(test - ref) / (np.abs(test) + np.abs(ref) + SMAPE_EPSILON)))


def flip_map(test: np.ndarray, ref: np.ndarray) -> np.ndarray | None:
    """Per-pixel HDR-FLIP error in [0, 1], shape (H, W), of linear RGB ``test`` against ``ref`` (flip-evaluator's
    defaults: 67 pixels per degree, ACES tone mapping, exposures chosen from the reference). None where HDR-FLIP
    is undefined: a non-finite pixel in either image, or a reference without light (its exposure range is empty;
    flip-evaluator would end the process)."""
    import flip_evaluator

    _check_shapes(test, ref)
    if nonfinite_pixels(test) or nonfinite_pixels(ref) or not np.any(np.asarray(ref)[..., :3] > 0):
        return None
    # Negative values (impossible for our estimators) are clamped, as the tone map does: FLIP expects radiance.
    test32, ref32 = (np.ascontiguousarray(np.maximum(a[..., :3], 0), dtype=np.float32) for a in (test, ref))
    error, _, _ = flip_evaluator.evaluate(ref32, test32, "HDR", applyMagma=False)
    return error[..., 0]


def flip(test: np.ndarray, ref: np.ndarray) -> float:
    """Mean HDR-FLIP error (:func:`flip_map`); NaN where it is undefined."""
    error = flip_map(test, ref)
    return math.nan if error is None else float(np.mean(error, dtype=np.float64))


def nonfinite_pixels(image: np.ndarray) -> int:
    """Number of pixels with a NaN or infinite channel."""
    return int(np.count_nonzero(~np.isfinite(image[..., :3]).all(axis=-1)))


def evaluate(test: np.ndarray, ref: np.ndarray) -> dict:
    """All metrics of ``test`` against ``ref``; a metric that a non-finite pixel touches is ``None`` (JSON null)."""
    _check_shapes(test, ref)
    result = {"mae": mae_tonemapped(test, ref), "mae_hdr": mae_hdr(test, ref), "mse": mse(test, ref),
              "relmse": relmse(test, ref), "relmse_trimmed": relmse_trimmed(test, ref), "smape": smape(test, ref),
              "flip": flip(test, ref)}
    result = {key: (value if np.isfinite(value) else None) for key, value in result.items()}
    result["nonfinite_pixels"] = nonfinite_pixels(test)
    result["reference_nonfinite_pixels"] = nonfinite_pixels(ref)
    result["pixels"] = int(test.shape[0] * test.shape[1])
    return result
