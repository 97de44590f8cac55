"""A tiny progress bar on stderr for long runs (no dependency)."""

from __future__ import annotations

import math
import sys
import time


class ProgressBar:
    """A one-line progress bar on `stream`: redrawn in place on a terminal; elsewhere (a log)
    printed as a new line at every tenth of the run. Call it with (done, total, elapsed_s)."""

    def __init__(self, label: str, stream=None, tty: bool | None = None, width: int = 28):
        self.label, self.width = label, width
        self.stream = sys.stderr if stream is None else stream
        self.tty = isatty(self.stream) if tty is None else tty
        self.first = None  # (done, elapsed) after the first call, which includes compilation
        self.last_draw = -math.inf
        self.last_tenth = -1
        self.drawn = False

    def __call__(self, done: int, total: int, elapsed: float) -> None:
        if self.first is None and done > 0:
            self.first = (done, elapsed)  # this call included the compilation
        frac = done / total if total else 1.0
        now = time.perf_counter()
        if self.tty:
            if done < total and now - self.last_draw < 0.1:
                return
        elif int(10 * frac) <= self.last_tenth and done < total:
            return
        self.last_draw, self.last_tenth = now, int(10 * frac)
        filled = int(round(self.width * frac))
        eta = ", compiling..." if done == 0 else ""
        d0, e0 = self.first or (done, elapsed)
        if d0 < done < total:
            eta = f", ~{(elapsed - e0) / (done - d0) * (total - done):.0f} s left"
        line = (
            f"{self.label} [{'#' * filled}{'.' * (self.width - filled)}] {100 * frac:3.0f}% "
            f"{done:,}/{total:,} steps, {elapsed:.1f} s{eta}"
        )
        if self.tty:
            self.stream.write("\r" + line + "\x1b[K")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
        self.drawn = True

    def close(self) -> None:
        if self.tty and self.drawn:
            self.stream.write("\n")
            self.stream.flush()


def isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False
