"""svgplot: small line plots as inline SVG, drawn straight from numpy arrays (numpy is the only
dependency).

Made for report.html: a page that has to open offline, print, and paste into a flight-test report,
with no script and no network. An inline ``<svg>`` does all of that, and building one takes
milliseconds. matplotlib/Agg took seconds to draw the same figures to PNG.

Usage::

    fig = Figure(2, 1, panel=(500, 160), sharex=True, title="Angular rate")
    ax = fig.ax(0, 0)
    ax.line(t, w, color="master", label="master")
    ax.band(t, lo, hi, color="compensated", label="±3σ")
    ax.title("roll"); ax.ylabel("deg"); ax.legend()
    markup = fig.to_svg("angular rates")

What it does:

* A ``Figure`` is a grid of ``Axes``. ``panel`` sets the size of each plot area in pixels. Margins
  for the tick labels, axis labels and titles are worked out from the text and added around the
  plot areas.
* Each axes draws, in the order added: ``line``, ``points`` (markers), ``band`` (a filled area
  between two curves), ``vline`` and ``vspan``. Bands and spans go under lines and markers.
* Ticks fall on 1-2-5 steps and are printed to the precision of the step. When the numbers are huge
  or tiny, an offset and/or a power of ten is noted at the end of the axis ("×10⁻³", "+1700000000").
  Grid lines are light.
* NaN or inf ends a line: a line with a gap becomes two paths. Non-finite limits are ignored. An
  axes without data says "no data".
* A long series is decimated to the min and max of each bucket of samples, about one bucket per
  pixel column, so a single-sample spike stays visible.
* Inside a plot area the drawing unit is 0.1 px (a nested ``<svg>`` with a 10x ``viewBox``). That
  makes every path coordinate an integer, rounded to 0.1 px. The nested ``<svg>`` also clips the
  data to the plot area, and it needs no id, so many figures can share one page.
* Every piece of text is XML-escaped. Labels use Unicode ("ωx", "±3σ"), not mathtext.

Line widths and marker sizes are in points, as in matplotlib (1 pt = 4/3 px). Colours are CSS
colours, or the names in ``COLORS`` ("master", "slave", "uncompensated", "compensated"), or
``"C0"``..``"C9"`` (matplotlib's default cycle). Dashes are ``"-"``, ``"--"``, ``":"`` or ``"-."``.
The look (fonts, sizes, greys) is set in one place, ``STYLE``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from html import escape

import numpy as np

__all__ = ["Figure", "Axes", "nice_ticks", "tick_labels", "decimate", "COLORS", "STYLE", "MAX_POINTS"]

# ---- style: the one place for the look -----------------------------------------------------------
STYLE = {
    "font": "system-ui,-apple-system,'Segoe UI',Roboto,Helvetica,Arial,sans-serif",
    "text": "#1d2733",       # titles, labels
    "tick_text": "#3d4a57",  # tick labels, notes
    "axis": "#6b7785",       # spines and tick marks
    "grid": "#e4e8ed",
    "legend_bg": "#ffffff", "legend_border": "#c9d1da", "legend_opacity": 0.88,
    "fs_tick": 11, "fs_label": 12, "fs_title": 12.5, "fs_suptitle": 14, "fs_legend": 11, "fs_note": 10.5,
    "char_w": 0.56,          # average glyph width / font size, to estimate text widths
    "tick_len": 4, "pad": 4,
    "x_margin": 0.02, "y_margin": 0.05,  # data margins inside the limits (fraction of the range)
    "x_tick_px": 60, "y_tick_px": 30, "max_ticks": 10,  # about one tick per this many pixels
    "col_gap": 22,           # extra space between columns, besides the tick labels
    "pt": 4 / 3,             # px per point: line widths and marker sizes are in points, as in matplotlib
}
#: named colours: the runs and logs of tapost, and matplotlib's default cycle as C0..C9
COLORS = {
    "master": "#000000", "slave": "#ff7f0e", "uncompensated": "#d62728", "compensated": "#1f77b4",
    **{f"C{i}": c for i, c in enumerate(("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b",
                                          "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"))},
}
#: dash patterns (in units of the line width), matplotlib's names
DASHES = {"-": None, "--": (3.7, 1.6), ":": (1.0, 1.65), "-.": (6.4, 1.6, 1.0, 1.6)}
#: the most points one series keeps after decimation (also capped at about two per pixel column)
MAX_POINTS = 4000
PT = STYLE["pt"]
SUB = 10  # drawing units per pixel inside a plot area (coordinates are integers in 0.1 px)
_CLAMP = 10_000_000  # |coordinate| bound in drawing units, so that far-off values stay finite


def _color(c: str | None) -> str:
    return COLORS.get(c, c) if c else COLORS["C0"]


def _text_w(s: str, fs: float) -> float:
    """Estimated width (px) of ``s`` in the sans-serif font at size ``fs``."""
    return len(s) * fs * STYLE["char_w"]


def _wrap(text: str, width_px: float, fs: float) -> list[str]:
    """``text`` split at its newlines, then word-wrapped to ``width_px`` (estimated)."""
    out: list[str] = []
    for para in str(text).split("\n"):
        line = ""
        for word in para.split(" "):
            trial = f"{line} {word}" if line else word
            if line and _text_w(trial, fs) > width_px:
                out.append(line)
                line = word
            else:
                line = trial
        out.append(line)
    return out


def _num(v: float) -> str:
    """A coordinate or size for an attribute: at most 0.1 px, no trailing zeros."""
    s = f"{v:.1f}"
    return s[:-2] if s.endswith(".0") else s


def _text(x: float, y: float, s: str, fs: float, *, anchor: str = "middle", fill: str | None = None,
          weight: str | None = None, rotate: bool = False) -> str:
    """One ``<text>`` element (escaped); ``y`` is the baseline, ``rotate`` turns it by -90 degrees."""
    attrs = f'x="{_num(x)}" y="{_num(y)}" font-size="{_num(fs)}"'
    if anchor != "start":
        attrs += f' text-anchor="{anchor}"'
    if fill:
        attrs += f' fill="{fill}"'
    if weight:
        attrs += f' font-weight="{weight}"'
    if rotate:
        attrs += f' transform="rotate(-90 {_num(x)} {_num(y)})"'
    return f"<text {attrs}>{escape(s)}</text>"


# ---- ticks ---------------------------------------------------------------------------------------
def nice_ticks(lo: float, hi: float, target: float = 6) -> np.ndarray:
    """Tick values on a 1-2-5 step (1, 2 or 5 times a power of ten) within [lo, hi]: the step whose
    tick count is nearest ``target``, with at least two ticks (the coarser step on a tie)."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return np.array([lo]) if math.isfinite(lo) else np.zeros(0)
    e = math.floor(math.log10((hi - lo) / max(target, 1.0)))
    best = None
    for step in (m * 10.0**k for k in (e - 1, e, e + 1) for m in (1, 2, 5)):
        k0, k1 = math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9)
        n = k1 - k0 + 1
        if n >= 2 and (best is None or abs(n - target) <= abs(best[0] - target)):
            best = (n, k0, k1, step)  # steps rise, so a tie goes to the coarser one
    _, k0, k1, step = best
    return np.arange(k0, k1 + 1) * step


