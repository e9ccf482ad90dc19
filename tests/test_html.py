"""report.html: self-contained (no network), the expected sections, inline SVG figures that parse,
and it renders in a real headless browser (Debian chromium; skipped with a reason when chromium is
not installed)."""
from __future__ import annotations

import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from pipelines import report as rp
from pipelines.html import render, write_html

sys.path.insert(0, str(Path(__file__).parent))
from test_report import fake_report, make_fake_analysis  # noqa: E402

SECTIONS = ("summary", "rates", "latency", "drift", "alignment", "residuals", "warnings", "timings")
FIGURE = re.compile(r'<figure aria-label="[^"]*">(.*?)</figure>', re.S)
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    an = make_fake_analysis(duration_s=60)
    rep = fake_report(an)
    path = tmp_path_factory.mktemp("html") / "report.html"
    write_html(str(path), rep, an)
    return path, rep


def test_self_contained_with_all_sections(page):
    path, rep = page
    text = path.read_text()
    for s in SECTIONS:
        assert f'<section id="{s}">' in text
    # offline: no external resource at all
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", text)
    assert "<script" not in text.lower()
    svgs = FIGURE.findall(text)
    assert len(svgs) >= 7  # rates, cost, drift, 3 state groups, residuals
    for svg in svgs:  # each figure one well-formed <svg> that scales with the page
        root = ET.fromstring(svg)
        assert root.tag == "{http://www.w3.org/2000/svg}svg"
        assert root.get("viewBox") and root.get("width") == "100%"
    assert "data:image" not in text
    assert "+25.000 ms" in text  # the latency in the summary table
    assert "master warning example" in text
    assert oct(path.stat().st_mode & 0o777) != "0o600"  # a normal, shareable file


def test_skipped_and_failed_runs_are_stated_not_plotted():
    an = make_fake_analysis(duration_s=20, with_alignment=False)
    an.latency = None
    an.slave_comp = None
    rep = rp.build_report(an.master, an.slave, latency=rp.latency_failed("no overlap between the logs"),
                          alignment={r: rp.alignment_skipped("latency failed", "kf", "vel+att") for r in rp.RUNS},
                          timings_s={})
    text = render(rep, an)
    assert "failed: no overlap between the logs" in text
    assert "skipped: latency failed" in text
    assert "Not available: latency was not estimated." in text
    assert len(FIGURE.findall(text)) == 1  # only the rates (before), nothing invented
    assert ">after compensation</text>" not in FIGURE.findall(text)[0]  # the before column only


def _chromium(args, tmp_path):
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
           "--disable-component-update", "--disable-sync", "--no-first-run",
           f"--user-data-dir={tmp_path / 'profile'}", *args]
    return subprocess.run(cmd, capture_output=True, timeout=90)


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (apt-get install -y chromium)")
def test_renders_in_headless_chromium(page, tmp_path):
    path, _ = page
    shot = tmp_path / "out.png"
    # one browser start for both: the screenshot to the file, the DOM on stdout
    run = _chromium([f"--screenshot={shot}", "--window-size=1280,4000", "--dump-dom", path.as_uri()], tmp_path)
    assert shot.exists() and shot.stat().st_size > 50_000
    img = _read_png(shot)
    assert img.shape[0] >= 3000 and img.shape[1] == 1280
    # not blank: many distinct colours, plots drawn across the page height
    assert img.std() > 0.05
    rows_with_ink = (img.std(axis=(1, 2)) > 0.02).mean()
    assert rows_with_ink > 0.5
    dom = run.stdout.decode()
    for s in SECTIONS:
        assert f'id="{s}"' in dom
    assert dom.count("<figure") >= 7 and dom.count("<svg") >= 7
    assert "tapost latency and transfer-alignment report" in dom


def test_state_plots_match_the_runs_states_by_name():
    """One run may carry states the other lacks (flexure, lever arm): the plots matched them by index, so
    the compensated run's lever arm went unplotted when the uncompensated one had six flexure states."""
    from dataclasses import replace

    from pipelines import html as H

    an = make_fake_analysis(duration_s=30)
    comp = an.alignment["compensated"]
    k = 6  # flexure-like states inserted before the accelerometer biases
    names = comp.history_names[:k] + ("flex_ang_x_arcmin",) + comp.history_names[k:]
    ins = lambda a: np.insert(a, k, 0.5, axis=1)  # noqa: E731
    an.alignment["compensated"] = replace(comp, history_names=names, history_x=ins(comp.history_x),
                                          history_sigma=ins(comp.history_sigma))
    figs = H.state_figures(an)
    axes = [ax for _, f in figs for ax in f.axes if ax.visible]
    lines = {ax.title_text: sorted(s.label for s in ax.series if s.kind == "line") for ax in axes}
    assert lines["accel_bias_x_mg"] == ["compensated", "uncompensated"]
    assert lines["flex_ang_x_arcmin"] == ["compensated"]
    x_plotted = next(s.y for ax in axes if ax.title_text == "accel_bias_x_mg"
                     for s in ax.series if s.kind == "line" and s.label == "compensated")
    assert np.allclose(x_plotted[-1], comp.history_x[-1, k])  # its own column, not the inserted one
    # and so in the markup: the flexure panel draws the compensated run only (line and band)
    svg = dict(H.fig_states(an))["other states"]
    panel = next(g for g in ET.fromstring(svg).iter("{http://www.w3.org/2000/svg}g")
                 if any(t.text == "flex_ang_x_arcmin" for t in g.iter("{http://www.w3.org/2000/svg}text")))
    labels = {e.get("aria-label") for e in panel.iter() if e.get("aria-label")}
    assert labels == {"compensated", "compensated ±3σ"}


