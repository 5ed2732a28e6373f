"""The command line run in this process (``guiding.cli.main``), and what a refusal of bad input must look like: exit
code 2, one line on stderr, nothing written."""

import contextlib
import io
from dataclasses import dataclass
from pathlib import Path

from guiding.cli import EXIT_BAD_INPUT, main


@dataclass
class CliRun:
    """What a command line run gave: exit code, stderr lines, stdout text."""

    code: int
    errors: list[str]
    output: str


def run_cli(argv: list[str]) -> CliRun:
    """Run ``python -m guiding ARGV`` in this process (``guiding.cli.main``), capturing its output."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return CliRun(code, err.getvalue().strip().splitlines(), out.getvalue())


def one_error_line(run: CliRun, fragment: str, code: int = EXIT_BAD_INPUT) -> list[str]:
    """Problems with a run that should have failed with exit ``code`` and one stderr line containing
    ``fragment``."""
    problems = []
    if run.code != code:
        problems.append(f"exit code {run.code} instead of {code}")
    if len(run.errors) != 1:
        problems.append(f"{len(run.errors)} stderr lines: {run.errors[:3]}")
    elif fragment not in run.errors[0]:
        problems.append(f"'{fragment}' not in: {run.errors[0]}")
    return problems


def files_in(folder) -> list[str]:
    """Files below ``folder`` (none when it does not exist)."""
    folder = Path(folder)
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()) if folder.is_dir() else []


def render_args(out: str, *extra: str, scene: str = "cornell") -> list[str]:
    """A valid, tiny ``render`` command line plus ``extra`` options (a later option overrides an earlier one)."""
    return ["render", "--scene", scene, "--scale", "0.05", "--method", "brdf", "--spp", "1", "--out", out,
            "--quiet", *extra]


def bad_input_violations(runs: list[tuple[str, list[str], str]], folder) -> list[str]:
    """Run each ``(label, argv, fragment)`` and collect what is wrong: not exit 2 with one line containing
    ``fragment``, or a new file below ``folder``."""
    problems = []
    for label, argv, fragment in runs:
        before = set(files_in(folder))
        run = run_cli(argv)
        problems += [f"{label}: {p}" for p in one_error_line(run, fragment)]
        problems += [f"{label}: wrote {f}" for f in sorted(set(files_in(folder)) - before)]
    return problems
