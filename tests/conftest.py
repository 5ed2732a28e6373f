"""Shared set-up: every test runs on the CPU variant with a pinned thread count.

The variant is set at import time, before test modules import the integrator (whose class derives from a
variant-specific Mitsuba type).
"""

import pytest

from guiding.backend import set_variant

VARIANT = set_variant("llvm_ad_rgb", threads=2)


@pytest.fixture(scope="session")
def cornell():
    from guiding.scenes import load_scene

    return load_scene("cornell", scale=0.125)