def _read_png(path: Path) -> np.ndarray:
    """A PNG as RGB floats in [0, 1] (Pillow, not matplotlib: the report no longer needs it)."""
    Image = pytest.importorskip("PIL.Image")
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), dtype=float) / 255.0


def test_timings_of_stages_written_after_the_page_point_to_report_json():
    """report.html is written before the report's and the recording's stages end: their cells say where
    the times are instead of showing 0.00 s."""
    an = make_fake_analysis(duration_s=20)
    rep = fake_report(an)
    rep["timings_s"] = {**rep.get("timings_s", {}), "parse": 0.5, "report": 0.0, "recording": 0.0}
    text = render(rep, an)
    sec = text[text.index('<section id="timings">'):]
    sec = sec[:sec.index("</section>")]
    assert sec.count("<td class=note>in report.json</td>") == 2 and "0.00 s" not in sec and "0.50 s" in sec


def test_every_warning_the_headline_counts_is_listed_in_the_warnings_section(page):
    """The result line says "N warnings (listed below)": the Warnings section lists those N (report.json's
    top-level warnings of every stage, an alignment consistency warning among them), each once."""
    from pipelines.batch import report_warnings

    path, rep = page
    rep = dict(rep, warnings=list(rep.get("warnings") or []) + [
        {"stage": "alignment", "text": "lever arms disagree: transfer alignment x y z = +0.169 -0.002 +0.520 m"}])
    text = render(rep, make_fake_analysis(duration_s=60))
    warns = report_warnings(rep)
    assert len(warns) >= 2 and f"{len(warns)} warnings" in text
    section = text.split('<section id="warnings">', 1)[1].split("</section>", 1)[0]
    for _, w in warns:
        assert section.count(html_escape(w)) == 1, w


def html_escape(s: str) -> str:
    import html

    return html.escape(s)


def test_summary_says_convergence_and_residuals_in_words():
    """The summary's "converged / residual rms" row: the headline card's words and the residuals with their
    units, not report.json's keys (a real DataFlash pair showed "-; vel_m_s 0.05168, att_deg 0.6874, ...")."""
    from pipelines.html import CSS, _convergence_text, _residual_text

    rms = {"vel_m_s": 0.05168409, "att_deg": 0.68744857, "nis_mean": 65.5587, "nis_dof": 6.0}
    assert _residual_text(rms) == "residual rms velocity 0.05168 m/s, attitude 0.6874 deg; mean NIS 65.56 (6 dof)"
    assert _residual_text({"vel_m_s": 0.1}) == "residual rms velocity 0.1 m/s"
    assert _residual_text({}) == "no residuals"
    assert _convergence_text({"converged_s": 12.34}) == "converged after 12.3 s"
    assert _convergence_text({"converged_s": None, "still_converging": False}).startswith("settled")
    assert _convergence_text({"converged_s": None, "still_converging": True}) == "not converged"
    # row headers break between words only: with the cells' overflow-wrap:anywhere the browser squeezed the
    # summary's first column to "select|or", "durati|on" beside long "stamps from" texts
    th_rule = re.search(r"(?m)^th\{[^}]*\}", CSS).group(0)
    assert "overflow-wrap:normal" in th_rule


def test_a_comparison_method_that_assumes_aligned_axes_or_disagrees_is_said_so_beside_its_figure():
    """The seeds' methods assume the units' axes aligned and give their grid's resolution as sigma: with a
    40 deg mounting they came out -770 ms +- 1.4 ms against 37.19 +- 0.03 ms, a row a reader would take at
    its word. The row now says both; a method within 3 combined sigma of the headline is left plain."""
    from pipelines.html import _method_caveat

    lat = {"method": "tapost", "latency_s": 0.03719, "sigma_s": 3.1e-5}
    seed = {"latency_s": -0.77, "sigma_s": 0.00144, "note": "eqs 1-5, axes assumed aligned; t_s=5.000 ms"}
    assert _method_caveat("s000-rate-integral", seed, lat) == \
        " (axes assumed aligned; differs from tapost by -807.190 ms)"
    assert _method_caveat("xcorr-norm", {"latency_s": 0.03602, "sigma_s": 0.00144, "note": "peak 1.000"}, lat) == ""
    assert _method_caveat("tapost", {"latency_s": 0.03719, "sigma_s": 3.1e-5}, lat) == ""
    assert _method_caveat("s000-rate-integral", {"latency_s": None, "sigma_s": None}, lat) == ""
