"""Latency estimation accuracy: Monte Carlo over the simulator's scenarios, every method side by side.

Runs ``logtools.sim`` pairs over

* scenarios ship, aircraft, vehicle, multirotor (round robin), 120 s each (the scenarios' default);
* latency uniform in [-1, 1] s (sub-sample values), drift uniform in +-100 ppm;
* mounting rotation uniform on SO(3) (normalised Gaussian quaternion);
* master and slave IMU rates independently uniform in [50, 400] Hz (nav rates capped at the IMU rate);
* slave noise and bias scaled by a level drawn from {0.5, 1, 3} x the scenario's, flexure on in 1/3
  of the runs, a random start-up phase of the slave's samples;
* the slave logs a nav solution (attitude, NED velocity, position) in 3/4 of the runs, its velocity with
  white noise of the same level x SLAVE_VEL_NOISE_M_S (drawn from a stream of its own, so the other
  draws are those of the earlier benchmark); in the other 1/4 it is an IMU alone;

and estimates the latency with every method through ``logtools.latency.estimate(..., compare=True)``
(``tapost``, ``xcorr-norm``, ``s000-rate-integral``, ``s002-attitude-shift`` read from ``methods``).
Truth is ``Truth.latency_at(result.t_mid_rel_s)`` (the instant where the estimate holds). Per method:
RMS, worst and median absolute error, fraction within 1 ms, coverage of sigma (fraction of runs with
|error| <= 2 sigma), failures (AnalysisError / NaN) and runtime per run (each method timed on its own).

Further sets: an aligned-axes control (runs/5, what the seeds assume) and a stamp-noise set (runs/5:
white noise on both units' stamps, std up to 0.3 of each IMU period, and two gaps in the slave).
"tapost-no-velocity" is tapost's method without the velocity matching, "tapost-gyro-only" without it and
without the accelerometer-aided GLS (ablations). For the flexure runs, the Cramer-Rao bound of the
latency (``latency_bound.py``: exact flexure and noise model, truth signals) is computed too, from the
rates and specific forces and, where the slave logs a nav velocity, with the velocities' information
added: the RMS and the within-1 ms fraction an efficient estimator would reach.

Second table: S000's Table 1 (aircraft, aligned axes, 200 Hz units, delays 10/50/100/150 ms, an exact
number of samples as in the paper) with S000's method (5 s record in the S manoeuvre, +-1 s search,
as published; and the whole overlap) and tapost's, next to the paper's published numbers.

    python benchmarks/bench_latency.py --quick        # 40 runs
    python benchmarks/bench_latency.py [--runs 200]   # full (>= 200 runs)

Writes ``benchmarks/results/latency.json`` (config, per-run rows, summary) and
``benchmarks/results/latency_s000_table1.json``; prints markdown tables.
"""
from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import os
import platform
import sys
import time
from datetime import datetime, timezone

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # latency_bound
RESULTS_DIR = os.path.join(ROOT, "benchmarks", "results")
OUT_MC = os.path.join(RESULTS_DIR, "latency.json")
OUT_T1 = os.path.join(RESULTS_DIR, "latency_s000_table1.json")

