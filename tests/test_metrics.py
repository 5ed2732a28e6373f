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
