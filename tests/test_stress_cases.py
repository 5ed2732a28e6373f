"""Numerical stability and bad input: every stress case of :mod:`guiding.stress` as one test.

``python -m guiding stress`` runs the same cases and writes ``results/stress.md``. A case whose check already
lives in another test file (its ``covered_by``) is not run twice.
"""

import pytest

from guiding import stress


@pytest.mark.parametrize("name", [name for name, case in stress.CASES.items() if case.covered_by is None])
def test_stress_case(name):
    figures = stress.CASES[name].run()
    assert isinstance(figures, dict)
