"""report.json: builder, JSON hygiene and the "tapost.report/1" schema.

The small fake pair (``make_fake_analysis``) is also used by test_html.py and test_recording.py; it
builds the result dataclasses directly, independently of the numerics. The real end-to-end check
(a simulated pair through ``tapost analyze``) is at the bottom and in test_analyze_cli.py.
"""
from __future__ import annotations

import json
import math
from dataclasses import replace

import jsonschema
import numpy as np
import pytest

from logtools.conventions import dcm_from_euler, quat_from_euler
from logtools.inslog import ChannelInfo, InsLog, LogMeta
from logtools.results import AlignmentResult, LatencyResult, MethodEstimate
from pipelines import report as rp

MOUNT_RPY_DEG = (1.5, -2.0, 30.0)
LATENCY_S = 0.025


def make_fake_analysis(duration_s: float = 60.0, rate_hz: float = 100.0, *, with_alignment: bool = True,
                       slave_t0_offset_ns: int = 0) -> rp.Analysis:
    """A coherent small pair: master with IMU+attitude+velocity+position, slave IMU rotated by
    MOUNT_RPY_DEG and LATENCY_S late; results built by hand (not estimated)."""
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    w = np.column_stack([0.3 * np.sin(0.9 * t), 0.2 * np.sin(1.7 * t + 1), 0.25 * np.sin(0.5 * t + 2)])
    rpy = np.column_stack([0.3 / 0.9 * (1 - np.cos(0.9 * t)), 0.1 * np.sin(0.3 * t), 0.05 * t])
    q = quat_from_euler(rpy)
    v = np.column_stack([20 + 2 * np.sin(0.1 * t), 5 * np.cos(0.1 * t), 0.1 * np.sin(t)])
    lat = 45.0 + np.cumsum(v[:, 0]) / rate_hz / 111_000
    lon = 7.0 + np.cumsum(v[:, 1]) / rate_hz / 78_000
    alt = 100.0 - np.cumsum(v[:, 2]) / rate_hz
    t0 = 1_700_000_000_000_000_000
    mmeta = LogMeta("master.csv", "csv", "", "epoch", t0, "csv time_s column",
                    {"imu": ChannelInfo(rate_hz, len(t), "csv"), "nav": ChannelInfo(rate_hz, len(t), "csv")},
                    ("master warning example",))
    master = InsLog.from_arrays(mmeta, t_imu_s=t, gyro_rad_s=w, accel_m_s2=np.tile([0, 0, -9.81], (len(t), 1)),
                                t_nav_s=t, quat_wxyz=q, vel_ned_m_s=v, lat_lon_alt=np.column_stack([lat, lon, alt]))
    R = dcm_from_euler(np.radians(MOUNT_RPY_DEG))
    ws = w @ R.T  # the same physical motion as the master's row, stamped LATENCY_S later
    clock = "epoch" if (t0 + slave_t0_offset_ns) > 10**18 else "boot"
    smeta = LogMeta("slave.csv", "csv", "", clock, t0 + slave_t0_offset_ns, "csv time_s column",
                    {"imu": ChannelInfo(rate_hz, len(t), "csv")})
    # slave stamps late by LATENCY_S (plus any clock offset): motion at master t is stamped t + LATENCY_S
    acc = np.tile([0, 0, -9.81], (len(t), 1))
    slave = InsLog.from_arrays(smeta, t_imu_s=t + LATENCY_S, gyro_rad_s=ws, accel_m_s2=acc)
    comp = InsLog.from_arrays(replace(smeta, t0_ns=t0), t_imu_s=t, gyro_rad_s=ws, accel_m_s2=acc)
    lags = np.linspace(-0.2, 0.2, 401)
    lres = LatencyResult(
        latency_s=LATENCY_S, sigma_s=0.0004, drift_ppm=1.5, method="tapost",
        window_s=(t0 * 1e-9 + 1.0, t0 * 1e-9 + duration_s - 1.0),
        quality={"motion_deg_s": 14.2, "periodic": False, "nan_fraction": np.float64(0.0)},
        methods={"tapost": MethodEstimate(LATENCY_S, 0.0004),
                 "xcorr-norm": MethodEstimate(0.026, 0.002, "baseline"),
                 "s000-rate-integral": MethodEstimate(float("nan"), float("nan"), "failed")},
        cost_lag_s=lags, cost=1 - np.exp(-((lags - LATENCY_S) / 0.03) ** 2),
        window_centers_s=np.linspace(5, duration_s - 5, 12),
        window_latency_s=LATENCY_S + 1.5e-6 * (np.linspace(5, duration_s - 5, 12) - duration_s / 2)
        + 1e-4 * np.sin(np.arange(12)),
        mounting_rpy_deg=MOUNT_RPY_DEG, t_mid_rel_s=duration_s / 2)
    align: dict = {}
    if with_alignment:
        th = t[::10]
        names = ("mount_roll_deg", "mount_pitch_deg", "mount_yaw_deg", "gyro_bias_x_dph", "gyro_bias_y_dph",
                 "gyro_bias_z_dph", "accel_bias_x_mg", "accel_bias_y_mg", "accel_bias_z_mg")
        truth = np.array(MOUNT_RPY_DEG + (3.0, -2.0, 1.0, 0.5, -0.3, 0.2))
        decay = np.exp(-th / 10.0)[:, None]
        for run, err in (("uncompensated", 0.3), ("compensated", 0.01)):
            x = truth + (err + decay * 2.0) * np.cos(th)[:, None] * 0.5
            s = 0.02 + decay * np.abs(truth).clip(1, None) * 0.5
            resid_t = t[::5]
            align[run] = AlignmentResult(
                filter="kf", match="vel+att", mounting_rpy_deg=tuple(x[-1, :3]),
                mounting_sigma_deg=tuple(s[-1, :3]), gyro_bias_dph=tuple(x[-1, 3:6]),
                accel_bias_mg=tuple(x[-1, 6:]), converged_s=12.5 if run == "compensated" else None,
                residual_rms={"vel_m_s": 0.02 + err / 10, "att_deg": 0.01 + err / 5},
                gyro_bias_sigma_dph=tuple(s[-1, 3:6]), accel_bias_sigma_mg=tuple(s[-1, 6:]),
                observability={"mounting": True, "accel_bias_z": False}, notes=(f"{run} note",),
                history_t_s=th, history_names=names, history_x=x, history_sigma=s,
                residual_t_s=resid_t, residual_names=("dv_n_m_s", "dv_e_m_s", "dv_d_m_s"),
                residuals=np.random.default_rng(1).normal(0, 0.02 + err / 10, (len(resid_t), 3)))
    return rp.Analysis(master=master, slave=slave, slave_comp=comp, latency=lres, alignment=align)


