"""An analysis as pandas DataFrames (``Analysis.frames()``, DESIGN.md "Python API").

Every frame is indexed by ``t_s``: seconds relative to the master's origin (``master.meta.t0_ns``), on the
master's clock, except ``latency_cost`` (indexed by the lag). Keys:

* ``rates``: the master's angular rate and the slave's, both on the master's IMU stamps and in the master's
  body axes (the slave's rotated by the estimated mounting): ``slave_raw_*`` with the slave's stamps at face
  value, ``slave_*`` on the master's clock (compensated). The two ``slave`` groups differ by the latency.
* ``latency_windows``: each window's latency (``latency_s``) at its centre.
* ``latency_cost``: the normalised cost of the lag search around the estimate (``lag_s`` index).
* ``states_uncompensated``, ``states_compensated``: the alignment filter's states over time, a column per
  state and ``<state>_sigma`` for its 1-sigma.
* ``residuals_uncompensated``, ``residuals_compensated``: the alignment's measurement residuals.
* ``slave_on_master_clock_imu``, ``slave_on_master_clock_nav``: the compensated slave's own samples.

A frame the analysis has no data for (the latency failed, an alignment run was skipped) is absent.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from logtools.inslog import GYRO, T

AXES = ("x", "y", "z")


def _rates(an) -> pd.DataFrame | None:
    m = an.master
    if not m.has_gyro:
        return None
    t = m.t_imu_s()
    cols = {f"master_{c}": m.imu[c].to_numpy(float) for c in GYRO}
    R, _ = an.mounting()  # v_slave = R v_master  ->  v_master = R.T v_slave
    for tag, log in (("slave_raw", an.slave_face_value()), ("slave", an.slave_comp)):
        if log is None or not log.has_gyro or len(log.imu) < 2:
            continue
        ts, w = log.t_imu_s(), log.gyro_rad_s() @ R  # rows: (R.T v)^T = v^T R
        inside = (t >= ts[0]) & (t <= ts[-1])
        for i, ax in enumerate(AXES):
            col = np.full(len(t), np.nan)
            col[inside] = np.interp(t[inside], ts, w[:, i])
            cols[f"{tag}_gyro_{ax}_rad_s"] = col
    return pd.DataFrame(cols, index=pd.Index(t, name=T))


def _history(res, kind: str) -> pd.DataFrame | None:
    if kind == "states":
        t, names, x = res.history_t_s, res.history_names, res.history_x
        if not len(t) or not names:
            return None
        cols = {n: x[:, i] for i, n in enumerate(names)}
        sig = res.history_sigma
        if sig.shape == x.shape:
            cols.update({f"{n}_sigma": sig[:, i] for i, n in enumerate(names)})
        return pd.DataFrame(cols, index=pd.Index(t, name=T))
    t, names, r = res.residual_t_s, res.residual_names, res.residuals
    if not len(t) or not names:
        return None
    return pd.DataFrame({n: r[:, i] for i, n in enumerate(names)}, index=pd.Index(t, name=T))


def analysis_frames(an) -> dict[str, pd.DataFrame]:
    """The DataFrames of an analysis (see the module docstring)."""
    out: dict[str, pd.DataFrame] = {}
    rates = _rates(an)
    if rates is not None:
        out["rates"] = rates
    lat = an.latency
    if lat is not None:
        if len(lat.window_centers_s):
            out["latency_windows"] = pd.DataFrame({"latency_s": np.asarray(lat.window_latency_s, float)},
                                                  index=pd.Index(np.asarray(lat.window_centers_s, float), name=T))
        if len(lat.cost_lag_s):
            out["latency_cost"] = pd.DataFrame({"cost": np.asarray(lat.cost, float)},
                                               index=pd.Index(np.asarray(lat.cost_lag_s, float), name="lag_s"))
    for run, res in an.alignment.items():
        if res is None:
            continue
        for kind in ("states", "residuals"):
            df = _history(res, kind)
            if df is not None:
                out[f"{kind}_{run}"] = df
    comp = an.slave_comp
    if comp is not None:
        out["slave_on_master_clock_imu"] = comp.imu
        out["slave_on_master_clock_nav"] = comp.nav
    return out