_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def tick_labels(ticks: np.ndarray) -> tuple[list[str], str]:
    """Labels for ``ticks`` (as made by ``nice_ticks``) at the precision of their step, and a note
    for the axis end: an offset when the numbers are large compared with their spread, a power of
    ten when they are huge or tiny ("" when neither is needed). label × scale + offset = value."""
    t = np.asarray(ticks, float)
    if t.size == 0:
        return [], ""
    step = float(np.min(np.diff(t))) if t.size > 1 else (abs(float(t[0])) or 1.0)
    offset = 0.0
    big = float(np.max(np.abs(t)))
    if big / step >= 1e5:  # e.g. UNIX seconds: 1700000080, 1700000100 -> 80, 100 and "+1700000000"
        p = 10.0 ** math.floor(math.log10(step * (t.size - 1 or 1)))  # the decade of the span
        offset = math.floor(float(t[0]) / p) * p
        t = t - offset
        big = float(np.max(np.abs(t)))
    exp = 0
    if big >= 1e5 or (0 < big < 1e-3):
        exp = int(math.floor(math.log10(big)))
        t, step = t / 10.0**exp, step / 10.0**exp
    dec = max(0, -math.floor(math.log10(step) + 1e-9))
    labels = []
    for v in t:
        s = f"{0.0 if abs(v) < step * 1e-6 else v:.{dec}f}"
        labels.append(s.replace("-", "\u2212"))
    note = []
    if exp:
        note.append("×10" + str(exp).translate(_SUPERSCRIPT))
    if offset:
        note.append(f"{offset:+.12g}".replace("-", "\u2212"))
    return labels, " ".join(note)


# ---- decimation ----------------------------------------------------------------------------------
def _buckets(n: int, nb: int) -> tuple[int, int]:
    """(samples per bucket, number of buckets) for ``n`` samples in at most ``nb`` buckets."""
    k = int(math.ceil(n / max(nb, 1)))
    return k, int(math.ceil(n / k))