def fake_report(an: rp.Analysis) -> dict:
    align = {run: an.alignment.get(run) or rp.alignment_skipped("not run in this fake", "kf", "vel+att")
             for run in rp.RUNS}
    return rp.build_report(an.master, an.slave, latency=an.latency, alignment=align,
                           timings_s={k: 0.1 for k in rp.TIMING_KEYS}, options={"filter": "kf"})


def test_fake_report_follows_schema_and_contract():
    an = make_fake_analysis()
    rep = fake_report(an)
    rp.validate(rep)
    text = rp.dumps(rep)
    assert "NaN" not in text and "Infinity" not in text
    back = json.loads(text)
    assert back["schema"] == "tapost.report/1"
    assert back["status"] == "ok"
    assert back["latency"]["latency_s"] == pytest.approx(LATENCY_S)
    assert back["latency"]["window_s"][0] > 1.7e9  # absolute master stamps
    assert back["latency"]["methods"]["s000-rate-integral"]["latency_s"] is None  # NaN -> null
    assert back["latency"]["quality"]["nan_fraction"] == 0.0
    assert back["master"]["t0_ns"] == 1_700_000_000_000_000_000
    assert back["master"]["channels"]["imu"] == {"rate_hz": 100.0, "count": 6000, "source": "csv"}
    assert back["master"]["warnings"] == ["master warning example"]
    c = back["alignment"]["compensated"]
    assert c["mounting_rpy_deg"] == pytest.approx(list(an.alignment["compensated"].mounting_rpy_deg))
    assert back["alignment"]["uncompensated"]["converged_s"] is None
    assert set(back["timings_s"]) >= {"parse", "latency", "alignment", "report", "recording", "total"}


