"""pipelines.svgplot: the report's inline SVG figures. The markup parses, NaN breaks lines, ticks are
nice numbers covering the range, decimation keeps spikes, text is escaped, edge cases draw."""
from __future__ import annotations

import math
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from pipelines import html as H
from pipelines.svgplot import Figure, decimate, nice_ticks, tick_labels

sys.path.insert(0, str(Path(__file__).parent))
from test_report import make_fake_analysis  # noqa: E402

NS = "{http://www.w3.org/2000/svg}"


def _series_group(svg: str, label: str) -> ET.Element:
    return next(g for g in ET.fromstring(svg).iter(NS + "g") if g.get("aria-label") == label)


def _path_points(d: str) -> np.ndarray:
    """The vertices (0.1 px units of the plot area) of a path "Mx y l dx dy dx dy ..." as svgplot writes it."""
    nums = [int(v) for v in d[1:].replace("l", " ").replace("h", " ").replace("z", " ").split()]
    return np.cumsum(np.array(nums[:2] + nums[2:], dtype=np.int64).reshape(-1, 2), axis=0)


def test_every_report_figure_is_well_formed_svg():
    an = make_fake_analysis(duration_s=30)
    R, src = an.mounting()
    figs = [H.fig_rates(an, R, src), H.fig_cost(an), H.fig_drift(an), H.fig_residuals(an)]
    figs += [svg for _, svg in H.fig_states(an)]
    assert len(figs) == 7 and all(figs)
    for svg in figs:
        root = ET.fromstring(svg)  # raises on malformed XML
        assert root.tag == NS + "svg"
        assert root.get("width") == "100%" and len(root.get("viewBox").split()) == 4
        assert root.find(NS + "title").text  # the accessible name
        assert "sans-serif" in root.get("font-family")
        assert "$" not in svg and "\\omega" not in svg  # Unicode, not mathtext
    assert "ωx (deg/s)" in figs[0] and "±3σ" in figs[1]


def test_a_line_with_nan_breaks_into_two_paths():
    fig = Figure(1, 1, panel=(300, 120))
    y = np.sin(np.linspace(0, 6, 200))
    y[90:95] = np.nan
    fig.ax(0).line(np.arange(200.0), y, label="gappy")
    paths = _series_group(fig.to_svg(), "gappy").findall(NS + "path")
    assert len(paths) == 2
    # the whole line is one path without the gap
    fig = Figure(1, 1, panel=(300, 120))
    fig.ax(0).line(np.arange(200.0), np.sin(np.linspace(0, 6, 200)), label="whole")
    assert len(_series_group(fig.to_svg(), "whole").findall(NS + "path")) == 1


@pytest.mark.parametrize("lo, hi", [(0, 1), (0.1, 0.7), (-4.13, 1.31), (94.0, 98.0), (-0.0321, 0.0412),
                                    (1e-7, 3.3e-7), (-2.5e6, 1.2e7), (99.999, 100.0002),
                                    (1_700_000_062.1, 1_700_000_182.3), (-400.0, 560.0)])
@pytest.mark.parametrize("target", [3, 5.5, 8])
def test_ticks_are_nice_numbers_covering_the_range(lo, hi, target):
    t = nice_ticks(lo, hi, target)
    assert len(t) >= 2
    step = float(np.diff(t).min())
    assert np.allclose(np.diff(t), step, rtol=1e-9)
    mant = step / 10 ** math.floor(math.log10(step))
    assert min(abs(mant - m) for m in (1, 2, 5)) < 1e-9  # a 1-2-5 step
    assert np.allclose(t / step, np.round(t / step), atol=1e-6)  # multiples of the step
    assert lo - 1e-9 * abs(lo) <= t[0] < lo + step and hi - step < t[-1] <= hi + 1e-9 * abs(hi)
    labels, note = tick_labels(t)
    assert len(set(labels)) == len(labels)  # distinct
    assert all(len(s) <= 8 for s in labels), labels  # readable: no 0.30000000000000004, no 1700000080
    # label x scale + offset gives the tick back
    scale, offset = 1.0, 0.0
    for part in note.split():
        if part.startswith("×10"):
            exp = part[3:].translate(str.maketrans("⁻⁰¹²³⁴⁵⁶⁷⁸⁹", "-0123456789"))
            scale = 10.0 ** int(exp)
        else:
            offset = float(part.replace("\u2212", "-"))
    back = np.array([float(s.replace("\u2212", "-")) for s in labels]) * scale + offset
    assert np.allclose(back, t, rtol=0, atol=step * 1e-6)


def test_tick_labels_are_short_and_exact():
    assert tick_labels(nice_ticks(0.1, 0.7, 6))[0] == ["0.1", "0.2", "0.3", "0.4", "0.5", "0.6", "0.7"]
    assert tick_labels(np.array([-1.0, 0.0, 1.0]))[0] == ["\u22121", "0", "1"]
    labels, note = tick_labels(nice_ticks(1_700_000_062.1, 1_700_000_182.3, 6))
    assert note == "+1700000000" and labels[0] == "80"


