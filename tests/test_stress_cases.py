"""Numerical stability and bad input: every stress case of :mod:`guiding.stress` as one test.

``python -m guiding stress`` runs the same cases and writes ``results/stress.md``.
"""

import pytest

from guiding import stress


@pytest.mark.parametrize("name", list(stress.CASES))
def test_stress_case(name):
    figures = stress.CASES[name].run()
    assert isinstance(figures, dict)