SCENARIOS = ("ship", "aircraft", "vehicle", "multirotor")
METHODS = ("tapost", "xcorr-norm", "s000-rate-integral", "s002-attitude-shift")
# the seeds again with the papers' own search range (+-1 s, S000 step 2), computed directly
PAPER_RANGE = {"s000-rate-integral@1s": "s000_rate_integral", "s002-attitude-shift@1s": "s002_attitude_shift"}
#: ablations: tapost's method without the velocity matching; and on the gyros alone (neither the velocity
#: matching nor the accelerometer-aided GLS)
NO_VEL = "tapost-no-velocity"
GYRO_ONLY = "tapost-gyro-only"
ALL_METHODS = METHODS[:1] + (NO_VEL, GYRO_ONLY) + METHODS[1:] + tuple(PAPER_RANGE)
MAX_LAG_S = 2.0  # tapost's default search window (DESIGN.md --max-lag); latencies are within +-1 s
NOISE_LEVELS = (0.5, 1.0, 3.0)
#: the bound with gyros and accelerometers, gyros alone, and with the velocities too (slave with nav)
BOUND_KEYS = ("aided", "gyro", "aided+velocity")
SLAVE_NAV_FRACTION = 0.75  # runs whose slave logs a nav solution (else an IMU alone)
SLAVE_VEL_NOISE_M_S = 0.005  # slave nav velocity white noise at noise level 1 (master: 0.002 m/s)
PAPER_TABLE1 = {10: (2, 10), 50: (10, 50), 100: (20, 100), 150: (30, 150)}  # ms: (shifted points, est. ms)


# ---- one Monte Carlo run --------------------------------------------------------------------------
def random_rotation_rpy_deg(rng: np.random.Generator) -> tuple[float, float, float]:
    """Uniform on SO(3): a normalised 4-D Gaussian is a uniform unit quaternion."""
    from logtools.conventions import euler_from_quat

    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    return tuple(float(x) for x in np.degrees(euler_from_quat(q)))


def draw_config(i: int, base_seed: int, aligned: bool = False, stamps: bool = False) -> dict:
    """Run i's random draw; ``aligned`` (the control set) keeps the draw but mounts the units aligned;
    ``stamps`` (the stamp-noise set) adds white noise to both units' stamps (std uniform in 0-0.3 of each
    unit's IMU period) and two gaps in the slave (0.05-2 s)."""
    rng = np.random.default_rng([base_seed, i, int(aligned) + 2 * int(stamps)])
    scenario = SCENARIOS[i % len(SCENARIOS)]
    m_imu = float(rng.uniform(50.0, 400.0))
    s_imu = float(rng.uniform(50.0, 400.0))
    extra = {}
    if stamps:
        extra = dict(master_jitter_s=float(rng.uniform(0.0, 0.3)) / m_imu,
                     slave_jitter_s=float(rng.uniform(0.0, 0.3)) / s_imu,
                     slave_gaps_s=[[float(rng.uniform(10.0, 50.0)), float(rng.uniform(0.05, 2.0))],
                                   [float(rng.uniform(60.0, 100.0)), float(rng.uniform(0.05, 2.0))]])
    return dict(
        **extra,
        run=i, set="aligned-control" if aligned else ("stamps" if stamps else "main"), scenario=scenario,
        seed=int(rng.integers(0, 2**31 - 1)),
        latency_s=float(rng.uniform(-1.0, 1.0)), drift_ppm=float(rng.uniform(-100.0, 100.0)),
        mount_rpy_deg=(0.0, 0.0, 0.0) if aligned else random_rotation_rpy_deg(rng),
        master_imu_rate_hz=m_imu, slave_imu_rate_hz=s_imu,
        noise_level=float(rng.choice(NOISE_LEVELS)), flexure=bool(rng.random() < 1.0 / 3.0),
        slave_nav=bool(np.random.default_rng([base_seed, i, 10 + int(aligned) + 2 * int(stamps)]).random()
                       < SLAVE_NAV_FRACTION),
    )


