"""``python -m guiding stress``: runs the stress cases and writes results/stress.md, failing with one line when a
case fails."""

import pytest

from guiding import stress
from guiding.cli import main


CHEAP_CASES = ["memory-limit-refusal", "bad-scenes"]


def test_report_lists_every_case_run_with_its_outcome(tmp_path):
    assert main(["stress", "--cases", ",".join(CHEAP_CASES), "--out", str(tmp_path)]) == 0
    report = (tmp_path / "stress.md").read_text()
    rows = [line for line in report.splitlines() if line.startswith("| ") and "`" in line]
    assert [row.split("`")[1] for row in rows] == CHEAP_CASES
    assert all("| pass (" in row for row in rows)
    assert f"**{len(CHEAP_CASES)} of {len(CHEAP_CASES)} cases pass**" in report


def test_a_failing_case_is_reported_and_fails_the_command(tmp_path, capsys, monkeypatch):
    def broken() -> dict:
        stress.check(False, "measured 2, expected 1")

    monkeypatch.setitem(stress.CASES, "broken", stress.Case("broken", "tables", "a case that fails", broken))
    assert main(["stress", "--cases", "broken", "--out", str(tmp_path)]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 1 and "stress cases failed: broken" in errors[0]
    assert "FAIL (" in (tmp_path / "stress.md").read_text() and "measured 2, expected 1" in \
        (tmp_path / "stress.md").read_text()


def test_unknown_case_is_one_line(tmp_path, capsys):
    assert main(["stress", "--cases", "no-such-case", "--out", str(tmp_path)]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 1 and "unknown stress case" in errors[0]
    assert not (tmp_path / "stress.md").exists()


@pytest.mark.parametrize("group", stress.GROUPS)
def test_every_group_has_cases_and_notes(group):
    assert any(case.group == group for case in stress.CASES.values())
    assert stress.NOTES[group]
