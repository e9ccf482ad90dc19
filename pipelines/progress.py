"""Progress on stderr for long steps: a one-line bar when stderr is a terminal, silent otherwise.

A ``Progress`` object is the ``progress(fraction, stage)`` callback the numerics accept (their ``progress=``
arguments; ``pipelines.api.analyze(..., progress=)`` passes one through).
Redrawing is rate-limited (at most ~10 times a second) so a callback per window costs nothing.
"""
from __future__ import annotations

import shutil
import sys
import time
from typing import TextIO

#: the stage's label takes what the terminal's width leaves beside the bar and the percentage, within these;
#: the bar is BAR_PREFERRED wide where the label has room, else narrower (down to BAR_MIN), up to BAR_MAX
LABEL_MIN, LABEL_MAX = 28, 60
BAR_MIN, BAR_PREFERRED, BAR_MAX = 10, 24, 30
#: the line's other characters: two of indent, " [", "] " and "100.0%"
_FIXED = 12


class Progress:
    """Callable ``progress(fraction: float, stage: str)``; ``enabled=None`` means "stderr is a tty"."""

    def __init__(self, stream: TextIO | None = None, enabled: bool | None = None, width: int | None = None):
        self.stream = stream if stream is not None else sys.stderr
        if enabled is None:
            try:
                enabled = bool(self.stream.isatty())
            except (AttributeError, ValueError):
                enabled = False
        self.enabled = enabled
        # the bar, the label and the percentage on one line of the terminal (a line longer than the terminal
        # wraps, and each redraw then adds a line): the label as wide as the rest leaves, within LABEL_MIN..MAX
        cols = shutil.get_terminal_size((80, 24)).columns
        self.label_width = min(max(cols - 1 - _FIXED - BAR_PREFERRED, LABEL_MIN), LABEL_MAX)
        self.width = (width if width is not None
                      else min(max(cols - 1 - _FIXED - self.label_width, BAR_MIN), BAR_MAX))
        self._last_draw = 0.0
        self._line = 0
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
        w = self.label_width
        label = stage if len(stage) <= w else stage[:w - 3] + "..."
        line = f"  {label:<{w}} [{'#' * n}{'.' * (self.width - n)}] {f * 100:5.1f}%"
        self._line = len(line)
        self.stream.write("\r" + line)
        self.stream.flush()
        self._drawn = True

    def stage(self, name: str) -> "Progress":
        """Announce a new stage (draws an empty bar)."""
        self(0.0, name)
        return self

    def done(self) -> None:
        """Erase the bar line (call before printing the summary)."""
        if self.enabled and self._drawn:
            self.stream.write("\r" + " " * self._line + "\r")
            self.stream.flush()
            self._drawn = False

    def scaled(self, lo: float, hi: float, stage: str) -> "_Scaled":
        """A callback mapping a sub-step's 0..1 onto ``lo..hi`` of this bar, under ``stage``."""
        return _Scaled(self, lo, hi, stage)


class _Scaled:
    def __init__(self, parent: Progress, lo: float, hi: float, stage: str):
        self.parent, self.lo, self.hi, self.stage = parent, lo, hi, stage

    def __call__(self, fraction: float, stage: str = "") -> None:
        label = f"{self.stage}: {_without_head(stage, self.stage)}" if stage and stage != self.stage else self.stage
        self.parent(self.lo + (self.hi - self.lo) * float(fraction), label)


def _without_head(sub: str, stage: str) -> str:
    """A sub-step's label without the stage's first word it repeats ("alignment (compensated)" and
    "alignment filter": "filter"; "latency" and "latency: done": "done")."""
    head = stage.split(" ", 1)[0].rstrip(":")
    if head and sub.startswith(head) and len(sub) > len(head) and sub[len(head)] in " :":
        return sub[len(head):].lstrip(" :") or sub
    return sub


def null_progress(fraction: float, stage: str = "") -> None:
    """A progress callback that does nothing."""
