"""Progress on stderr for long steps: a one-line bar when stderr is a terminal, silent otherwise.

A ``Progress`` object is the ``progress(fraction, stage)`` callback the numerics accept (their ``progress=``
arguments; ``pipelines.api.analyze(..., progress=)`` passes one through).
Redrawing is rate-limited (at most ~10 times a second) so a callback per window costs nothing.
"""
from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """Callable ``progress(fraction: float, stage: str)``; ``enabled=None`` means "stderr is a tty"."""

    def __init__(self, stream: TextIO | None = None, enabled: bool | None = None, width: int = 30):
        self.stream = stream if stream is not None else sys.stderr
        if enabled is None:
            try:
                enabled = bool(self.stream.isatty())
            except (AttributeError, ValueError):
                enabled = False
        self.enabled = enabled
        self.width = width
        self._last_draw = 0.0
        self._stage = ""
        self._drawn = False

    def __call__(self, fraction: float, stage: str = "") -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        stage = stage or self._stage
        if stage == self._stage and now - self._last_draw < 0.1 and fraction < 1.0:
            return
        self._stage, self._last_draw = stage, now
        f = min(max(float(fraction), 0.0), 1.0) if fraction == fraction else 0.0
        n = int(round(f * self.width))
        line = f"\r  {stage[:28]:<28} [{'#' * n}{'.' * (self.width - n)}] {f * 100:5.1f}%"
        self.stream.write(line)
        self.stream.flush()
        self._drawn = True

    def stage(self, name: str) -> "Progress":
        """Announce a new stage (draws an empty bar)."""
        self(0.0, name)
        return self

    def done(self) -> None:
        """Erase the bar line (call before printing the summary)."""
        if self.enabled and self._drawn:
            self.stream.write("\r" + " " * (self.width + 48) + "\r")
            self.stream.flush()
            self._drawn = False

    def scaled(self, lo: float, hi: float, stage: str) -> "_Scaled":
        """A callback mapping a sub-step's 0..1 onto ``lo..hi`` of this bar, under ``stage``."""
        return _Scaled(self, lo, hi, stage)


class _Scaled:
    def __init__(self, parent: Progress, lo: float, hi: float, stage: str):
        self.parent, self.lo, self.hi, self.stage = parent, lo, hi, stage

    def __call__(self, fraction: float, stage: str = "") -> None:
        label = f"{self.stage}: {stage}" if stage and stage != self.stage else self.stage
        self.parent(self.lo + (self.hi - self.lo) * float(fraction), label)


def null_progress(fraction: float, stage: str = "") -> None:
    """A progress callback that does nothing."""
