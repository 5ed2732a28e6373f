"""Snakemake runs of this checkout's workflow, for the harness's tests (tests/test_harness.py, tests/test_slurm.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CI_CONFIG = ROOT / "config" / "ci.yaml"


def checkout_env() -> dict[str, str]:
    """The environment with this checkout first on PYTHONPATH: jobs run in another folder (--directory), where
    `python -m guiding` would otherwise import whichever copy of the package pip installed."""
    paths = [str(ROOT), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}


def snakemake_command(*args) -> list[str]:
    return [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), *map(str, args)]


def snakemake(*args, cwd=ROOT, timeout=300, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(snakemake_command(*args), cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env=checkout_env(), **kwargs)
