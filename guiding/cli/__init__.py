"""Command line: ``python -m guiding {render, reference, evaluate, bench, demo, validate, sdtree-baseline,
show-guide, scenes, methods}``.

Bad input ends with one line on stderr and a non-zero exit, before any output is written; an interrupted run
(Ctrl-C: exit code 130) leaves no output files behind (they are written atomically, together, last of all).
:mod:`~guiding.cli.parser` reads the arguments (and resolves a render's method, once); :mod:`~guiding.cli.render`
and :mod:`~guiding.cli.studies` run the commands, :mod:`guiding.bench.command` the benchmarks.
"""

from __future__ import annotations

import sys

from guiding.bench.command import command_bench
from guiding.cli.parser import parse_args
from guiding.cli.render import (command_demo, command_evaluate, command_methods, command_reference, command_render,
                                command_scenes, command_show_guide)
from guiding.cli.studies import command_sdtree_baseline, command_validate
from guiding.errors import GuidingError

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130

COMMANDS = {"render": command_render, "reference": command_reference, "evaluate": command_evaluate,
            "bench": command_bench, "validate": command_validate, "demo": command_demo,
            "sdtree-baseline": command_sdtree_baseline,
            "show-guide": command_show_guide, "scenes": command_scenes, "methods": command_methods}


def _interrupted(error: BaseException) -> bool:
    """Whether ``error`` is, or was caused by, Ctrl-C: a KeyboardInterrupt raised inside Python code that Dr.Jit
    calls back (while tracing a loop) can reach us wrapped in another exception."""
    while error is not None:
        if isinstance(error, KeyboardInterrupt):
            return True
        error = error.__cause__ or error.__context__
    return False


def main(argv: list[str] | None = None) -> int:
    try:
        args = parse_args(argv)
        COMMANDS[args.command](args)
    except GuidingError as error:
        print(f"error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BaseException as error:
        if not _interrupted(error):
            raise
        print("interrupted: no output was written", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0