def sim_config(d: dict):
    from logtools import sim

    base = sim.scenario_config(d["scenario"])
    lvl = d["noise_level"]
    ov = dict(
        seed=d["seed"], latency_s=d["latency_s"], drift_ppm=d["drift_ppm"], mount_rpy_deg=d["mount_rpy_deg"],
        master_imu_rate_hz=d["master_imu_rate_hz"], slave_imu_rate_hz=d["slave_imu_rate_hz"],
        master_nav_rate_hz=min(base.master_nav_rate_hz, d["master_imu_rate_hz"]),
        slave_nav_rate_hz=min(base.slave_nav_rate_hz, d["slave_imu_rate_hz"]),
        slave_gyro_bias_dph=tuple(lvl * x for x in base.slave_gyro_bias_dph),
        slave_accel_bias_mg=tuple(lvl * x for x in base.slave_accel_bias_mg),
        slave_gyro_arw_dpsh=lvl * base.slave_gyro_arw_dpsh,
        slave_accel_vrw_ug_rthz=lvl * base.slave_accel_vrw_ug_rthz, flexure=d["flexure"],
        slave_nav=d.get("slave_nav", True), slave_vel_noise_m_s=lvl * SLAVE_VEL_NOISE_M_S,
    )
    for k in ("master_jitter_s", "slave_jitter_s", "slave_gaps_s", "duration_s"):
        if k in d:
            ov[k] = d[k]
    for k in ("rigid_vibration_deg", "rigid_vibration_hz"):
        if k in d:
            ov[k] = tuple(d[k])
    return sim.scenario_config(d["scenario"], **ov)