def test_failed_and_skipped_sections_validate():
    an = make_fake_analysis(with_alignment=False)
    rep = rp.build_report(
        an.master, an.slave, latency=rp.latency_failed("no overlap between the two logs"),
        alignment={r: rp.alignment_skipped("latency failed", "kf", "vel+att") for r in rp.RUNS},
        timings_s={k: 0.0 for k in rp.TIMING_KEYS})
    rp.validate(rep)
    assert rep["status"] == "failed"
    assert rep["skipped"]["latency"] == "no overlap between the two logs"
    for run in rp.RUNS:  # DESIGN.md's RESULT keys are there, null
        sec = rep["alignment"][run]
        assert all(sec[k] is None for k in ("mounting_rpy_deg", "mounting_sigma_deg", "gyro_bias_dph",
                                            "accel_bias_mg", "converged_s")) and sec["residual_rms"] == {}
    assert rep["latency"]["latency_s"] is None


def test_a_bias_axis_the_data_did_not_determine_is_null_not_its_prior():
    """DESIGN.md: an estimate the data cannot determine is null with a reason, never its prior: the biases
    and the lever arm as the mounting."""
    an = make_fake_analysis()
    res = an.alignment["compensated"]
    obs = {**res.observability, "gyro_bias_x": True, "gyro_bias_y": True, "gyro_bias_z": False,
           "accel_bias_x": False, "accel_bias_y": True, "accel_bias_z": True}
    sec = rp.alignment_section(replace(res, observability=obs))
    assert sec["gyro_bias_dph"][2] is None and sec["gyro_bias_dph"][:2] == list(res.gyro_bias_dph[:2])
    assert sec["accel_bias_mg"][0] is None and sec["accel_bias_mg"][1:] == list(res.accel_bias_mg[1:])
    assert sec["states_not_determined"] == ["gyro_bias_z", "accel_bias_x"]
    assert "states_not_determined" not in rp.alignment_section(replace(res, observability={}))
    delayed = rp.alignment_section(replace(res, delay_s=0.004, delay_sigma_s=0.1, observability={"delay": False}))
    assert delayed["delay_s"] is None and delayed["states_not_determined"] == ["delay"]


def test_an_uncompensated_run_that_does_not_apply_is_a_note_not_a_skip():
    """Logs on different clocks (UNIX time against time since boot) cannot overlap at face value: the
    uncompensated run has no meaning there, which leaves the status ok and says so as a note."""
    an = make_fake_analysis()
    why = "no time overlap between the master and the slave on uncompensated stamps"
    rep = rp.build_report(an.master, an.slave, latency=an.latency,
                          alignment={"uncompensated": rp.alignment_skipped(why, "kf", "vel+att", applies=False),
                                     "compensated": an.alignment["compensated"]},
                          timings_s={k: 0.0 for k in rp.TIMING_KEYS})
    rp.add_findings(rep)
    rp.validate(rep)
    assert rep["status"] == "ok" and rep["skipped"] == {}
    assert rep["alignment"]["uncompensated"]["not_applicable"] is True
    assert any(why in n["text"] for n in rep["notes"]) and not any(why in w["text"] for w in rep["warnings"])
    applies = rp.build_report(an.master, an.slave, latency=an.latency,
                              alignment={"uncompensated": rp.alignment_skipped(why, "kf", "vel+att"),
                                         "compensated": an.alignment["compensated"]},
                              timings_s={k: 0.0 for k in rp.TIMING_KEYS})
    assert applies["status"] == "partial" and "alignment.uncompensated" in applies["skipped"]


