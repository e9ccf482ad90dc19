"""recording.rrd: the analysis as a rerun recording (rerun-sdk 0.41), opened by ``tapost view``.

Everything is sent column-wise (``send_columns`` with a time column), never one call per sample.
Application id ``tapost``; recording name ``tapost: <pair name>`` (the batch pair name, else
``<master stem> vs <slave stem>``); recording property ``results`` (``/__properties/results``) with the
headline: latency_s, sigma_s, drift_ppm, mounting_rpy_deg, mounting_sigma_deg, mounting_run, status,
master, slave (a value the analysis could not give is left out).

Timeline ``time``: seconds since the master's first sample (master clock). A master on UNIX time also
gets timeline ``utc`` (timestamps, the same instants) on every series of ``time``. Timeline ``lag``:
the latency search grid (for the cost curve). Entity layout::

    /rates/{x,y,z}/{master,slave_raw,slave_comp}   angular rate (deg/s), slave rotated into the
                                                    master frame; slave_raw = stamps at face value
    /accel/{x,y,z}/{master,slave_raw,slave_comp}   specific force (m/s^2), likewise rotated
    /velocity/{n,e,d}/{master,slave_raw,slave_comp}  NED velocity (m/s)
    /world/track                                    master NED track (LineStrips3D, m, origin = start)
    /world/master                                   master body pose (Transform3D, FRD in NED)
    /latency/cost/<method>                          normalised cost vs lag (timeline ``lag``)
    /latency/window                                 per-window latency (ms) vs time (drift)
    /alignment/<run>/<state>/{value,upper,lower}    filter states with 3-sigma bounds
    /alignment/<run>/residuals/<name>               residuals

Downsampling rule (very long logs): a series longer than ``max_rows`` samples is reduced by an
integer factor k = ceil(n / max_rows) with a block mean (average of k consecutive samples at the
block's mean time: an anti-aliasing boxcar, not a plain stride); filter states, bounds and residuals
(smooth, many series) use ``max_rows // 10``. Poses are sent at <= ``pose_rate_hz``.
The factors used are returned and stored in report.json ("recording").
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Callable

import numpy as np

from logtools.earth import radii_m
from logtools.inslog import InsLog
from pipelines.report import RUNS, Analysis
from parsers.atomic import atomic_path

MAX_ROWS = 100_000
POSE_RATE_HZ = 10.0
AXES = ("x", "y", "z")
NED = ("n", "e", "d")
COLORS = {"master": [30, 30, 30], "slave_raw": [230, 120, 20], "slave_comp": [31, 119, 180]}
RUN_COLORS = {"uncompensated": [214, 39, 40], "compensated": [31, 119, 180]}


class _PandasRefused:
    """A module finder that refuses pandas (see :func:`without_pandas`)."""

    @staticmethod
    def find_spec(name, path=None, target=None):
        if name == "pandas" or name.startswith("pandas."):
            raise ModuleNotFoundError(f"No module named {name!r} (refused in the recording's process)", name=name)
        return None


def without_pandas() -> None:
    """pandas refused for the rest of this process: the recording's prepared child (``pipelines.analyze.
    RECORDING_CHILD_SETUP``), which writes numpy arrays only. pyarrow, under rerun, imports pandas on its
    first array only to ask whether the arrays it converts are pandas objects, and again where rerun builds
    a bar chart's tensor; without pandas it skips those checks. That import was 0.1-0.25 s of CPU in every
    short run's recording child, beside the analysis that wants both cores, and once it came late, on the
    run's last stretch. The recording is the same (tested with ``rerun rrd compare``); should a later rerun
    need pandas to write, the recording fails with ModuleNotFoundError and ``write_outputs`` writes it in the
    analysing process instead. Nothing where pandas is loaded already."""
    import sys

    if "pandas" not in sys.modules and not any(isinstance(f, _PandasRefused) for f in sys.meta_path):
        sys.meta_path.insert(0, _PandasRefused())


def refused_pandas(exc: BaseException) -> bool:
    """Whether ``exc`` is :func:`without_pandas`' refusal (the recording is then written elsewhere)."""
    return isinstance(exc, ModuleNotFoundError) and (exc.name or "").partition(".")[0] == "pandas"


