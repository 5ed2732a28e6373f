"""Shared set-up: every test runs on the CPU variant with a pinned thread count.

The variant is set at import time, before test modules import the integrator (whose class derives from a
variant-specific Mitsuba type). ``GUIDING_TEST_THREADS`` sets the Dr.Jit thread count (default 2): the verdicts
must not depend on it, and CI-like checks run the suite with 1 and with 2.
"""

import os
import time

import pytest

from guiding.backend import set_variant
from workflow_runs import CI_CONFIG, snakemake

THREADS = int(os.environ.get("GUIDING_TEST_THREADS", "2"))
VARIANT = set_variant("llvm_ad_rgb", threads=THREADS)


@pytest.fixture(scope="session")
def ci_run(tmp_path_factory):
    """One local run of `snakemake --cores 2 --configfile config/ci.yaml` in a temporary working directory, shared by
    the harness's end-to-end tests and the SLURM run they compare with: (working directory, seconds)."""
    workdir = tmp_path_factory.mktemp("ci-run")
    start = time.perf_counter()
    result = snakemake("--cores", 2, "--configfile", CI_CONFIG, "--directory", workdir)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return workdir, time.perf_counter() - start


@pytest.fixture(scope="session")
def cornell():
    from guiding.scenes import load_scene

    return load_scene("cornell", scale=0.125)


def pytest_addoption(parser):
    # Here rather than in tests/stress/conftest.py, so that the option is known whatever paths the run is given.
    parser.addoption("--stress-report", metavar="PATH", default=None,
                     help="write what the stress tests (tests/stress) checked and measured to PATH (Markdown)")
