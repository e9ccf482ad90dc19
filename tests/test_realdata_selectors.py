"""Every selector ``tapost inspect`` offers for the real logs in ../shared/realdata runs ``analyze`` to an
alignment result (issue 22): each in a pair, as the master where it carries a navigation solution the
alignment can use, else as the slave. A selector inspect offers that is in no pair here fails the
coverage test (inspect must stop offering what cannot run, or a pair must show that it can)."""
from __future__ import annotations

from pathlib import Path

import pytest

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"

BP, EL = "arduplane_box_pilot.BIN", "arduplane_elevator.BIN"
C36, C14 = "arducopter_log0036.bin", "arducopter_2014-10-18_20-04-24.bin"
TLOG, ULG, BAG = "sitl_vtol.tlog", "px4_sample.ulg", "car_xsens_stereo_test1.bag"
ATT_GPS = "imu=IMU,att=ATT,vel=GPS,pos=GPS"
#: (log, master selector, slave selector); "" is the log without a selector
PAIRS = [
    (BP, "imu=IMU,nav=NKF1", "imu=IMU2,nav=NKF6"),
    (BP, "imu=IMU,nav=XKF1", "imu=IMU2,nav=XKF6"),
    (BP, ATT_GPS, "imu=IMU2,att=AHR2"),  # ATT 25 Hz and GPS 5 Hz never share a stamp
    # the elevator log's EKF outputs are frozen: its EKF selectors run as slaves against ATT
    (EL, "imu=IMU,att=ATT", "imu=IMU2,nav=XKF6"),
    (EL, "imu=IMU,att=ATT", "imu=IMU2,nav=NKF6"),
    (EL, "imu=IMU,att=ATT", "imu=IMU,nav=XKF1"),
    (EL, "imu=IMU,att=ATT", "imu=IMU,nav=NKF1"),
    (C36, "imu=IMU,nav=NKF1", "imu=IMU2,nav=NKF6"),
    (C36, ATT_GPS, "imu=IMU2,att=AHR2"),
    (C14, ATT_GPS, "imu=IMU2"),
    (TLOG, "imu=RAW_IMU,att=ATTITUDE,vel=GLOBAL_POSITION_INT,pos=GLOBAL_POSITION_INT", "imu=SCALED_IMU2,att=AHRS2"),
    (ULG, "imu=sensor_combined,att=vehicle_attitude,vel=vehicle_local_position",
     "imu=sensor_combined,att=vehicle_attitude,vel=vehicle_local_position"),  # against a shifted copy
    (BAG, "odom=/stereo_odometer/odometry", "imu=/xsens/imu_data"),
    (BAG, "odom=/wheel_odometry", "imu=/xsens/imu_data"),
    ("ngimu_session/blue", "", ""),
    ("ngimu_session/green", "", ""),
    ("ngimu_session/red", "", ""),
]
SLAVE_OF_NGIMU = "ngimu_session/blue"  # the NGIMU units: each against the blue one (blue against green)


def _arg(log: str, sel: str) -> str:
    return str(REAL / log) + (f"::{sel}" if sel else "")


def _need_real():
    if not REAL.exists():
        pytest.skip("../shared/realdata absent")


@pytest.mark.realdata
def test_every_selector_inspect_offers_is_in_a_pair():
    _need_real()
    from parsers import inspect_log

    covered = {(log, s) for log, m, sl in PAIRS for s in (m, sl)}
    logs = sorted({log for log, _, _ in PAIRS})
    missing = []
    for log in logs:
        for sel in inspect_log(str(REAL / log)).selectors:
            if (log, sel) not in covered:
                missing.append(f"{log}::{sel}")
    assert not missing, missing


@pytest.mark.realdata
@pytest.mark.slow
@pytest.mark.parametrize("log,master_sel,slave_sel", PAIRS, ids=[f"{p[0]}:{p[1]}|{p[2]}" for p in PAIRS])
def test_selector_pair_runs_analyze_with_an_alignment(log, master_sel, slave_sel, tmp_path):
    _need_real()
    from pipelines.analyze import AnalyzeOptions, analyze_pair

    if log.startswith("ngimu_session/"):
        other = "ngimu_session/green" if log == SLAVE_OF_NGIMU else SLAVE_OF_NGIMU
        master, slave = _arg(other, ""), _arg(log, "")
    elif log == ULG:  # the log against a copy of itself 25 ms late (the same stream twice is refused)
        from parsers.restamp import ClockShift
        from parsers.restamp_ulog import restamp_ulog

        copy = tmp_path / "late.ulg"
        restamp_ulog(str(REAL / log), str(copy), ClockShift(-0.025, 0.0, 0))
        master, slave = _arg(log, master_sel), f"{copy}::{slave_sel}"
    else:
        master, slave = _arg(log, master_sel), _arg(log, slave_sel)
    out = analyze_pair(master, slave, str(tmp_path), AnalyzeOptions(recording=False, compare=False))
    al = out.report["alignment"]
    comp = al["compensated"]
    assert "skipped" not in comp, comp.get("skipped")
    assert any(x is not None for x in comp["mounting_rpy_deg"]) or comp.get("mounting_not_determined")
    if "imu_to_imu" in al:  # both units log an IMU: the direct rotation and the comparison are reported
        assert "consistency" in al and isinstance(al["consistency"]["note"], str) and al["consistency"]["note"]
    from pipelines.report import validate

    validate(out.report)