def block_mean(t: np.ndarray, y: np.ndarray, max_rows: int = MAX_ROWS) -> tuple[np.ndarray, np.ndarray, int]:
    """(t, y, k): ``y`` (n,) or (n, m) block-averaged by k = ceil(n / max_rows) (k = 1: unchanged)."""
    n = len(t)
    k = max(1, int(math.ceil(n / max_rows)))
    if k == 1:
        return t, y, 1
    m = (n // k) * k
    tb = t[:m].reshape(-1, k).mean(axis=1)
    if y.ndim == 1:
        return tb, y[:m].reshape(-1, k).mean(axis=1), k
    # a column's blocks as its own (n,) series would give them (the sums along each block; numpy's reduction
    # over the middle axis of (blocks, k, m) is several times slower), from one transposed copy
    cols = np.ascontiguousarray(y[:m].reshape(m, -1).T)
    yb = cols.reshape(len(cols), -1, k).mean(axis=2).T.reshape((-1,) + y.shape[1:])
    return tb, yb, k


def _stride_to_rate(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices keeping at most ``rate_hz`` samples per second."""
    if len(t) < 2:
        return np.arange(len(t))
    dt = float(np.median(np.diff(t)))
    k = max(1, int(round((1.0 / rate_hz) / dt))) if dt > 0 else 1
    return np.arange(0, len(t), k)


def ned_track(log: InsLog) -> tuple[np.ndarray, np.ndarray] | None:
    """(t_s, NED metres from the first fix) from lat/lon/alt (local tangent plane), else None."""
    if not log.has_pos:
        return None
    t, lla = log.lat_lon_alt()
    if len(t) == 0:
        return None
    lat0 = np.radians(lla[0, 0])
    rn, re = radii_m(np.array([lat0]))
    n = np.radians(lla[:, 0] - lla[0, 0]) * (float(rn[0]) + lla[0, 2])
    e = np.radians(lla[:, 1] - lla[0, 1]) * (float(re[0]) + lla[0, 2]) * np.cos(lat0)
    d = -(lla[:, 2] - lla[0, 2])
    return t, np.column_stack([n, e, d])


@dataclass(frozen=True)
class Rest:
    """What a recording started before the analysis ended gets later (``write_recording``'s ``later``): the
    report and the alignment runs it started without. The analysis starts the recording once the compensated
    run is done, while the uncompensated one still runs in its child (``pipelines.analyze.compute``); that
    run's states are logged when this comes."""

    report: dict
    alignment: dict


def pair_name(an: Analysis, rep: dict | None = None) -> str:
    """The pair's name: the batch's (report options ``name``), else ``<master stem> vs <slave stem>``."""
    name = ((rep or {}).get("options") or {}).get("name") or getattr(getattr(an, "options", None), "name", None)
    if name:
        return str(name)

    def stem(log: InsLog) -> str:
        p = (log.meta.source_path or "").rstrip("/\\")
        base = os.path.basename(p) or p
        return os.path.splitext(base)[0] or base or "?"

    return f"{stem(an.master)} vs {stem(an.slave)}"


def headline(an: Analysis, rep: dict | None = None) -> dict:
    """The recording's ``results`` property: the headline numbers (None = not determined)."""
    lat = an.latency
    out: dict = {"status": (rep or {}).get("status")}
    if lat is not None:
        drift = lat.drift_reported_ppm
        out.update(latency_s=float(lat.latency_s), sigma_s=float(lat.sigma_s),
                   drift_ppm=None if drift is None else float(drift))
    for run in ("compensated", "uncompensated"):
        res = an.alignment.get(run)
        if res is not None and np.all(np.isfinite(res.mounting_rpy_deg)):
            out.update(mounting_rpy_deg=[float(x) for x in res.mounting_rpy_deg],
                       mounting_sigma_deg=[float(x) for x in res.mounting_sigma_deg], mounting_run=run)
            break
    if rep is not None:
        out.update(master=str(rep["master"].get("path")), slave=str(rep["slave"].get("path")))
    return out


class _Clock:
    """The master's clock: ``utc`` timestamps beside ``time`` when the master is on UNIX time."""

    def __init__(self, an: Analysis):
        self.epoch_ns = int(an.master.meta.t0_ns) if an.master.meta.clock == "epoch" else None

    def indexes(self, rr, t: np.ndarray, timeline: str) -> list:
        idx = [rr.TimeColumn(timeline, duration=t)]
        if timeline == "time" and self.epoch_ns is not None:
            ns = self.epoch_ns + np.round(t * 1e9).astype(np.int64)
            idx.append(rr.TimeColumn("utc", timestamp=ns.astype("datetime64[ns]")))
        return idx


def _send_scalars(rec, rr, path: str, t: np.ndarray, y: np.ndarray, max_rows: int,
                  timeline: str = "time", clock: _Clock | None = None) -> int:
    ok = np.isfinite(t) & np.isfinite(y)
    t, y = t[ok], y[ok]
    if len(t) == 0:
        return 0
    t, y, k = block_mean(t, y, max_rows)
    idx = clock.indexes(rr, t, timeline) if clock is not None else [rr.TimeColumn(timeline, duration=t)]
    rec.send_columns(path, indexes=idx, columns=rr.Scalars.columns(scalars=y))
    return k


def _send_axes(rec, rr, paths: list[str], t: np.ndarray, y: np.ndarray, max_rows: int, clock: _Clock) -> list[int]:
    """:func:`_send_scalars` of each column of ``y`` (n, len(paths)) to its path; the stamps' block means (and
    their time columns) made once for all the columns where every sample is finite (the logs' usual case;
    else column by column, each without its own non-finite samples)."""
    if not (len(t) and np.isfinite(t).all() and np.isfinite(y).all()):
        return [_send_scalars(rec, rr, path, t, y[:, i], max_rows, clock=clock) for i, path in enumerate(paths)]
    tb, yb, k = block_mean(t, y, max_rows)
    idx = clock.indexes(rr, tb, "time")
    for i, path in enumerate(paths):
        rec.send_columns(path, indexes=idx, columns=rr.Scalars.columns(scalars=yb[:, i]))
    return [k] * len(paths)


def _comparisons(an: Analysis) -> list[tuple[str, str, tuple[str, ...], str, object]]:
    """(entity root, label, axis names, unit, getter(log) -> (t, values in the master frame) | None)."""
    R, _ = an.mounting()

    def gyro(log: InsLog, slave: bool):
        if not log.has_gyro:
            return None
        g = np.degrees(log.gyro_rad_s())
        return log.t_imu_s(), (g @ R if slave else g)  # rows of R.T @ w: slave rate in the master frame

    def accel(log: InsLog, slave: bool):
        if not log.has_accel:
            return None
        a = log.accel_m_s2()
        return log.t_imu_s(), (a @ R if slave else a)

    def vel(log: InsLog, slave: bool):
        if not log.has_vel:
            return None
        return log.vel_ned_m_s()

    return [("rates", "angular rate", AXES, "deg/s", gyro), ("accel", "specific force", AXES, "m/s²", accel),
            ("velocity", "velocity", NED, "m/s", vel)]


def build(an: Analysis, rep: dict | None = None, *, max_rows: int = MAX_ROWS,
          pose_rate_hz: float = POSE_RATE_HZ, application_id: str = "tapost", save_to: str | None = None):
    """Fill a RecordingStream (not yet saved; with ``save_to``, streamed to that file as it is filled: rerun's
    encoder then runs in its own thread beside this one). Returns (rec, info) with the downsampling factors.
    ``rep``: the report, or a function that returns it (called once the series are logged)."""
    import rerun as rr
    import rerun.blueprint as rrb

    rec = rr.RecordingStream(application_id, recording_id=None, send_properties=True)
    if save_to is not None:
        rec.save(save_to)
    try:
        return rec, _fill(rec, rr, rrb, an, rep, max_rows, pose_rate_hz)
    except BaseException:
        if save_to is not None:
            rec.disconnect()  # (the file's writer stopped before the caller removes the file)
        raise


def _fill(rec, rr, rrb, an: Analysis, rep: dict | None, max_rows: int, pose_rate_hz: float) -> dict:
    """Everything :func:`build` logs, into ``rec``; returns the downsampling info."""
    name = pair_name(an, None if callable(rep) else rep)
    rec.send_recording_name(f"tapost: {name}")
    R, mount_src = an.mounting()
    clock = _Clock(an)
    info: dict = {"max_rows": max_rows, "rule": "block mean by k = ceil(n / max_rows)",
                  "factors": {}, "mounting_for_plots": mount_src, "name": f"tapost: {name}",
                  "timelines": ["time", "lag"] + (["utc"] if clock.epoch_ns is not None else [])}

    # -- angular rates, accelerometers, velocity: master, slave at face value, slave compensated
    streams: list[tuple[str, InsLog]] = [("master", an.master), ("slave_raw", an.slave_face_value())]
    if an.slave_comp is not None:
        streams.append(("slave_comp", an.slave_comp))
    comparisons = _comparisons(an)
    info["comparisons"] = {}
    for root, _label, axes, _unit, get in comparisons:
        for who, log in streams:
            got = get(log, who != "master")
            if got is None:
                continue
            t, v = got
            info["comparisons"].setdefault(root, []).append(who)
            paths = [f"/{root}/{ax}/{who}" for ax in axes]
            for path in paths:
                rec.log(path, rr.SeriesLines(names=who, colors=[COLORS[who]], widths=1.0), static=True)
            info["factors"].update(zip(paths, _send_axes(rec, rr, paths, t, v, max_rows, clock)))

    # -- 3D: track and attitude in NED
    rec.log("/world", rr.ViewCoordinates.FRD, static=True)  # x north, y east, z down
    trk = ned_track(an.master)
    if trk is not None:
        t_trk, ned = trk
        _, ned_ds, k = block_mean(t_trk, ned, max_rows)
        rec.log("/world/track", rr.LineStrips3D([ned_ds], colors=[[31, 119, 180]], radii=0.5), static=True)
        info["factors"]["/world/track"] = k
    if an.master.has_quat:
        tq, q = an.master.quat_wxyz()
        idx = _stride_to_rate(tq, pose_rate_hz)
        tq, q = tq[idx], q[idx]
        if trk is not None:
            pos = np.column_stack([np.interp(tq, trk[0], trk[1][:, j]) for j in range(3)])
        else:
            pos = np.zeros((len(tq), 3))
        span = float(np.ptp(trk[1], axis=0).max()) if trk is not None and len(trk[1]) else 10.0
        rec.log("/world/master", rr.TransformAxes3D(axis_length=max(span / 20.0, 1.0)), static=True)
        rec.send_columns("/world/master", indexes=clock.indexes(rr, tq, "time"),
                         columns=rr.Transform3D.columns(translation=pos, quaternion=q[:, [1, 2, 3, 0]]))
        # the slave's body axes (master attitude composed with the mounting) as arrows
        axes_m = np.eye(3) * max(span / 30.0, 0.7)
        slave_axes_body = axes_m @ R  # rows: slave x/y/z axes expressed in the master body frame
        rec.log("/world/master/slave_axes",
                rr.Arrows3D(vectors=slave_axes_body, colors=[[230, 60, 60], [60, 180, 60], [60, 60, 230]]),
                static=True)
        info["factors"]["/world/master"] = int(idx[1] - idx[0]) if len(idx) > 1 else 1

    # -- latency
    lat = an.latency
    if lat is not None and len(lat.cost_lag_s):
        path = f"/latency/cost/{lat.method}"
        rec.log(path, rr.SeriesLines(names=f"cost {lat.method}", colors=[[31, 119, 180]]), static=True)
        _send_scalars(rec, rr, path, np.asarray(lat.cost_lag_s, float), np.asarray(lat.cost, float),
                      max_rows, timeline="lag")
        lag_ms = np.asarray(lat.cost_lag_s, float) * 1e3
        cost = np.asarray(lat.cost, float)
        stride = max(1, int(math.ceil(len(lag_ms) / 2000)))
        width = float(np.median(np.diff(lag_ms[::stride]))) if len(lag_ms) > stride else 1.0
        # static chart: visible whatever timeline is selected (x = lag in ms)
        rec.log("/latency/cost_chart", rr.BarChart(np.nan_to_num(cost[::stride]), abscissa=lag_ms[::stride],
                                                   widths=[width], color=[31, 119, 180]), static=True)
        rec.log("/latency/estimate",
                rr.TextDocument(f"latency {lat.latency_s * 1e3:+.3f} ms ± {lat.sigma_s * 1e3:.3f} ms (1σ), "
                                + (f"drift {lat.drift_reported_ppm:+.2f} ppm" if lat.drift_reported_ppm is not None
                                   else "drift not estimated") + f", method {lat.method}"), static=True)
    if lat is not None and len(lat.window_latency_s):
        rec.log("/latency/window", rr.SeriesPoints(names="per-window latency (ms)", marker_sizes=3.0),
                static=True)
        _send_scalars(rec, rr, "/latency/window", np.asarray(lat.window_centers_s, float),
                      np.asarray(lat.window_latency_s, float) * 1e3, max_rows, clock=clock)
        tt = np.asarray(lat.window_centers_s, float)
        rec.log("/latency/fit", rr.SeriesLines(names="latency fit (ms)", colors=[[214, 39, 40]]), static=True)
        _send_scalars(rec, rr, "/latency/fit", tt, lat.latency_at(tt) * 1e3, max_rows, clock=clock)

    # -- alignment states with 3-sigma bounds, residuals: the runs in ``an`` now; a run that still ran when the
    # recording started (see Rest) once the rest comes
    state_rows = max(1000, max_rows // 10)
    info["max_rows_states"] = state_rows
    run_factors: dict[str, dict] = {}
    _log_runs(rec, rr, an, run_factors, state_rows, clock)

    # -- the report's parts: the headline property and the summary text (last: the report may still be in
    # the making while the series above are logged, see write_recording)
    if callable(rep):
        rep = rep()
        if isinstance(rep, Rest):
            an.alignment.update({k: v for k, v in rep.alignment.items() if an.alignment.get(k) is None})
            rep = rep.report
            _log_runs(rec, rr, an, run_factors, state_rows, clock)
    for run in RUNS:  # (the factors in the runs' order, however they came)
        info["factors"].update(run_factors.get(run, {}))
    props = {k: v for k, v in headline(an, rep).items() if v is not None}
    rec.send_property("results", rr.AnyValues(**props))
    if rep is not None:
        lines = [f"# tapost {rep.get('status', '')}", "",
                 f"master: {rep['master']['path']}", f"slave: {rep['slave']['path']}"]
        for k, v in rep.get("skipped", {}).items():
            lines.append(f"- skipped {k}: {v}")
        rec.log("/summary", rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN), static=True)

    rec.send_blueprint(_blueprint(rrb, an, [c for c in comparisons if c[0] in info["comparisons"]]))
    return info


def _log_runs(rec, rr, an: Analysis, run_factors: dict, state_rows: int, clock: _Clock) -> None:
    """Each alignment run of ``an`` not logged yet (not in ``run_factors``): its filter states with 3-sigma
    bounds and its residuals; its downsampling factors into ``run_factors[run]``."""
    for run in RUNS:
        res = an.alignment.get(run)
        if res is None or run in run_factors:
            continue
        factors = run_factors[run] = {}
        c = RUN_COLORS.get(run, [100, 100, 100])
        if res.history_x.size:
            t = np.asarray(res.history_t_s, float)
            for i, name in enumerate(res.history_names):
                base = f"/alignment/{run}/{rr.escape_entity_path_part(name)}"
                x, s = res.history_x[:, i], res.history_sigma[:, i]
                for part, y, w in (("value", x, 1.5), ("upper", x + 3 * s, 0.7), ("lower", x - 3 * s, 0.7)):
                    rec.log(f"{base}/{part}", rr.SeriesLines(names=f"{name} {part if part != 'value' else ''}".strip(),
                                                             colors=[c], widths=w), static=True)
                    factors[f"{base}/{part}"] = _send_scalars(rec, rr, f"{base}/{part}", t, y, state_rows,
                                                              clock=clock)
        if res.residuals.size:
            t = np.asarray(res.residual_t_s, float)
            for i, name in enumerate(res.residual_names):
                path = f"/alignment/{run}/residuals/{rr.escape_entity_path_part(name)}"
                rec.log(path, rr.SeriesPoints(names=name, colors=[c], marker_sizes=1.5), static=True)
                factors[path] = _send_scalars(rec, rr, path, t, res.residuals[:, i], state_rows, clock=clock)


def _blueprint(rrb, an: Analysis, comparisons=()):
    rates = rrb.Vertical(*[rrb.TimeSeriesView(origin=f"/rates/{ax}", name=f"angular rate {ax} (deg/s)")
                           for ax in AXES], name="rates")
    # master, slave raw and slave compensated side by side: rates | accelerometers | velocity
    columns = [rrb.Vertical(*[rrb.TimeSeriesView(origin=f"/{root}/{ax}", name=f"{label} {ax} ({unit})")
                              for ax in axes], name=label)
               for root, label, axes, unit, _ in comparisons]
    right = [rrb.Spatial3DView(origin="/world", name="master track and attitude (NED)")]
    if an.latency is not None:
        right.append(rrb.BarChartView(origin="/latency/cost_chart", name="latency cost vs lag (ms)"))
        right.append(rrb.TimeSeriesView(origin="/latency", contents=["/latency/window", "/latency/fit"],
                                        name="latency per window (ms)"))
    overview = rrb.Horizontal(rates, rrb.Vertical(*right), column_shares=[3, 2], name="overview")
    tabs = [overview]
    if len(columns) > 1:
        tabs.append(rrb.Horizontal(*columns, name="rates, accelerometers, velocity"))
    for run in RUNS:
        res = an.alignment.get(run)
        if res is None or not res.history_x.size:
            continue
        import rerun as rr

        views = [rrb.TimeSeriesView(origin=f"/alignment/{run}/{rr.escape_entity_path_part(n)}", name=n)
                 for n in res.history_names]
        if res.residuals.size:
            views.append(rrb.TimeSeriesView(origin=f"/alignment/{run}/residuals", name="residuals"))
        tabs.append(rrb.Grid(*views, name=f"alignment {run}"))
    return rrb.Blueprint(rrb.Tabs(*tabs, active_tab=0), rrb.TimePanel(state="collapsed"),
                         collapse_panels=False)


def write_recording(path: str, an: Analysis, rep: dict | None = None, *, max_rows: int = MAX_ROWS,
                    later: Callable[[], dict] | None = None) -> dict:
    """Build and save the recording to ``path`` atomically; returns the downsampling info. With ``later`` (a
    ``parallel.submit_awaiting`` call) the report is ``later()``, asked for only once the series are logged:
    the recording can start before the report exists."""
    if later is not None:
        rep = later
    with atomic_path(path) as tmp:
        rec, info = build(an, rep, max_rows=max_rows, save_to=tmp)
        rec.flush(timeout_sec=120.0) if _flush_takes_timeout(rec) else rec.flush()
        rec.disconnect()
        if not os.path.getsize(tmp):
            raise OSError(f"rerun wrote an empty recording: {path}")
    return info


def _flush_takes_timeout(rec) -> bool:
    import inspect

    try:
        return "timeout_sec" in inspect.signature(rec.flush).parameters
    except (TypeError, ValueError):
        return False


def read_entities(path: str) -> dict[str, dict]:
    """{entity_path: {"rows": n_temporal_rows, "static": has_static, "timelines": [...]}} read back
    with rerun's own reader (``rerun.chunk.RrdReader``). Used by tests and ``tapost view`` checks."""
    from rerun.chunk import RrdReader

    out: dict[str, dict] = {}
    for ch in RrdReader(path).stream().to_chunks():
        e = out.setdefault(str(ch.entity_path), {"rows": 0, "static": False, "timelines": set()})
        if ch.is_static:
            e["static"] = True
        else:
            e["rows"] += int(ch.num_rows)
            e["timelines"].update(ch.timeline_names)
    for e in out.values():
        e["timelines"] = sorted(e["timelines"])
    return out


def read_properties(path: str) -> dict:
    """{"application_id", "name", "results": {...}} of a recording, read back with rerun's own reader
    (``rerun.chunk.RrdReader``: the store entry and the ``/__properties`` chunks)."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    entries = [e for e in reader.recordings() if e.kind == "recording"]
    out: dict = {"application_id": entries[0].application_id if entries else None, "name": None, "results": {}}
    for ch in reader.stream().to_chunks():
        ent = str(ch.entity_path)
        if not ent.startswith("/__properties"):
            continue
        for row in ch.to_record_batch().to_pylist():
            for k, v in row.items():
                if k.startswith("rerun.controls"):
                    continue
                v = v[0] if isinstance(v, list) and len(v) == 1 else v
                if ent == "/__properties" and k == "RecordingInfo:name":
                    out["name"] = v
                elif ent == "/__properties/results":
                    out["results"][k] = v
    return out