@pytest.mark.parametrize("mutate", [
    lambda r: r.pop("latency"),
    lambda r: r["latency"].__setitem__("latency_s", "fast"),
    lambda r: r["alignment"]["compensated"].pop("mounting_rpy_deg"),
    lambda r: r["alignment"]["compensated"].__setitem__("mounting_rpy_deg", [1.0, 2.0]),
    lambda r: r.__setitem__("schema", "tapost.report/2"),
    lambda r: r["master"].__setitem__("t0_ns", 1.5),
    lambda r: r["alignment"].__setitem__("uncompensated", {"skipped": ""}),
])
def test_schema_rejects_broken_reports(mutate):
    rep = fake_report(make_fake_analysis(duration_s=10))
    mutate(rep)
    with pytest.raises(jsonschema.ValidationError):
        rp.validate(rep)


def test_json_safe_and_atomic_write(tmp_path):
    assert rp.json_safe({"a": np.float32(np.nan), "b": (np.int64(3), np.inf), 1: np.array([1.5])}) == \
        {"a": None, "b": [3, None], "1": [1.5]}
    p = tmp_path / "r.json"
    rep = fake_report(make_fake_analysis(duration_s=10))
    rp.write_report(str(p), rep)
    assert rp.is_complete(str(p))
    assert [x.name for x in tmp_path.iterdir()] == ["r.json"]  # no temp file left
    p.write_text("{ half")
    assert not rp.is_complete(str(p))


def test_mounting_source_priority():
    an = make_fake_analysis(duration_s=5)
    R, src = an.mounting()
    assert src == "alignment (compensated)"
    an2 = make_fake_analysis(duration_s=5, with_alignment=False)
    R2, src2 = an2.mounting()
    assert src2.startswith("latency")
    assert np.allclose(R2, dcm_from_euler(np.radians(MOUNT_RPY_DEG)))


def test_real_analyze_report_validates(tmp_path):
    """A real analyze (simulated pair, real numerics) writes a schema-valid report."""
    sim = pytest.importorskip("logtools.sim")
    pytest.importorskip("logtools.latency")
    pytest.importorskip("logtools.compensate")
    from pipelines.analyze import AnalyzeOptions, analyze_pair
    from parsers import registry

    pair = sim.simulate(sim.scenario_config("aircraft", duration_s=120.0))
    registry.write(str(tmp_path / "m.csv"), pair.master, "csv")
    registry.write(str(tmp_path / "s.csv"), pair.slave, "csv")
    out = analyze_pair(str(tmp_path / "m.csv"), str(tmp_path / "s.csv"), str(tmp_path / "out"),
                       AnalyzeOptions(recording=False))
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    rp.validate(rep)
    assert rep == json.loads(json.dumps(out.report))
    truth = pair.truth.to_dict()
    assert math.isclose(rep["latency"]["latency_s"], truth["latency_s"], abs_tol=2e-3)


@pytest.mark.parametrize("still, where", [(False, "notes"), (True, "warnings"), (None, "warnings")])
def test_a_mounting_sigma_that_settled_above_the_thresholds_is_a_note(still, where):
    """converged_s null (the sigma never went below the navigation-grade 1/1/2 arcmin): where the sigma had
    settled by the end of the log (a MEMS slave's 2-10') that is what the pair allows, a note; where it still
    fell at the end (or a report that does not say), a warning that more data would tighten it."""
    an = make_fake_analysis()
    rep = rp.build_report(an.master, an.slave, latency=an.latency, alignment=an.alignment,
                          timings_s={k: 0.0 for k in rp.TIMING_KEYS})
    sec = rep["alignment"]["compensated"]
    sec["converged_s"], sec["still_converging"] = None, still
    sec["mounting_sigma_deg"] = [0.05, 0.04, 0.1]
    rp.add_findings(rep)
    texts = {k: [f["text"] for f in rep[k]] for k in ("notes", "warnings")}
    hits = [t for t in texts[where] if "mounting's sigma" in t]
    assert len(hits) == 1 and "3/2.4/6' (roll/pitch/yaw)" in hits[0], texts
    other = "warnings" if where == "notes" else "notes"
    assert not any("mounting's sigma" in t for t in texts[other])
    rp.validate(rep)
