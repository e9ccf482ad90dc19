"""A unit mix-up (gyro in deg/s, accelerometer in g) told from the sizes of the two units' measurements,
which a rotation keeps: a warning, and the reason in the line of a latency that finds no match."""
from __future__ import annotations

import numpy as np
import pytest

from logtools import sim
from logtools.conventions import G0_M_S2
from logtools.inslog import ACCEL, GYRO
from logtools.units_check import scale_findings
from pipelines.analyze import AnalyzeOptions, compute


@pytest.fixture(scope="module")
def pair():
    return sim.simulate(sim.scenario_config("aircraft", seed=3, duration_s=40.0, mount_rpy_deg=(20.0, -70.0, 135.0)))


def _scaled(log, cols, factor):
    imu = log.imu.copy()
    imu[list(cols)] *= factor
    return type(log)(imu=imu, nav=log.nav, meta=log.meta)


def test_consistent_units_say_nothing(pair):
    assert scale_findings(pair.master, pair.slave) == []


@pytest.mark.parametrize("who", ["slave", "master"])
def test_a_gyro_in_deg_s_is_named(pair, who):
    m, s = pair.master, pair.slave
    if who == "slave":
        s = _scaled(s, GYRO, np.degrees(1.0))
    else:
        m = _scaled(m, GYRO, np.degrees(1.0))
    out = scale_findings(m, s)
    assert len(out) == 1 and out[0].startswith(f"the {who}'s angular rates are 57.3 times") and "deg/s" in out[0]


def test_an_accelerometer_in_g_is_named(pair):
    out = scale_findings(pair.master, _scaled(pair.slave, ACCEL, 1.0 / G0_M_S2))
    assert len(out) == 1 and out[0].startswith("the slave's specific force") and "in g" in out[0]


def test_a_latency_without_a_match_says_why(pair):
    an = compute(pair.master, _scaled(pair.slave, GYRO, np.degrees(1.0)), AnalyzeOptions(compare=False))
    assert an.failure is not None and "57.3 times" in an.failure
    assert any("57.3 times" in w["text"] for w in an.extra["warnings"])
