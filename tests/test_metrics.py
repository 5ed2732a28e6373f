import numpy as np
import pytest

from guiding import metrics
from guiding.errors import GuidingError


def test_tone_map_matches_hand_computation():
    pixel = np.array([[[1.0, 0.5, 0.25]]])
    luminance = 0.3 * 1.0 + 0.6 * 0.5 + 0.1 * 0.25  # 0.625
    scale = 1.0 / (1.0 + luminance / 1.5)
    expected = (np.array([1.0, 0.5, 0.25]) * scale) ** (1 / 2.2)
    np.testing.assert_allclose(metrics.tone_map(pixel)[0, 0], expected, rtol=1e-12)
    assert metrics.tone_map(np.zeros((1, 1, 3))).sum() == 0


def test_mae_relmse_on_two_pixels():
    test = np.array([[[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]]])
    ref = np.array([[[0.5, 0.5, 0.5], [0.0, 0.0, 0.1]]])
    # Gray pixels: L = c, T(c) = (c / (1 + c/1.5))^(1/2.2).
    t = lambda c: (c / (1 + c / 1.5)) ** (1 / 2.2)
    # Second reference pixel: L = 0.01, only blue is non-zero.
    t_blue = (0.1 / (1 + 0.01 / 1.5)) ** (1 / 2.2)
    expected_mae = (3 * abs(t(1.0) - t(0.5)) + t_blue) / 6
    assert metrics.mae_tonemapped(test, ref) == pytest.approx(expected_mae, rel=1e-12)
    assert metrics.mae_hdr(test, ref) == pytest.approx((3 * 0.5 + 0.1) / 6)
    expected_relmse = (3 * 0.25 / (0.25 + 0.01) + 2 * 0 + 0.01 / (0.01 + 0.01)) / 6
    assert metrics.relmse(test, ref) == pytest.approx(expected_relmse)


def test_identical_images_have_zero_error():
    image = np.random.default_rng(1).random((4, 3, 3))
    result = metrics.evaluate(image, image)
    assert result["mae"] == 0 and result["mae_hdr"] == 0 and result["relmse"] == 0
    assert result["nonfinite_pixels"] == 0 and result["pixels"] == 12


def test_nonfinite_pixels_are_counted_not_averaged_away():
    ref = np.ones((2, 2, 3))
    test = ref.copy()
    test[0, 0, 1] = np.nan
    test[1, 1, 2] = np.inf
    result = metrics.evaluate(test, ref)
    assert result["nonfinite_pixels"] == 2
    assert result["mae"] is None and result["relmse"] is None


def test_size_mismatch_is_an_error():
    with pytest.raises(GuidingError, match="differ in size"):
        metrics.evaluate(np.zeros((2, 2, 3)), np.zeros((2, 3, 3)))


def test_mse_smape_and_trimmed_relmse_by_hand():
    test = np.array([[[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]]])
    ref = np.array([[[0.5, 0.5, 0.5], [0.0, 0.0, 0.1]]])
    assert metrics.mse(test, ref) == pytest.approx((3 * 0.25 + 0.01) / 6)
    assert metrics.smape(test, ref) == pytest.approx((3 * 0.5 / 1.51 + 0.1 / 0.11) / 6)
    # Two pixels: ⌊0.1 % · 2⌋ = 0 trimmed, so the trimmed relMSE is relMSE itself.
    assert metrics.relmse_trimmed(test, ref) == pytest.approx(metrics.relmse(test, ref))


def test_trimmed_relmse_leaves_out_fireflies_but_never_nonfinite_pixels():
    rng = np.random.default_rng(3)
    ref = rng.random((50, 40, 3)) + 0.5
    test = ref * 1.1
    test[7, 9] = 1e4                                  # one firefly among 2000 pixels: ⌊2⌋ largest are trimmed
    assert metrics.relmse(test, ref) > 1e4
    assert metrics.relmse_trimmed(test, ref) == pytest.approx(metrics.relmse(ref * 1.1, ref), rel=2e-3)
    test[7, 9] = np.inf                              # trimming must not hide a non-finite pixel
    assert np.isnan(metrics.relmse_trimmed(test, ref))
    assert metrics.evaluate(test, ref)["relmse_trimmed"] is None


def test_flip_is_hdr_flip_of_flip_evaluator():
    import flip_evaluator

    rng = np.random.default_rng(4)
    ref = (rng.random((40, 48, 3)) * 4).astype(np.float32)
    test = ref * 1.3
    expected = flip_evaluator.evaluate(ref, test, "HDR", applyMagma=False)[1]
    assert metrics.flip(test, ref) == pytest.approx(expected, rel=1e-5) and 0 < expected < 1  # float64 mean
    assert metrics.flip_map(test, ref).shape == (40, 48)
    assert metrics.flip(ref, ref) == 0
    # Undefined (flip-evaluator would end the process): a black reference, or a non-finite pixel.
    assert metrics.flip_map(test, np.zeros_like(ref)) is None
    test[0, 0, 0] = np.nan
    assert metrics.flip_map(test, ref) is None and metrics.evaluate(test, ref)["flip"] is None


def test_evaluate_reports_every_metric():
    rng = np.random.default_rng(5)
    ref = rng.random((20, 30, 3)) + 0.1
    result = metrics.evaluate(ref * 1.2, ref)
    assert set(metrics.METRICS) <= set(result)
    assert all(result[name] > 0 for name in metrics.METRICS)
