"""Shared set-up: every test runs on the CPU variant with a pinned thread count.

The variant is set at import time, before test modules import the integrator (whose class derives from a
variant-specific Mitsuba type). ``GUIDING_TEST_THREADS`` sets the Dr.Jit thread count (default 2): the verdicts
must not depend on it, and CI-like checks run the suite with 1 and with 2.
"""

import os

import pytest

from guiding.backend import set_variant

THREADS = int(os.environ.get("GUIDING_TEST_THREADS", "2"))
VARIANT = set_variant("llvm_ad_rgb", threads=THREADS)


@pytest.fixture(scope="session")
def cornell():
    from guiding.scenes import load_scene

    return load_scene("cornell", scale=0.125)


def pytest_addoption(parser):
    # Here rather than in tests/stress/conftest.py, so that the option is known whatever paths the run is given.
    parser.addoption("--stress-report", metavar="PATH", default=None,
                     help="write what the stress tests (tests/stress) checked and measured to PATH (Markdown)")
