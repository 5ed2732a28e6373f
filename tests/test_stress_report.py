"""``--stress-report PATH`` (tests/stress/conftest.py): the stress tests' outcomes and measured figures, written
from the test run."""

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

TESTS = Path(__file__).parent
#: The runs below start a new pytest each: without the plugins they do not use, they start in half the time.
LEAN = ("-p", "no:cacheprovider", "-p", "no:hypothesispytest", "-p", "no:benchmark")

#: A group of stress tests that pass, fail and crash, run beside copies of the real conftest files.
EXAMPLE_GROUP = '''
"""Example group: what it drives.

What it found."""

import pytest


def test_measures(figures):
    """Measures the answer.

    (Not part of the description.)"""
    figures["answer"] = 42
    figures["nested"] = {"x": 0.5}


def test_fails(figures):
    """A check that fails."""
    figures["measured"] = 2
    assert 2 == 1, "measured 2, expected 1"


def test_crashes():
    """A test that raises."""
    raise ValueError("broken input")


@pytest.mark.parametrize("case", ["a", "b"])
def test_parametrised(case, figures):
    """One description for all cases."""
    figures["case"] = case
'''


@pytest.fixture
def stress_suite(pytester):
    """A copy of the test layout: the two conftest files (and the helper module the top one imports) and
    ``stress/test_example.py``."""
    pytester.makeini("[pytest]\n")
    pytester.makeconftest((TESTS / "conftest.py").read_text())
    pytester.makepyfile(workflow_runs=(TESTS / "workflow_runs.py").read_text())
    stress = pytester.mkdir("stress")
    (stress / "conftest.py").write_text((TESTS / "stress" / "conftest.py").read_text())
    (stress / "test_example.py").write_text(EXAMPLE_GROUP)
    return pytester


def rows(report: str) -> dict[str, str]:
    """The report's table rows by test name."""
    return {line.split("`")[1]: line for line in report.splitlines() if line.startswith("| `")}


def test_report_lists_every_test_with_its_outcome_and_figures(stress_suite):
    result = stress_suite.runpytest_subprocess(*LEAN, "stress", "--stress-report", "out/stress.md")
    result.assert_outcomes(passed=3, failed=2)
    report = (stress_suite.path / "out" / "stress.md").read_text()
    assert "**3 of 5 tests pass**" in report and "--stress-report out/stress.md" in report
    assert "## example (`test_example.py`)" in report and "What it found." in report
    row = rows(report)
    assert list(row) == ["test_measures", "test_fails", "test_crashes", "test_parametrised[a]",
                         "test_parametrised[b]"]
    assert "| Measures the answer. | pass (" in row["test_measures"]
    assert "answer=42; nested/x=0.5" in row["test_measures"]
    assert "| FAIL (" in row["test_fails"] and "measured 2, expected 1" in row["test_fails"]
    assert "measured=2" in row["test_fails"]
    assert "| ERROR (" in row["test_crashes"] and "ValueError: broken input" in row["test_crashes"]
    assert "One description" in row["test_parametrised[a]"] and "One description" not in row["test_parametrised[b]"]
    assert "case=b" in row["test_parametrised[b]"]


def test_an_interrupted_run_leaves_the_previous_report(stress_suite):
    (stress_suite.path / "stress" / "test_interrupted.py").write_text(
        "def test_ctrl_c():\n    raise KeyboardInterrupt\n")
    previous = stress_suite.path / "stress.md"
    previous.write_text("the previous report\n")
    result = stress_suite.runpytest_subprocess(*LEAN, "stress", "--stress-report", "stress.md")
    assert result.ret == pytest.ExitCode.INTERRUPTED
    assert previous.read_text() == "the previous report\n"
    assert [p.name for p in stress_suite.path.iterdir() if "stress.md" in p.name] == ["stress.md"]   # no temporary


def test_report_of_a_real_stress_test(tmp_path):
    report = tmp_path / "stress.md"
    root = TESTS.parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", *LEAN,
                           "tests/stress/test_bad_input.py::test_unwritable_output", "--stress-report", str(report)],
                          cwd=root, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    text = report.read_text()
    assert "**1 of 1 tests pass**" in text and "## bad input (`test_bad_input.py`)" in text
    assert "| pass (" in rows(text)["test_unwritable_output"] and "inputs=2" in rows(text)["test_unwritable_output"]


@pytest.mark.parametrize("module", sorted(p.name for p in (TESTS / "stress").glob("test_*.py")))
def test_every_stress_group_and_test_describes_itself(module):
    """The report's text comes from docstrings: a group's summary and findings, and what each test checks."""
    tree = ast.parse((TESTS / "stress" / module).read_text())
    summary, _, findings = (ast.get_docstring(tree) or "").partition("\n\n")
    assert summary and findings, f"{module}: the docstring needs a summary line and a paragraph of findings"
    undescribed = [node.name for node in tree.body if isinstance(node, ast.FunctionDef)
                   and node.name.startswith("test_") and not ast.get_docstring(node)]
    assert not undescribed, f"{module}: tests without a docstring: {undescribed}"
