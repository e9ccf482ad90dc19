"""Issue 19 (outputs): what the batch summary, report.html, ``tapost view``, the recording and
``tapost inspect`` show. The numerics are the stand-ins of test_analyze_cli (fast, exact)."""
from __future__ import annotations

import sys
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


def test_latency_instant_in_utc_for_an_epoch_master():
    rep = {"master": {"clock": "epoch", "t0_ns": 1_700_000_000_000_000_000},
           "latency": {"latency_s": 0.1, "t_mid_rel_s": 60.0, "window_s": [1_700_000_000.3, 1_700_000_119.7]}}
    t, utc = batch.latency_instant(rep)
    assert t == pytest.approx(1_700_000_060.0) and utc == "2023-11-14T22:14:20.000Z"
    boot = {"master": {"clock": "boot", "t0_ns": 5_000_000_000},
            "latency": {"latency_s": 0.1, "window_s": [10.0, 30.0]}}
    assert batch.latency_instant(boot) == (20.0, None)
    assert batch.latency_instant({"master": {}, "latency": {"failed": "x", "latency_s": None}}) == (None, None)