def run_pool(fn, jobs: list, workers: int, every: int = 10) -> list:
    """fn over jobs in ``workers`` processes (spawned; in this one with 1), progress on stderr every
    ``every`` results; results in completion order."""
    t0 = time.perf_counter()
    if workers <= 1:
        return [fn(j) for j in jobs]
    out = []
    with mp.get_context("spawn").Pool(workers) as pool:
        for k, r in enumerate(pool.imap_unordered(fn, jobs)):
            out.append(r)
            if (k + 1) % every == 0:
                print(f"  {k + 1}/{len(jobs)} runs, {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return out


def write_json_atomic(path: str, obj: dict) -> None:
    """A results file written whole or not at all."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1, default=float)
    os.replace(tmp, path)


def _timed(fn, *a, **kw):
    t = time.perf_counter()
    try:
        out, err = fn(*a, **kw), None
    except Exception as exc:  # noqa: BLE001 - a benchmark row records the failure, never stops
        out, err = None, f"{type(exc).__name__}: {getattr(exc, 'problem', exc)}"
    return out, err, time.perf_counter() - t


def run_one(d: dict) -> dict:
    from logtools import latency_seeds, sim
    from logtools.latency import estimate

    row = dict(d)
    row["mount_rpy_deg"] = list(d["mount_rpy_deg"])
    cfg = sim_config(d)
    pair = sim.simulate(cfg)
    m, s, truth = pair.master, pair.slave, pair.truth
    if d["flexure"]:  # what no estimator can beat on this run (benchmarks/latency_bound.py)
        from latency_bound import latency_bound_s

        row["bound_s"] = latency_bound_s(cfg, truth)
    res, err, t_all = _timed(estimate, m, s, max_lag_s=MAX_LAG_S, compare=True)
    row["runtime_compare_all_s"] = t_all
    if res is not None:
        t_mid = float(res.t_mid_rel_s)
        got = {k: (float(v.latency_s), float(v.sigma_s), v.note) for k, v in res.methods.items()}
        row["tapost_drift_ppm"] = float(res.drift_ppm)
        row["tapost_quality"] = {k: v for k, v in res.quality.items() if isinstance(v, (bool, int, float, str))}
        vq = res.quality.get("velocity_fit")
        if vq:  # the velocity-matched estimate on its own (fused or not)
            row["velocity_fit"] = {k: vq[k] for k in ("latency_s", "sigma_s", "agreement_chi2", "fused")}
    else:  # the headline failed: the others are still measured on their own
        a0, a1 = max(m.span_s()[0], s.rebased(m.meta.t0_ns).span_s()[0]), m.span_s()[1]
        t_mid = 0.5 * (a0 + a1)
        got = {"tapost": (math.nan, math.nan, err)}
    row["t_mid_rel_s"] = t_mid
    row["truth_latency_s"] = float(truth.latency_at(t_mid))
    if "velocity_fit" in row:
        row["velocity_fit"]["error_s"] = row["velocity_fit"]["latency_s"] - row["truth_latency_s"]
    # per-method runtime (each on its own) and fallback values when estimate() did not give them
    solo = {
        "tapost": lambda: estimate(m, s, max_lag_s=MAX_LAG_S, compare=False),
        NO_VEL: lambda: estimate(m, s, max_lag_s=MAX_LAG_S, compare=False, velocity=False),
        GYRO_ONLY: lambda: estimate(m, s, max_lag_s=MAX_LAG_S, compare=False, accelerometers=False,
                                    velocity=False),
        "xcorr-norm": lambda: estimate(m, s, method="xcorr-norm", max_lag_s=MAX_LAG_S, compare=False),
        "s000-rate-integral": lambda: latency_seeds.s000_rate_integral(m, s, max_lag_s=MAX_LAG_S),
        "s002-attitude-shift": lambda: latency_seeds.s002_attitude_shift(m, s, max_lag_s=MAX_LAG_S),
    }
    for name, fn in PAPER_RANGE.items():
        solo[name] = (lambda f: lambda: f(m, s, max_lag_s=1.0))(getattr(latency_seeds, fn))
    for name in ALL_METHODS:
        out, e, dt = _timed(solo[name])
        row[f"runtime_{name}_s"] = dt
        if name not in got:
            if out is None:
                got[name] = (math.nan, math.nan, e)
            else:
                got[name] = (float(out.latency_s), float(out.sigma_s), getattr(out, "note", ""))
        lat, sig, note = got[name]
        row[name] = dict(latency_s=lat, sigma_s=sig, error_s=lat - row["truth_latency_s"],
                         note=(note or "")[:200])
    return row


# ---- summary ---------------------------------------------------------------------------------------
def summarize(rows: list[dict], methods=ALL_METHODS) -> dict:
    out = {}
    for name in methods:
        err = np.array([r[name]["error_s"] for r in rows], float)
        sig = np.array([r[name]["sigma_s"] for r in rows], float)
        ok = np.isfinite(err)
        e = np.abs(err[ok])
        rt = np.array([r.get(f"runtime_{name}_s", np.nan) for r in rows], float)
        out[name] = dict(
            runs=len(rows), failed=int((~ok).sum()),
            rms_ms=float(np.sqrt(np.mean(e ** 2)) * 1e3) if len(e) else math.nan,
            worst_ms=float(e.max() * 1e3) if len(e) else math.nan,
            median_ms=float(np.median(e) * 1e3) if len(e) else math.nan,
            within_1ms=float(np.sum(e <= 1e-3) / len(rows)) if rows else math.nan,  # failures count as misses
            coverage_2sigma=float(np.sum(np.abs(err[ok]) <= 2.0 * sig[ok]) / len(rows)) if rows else math.nan,
            runtime_mean_s=float(np.nanmean(rt)) if np.isfinite(rt).any() else math.nan,
        )
    return out


def summarize_bound(rows: list[dict]) -> dict:
    """The Cramer-Rao bound over the flexure runs that have it: its RMS (what an efficient estimator's
    RMS error would be) and the fraction of runs an efficient, unbiased Gaussian estimator would bring
    within 1 ms (mean of erf(1 ms / (sqrt 2 bound))), with the gyros and accelerometers, the gyros alone, and
    (runs whose slave logs a nav velocity) the gyros, accelerometers and velocities."""
    out = {}
    for key in BOUND_KEYS:
        b = np.array([r["bound_s"][key] for r in rows if key in r.get("bound_s", {})], float)
        if not len(b):
            continue
        out[key] = dict(runs=int(len(b)), rms_ms=float(np.sqrt(np.mean(b ** 2)) * 1e3),
                        worst_ms=float(b.max() * 1e3),
                        expected_within_1ms=float(np.mean([math.erf(1e-3 / (math.sqrt(2.0) * x)) for x in b])))
    return out


def bound_md(bounds: dict) -> str:
    lines = ["### Cramer-Rao bound of the latency, flexure runs (benchmarks/latency_bound.py)", "",
             "| runs | " + " | ".join(f"{k}: runs / RMS (ms) / worst (ms) / expected within 1 ms" for k in BOUND_KEYS)
             + " |", "|---|" + "---|" * len(BOUND_KEYS)]
    for name, b in bounds.items():
        if not b:
            continue
        cells = [f"{b[k]['runs']} / {b[k]['rms_ms']:.3f} / {b[k]['worst_ms']:.3f} / "
                 f"{100 * b[k]['expected_within_1ms']:.1f} %" if k in b else "-" for k in BOUND_KEYS]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def md_table(summary: dict, title: str) -> str:
    lines = [f"### {title}", "",
             "| method | runs | failed | RMS (ms) | worst (ms) | median (ms) | within 1 ms "
             "| coverage (err <= 2 sigma) | runtime/run (s) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, s in summary.items():
        lines.append(f"| {name} | {s['runs']} | {s['failed']} | {s['rms_ms']:.3f} | {s['worst_ms']:.3f} | "
                     f"{s['median_ms']:.3f} | {100 * s['within_1ms']:.1f} % | {100 * s['coverage_2sigma']:.1f} % | "
                     f"{s['runtime_mean_s']:.3f} |")
    return "\n".join(lines)


# ---- S000 Table 1 ----------------------------------------------------------------------------------
def table1(seed: int = 0) -> dict:
    from logtools import latency_seeds, sim
    from logtools.latency import estimate

    rows = []
    for lat_ms, (pts, paper_ms) in PAPER_TABLE1.items():
        cfg = sim.scenario_config("aircraft", latency_s=lat_ms / 1000.0, drift_ppm=0.0,
                                  mount_rpy_deg=(0.0, 0.0, 0.0), master_imu_rate_hz=200.0,
                                  slave_imu_rate_hz=200.0, slave_start_phase=0.0, seed=seed + lat_ms)
        p = sim.simulate(cfg)
        start = cfg.turn_start_s + 5.0  # a 5 s record inside the S manoeuvre (S000 sec. 5)
        row = dict(delay_ms=lat_ms, paper_shifted_points=pts, paper_estimated_ms=paper_ms)
        for key, fn in (
            ("s000_5s_record", lambda: latency_seeds.s000_rate_integral(p.master, p.slave, max_lag_s=1.0,
                                                                        record_s=5.0, record_start_s=start)),
            ("s000_whole_overlap", lambda: latency_seeds.s000_rate_integral(p.master, p.slave, max_lag_s=1.0)),
            ("tapost", lambda: estimate(p.master, p.slave, max_lag_s=MAX_LAG_S, compare=False)),
        ):
            out, err, dt = _timed(fn)
            if out is None:
                row[key] = dict(estimated_ms=math.nan, error_ms=math.nan, note=err)
                continue
            t_mid = getattr(out, "t_mid_rel_s", 0.5 * cfg.duration_s)
            truth_ms = p.truth.latency_at(t_mid) * 1e3
            row[key] = dict(estimated_ms=out.latency_s * 1e3, error_ms=out.latency_s * 1e3 - truth_ms,
                            sigma_ms=out.sigma_s * 1e3, runtime_s=dt)
            if key.startswith("s000"):
                row[key]["shifted_points"] = int(round(out.latency_s / 0.005))
        rows.append(row)
    return dict(
        description=("S000 Tab. 1 reproduced: aircraft S manoeuvre (32N 118E, 1000 m, 200 m/s), aligned axes, "
                     "200 Hz units (5 ms = one sample), slave gyro 1 deg/h + noise, accel 0.2 mg + noise; "
                     "delays an exact number of samples as in the paper. S000 searches +-1 s as published."),
        rows=rows)


def table1_md(t1: dict) -> str:
    lines = ["### S000 Table 1 reproduced (aircraft, aligned axes, 200 Hz)", "",
             "| delay (ms) | paper: shifted points | paper: estimated (ms) | S000, 5 s record (ms) | "
             "S000, whole overlap (ms) | tapost (ms) | tapost error (ms) |",
             "|---:|---:|---:|---:|---:|---:|---:|"]
    for r in t1["rows"]:
        lines.append(f"| {r['delay_ms']} | {r['paper_shifted_points']} | {r['paper_estimated_ms']} | "
                     f"{r['s000_5s_record']['estimated_ms']:.1f} | {r['s000_whole_overlap']['estimated_ms']:.1f} | "
                     f"{r['tapost']['estimated_ms']:.3f} | {r['tapost']['error_ms']:+.4f} |")
    return "\n".join(lines)


# ---- main ------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="40 runs")
    ap.add_argument("--runs", type=int, default=None, help="number of Monte Carlo runs (full: 200)")
    ap.add_argument("--control", type=int, default=None,
                    help="extra runs with aligned axes (control for the seeds; default runs/5)")
    ap.add_argument("--stamps", type=int, default=None,
                    help="extra runs with noisy stamps and slave gaps (default runs/5)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--out", default=OUT_MC)
    ap.add_argument("--table1-out", default=OUT_T1)
    args = ap.parse_args(argv)
    n_runs = args.runs if args.runs is not None else (40 if args.quick else 200)
    n_ctrl = args.control if args.control is not None else n_runs // 5
    n_stamps = args.stamps if args.stamps is not None else n_runs // 5
    configs = [draw_config(i, args.seed) for i in range(n_runs)]
    configs += [draw_config(n_runs + i, args.seed, aligned=True) for i in range(n_ctrl)]
    configs += [draw_config(n_runs + n_ctrl + i, args.seed, stamps=True) for i in range(n_stamps)]
    t_start = time.perf_counter()
    if args.workers > 1:
        with mp.get_context("spawn" if sys.platform == "darwin" else "fork").Pool(args.workers) as pool:
            rows = []
            for k, r in enumerate(pool.imap_unordered(run_one, configs)):
                rows.append(r)
                if (k + 1) % 10 == 0:
                    print(f"  {k + 1}/{len(configs)} runs, {time.perf_counter() - t_start:.0f} s", file=sys.stderr)
    else:
        rows = [run_one(c) for c in configs]
    rows.sort(key=lambda r: r["run"])
    wall = time.perf_counter() - t_start
    main_rows = [r for r in rows if r["set"] == "main"]
    ctrl_rows = [r for r in rows if r["set"] == "aligned-control"]
    stamp_rows = [r for r in rows if r["set"] == "stamps"]
    summary = summarize(main_rows)
    by_scenario = {sc: summarize([r for r in main_rows if r["scenario"] == sc]) for sc in SCENARIOS}
    control = summarize(ctrl_rows) if ctrl_rows else {}
    stamp_noise = summarize(stamp_rows, methods=("tapost", NO_VEL, GYRO_ONLY, "xcorr-norm")) if stamp_rows else {}
    by_flexure = {f"flexure={f}": summarize(sel) for f in (False, True)
                  if (sel := [r for r in main_rows if r["flexure"] == f])}
    tap = ("tapost", NO_VEL, GYRO_ONLY)
    by_slave_nav = {f"slave_nav={v}, flexure={f}": summarize(sel, methods=tap) for v in (True, False)
                    for f in (False, True)
                    if (sel := [r for r in main_rows if r.get("slave_nav", True) == v and r["flexure"] == f])}
    flex_rows = [r for r in main_rows if r["flexure"]]
    flexure_by_scenario = {f"{sc}, slave_nav={v}": summarize(sel, methods=tap) for sc in SCENARIOS
                           for v in (True, False)
                           if (sel := [r for r in flex_rows if r["scenario"] == sc and r.get("slave_nav", True) == v])}
    bound = {"all flexure runs": summarize_bound(flex_rows),
             "flexure runs, IMU-only slave": summarize_bound([r for r in flex_rows if not r.get("slave_nav", True)]),
             "flexure runs, slave with nav": summarize_bound([r for r in flex_rows if r.get("slave_nav", True)])}
    bound.update({f"{sc}, slave_nav={v}": summarize_bound(sel) for sc in SCENARIOS for v in (True, False)
                  if (sel := [r for r in flex_rows if r["scenario"] == sc and r.get("slave_nav", True) == v])})
    t1 = table1()
    result = dict(
        benchmark="latency", created_utc=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        config=dict(runs=n_runs, aligned_control_runs=n_ctrl, stamp_noise_runs=n_stamps,
                    stamp_noise="white, std uniform in [0, 0.3] IMU period per unit; 2 slave gaps 0.05-2 s", quick=bool(args.quick), workers=args.workers,
                    seed=args.seed,
                    max_lag_s=MAX_LAG_S, scenarios=list(SCENARIOS), latency_s=[-1.0, 1.0],
                    drift_ppm=[-100.0, 100.0], mounting="uniform on SO(3)", imu_rate_hz=[50.0, 400.0],
                    noise_levels=list(NOISE_LEVELS), flexure_fraction=1 / 3, duration_s="scenario default",
                    slave_nav_fraction=SLAVE_NAV_FRACTION, slave_vel_noise_m_s_at_level_1=SLAVE_VEL_NOISE_M_S,
                    truth="Truth.latency_at(result.t_mid_rel_s)", sigma_coverage="|error| <= 2 sigma",
                    python=platform.python_version(), machine=platform.machine(), cpus=os.cpu_count()),
        wall_time_s=wall, runtime_per_run_s=wall * args.workers / max(len(rows), 1),
        summary=summary, by_scenario=by_scenario, by_flexure=by_flexure, by_slave_nav=by_slave_nav,
        flexure_by_scenario=flexure_by_scenario, bound_flexure=bound,
        aligned_control=control, stamp_noise=stamp_noise, rows=rows,
        notes=("summary/by_scenario: random mountings (main set). aligned_control: the same kind of draws with "
               "the units' axes aligned (what the seeds assume). stamp_noise: noisy stamps and slave gaps. '@1s' rows: the seeds with the papers' +-1 s "
               "search instead of estimate()'s 2 s. within_1ms and coverage count failures as misses; "
               "RMS/worst/median are over the runs that returned a value."),
    )
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(result, fh, indent=1, default=float)
    with open(args.table1_out, "w") as fh:
        json.dump(t1, fh, indent=1, default=float)
    print(md_table(summary, f"Latency Monte Carlo: {n_runs} runs with random mountings "
                            f"({len(rows)} runs incl. control, {wall:.0f} s wall with {args.workers} workers)"))
    for sc in SCENARIOS:
        print()
        print(md_table(by_scenario[sc], f"{sc}"))
    for k, v in by_flexure.items():
        print()
        print(md_table(v, k))
    for k, v in by_slave_nav.items():
        print()
        print(md_table(v, k))
    for sc, v in flexure_by_scenario.items():
        print()
        print(md_table(v, f"{sc}, flexure runs"))
    print()
    print(bound_md(bound))
    if control:
        print()
        print(md_table(control, f"Aligned-axes control: {len(ctrl_rows)} runs (what the seeds assume)"))
    if stamp_noise:
        print()
        print(md_table(stamp_noise, f"Noisy stamps and slave gaps: {len(stamp_rows)} runs"))
    print()
    print(table1_md(t1))
    print(f"\nwrote {os.path.relpath(args.out, ROOT)} and {os.path.relpath(args.table1_out, ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
