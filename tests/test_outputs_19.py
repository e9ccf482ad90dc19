"""Issue 19 (outputs): what the batch summary, report.html, ``tapost view``, the recording and
``tapost inspect`` show. The numerics are the stand-ins of test_analyze_cli (fast, exact)."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from pipelines import batch

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))
from test_analyze_cli import fake_numerics, write_fake_pair  # noqa: E402,F401


# ---- batch ------------------------------------------------------------------------------------
def _damaged_campaign(root: Path) -> Path:
    camp = root / "campaign"
    for name in ("good", "damaged"):
        (camp / name).mkdir(parents=True)
        write_fake_pair(camp / name, duration_s=40.0, name=("master.csv", "slave.csv"))
    s = camp / "damaged" / "slave.csv"
    data = s.read_bytes()
    s.write_bytes(data[: len(data) // 2 + 5])  # half the slave, its last row cut short
    (camp / "broken").mkdir()  # unreadable: a failed row (no report, no warnings count)
    (camp / "broken" / "master.csv").write_bytes(b"\x89garbage\x00" * 50)
    (camp / "broken" / "slave.csv").write_bytes(b"\x89garbage\x00" * 50)
    return camp


def test_batch_summary_shows_a_damaged_input_warnings_and_the_quoted_instant(tmp_path, fake_numerics, capsys):
    camp = _damaged_campaign(tmp_path)
    out = tmp_path / "out"
    rows, counts = batch.run_batch(str(camp), str(out), jobs=1, log=lambda m: None)
    by = {r["pair"]: r for r in rows}
    assert set(by) == {"good", "damaged", "broken"} and counts["failed"] == 1
    assert by["broken"]["status"] == "failed" and by["broken"]["latency_at_s"] is None
    csv = pd.read_csv(out / "summary.csv").set_index("pair")
    pq = pd.read_parquet(out / "summary.parquet").set_index("pair")
    for df in (csv, pq):
        # the damaged pair is analysed on its readable part, and says so beside its status
        assert df.loc["damaged", "status"] == "ok"
        assert "slave" in df.loc["damaged", "input_damage"] and "truncated" in df.loc["damaged", "input_damage"]
        assert df.loc["damaged", "warnings"] >= 1
        assert "truncated" in df.loc["damaged", "worst_warning"]
        assert pd.isna(df.loc["good", "input_damage"])
        # the instant the latency is quoted at: the middle of the analysed window, master seconds
        for pair in ("good", "damaged"):
            import json

            rep = json.loads((out / pair / "report.json").read_text())
            w0, w1 = rep["latency"]["window_s"]
            assert df.loc[pair, "latency_at_s"] == pytest.approx(0.5 * (w0 + w1), abs=1e-6)
            assert w0 < df.loc[pair, "latency_at_s"] < w1
    assert csv.loc["good", "warnings"] == 0 and pd.isna(csv.loc["good", "worst_warning"])
    from pipelines.recording import read_properties

    assert read_properties(str(out / "good" / "recording.rrd"))["name"] == "tapost: good"  # the pair's name
    page = (out / "index.html").read_text()
    assert "ok (damaged input)" in page and "1 with a damaged input" in page
    assert "last row cut short" in page
    # the command's own printout does not call it a bare "ok" either
    assert batch.display_status("ok", by["damaged"]["input_damage"]) == "ok (damaged input)"
    assert batch.display_status("ok", None) == "ok"


def test_report_warnings_prefers_the_contracts_list_and_ranks_damage_first():
    rep = {"master": {"warnings": ["note: selected imu=/imu", "gap of 2.0 s in gyro"]},
           "slave": {"warnings": ["damaged tlog: skipped 12 bad bytes (1 place)"]},
           "latency": {"quality": {"warnings": ["stamps are whole multiples of 1 ms"]}},
           "skipped": {}}
    ws = batch.report_warnings(rep)
    assert [t for _, t in ws] == ["gap of 2.0 s in gyro", "damaged tlog: skipped 12 bad bytes (1 place)",
                                  "stamps are whole multiples of 1 ms"]  # notes are not warnings
    assert max(ws, key=lambda w: batch.warning_severity(*w))[1].startswith("damaged tlog")
    top = {**rep, "warnings": [{"stage": "latency", "text": "stamps are whole multiples of 1 ms"}],
           "skipped": {"recording": "OSError: disk full"}}
    assert batch.report_warnings(top) == [("latency", "stamps are whole multiples of 1 ms"),
                                          ("skipped recording", "recording: OSError: disk full")]
    # a skipped step the contract's list already says in its own words is counted once
    said = {**rep, "warnings": [{"stage": "latency", "text": "latency failed: no overlap between the two logs"},
                                {"stage": "alignment", "text": "alignment skipped (both runs): latency failed"}],
            "skipped": {"latency": "no overlap between the two logs", "alignment.compensated": "latency failed",
                        "alignment.uncompensated": "latency failed"}}
    assert len(batch.report_warnings(said)) == 2


def test_latency_instant_in_utc_for_an_epoch_master():
    rep = {"master": {"clock": "epoch", "t0_ns": 1_700_000_000_000_000_000},
           "latency": {"latency_s": 0.1, "t_mid_rel_s": 60.0, "window_s": [1_700_000_000.3, 1_700_000_119.7]}}
    t, utc = batch.latency_instant(rep)
    assert t == pytest.approx(1_700_000_060.0) and utc == "2023-11-14T22:14:20.000Z"
    boot = {"master": {"clock": "boot", "t0_ns": 5_000_000_000},
            "latency": {"latency_s": 0.1, "window_s": [10.0, 30.0]}}
    assert batch.latency_instant(boot) == (20.0, None)
    assert batch.latency_instant({"master": {}, "latency": {"failed": "x", "latency_s": None}}) == (None, None)


# ---- tapost view ------------------------------------------------------------------------------
def _tiny_rrd(path: Path) -> Path:
    import rerun as rr

    rec = rr.RecordingStream("tapost", recording_id=None)
    rec.save(str(path))
    rec.log("/a", rr.Scalars(1.0))
    rec.flush()
    rec.disconnect()
    return path


def test_view_without_a_display_says_what_to_do_in_one_line(tmp_path, monkeypatch, capsys):
    import subprocess

    from pipelines import view_cmd
    from pipelines.cli import main

    _tiny_rrd(tmp_path / "recording.rrd")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(view_cmd.sys, "platform", "linux")

    def no_viewer(*a, **k):
        raise AssertionError("the viewer must not be started without a display")

    monkeypatch.setattr(subprocess, "Popen", no_viewer)
    monkeypatch.setattr(subprocess, "call", no_viewer)
    assert main(["view", str(tmp_path)]) == 1
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and cap.out == ""
    assert "--web" in lines[0] and "report.html" in lines[0] and "no display" in lines[0]


def _listening(port: int) -> list[str]:
    """Local addresses (hex, as in /proc/net/tcp{,6}) listening on ``port``."""
    out = []
    for f in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            rows = Path(f).read_text().splitlines()[1:]
        except OSError:
            continue
        for r in rows:
            parts = r.split()
            addr, p = parts[1].split(":")
            if parts[3] == "0A" and int(p, 16) == port:
                out.append(addr)
    return out


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="reads the listening sockets from /proc/net/tcp")
def test_view_web_listens_on_loopback_only_and_stops_on_ctrl_c(tmp_path):
    import os
    import re
    import signal
    import subprocess
    import urllib.request

    rrd = _tiny_rrd(tmp_path / "recording.rrd")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["PYTHONPATH"] = str(HERE.parent) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.Popen([sys.executable, "-m", "pipelines.cli", "view", str(tmp_path), "--web"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        line = proc.stdout.readline()  # the one line with the address, printed once rerun runs
        m = re.search(r"http://127\.0\.0\.1:(\d+)/\?url=http%3A%2F%2F127\.0\.0\.1%3A(\d+)%2Frecording\.rrd", line)
        assert m, line
        web, files = int(m[1]), int(m[2])
        deadline = time.time() + 30
        while not _listening(web) and time.time() < deadline:
            time.sleep(0.2)
        for port in (web, files):
            assert _listening(port) == ["0100007F"], port  # 127.0.0.1 only, not 0.0.0.0
        with urllib.request.urlopen(f"http://127.0.0.1:{files}/recording.rrd", timeout=10) as r:
            assert r.read() == rrd.read_bytes() and r.headers["Access-Control-Allow-Origin"] == "*"
        with pytest.raises(urllib.error.HTTPError):  # one file served, nothing else of the folder
            urllib.request.urlopen(f"http://127.0.0.1:{files}/", timeout=10)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
        assert "stopped" in proc.stderr.read()
        deadline = time.time() + 10
        while _listening(web) and time.time() < deadline:  # rerun stopped with us
            time.sleep(0.2)
        assert not _listening(web) and not _listening(files)
    finally:
        if proc.poll() is None:
            proc.kill()


# ---- the recording ----------------------------------------------------------------------------
def test_recording_name_properties_comparisons_and_utc_timeline(tmp_path):
    import numpy as np

    from pipelines.recording import read_entities, read_properties, write_recording
    from test_report import fake_report, make_fake_analysis

    an = make_fake_analysis(duration_s=20, rate_hz=50)
    rep = fake_report(an)
    path = tmp_path / "recording.rrd"
    info = write_recording(str(path), an, rep)
    props = read_properties(str(path))  # rerun's own reader: store entry + /__properties chunks
    assert props["application_id"] == "tapost"
    assert props["name"] == "tapost: master vs slave" == info["name"]  # <master stem> vs <slave stem>
    res = props["results"]
    assert res["latency_s"] == an.latency.latency_s and res["sigma_s"] == an.latency.sigma_s
    assert res["drift_ppm"] == an.latency.drift_ppm and res["status"] == rep["status"] == "ok"
    comp = an.alignment["compensated"]
    assert res["mounting_run"] == "compensated"
    assert np.allclose(res["mounting_rpy_deg"], comp.mounting_rpy_deg)
    assert np.allclose(res["mounting_sigma_deg"], comp.mounting_sigma_deg)
    ents = read_entities(str(path))
    n = len(an.master.t_imu_s())
    for ax in "xyz":
        for who in ("master", "slave_raw", "slave_comp"):
            e = ents[f"/accel/{ax}/{who}"]
            assert e["rows"] == n and e["timelines"] == ["time", "utc"]  # master on UNIX time
    for ax in "ned":  # the fake slave logs no velocity: the master's only
        assert ents[f"/velocity/{ax}/master"]["rows"] == len(an.master.vel_ned_m_s()[0])
        assert f"/velocity/{ax}/slave_raw" not in ents
    assert info["comparisons"] == {"rates": ["master", "slave_raw", "slave_comp"],
                                   "accel": ["master", "slave_raw", "slave_comp"], "velocity": ["master"]}

    # a batch pair is named after the pair; a master on boot time has no timestamp timeline
    boot = make_fake_analysis(duration_s=20, rate_hz=50)
    boot.master = boot.master.with_meta(clock="boot")
    rep2 = {**fake_report(boot), "options": {"name": "flight7"}}
    p2 = tmp_path / "boot.rrd"
    write_recording(str(p2), boot, rep2)
    assert read_properties(str(p2))["name"] == "tapost: flight7"
    ents2 = read_entities(str(p2))
    assert ents2["/rates/x/master"]["timelines"] == ["time"]
    assert all("utc" not in e["timelines"] for e in ents2.values())


def test_utc_timeline_is_the_master_clock_in_ns(tmp_path):
    import numpy as np
    from rerun.chunk import RrdReader

    from pipelines.recording import write_recording
    from test_report import fake_report, make_fake_analysis

    an = make_fake_analysis(duration_s=10, rate_hz=20)
    path = tmp_path / "r.rrd"
    write_recording(str(path), an, fake_report(an))
    for ch in RrdReader(str(path)).stream().to_chunks():
        if str(ch.entity_path) == "/rates/x/master" and not ch.is_static:
            rb = ch.to_record_batch()
            utc = np.asarray(rb.column("utc").cast("int64").to_pylist(), dtype=np.int64)
            rel = np.asarray(rb.column("time").cast("int64").to_pylist(), dtype=np.int64)
            assert np.array_equal(utc - rel, np.full(len(utc), an.master.meta.t0_ns))
            break
    else:
        raise AssertionError("no /rates/x/master rows")


# ---- report.html ------------------------------------------------------------------------------
def _page(rep=None, an=None):
    from pipelines.html import render
    from test_report import fake_report, make_fake_analysis

    an = an or make_fake_analysis(duration_s=30)
    rep = rep or fake_report(an)
    return render(rep, an), rep, an


def test_html_headline_comes_first_and_states_the_results():
    import re

    page, rep, an = _page()
    body = page.split("<main>", 1)[1]
    first = re.search(r'<section id="([a-z]+)"', body)[1]
    assert first == "headline"  # the verdict before any table or figure
    head = body.split('<section id="summary"')[0]
    lat = rep["latency"]
    assert f"{lat['latency_s'] * 1e3:+.3f} ms" in head and f"{lat['sigma_s'] * 1e3:.3f}" in head
    assert f"{lat['drift_ppm']:+.2f} ppm" in head
    m = rep["alignment"]["compensated"]["mounting_rpy_deg"]
    assert " / ".join(f"{x:+.4f}" for x in m) in head and "(1&sigma;, arcmin)" in head
    assert "2023-11-14T22:13:35.000Z" in head  # quoted at the window middle (t0 + 15 s), UTC
    assert "converged" in head and "Status <span class=ok>ok</span>" in head
    assert "1 warning " in head or "1 warning (" in head  # the master's example warning; no notes counted


def test_html_quality_is_a_grouped_table_with_the_raw_values_collapsed():
    import json

    from test_report import fake_report, make_fake_analysis

    an = make_fake_analysis(duration_s=30)
    an.latency.quality.update({
        "coarse_latency_s": 0.0251, "stamp_resolution_s": {"master": 0.001, "slave": 0.0},
        "velocity_fit": {"latency_s": 0.0249, "sigma_s": 0.0006, "agrees": True, "fused": False},
        "sigma_budget": {"fit_curvature": 0.0003, "stamp_resolution": 0.0004},
        "too_little_motion": False, "best_instant_s": 1_700_000_010.0, "some_new_figure": 3})
    page, rep, _ = _page(fake_report(an), an)
    q = page.split('<section id="quality"')[1].split("</section>")[0]
    for group in ("Motion", "Search and fit", "Velocity fit", "Stamps", "Sigma budget", "Other"):
        assert f"<th colspan=2 class=grp>{group}" in q, group
    assert "<td>coarse search minimum</td><td class=num>25.100 ms</td>" in q
    assert "master 1.000 ms, slave 0.000 ms" in q
    assert "<b>0.500 ms</b>" in q  # the budget's root-sum-square, beside the quoted sigma
    assert "(2023-11-14 22:13:30.000 UTC)" in q  # an absolute instant on UNIX time, in words
    assert "some new figure" in q  # a key not in the table's groups is still shown
    assert "<details><summary>raw values" in q and "<pre>" in q
    raw = q.split("<pre>")[1].split("</pre>")[0]
    import html

    assert json.loads(html.unescape(raw))["some_new_figure"] == 3
    assert "quality: " not in page and "{'" not in page  # no Python dict dump left


def test_html_headline_of_a_damaged_input_and_of_a_failed_latency():
    from pipelines import report as rp
    from test_report import make_fake_analysis

    an = make_fake_analysis(duration_s=30)
    an.slave = an.slave.with_meta(warnings=("truncated tlog: last 23 byte(s) hold an incomplete frame",))
    from test_report import fake_report

    page, rep, _ = _page(fake_report(an), an)
    head = page.split('<section id="summary"')[0]
    assert "(damaged input)" in head and "Damaged input: slave: truncated tlog" in head
    failed = rp.build_report(an.master, an.slave, latency=rp.latency_failed("too little motion"),
                             alignment={r: rp.alignment_skipped("latency failed", "kf", "vel+att") for r in rp.RUNS},
                             timings_s={})
    an.latency, an.alignment, an.slave_comp = None, {}, None
    page, _, _ = _page(failed, an)
    head = page.split('<section id="summary"')[0]
    assert "not determined" in head and "too little motion" in head
    assert "Status <span class=fail>failed</span>" in head
    assert "No quality figures" in page
    # both alignment runs skipped: the alignment card says so (it said "not converged")
    card = head.split("<div class=t>alignment</div>")[1].split("</div>")[0]
    assert "<span class=warn>skipped</span>" in card and "not converged" not in card


# ---- tapost inspect ---------------------------------------------------------------------------
def test_inspect_clock_wording_matches_what_analyze_loads(tmp_path, capsys):
    from parsers import dataflash, inspect_log, load
    from pipelines.cli import main
    from test_report import make_fake_analysis

    master = make_fake_analysis(duration_s=20).master  # on UNIX time: the .bin gets GPS week/ms
    path = tmp_path / "flight.bin"
    dataflash.write(str(path), master)
    clock = load(str(path)).meta.clock  # what analyze prints as "<clock> clock"
    assert clock == "epoch"
    assert main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    note = [ln for ln in out.splitlines() if ln.strip().startswith("note:")][0]
    assert f"loaded on the {clock} clock" in note and "as analyze reports it" in note
    assert "stamps are boot time (TimeUS)" in note  # the streams' own stamps (the start_s column)
    assert all(s.clock == "boot (TimeUS)" for s in inspect_log(str(path)).streams)


def test_inspect_shows_streams_that_are_not_time_series_as_such():
    from parsers.base import Inventory, StreamInfo
    from pipelines.inspect_cmd import format_inventory, inventory_dict

    inv = Inventory(path="x.ulg", format="ulog", selectors=(), streams=(
        StreamInfo("sensor_combined", "imu", 1000, 250.0, 112.6, 3.996, "boot"),
        StreamInfo("ekf2_innovations", "other", 3271, 0.0, 0.0, 0.0, "boot"),
        StreamInfo("commander_state", "other", 1, 0.0, 2.07, 0.0, "boot")))
    lines = format_inventory(inv)
    row = {ln.split()[0]: ln for ln in lines[2:5]}
    assert "250.00" in row["sensor_combined"] and "not a time series" not in row["sensor_combined"]
    tok = row["ekf2_innovations"].split()  # name kind count rate start dur clock...
    assert tok[3] == "-" and tok[5] == "-" and tok[4] == "0.000"  # no rate, no duration; its one stamp
    assert "not a time series (all 3271 records share one stamp)" in row["ekf2_innovations"]
    assert "not a time series (one record)" in row["commander_state"]
    d = inventory_dict(inv)
    assert [s["time_series"] for s in d["streams"]] == [True, False, False]