def decimate(x: np.ndarray, y: np.ndarray, n: int = MAX_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """At most about ``n`` points of (x, y) that keep the shape: the min and the max of each bucket
    of consecutive samples, in their order, so that a one-sample spike survives. A bucket that holds
    a NaN also keeps one NaN, so a gap stays a gap. Arrays shorter than ``n`` are returned as given."""
    x, y = np.asarray(x), np.asarray(y, float)
    m = len(y)
    if m <= n:
        return x, y
    k, nb = _buckets(m, max(n // 2, 1))
    yy = np.full(nb * k, np.nan)
    yy[:m] = y
    yy = yy.reshape(nb, k)
    finite = np.isfinite(yy)
    base = np.arange(nb) * k
    i_lo = base + np.where(finite, yy, np.inf).argmin(axis=1)
    i_hi = base + np.where(finite, yy, -np.inf).argmax(axis=1)
    real = (base[:, None] + np.arange(k)) < m
    gap = ~finite & real
    i_gap = np.where(gap.any(axis=1), base + gap.argmax(axis=1), i_lo)
    idx = np.unique(np.concatenate([i_lo, i_hi, i_gap]))
    idx = idx[idx < m]
    return x[idx], y[idx]


def _envelope(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, nb: int):
    """A band reduced to ``nb`` buckets: per bucket its first and last x, the lowest ``lo`` and the
    highest ``hi`` (a step envelope that contains every sample)."""
    m = len(x)
    if m <= 2 * nb:
        return x, lo, hi
    k, nb = _buckets(m, nb)
    pad = nb * k - m

    def grid(a, fill):
        return np.concatenate([np.asarray(a, float), np.full(pad, fill)]).reshape(nb, k)

    blo = np.fmin.reduce(grid(lo, np.nan), axis=1)  # fmin/fmax skip NaN (an all-NaN bucket stays NaN)
    bhi = np.fmax.reduce(grid(hi, np.nan), axis=1)
    first = np.arange(nb) * k
    last = np.minimum(first + k - 1, m - 1)
    xx = np.column_stack([x[first], x[last]]).ravel()
    return xx, np.repeat(blo, 2), np.repeat(bhi, 2)


def _runs(ok: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of each run of True in ``ok``."""
    d = np.diff(np.concatenate([[0], ok.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


# ---- data --------------------------------------------------------------------------------------
@dataclass
class Series:
    """One thing drawn in an axes. ``kind`` is line, points, band (``y`` low, ``y2`` high), vline or
    vspan (``x`` and ``x2``)."""

    kind: str
    x: np.ndarray
    y: np.ndarray | None = None
    y2: np.ndarray | None = None
    x2: float | None = None
    color: str = "C0"
    dash: str | None = None
    width: float = 1.2
    opacity: float = 1.0
    size: float = 3.5
    label: str | None = None

    @property
    def layer(self) -> int:
        return 0 if self.kind in ("band", "vspan") else 1


def _finite_range(*arrays) -> tuple[float, float] | None:
    vals = [a[np.isfinite(a)] for a in arrays if a is not None and np.size(a)]
    vals = [v for v in vals if v.size]
    if not vals:
        return None
    return float(min(v.min() for v in vals)), float(max(v.max() for v in vals))


class Axes:
    """One panel of a Figure: its series, labels and limits (drawn by ``Figure.to_svg``)."""

    def __init__(self, row: int, col: int):
        self.row, self.col = row, col
        self.series: list[Series] = []
        self.title_text = ""
        self.xlabel_text = ""
        self.ylabel_text = ""
        self.xlim_given: tuple[float | None, float | None] = (None, None)
        self.ylim_given: tuple[float | None, float | None] = (None, None)
        self.legend_loc: str | None = None
        self.visible = True

    # -- content
    def line(self, x, y, color: str = "C0", dash: str | None = None, width: float = 1.2,
             label: str | None = None, opacity: float = 1.0) -> None:
        """A polyline through (x, y), ``width`` in points; a non-finite value breaks it."""
        self.series.append(Series("line", np.asarray(x, float), np.asarray(y, float), color=color, dash=dash,
                                  width=width, opacity=opacity, label=label))

    def points(self, x, y, color: str = "C0", size: float = 3.5, label: str | None = None,
               opacity: float = 1.0) -> None:
        """Round markers of diameter ``size`` points at (x, y)."""
        self.series.append(Series("points", np.asarray(x, float), np.asarray(y, float), color=color,
                                  size=size, opacity=opacity, label=label))

    def band(self, x, lo, hi, color: str = "C0", opacity: float = 0.15, label: str | None = None) -> None:
        """The area between ``lo`` and ``hi`` (matplotlib's fill_between)."""
        self.series.append(Series("band", np.asarray(x, float), np.asarray(lo, float), np.asarray(hi, float),
                                  color=color, opacity=opacity, label=label))

    def vline(self, x: float, color: str = "C0", dash: str | None = None, width: float = 1.0,
              label: str | None = None) -> None:
        """A vertical line across the panel at ``x`` (skipped when not finite)."""
        self.series.append(Series("vline", np.array([float(x)]), color=color, dash=dash, width=width, label=label))

    def vspan(self, x0: float, x1: float, color: str = "C0", opacity: float = 0.15, label: str | None = None) -> None:
        """A shaded vertical strip from ``x0`` to ``x1``."""
        self.series.append(Series("vspan", np.array([float(x0)]), x2=float(x1), color=color, opacity=opacity,
                                  label=label))

    # -- decoration
    def title(self, s: str) -> None:
        self.title_text = str(s)

    def xlabel(self, s: str) -> None:
        self.xlabel_text = str(s)

    def ylabel(self, s: str) -> None:
        self.ylabel_text = str(s)

    def xlim(self, lo: float | None = None, hi: float | None = None) -> None:
        """Fixed x limits (a non-finite or None side is autoscaled)."""
        self.xlim_given = (lo, hi)

    def ylim(self, lo: float | None = None, hi: float | None = None) -> None:
        self.ylim_given = (lo, hi)

    def legend(self, loc: str = "best") -> None:
        """A legend of the labelled series inside the panel: ``best`` (the corner with the least data
        under it) or upper/lower right/left/center."""
        self.legend_loc = loc

    def hide(self) -> None:
        """Leave this grid cell empty."""
        self.visible = False

    # -- limits
    def has_data(self) -> bool:
        return any(_finite_range(s.y, s.y2) is not None for s in self.series if s.kind in ("line", "points", "band"))

    def data_xrange(self) -> tuple[float, float] | None:
        xs = []
        for s in self.series:
            if s.kind in ("line", "points", "band"):
                ok = np.isfinite(s.y) | (np.isfinite(s.y2) if s.y2 is not None else False)
                xs.append(s.x[ok])
            else:
                xs.append(np.array([s.x[0], s.x2 if s.x2 is not None else s.x[0]]))
        return _finite_range(*xs)

    def data_yrange(self, x0: float, x1: float) -> tuple[float, float] | None:
        ys = []
        for s in self.series:
            if s.kind in ("line", "points", "band"):
                m = (s.x >= x0) & (s.x <= x1)
                ys += [s.y[m]] + ([s.y2[m]] if s.y2 is not None else [])
        return _finite_range(*ys)


def _limits(given: tuple, auto: tuple[float, float] | None, margin: float) -> tuple[float, float]:
    """Axis limits: the given finite sides, else the data range with a margin; never empty."""
    lo, hi = auto if auto is not None else (0.0, 1.0)
    if auto is not None:
        if hi == lo:
            d = abs(lo) * 0.05 or 0.5
            lo, hi = lo - d, hi + d
        else:
            pad = (hi - lo) * margin
            lo, hi = lo - pad, hi + pad
    g0, g1 = (v if v is not None and math.isfinite(v) else None for v in given)
    lo, hi = (g0 if g0 is not None else lo), (g1 if g1 is not None else hi)
    if not hi > lo:
        d = abs(lo) * 0.05 or 0.5
        lo, hi = lo - d, lo + d
    return float(lo), float(hi)


# ---- figure --------------------------------------------------------------------------------------
@dataclass
class _Panel:
    """An axes being laid out and drawn: its limits, ticks and position."""

    ax: Axes
    x0: float = 0.0
    x1: float = 1.0
    y0: float = 0.0
    y1: float = 1.0
    xt: np.ndarray = field(default_factory=lambda: np.zeros(0))
    yt: np.ndarray = field(default_factory=lambda: np.zeros(0))
    xl: list = field(default_factory=list)
    yl: list = field(default_factory=list)
    xnote: str = ""
    ynote: str = ""
    show_x: bool = True  # x tick labels and label (False above the bottom row of a shared x)
    note_row: bool = False  # a panel of this row has a y note: the titles sit one line higher
    left: float = 0.0    # plot area origin in figure pixels
    top: float = 0.0


class Figure:
    """A grid of ``rows`` x ``cols`` axes, each plot area ``panel`` = (width, height) pixels.

    ``sharex``: one x range for every panel, tick labels only on the bottom panel of each column.
    ``title``: the figure's title above the grid."""

    def __init__(self, rows: int, cols: int, panel: tuple[int, int] = (360, 180), sharex: bool = False,
                 title: str | None = None):
        self.rows, self.cols = rows, cols
        self.pw, self.ph = int(panel[0]), int(panel[1])
        self.sharex = sharex
        self.title = title or ""
        self.axes = [Axes(r, c) for r in range(rows) for c in range(cols)]

    def ax(self, row: int, col: int = 0) -> Axes:
        return self.axes[row * self.cols + col]

    # -- layout
    def _panels(self) -> list[_Panel]:
        panels = [_Panel(a) for a in self.axes if a.visible]
        shared = None
        if self.sharex:
            rs = [p.ax.data_xrange() for p in panels]
            rs = [r for r in rs if r is not None]
            shared = (min(r[0] for r in rs), max(r[1] for r in rs)) if rs else None
        bottom = {}
        for p in panels:
            bottom[p.ax.col] = max(bottom.get(p.ax.col, -1), p.ax.row)
        for p in panels:
            a = p.ax
            p.x0, p.x1 = _limits(a.xlim_given, shared or a.data_xrange(), STYLE["x_margin"])
            p.y0, p.y1 = _limits(a.ylim_given, a.data_yrange(p.x0, p.x1), STYLE["y_margin"])
            p.show_x = not self.sharex or a.row == bottom[a.col]
            if a.has_data():
                _make_legend_room(p, self.pw, self.ph)
                p.yt = nice_ticks(p.y0, p.y1, min(STYLE["max_ticks"], max(2.0, self.ph / STYLE["y_tick_px"])))
                p.yl, p.ynote = tick_labels(p.yt)
                p.xt, p.xl, p.xnote = _x_ticks(p.x0, p.x1, self.pw)
        return panels

    def _layout(self, panels: list[_Panel]) -> tuple[float, float, list[str]]:
        """Positions every plot area; returns the figure size and the title lines."""
        S = STYLE
        fs_t, lh_t = S["fs_title"], S["fs_title"] * 1.25
        left = [0.0] * self.cols
        right = [0.0] * self.cols
        top = [0.0] * self.rows
        bottom = [0.0] * self.rows
        for p in panels:
            a, c, r = p.ax, p.ax.col, p.ax.row
            tw = max((_text_w(s, S["fs_tick"]) for s in p.yl), default=0.0)
            lw = S["tick_len"] + S["pad"] + tw + (S["fs_label"] + 11 if a.ylabel_text else 0) + 4
            left[c] = max(left[c], lw)
            half_last = _text_w(p.xl[-1], S["fs_tick"]) / 2 if p.xl and p.show_x else 0.0
            right[c] = max(right[c], 10.0 if c == self.cols - 1 else S["col_gap"], half_last + 2)
            n_title = len(_wrap(a.title_text, self.pw + 40, fs_t)) if a.title_text else 0
            top[r] = max(top[r], 8 + n_title * lh_t + (S["fs_note"] + 4 if p.ynote else 0))
            b = S["pad"] + 2
            if p.show_x:
                b = S["tick_len"] + S["pad"] + S["fs_tick"] + 6
                if a.xlabel_text or p.xnote:
                    b += S["fs_label"] + 6
            bottom[r] = max(bottom[r], b)
        width = sum(left) + sum(right) + self.cols * self.pw
        sup = _wrap(self.title, width - 20, S["fs_suptitle"]) if self.title else []
        y = 6 + len(sup) * S["fs_suptitle"] * 1.3 + (8 if sup else 0)
        row_top = []
        for r in range(self.rows):
            row_top.append(y + top[r])
            y += top[r] + self.ph + bottom[r]
        col_left, x = [], 0.0
        for c in range(self.cols):
            col_left.append(x + left[c])
            x += left[c] + self.pw + right[c]
        noted = {p.ax.row for p in panels if p.ynote}
        for p in panels:
            p.left, p.top = col_left[p.ax.col], row_top[p.ax.row]
            p.note_row = p.ax.row in noted
        return width, y + 4, sup

    # -- output
    def to_svg(self, alt: str | None = None) -> str:
        """The figure as one ``<svg>`` element that scales with the page (width 100%, at most its
        natural size); ``alt`` (or the title) becomes its ``<title>`` for screen readers."""
        panels = self._panels()
        width, height, sup = self._layout(panels)
        S = STYLE
        out = [f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {_num(width)} {_num(height)}" '
               f'width="100%" style="max-width:{_num(width)}px;height:auto" role="img" '
               f'font-family="{escape(S["font"])}" fill="{S["text"]}">',
               f"<title>{escape(alt or self.title or 'figure')}</title>"]
        for i, s in enumerate(sup):
            out.append(_text(width / 2, 6 + (i + 0.85) * S["fs_suptitle"] * 1.3, s, S["fs_suptitle"],
                             weight="600"))
        for p in panels:
            out.append(_draw_panel(p, self.pw, self.ph))
        out.append("</svg>")
        return "".join(out)


def _x_ticks(x0: float, x1: float, pw: int):
    """x ticks whose labels fit side by side in ``pw`` pixels."""
    n = min(STYLE["max_ticks"], max(2.0, pw / STYLE["x_tick_px"]))
    while True:
        t = nice_ticks(x0, x1, n)
        labels, note = tick_labels(t)
        widest = max((_text_w(s, STYLE["fs_tick"]) for s in labels), default=0.0)
        if n <= 2 or len(t) * (widest + 12) <= pw:
            return t, labels, note
        n = max(2.0, n - 1)


# ---- drawing one panel ---------------------------------------------------------------------------
def _dash_attr(dash: str | None, width: float, unit: float = SUB) -> str:
    """The stroke-dasharray attribute of a dash style for a line ``width`` points wide ("" if solid),
    in ``unit`` drawing units per pixel."""
    pat = DASHES.get(dash or "-")
    if not pat:
        return ""
    return ' stroke-dasharray="' + " ".join(_num(v * max(width, 1.0) * PT * unit) for v in pat) + '"'


def _path_d(px: np.ndarray, py: np.ndarray) -> str:
    """SVG path data through integer points: one absolute move, then relative line-tos, repeated
    points dropped."""
    pts = np.column_stack([px, py])
    keep = np.ones(len(pts), bool)
    keep[1:] = np.any(pts[1:] != pts[:-1], axis=1)
    pts = pts[keep]
    if len(pts) == 1:
        return f"M{pts[0, 0]} {pts[0, 1]}h0"
    d = np.diff(pts, axis=0)
    return f"M{pts[0, 0]} {pts[0, 1]}l" + " ".join(map(str, d.ravel().tolist()))


class _Mapper:
    """Data to drawing units (0.1 px, integers) of one plot area; a non-finite value maps to 0 (the
    callers mask those samples out)."""

    def __init__(self, p: _Panel, pw: int, ph: int):
        self.p, self.w, self.h = p, pw * SUB, ph * SUB

    @staticmethod
    def _units(u: np.ndarray) -> np.ndarray:
        u = np.nan_to_num(u, nan=0.0, posinf=_CLAMP, neginf=-_CLAMP)
        return np.rint(np.clip(u, -_CLAMP, _CLAMP)).astype(np.int64)

    def x(self, v) -> np.ndarray:
        p = self.p
        return self._units((np.asarray(v, float) - p.x0) / (p.x1 - p.x0) * self.w)

    def y(self, v) -> np.ndarray:
        p = self.p
        return self._units(self.h - (np.asarray(v, float) - p.y0) / (p.y1 - p.y0) * self.h)


def _visible(s: Series, p: _Panel) -> np.ndarray:
    """Indices of the samples within the x limits, plus one either side (so lines reach the edge)."""
    inside = (s.x >= p.x0) & (s.x <= p.x1)
    if inside.all():
        return np.arange(len(s.x))
    near = inside.copy()
    near[1:] |= inside[:-1]
    near[:-1] |= inside[1:]
    return np.flatnonzero(near)


def _draw_series(s: Series, m: _Mapper, pw: int, markup: bool = True) -> tuple[str, list[np.ndarray]]:
    """The markup of one series, and what it covers as polylines ((n, 2) arrays in drawing units;
    markers as one-point lines) for placing the legend; ``markup=False`` leaves the paths out when
    only the polylines are wanted. Vertical lines and spans cover nothing: they run across the whole
    panel, so a legend over one end leaves them readable."""
    p = m.p
    col = _color(s.color)
    label = f' aria-label="{escape(s.label)}"' if s.label else ""
    op = f' opacity="{s.opacity:g}"' if s.opacity < 1 else ""
    if s.kind == "vline":
        if not math.isfinite(s.x[0]):
            return "", []
        x = int(m.x(s.x)[0])
        return (f'<path{label} d="M{x} 0v{m.h}" stroke="{col}" stroke-width="{_num(s.width * PT * SUB)}"'
                f'{_dash_attr(s.dash, s.width)} fill="none"/>'), []  # a legend over a part of it hides nothing
    if s.kind == "vspan":
        if not (math.isfinite(s.x[0]) and s.x2 is not None and math.isfinite(s.x2)):
            return "", []
        a, b = sorted(m.x(np.array([s.x[0], s.x2])).tolist())
        return (f'<rect{label} x="{a}" y="0" width="{max(b - a, 1)}" height="{m.h}" fill="{col}" '
                f'fill-opacity="{s.opacity:g}"/>'), []
    idx = _visible(s, p)
    x = s.x[idx]
    if s.kind == "band":
        x, lo, hi = _envelope(x, s.y[idx], s.y2[idx], max(pw // 2, 1))
        ok = np.isfinite(x) & np.isfinite(lo) & np.isfinite(hi)
        X, L, H = m.x(x), m.y(lo), m.y(hi)
        paths, edges = [], []
        for a, b in _runs(ok):
            edges += [np.column_stack([X[a:b], L[a:b]]), np.column_stack([X[a:b], H[a:b]])]
            if markup:  # along the upper edge, back along the lower one
                d = _path_d(np.concatenate([X[a:b], X[a:b][::-1]]), np.concatenate([H[a:b], L[a:b][::-1]]))
                paths.append(f'<path d="{d}z"/>')
        return (f'<g{label} fill="{col}" fill-opacity="{s.opacity:g}" stroke="none">' + "".join(paths) + "</g>",
                edges)
    y = s.y[idx]
    if s.kind == "points":
        x, y = decimate(x, y, MAX_POINTS)
        ok = np.isfinite(x) & np.isfinite(y)
        X, Y = m.x(x[ok]), m.y(y[ok])
        r = _num(s.size / 2 * PT * SUB)
        dots = "".join(f'<circle cx="{a}" cy="{b}" r="{r}"/>' for a, b in zip(X.tolist(), Y.tolist()) if markup)
        return f'<g{label} fill="{col}"{op}>{dots}</g>', [np.column_stack([X, Y])]
    x, y = decimate(x, y, min(MAX_POINTS, 2 * pw))
    ok = np.isfinite(x) & np.isfinite(y)
    X, Y = m.x(x), m.y(y)
    runs = [(a, b) for a, b in _runs(ok) if b - a >= 2]
    paths = [f'<path d="{_path_d(X[a:b], Y[a:b])}"/>' for a, b in runs if markup]
    return (f'<g{label} fill="none" stroke="{col}" stroke-width="{_num(s.width * PT * SUB)}"'
            f'{_dash_attr(s.dash, s.width)} stroke-linejoin="round" stroke-linecap="round"{op}>'
            + "".join(paths) + "</g>",
            [np.column_stack([X[a:b], Y[a:b]]) for a, b in runs])


def _densify(line: np.ndarray, w: int, h: int, step: float = 3 * SUB) -> np.ndarray:
    """The points of a polyline (drawing units) every ``step`` or closer, the line clipped to the
    plot area first (so that its length stays bounded): what a legend box placed there would hide."""
    pts = np.column_stack([np.clip(line[:, 0], 0, w), np.clip(line[:, 1], 0, h)]).astype(float)
    if len(pts) < 2:
        return pts
    d = np.diff(pts, axis=0)
    n = np.clip(np.ceil(np.hypot(d[:, 0], d[:, 1]) / step), 1, None).astype(np.int64)
    seg = np.repeat(np.arange(len(d)), n)
    frac = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / n[seg]
    return np.vstack([pts[:-1][seg] + d[seg] * frac[:, None], pts[-1:]])


def _draw_panel(p: _Panel, pw: int, ph: int) -> str:
    """Grid, data (clipped to the plot area), axes, ticks, labels, title and legend of one panel."""
    S = STYLE
    a = p.ax
    L, T = p.left, p.top
    out = ["<g>"]
    m = _Mapper(p, pw, ph)
    # grid
    gx = [L + float(v) / SUB for v in m.x(p.xt)]
    gy = [T + float(v) / SUB for v in m.y(p.yt)]
    grid = "".join(f"M{_num(x)} {_num(T)}v{ph}" for x in gx) + "".join(f"M{_num(L)} {_num(y)}h{pw}" for y in gy)
    if grid:
        out.append(f'<path d="{grid}" stroke="{S["grid"]}" stroke-width="1" fill="none"/>')
    # data
    legend_items, lines = [], []
    if a.has_data():
        out.append(f'<svg x="{_num(L)}" y="{_num(T)}" width="{pw}" height="{ph}" viewBox="0 0 {pw * SUB} {ph * SUB}">')
        for s in sorted(a.series, key=lambda s: s.layer):
            markup, drawn = _draw_series(s, m, pw)
            out.append(markup)
            lines += drawn
        out.append("</svg>")
        legend_items = _legend_items(a)
    else:
        out.append(_text(L + pw / 2, T + ph / 2 + 4, "no data", S["fs_label"], fill=S["tick_text"]))
    # spines and ticks
    tl = S["tick_len"]
    ticks = "".join(f"M{_num(x)} {_num(T + ph)}v{tl}" for x in gx) + "".join(f"M{_num(L)} {_num(y)}h-{tl}" for y in gy)
    out.append(f'<path d="M{_num(L)} {_num(T)}V{_num(T + ph)}H{_num(L + pw)}{ticks}" stroke="{S["axis"]}" '
               f'stroke-width="1" fill="none"/>')
    fs = S["fs_tick"]
    out.append(f'<g fill="{S["tick_text"]}">')
    if p.show_x:
        out += [_text(x, T + ph + tl + S["pad"] + fs * 0.8, s, fs) for x, s in zip(gx, p.xl)]
    out += [_text(L - tl - S["pad"], y + fs * 0.35, s, fs, anchor="end") for y, s in zip(gy, p.yl)]
    if p.ynote:
        out.append(_text(L, T - 5, p.ynote, S["fs_note"], anchor="start"))
    x_row = T + ph + tl + S["pad"] + fs + 6 + S["fs_label"] * 0.85
    if p.xnote and p.show_x:
        out.append(_text(L + pw, x_row, p.xnote, S["fs_note"], anchor="end"))
    out.append("</g>")
    # labels and title
    if a.xlabel_text and p.show_x:
        out.append(_text(L + pw / 2, x_row, a.xlabel_text, S["fs_label"]))
    if a.ylabel_text:
        tw = max((_text_w(s, fs) for s in p.yl), default=0.0)
        out.append(_text(L - tl - S["pad"] - tw - 9, T + ph / 2, a.ylabel_text, S["fs_label"], rotate=True))
    if a.title_text:
        rows = _wrap(a.title_text, pw + 40, S["fs_title"])
        base = T - 6 - (S["fs_note"] + 4 if p.note_row else 0)
        for i, s in enumerate(rows):
            out.append(_text(L + pw / 2, base - (len(rows) - 1 - i) * S["fs_title"] * 1.25, s, S["fs_title"]))
    if a.legend_loc and legend_items:
        out.append(_legend(legend_items, a.legend_loc, L, T, pw, ph, lines))
    out.append("</g>")
    return "".join(out)


# ---- legend --------------------------------------------------------------------------------------
_LOCS = ("upper right", "upper left", "lower left", "lower right", "upper center", "lower center")


_LEGEND_ROW, _LEGEND_SAMPLE, _LEGEND_PAD, _LEGEND_INSET = 1.4, 22.0, 6.0, 6.0  # row (x font size), px


def _legend_items(a: Axes) -> list[Series]:
    return [s for s in a.series if s.label and not s.label.startswith("_")]


def _legend_box(items: list[Series], loc: str, pw: int, ph: int) -> tuple[float, float, float, float]:
    """(x, y, width, height) of the legend box at ``loc`` in plot-area pixels."""
    fs = STYLE["fs_legend"]
    bw = _LEGEND_PAD + _LEGEND_SAMPLE + 6 + max(_text_w(s.label, fs) for s in items) + _LEGEND_PAD
    bh = 2 * _LEGEND_PAD + fs * _LEGEND_ROW * len(items) - fs * (_LEGEND_ROW - 1) / 2
    vert, horiz = (loc if loc in _LOCS else "upper right").split(" ")
    x = {"left": _LEGEND_INSET, "right": pw - _LEGEND_INSET - bw, "center": (pw - bw) / 2}[horiz]
    y = _LEGEND_INSET if vert == "upper" else ph - _LEGEND_INSET - bh
    return x, y, bw, bh


def _best_loc(items: list[Series], lines: list[np.ndarray], pw: int, ph: int) -> tuple[str, int]:
    """The place of ``_LOCS`` where the legend hides the least of ``lines`` (drawing units), the first
    such place on a tie, and how many line points it hides there."""
    pts = np.concatenate([_densify(v, pw * SUB, ph * SUB) for v in lines] or [np.zeros((0, 2))]) / SUB

    def hidden(loc: str) -> int:
        x, y, bw, bh = _legend_box(items, loc, pw, ph)
        inside = (pts[:, 0] >= x) & (pts[:, 0] <= x + bw) & (pts[:, 1] >= y) & (pts[:, 1] <= y + bh)
        return int(np.count_nonzero(inside))

    counts = {loc: hidden(loc) for loc in _LOCS}
    loc = min(_LOCS, key=counts.get)
    return loc, counts[loc]


def _make_legend_room(p: _Panel, pw: int, ph: int, most: float = 1.6) -> None:
    """For a ``best`` legend that would hide data wherever it goes: raise the top of the y range (to
    at most ``most`` times the range) so that an upper corner is free, if that is enough."""
    a = p.ax
    items = _legend_items(a)
    top_given = a.ylim_given[1] is not None and math.isfinite(a.ylim_given[1])
    if a.legend_loc != "best" or not items or top_given:
        return
    m = _Mapper(p, pw, ph)
    lines = [ln for s in a.series for ln in _draw_series(s, m, pw, markup=False)[1]]
    if _best_loc(items, lines, pw, ph)[1] == 0:
        return
    tops = []
    for loc in ("upper right", "upper left"):
        x, _, bw, bh = _legend_box(items, loc, pw, ph)
        xa, xb = (p.x0 + (v / pw) * (p.x1 - p.x0) for v in (x, x + bw))
        under = [s.y2 if s.y2 is not None else s.y for s in a.series if s.kind in ("line", "points", "band")]
        xs = [s.x for s in a.series if s.kind in ("line", "points", "band")]
        r = _finite_range(*(y[(x_ >= xa) & (x_ <= xb)] for x_, y in zip(xs, under)))
        if r is None:
            continue
        free = 1 - (bh + _LEGEND_INSET + 4) / ph  # the part of the height under the box
        tops.append(p.y0 + (r[1] - p.y0) / free if free > 0 else math.inf)
    if tops and min(tops) <= p.y0 + most * (p.y1 - p.y0):
        p.y1 = max(p.y1, min(tops))


def _legend(items: list[Series], loc: str, L: float, T: float, pw: int, ph: int, lines: list[np.ndarray]) -> str:
    """A legend box inside the plot area at ``loc``; for ``best`` the place of ``_LOCS`` that hides the
    least of the plotted ``lines`` (drawing units)."""
    S = STYLE
    fs = S["fs_legend"]
    row, sw, pad = fs * _LEGEND_ROW, _LEGEND_SAMPLE, _LEGEND_PAD
    if loc == "best":
        loc = _best_loc(items, lines, pw, ph)[0]
    x, y, bw, bh = _legend_box(items, loc, pw, ph)
    x, y = L + x, T + y
    out = [f'<g font-size="{_num(fs)}"><rect x="{_num(x)}" y="{_num(y)}" width="{_num(bw)}" height="{_num(bh)}" '
           f'rx="3" fill="{S["legend_bg"]}" fill-opacity="{S["legend_opacity"]}" stroke="{S["legend_border"]}"/>']
    for i, s in enumerate(items):
        cy = y + pad + row * i + fs * 0.5
        x0 = x + pad
        col = _color(s.color)
        if s.kind in ("band", "vspan"):
            out.append(f'<rect x="{_num(x0)}" y="{_num(cy - 5)}" width="{_num(sw)}" height="10" fill="{col}" '
                       f'fill-opacity="{max(s.opacity, 0.25):g}"/>')
        elif s.kind == "points":
            out.append(f'<circle cx="{_num(x0 + sw / 2)}" cy="{_num(cy)}" r="{_num(s.size / 2 * PT)}" fill="{col}"/>')
        else:
            dash = _dash_attr(s.dash, s.width, unit=1)
            op = f' opacity="{s.opacity:g}"' if s.opacity < 1 else ""
            out.append(f'<path d="M{_num(x0)} {_num(cy)}h{_num(sw)}" stroke="{col}" '
                       f'stroke-width="{_num(max(s.width, 1.0) * PT)}"{dash}{op}/>')
        out.append(_text(x0 + sw + 6, cy + fs * 0.35, s.label, fs, anchor="start"))
    out.append("</g>")
    return "".join(out)
