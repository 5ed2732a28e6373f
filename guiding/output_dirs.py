"""Output folders of the commands: made (or refused with one line) before anything is written, and removed again if
the command fails before writing to them."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from guiding.errors import GuidingError


def prepare_output_dir(path: str) -> Path:
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise GuidingError(f"output folder '{out}' exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise GuidingError(f"cannot create output folder '{out}': {error.strerror}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise GuidingError(f"output folder '{out}' is not writable")
    return out


@contextlib.contextmanager
def output_dir(path: str):
    """:func:`prepare_output_dir`, and the folders it made removed again if the block fails: bad input found
    later (a broken scene file) or Ctrl-C leaves no empty output folder behind."""
    out = Path(path)
    made = [folder for folder in (out, *out.parents) if not folder.exists()]   # deepest first
    folder = prepare_output_dir(path)
    try:
        yield folder
    except BaseException:
        for made_folder in made:
            with contextlib.suppress(OSError):   # not empty: something else wrote there, keep it
                made_folder.rmdir()
        raise
