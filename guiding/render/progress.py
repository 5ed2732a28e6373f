"""What a render shows while it runs: progress on stderr with an ETA, and snapshots of its image as EXR files."""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from guiding.imageio import write_exr

class SnapshotWriter:
    """A ``snapshot`` callback for :func:`render` that writes ``image_snapNNNNN.exr`` (spp zero-padded to five
    digits, atomically) into ``folder`` and lists them in :attr:`entries` (for ``stats.json``). ``metadata``: the
    EXR header attributes every snapshot carries (:func:`guiding.imageio.write_exr`), its spp added."""

    def __init__(self, folder: str | Path, metadata: dict | None = None):
        self.folder = Path(folder)
        self.metadata = metadata or {}
        self.entries: list[dict] = []

    def __call__(self, spp: int, image: np.ndarray, seconds: float, spp_in_image: int) -> None:
        name = f"image_snap{spp:05d}.exr"
        # Listed before it is written: a Ctrl-C that lands between the file's rename and its listing (Mitsuba
        # delivers it late) must still find the file to remove; stats.json, written last, never lists a failed one.
        self.entries.append({"spp": spp, "file": name, "seconds": seconds, "spp_in_image": spp_in_image})
        write_exr(self.folder / name, image, {**self.metadata, "spp": spp, "spp_in_image": spp_in_image})


#: Seconds between two progress lines when stderr is not a terminal (a Snakemake job's log, a pipe): often enough to
#: show that a long reference is alive, rarely enough to keep its log short.
PROGRESS_LINE_SECONDS = 10.0


class Progress:
    """Progress of a render on stderr, with its ETA: a tqdm bar on a terminal; elsewhere (a Snakemake job's log, a
    pipe), where a redrawn bar would be one endless line, a plain line of tqdm's meter every
    :data:`PROGRESS_LINE_SECONDS` and one when the budget is spent.

    ``budget``: the render's budget (spp, or counted seconds, are the progress). ``enabled``: None: the bar on a
    terminal, lines elsewhere; True: the bar; False: nothing.
    """

    def __init__(self, budget, enabled: bool | None):
        self.by_spp = budget.spp is not None
        self.total = budget.spp if self.by_spp else budget.seconds
        amount = "{n:g}/{total:g} spp" if self.by_spp else "{n:.1f}/{total:g} s counted"
        self.lines = enabled is None and not sys.stderr.isatty()
        self.started = time.monotonic()
        self.last_line = -math.inf
        self.bar = None
        if enabled or (enabled is None and not self.lines):
            meter = "{desc}: {percentage:3.0f}%|{bar}| " + amount + " [{elapsed}<{remaining}{postfix}]"
            self.bar = tqdm(total=self.total, desc="render", file=sys.stderr, bar_format=meter)
        self.line_format = "{desc}: " + amount + " ({percentage:.0f}%), {elapsed} elapsed, ETA {remaining}{postfix}"

    def _done(self, spp: int, counted: float) -> float:
        return spp if self.by_spp else min(counted, self.total)

    def show(self, spp: int, counted: float) -> None:
        """After a pass: ``spp`` samples per pixel rendered, ``counted`` seconds counted against the budget."""
        done = self._done(spp, counted)
        postfix = None if self.by_spp else f"{spp} spp"
        if self.bar is not None:
            self.bar.set_postfix_str(postfix or "", refresh=False)
            self.bar.update(done - self.bar.n)
            return
        now = time.monotonic()
        if self.lines and (now - self.last_line >= PROGRESS_LINE_SECONDS or done >= self.total):
            self.last_line = now
            print(tqdm.format_meter(done, self.total, now - self.started, prefix="render", postfix=postfix,
                                    bar_format=self.line_format), file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