def test_decimation_keeps_a_single_sample_spike_and_the_gaps():
    rng = np.random.default_rng(3)
    x = np.arange(200_000.0)
    y = rng.normal(0, 0.01, x.size)
    y[123_457] = 5.0
    y[150_000:150_010] = np.nan
    xd, yd = decimate(x, y, 2000)
    assert len(xd) <= 3000
    assert yd[np.isfinite(yd)].max() == 5.0 and 123_457.0 in xd
    assert np.isnan(yd).any()  # the gap is still a gap
    assert np.all(np.diff(xd) > 0)  # in order
    # and the drawn line reaches the spike: its highest point is at the top of the data
    fig = Figure(1, 1, panel=(300, 120))
    fig.ax(0).line(x, y, label="spiky")
    fig.ax(0).ylim(-1, 5)
    paths = _series_group(fig.to_svg(), "spiky").findall(NS + "path")
    assert min(_path_points(p.get("d"))[:, 1].min() for p in paths) <= 1  # 0.1 px units: y = 5 is the top, 0


def test_text_is_escaped():
    fig = Figure(1, 1, panel=(300, 120), title='a <b>&"c"</b>')
    ax = fig.ax(0)
    ax.line([0, 1], [0, 1], label="x < y & z")
    ax.title("<script>alert(1)</script>")
    ax.legend()
    svg = fig.to_svg("alt & <text>")
    assert "<script" not in svg and "<b>" not in svg
    root = ET.fromstring(svg)
    texts = [t.text for t in root.iter(NS + "text")]
    assert 'a <b>&"c"</b>' in texts and "<script>alert(1)</script>" in texts and "x < y & z" in texts
    assert root.find(NS + "title").text == "alt & <text>"


def test_empty_and_non_finite_data_draw_without_error():
    fig = Figure(2, 2, panel=(200, 100), sharex=True)
    fig.ax(0, 0).line([], [])
    fig.ax(0, 1).line([0, 1, 2], [np.nan, np.inf, -np.inf])
    a = fig.ax(1, 0)
    a.line([0, 1, 2], [1.0, 1.0, 1.0])  # a constant: the range is widened, not empty
    a.xlim(np.nan, np.inf)  # non-finite limits: autoscaled
    a.vline(np.nan)
    a.vspan(0.5, np.inf)
    fig.ax(1, 1).hide()
    svg = fig.to_svg()
    root = ET.fromstring(svg)
    texts = [t.text for t in root.iter(NS + "text")]
    assert texts.count("no data") == 2
    assert "nan" not in svg.lower() and "inf" not in svg


def test_huge_numbers_get_a_scale_note_and_a_legend_stays_inside():
    fig = Figure(1, 1, panel=(300, 150))
    ax = fig.ax(0)
    ax.line(np.linspace(0, 1, 50), np.linspace(0, 3e7, 50), label="big")
    ax.legend("best")
    root = ET.fromstring(fig.to_svg())
    texts = [t.text for t in root.iter(NS + "text")]
    assert "×10⁷" in texts
    box = next(r for r in root.iter(NS + "rect") if r.get("rx"))  # the legend frame
    # the line runs bottom-left to top-right: the legend is in the upper left corner
    x, y = float(box.get("x")), float(box.get("y"))
    nested = list(root.iter(NS + "svg"))[1]  # the plot area (the first is the figure itself)
    px, py = float(nested.get("x")), float(nested.get("y"))
    assert px < x < px + 40 and py < y < py + 40


def test_render_is_pure():
    from test_report import fake_report

    an = make_fake_analysis(duration_s=20)
    rep = fake_report(an)
    assert H.render(rep, an) == H.render(rep, an)


def test_a_best_legend_makes_room_rather_than_hide_data():
    """Noise over the whole panel: every corner would hide data, so the y range grows upwards (by at
    most 60 %) and the legend sits above the data."""
    rng = np.random.default_rng(0)
    fig = Figure(1, 1, panel=(335, 165))
    ax = fig.ax(0)
    ax.line(np.arange(3000.0), rng.normal(0, 1, 3000), label="noise (rms 1.00)")
    ax.legend("best")
    svg = fig.to_svg()
    root = ET.fromstring(svg)
    top = float(list(root.iter(NS + "svg"))[1].get("y"))  # the plot area's
    box = next(r for r in root.iter(NS + "rect") if r.get("rx"))
    box_bottom = float(box.get("y")) + float(box.get("height")) - top  # px in the plot area
    data_top = min(_path_points(p.get("d"))[:, 1].min() for p in _series_group(svg, "noise (rms 1.00)"))
    assert data_top / 10 > box_bottom
