"""Speed of the whole ``tapost analyze`` pipeline on long logs, against pymavlink's plain read loop.

Pair (issue 4): master 200 Hz MCAP (/imu Imu with orientation, /velocity TwistStamped at 200 Hz, /fix NavSatFix
at ``--fix-rate`` Hz, 10 by default), slave 200 Hz MAVLink tlog (HIGHRES_IMU, ATTITUDE_QUATERNION + ATTITUDE and
GLOBAL_POSITION_INT at 200 Hz, plus 1 Hz housekeeping), simulated by ``logtools.sim`` ("aircraft") and written by
``parsers.registry.write(path, log, "mcap" | "tlog")``. For each log length:

* the pair is simulated and written in a child process (its time and peak memory are reported too);
* messages per stream counted (``parsers.inspect_log``);
* pymavlink's plain ``recv_match()`` loop over the slave tlog, timed in this run (the baseline a user writes);
* one ``analyze_pair`` (report.json + report.html + recording.rrd) in a fresh child process: wall time of each
  stage (report.json ``timings_s``), of the call, and of the whole process (interpreter start, imports and
  numba cache loading included), with its peak RSS (``ru_maxrss``);
* a parse-only child (each file loaded alone) to split the parse stage between master and slave.
The shortest length also gets a cold-numba-cache analyze (``NUMBA_CACHE_DIR`` = an empty temp dir) and a
cProfile of the analyze (``benchmarks/results/pipeline_profile_<N>s.txt``). Target: whole analyze process
<= 0.5 x pymavlink loop. The 1-minute load average is recorded before each timed step (shared machine).

    python benchmarks/bench_pipeline.py            # 10 min and 1 h
    python benchmarks/bench_pipeline.py --quick    # 10 min only
    python benchmarks/bench_pipeline.py --long     # 10 min, 1 h and 4 h (about 12 min, 5 GB)
    python benchmarks/bench_pipeline.py --long --profile-all   # and a cProfile at each length

Figures go to ``benchmarks/results/bench_pipeline.json``.
"""
from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import platform
import pstats
import resource
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
RESULTS_DIR = os.path.join(ROOT, "benchmarks", "results")
RESULTS = os.path.join(RESULTS_DIR, "bench_pipeline.json")
RATE_HZ = 200.0
TAG = "BENCH_JSON "


def _loadavg() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _emit(res: dict) -> None:
    print(TAG + json.dumps(res), flush=True)


# ---- children ---------------------------------------------------------------------------------

def make_child(duration_s: float, d: str, fix_rate_hz: float, scenario: str = "aircraft") -> None:
    """Simulate the pair and write master.mcap / slave.tlog in ``d``."""
    import numpy as np

    from logtools import sim
    from logtools.inslog import POS, InsLog
    from parsers import registry

    cfg = sim.scenario_config(scenario, duration_s=duration_s, master_imu_rate_hz=RATE_HZ,
                              master_nav_rate_hz=RATE_HZ, slave_imu_rate_hz=RATE_HZ, slave_nav_rate_hz=RATE_HZ)
    t = time.perf_counter()
    pair = sim.simulate(cfg)
    t_sim = time.perf_counter() - t
    master = pair.master
    if fix_rate_hz < RATE_HZ:  # /fix thinned to fix_rate_hz (a GNSS rate); velocity and attitude stay at 200 Hz
        nav = master.nav.copy()
        keep = np.zeros(len(nav), bool)
        keep[::max(1, int(round(RATE_HZ / fix_rate_hz)))] = True
        nav.loc[~keep, list(POS)] = np.nan
        master = InsLog(imu=master.imu, nav=nav, meta=master.meta)
    m, s = os.path.join(d, "master.mcap"), os.path.join(d, "slave.tlog")
    t = time.perf_counter()
    registry.write(m, master, "mcap")
    t_wm = time.perf_counter() - t
    t = time.perf_counter()
    registry.write(s, pair.slave, "tlog")
    t_ws = time.perf_counter() - t
    truth = pair.truth.to_dict()
    _emit({"master": m, "slave": s, "simulate_s": t_sim, "write_master_s": t_wm, "write_slave_s": t_ws,
           "truth_latency_s": truth.get("latency_s"), "truth_drift_ppm": truth.get("drift_ppm"),
           "master_bytes": os.path.getsize(m), "slave_bytes": os.path.getsize(s),
           "peak_rss_mb": _peak_rss_mb()})


def count_messages(path: str) -> dict:
    from parsers import inspect_log

    inv = inspect_log(path)
    per = {s.name: int(s.count) for s in inv.streams}
    return {"total": int(sum(per.values())), "streams": per}


def count_child(master: str, slave: str) -> None:
    _emit({"master": count_messages(master), "slave": count_messages(slave)})


def pymavlink_child(path: str) -> None:
    """The baseline: pymavlink's plain recv_match() loop over the whole tlog (timed after the import)."""
    from pymavlink import mavutil

    t = time.perf_counter()
    conn = mavutil.mavlink_connection(path, dialect="common")
    n = 0
    while True:
        msg = conn.recv_match()
        if msg is None:
            break
        n += 1
    conn.close()
    _emit({"seconds": time.perf_counter() - t, "messages": n, "peak_rss_mb": _peak_rss_mb()})


def parse_child(master: str, slave: str) -> None:
    from parsers import load

    t = time.perf_counter()
    load(master)
    t_m = time.perf_counter() - t
    t = time.perf_counter()
    load(slave)
    t_s = time.perf_counter() - t
    _emit({"master_s": t_m, "slave_s": t_s, "peak_rss_mb": _peak_rss_mb()})


def analyze_child(master: str, slave: str, out: str, profile: str | None) -> None:
    """One analyze in this fresh process: timings and peak memory as JSON on stdout."""
    t_imp = time.perf_counter()
    from pipelines.analyze import AnalyzeOptions, analyze_pair

    import_s = time.perf_counter() - t_imp
    prof = cProfile.Profile() if profile else None
    t = time.perf_counter()
    if prof:
        prof.enable()
    try:
        outcome = analyze_pair(master, slave, out, AnalyzeOptions(max_lag_s=2.0, recording=True))
        rep, err = outcome.report, None
    except Exception as exc:  # report the failure in the figures, honestly
        rep, err = None, f"{type(exc).__name__}: {exc}"
    wall = time.perf_counter() - t
    if prof:
        prof.disable()
        buf = io.StringIO()
        st = pstats.Stats(prof, stream=buf)
        buf.write(f"cProfile of analyze_pair({os.path.basename(master)}, {os.path.basename(slave)}): "
                  f"{wall:.2f} s under the profiler\n\n== by cumulative time ==\n")
        st.sort_stats("cumulative").print_stats(45)
        buf.write("\n== by own (tottime) ==\n")
        st.sort_stats("tottime").print_stats(30)
        with open(profile, "w") as fh:
            fh.write(buf.getvalue().replace(ROOT + os.sep, ""))
    lat = (rep or {}).get("latency") or {}
    _emit({"wall_s": wall, "import_s": import_s, "error": err,
           "timings_s": rep["timings_s"] if rep else None,
           "latency_s": lat.get("latency_s"), "sigma_s": lat.get("sigma_s"), "drift_ppm": lat.get("drift_ppm"),
           "status": rep.get("status") if rep else "failed",
           "skipped": rep.get("skipped") if rep else None,
           "outputs_bytes": {f: os.path.getsize(os.path.join(out, f)) for f in sorted(os.listdir(out))
                             if not f.startswith(".")} if os.path.isdir(out) else {},
           "peak_rss_mb": _peak_rss_mb()})


# ---- parent -----------------------------------------------------------------------------------

def run_child(args: list[str], env: dict | None = None, timeout_s: float = 3600.0) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--child", *args]
    load0 = _loadavg()
    t = time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout_s:.0f} s", "process_wall_s": time.perf_counter() - t}
    wall = time.perf_counter() - t
    for line in p.stdout.splitlines():
        if line.startswith(TAG):
            res = json.loads(line[len(TAG):])
            res["process_wall_s"] = wall  # interpreter start, imports and numba cache loading included
            res["loadavg_1_5_15_before"] = load0
            return res
    return {"error": f"child {args[0]} failed (rc {p.returncode}): {' | '.join(p.stderr.strip().splitlines()[-3:])}",
            "process_wall_s": wall, "loadavg_1_5_15_before": load0}


def bench_length(duration_s: float, work: str, fix_rate_hz: float, profile: bool, cold: bool) -> dict:
    d = tempfile.mkdtemp(prefix=f"{int(duration_s)}s_", dir=work)
    print(f"-- {duration_s / 60:.0f} min: simulating and writing", flush=True)
    pair = run_child(["make", str(duration_s), d, str(fix_rate_hz)])
    if "error" in pair:
        raise RuntimeError(pair["error"])
    m, s = pair["master"], pair["slave"]
    print(f"   simulate {pair['simulate_s']:.1f} s, write mcap {pair['write_master_s']:.1f} s, "
          f"tlog {pair['write_slave_s']:.1f} s; {pair['master_bytes'] / 1e6:.0f} + {pair['slave_bytes'] / 1e6:.0f} MB",
          flush=True)
    msgs = run_child(["count", m, s])
    if "error" in msgs:
        raise RuntimeError(msgs["error"])
    total = msgs["master"]["total"] + msgs["slave"]["total"]
    print(f"   messages: master {msgs['master']['total']}, slave {msgs['slave']['total']}, total {total}", flush=True)
    base = run_child(["pymavlink", s])
    print(f"   pymavlink recv_match loop over the slave tlog: {base.get('seconds', float('nan')):.1f} s "
          f"({base.get('messages')} messages, load {base.get('loadavg_1_5_15_before')})", flush=True)
    cold_run = None
    if cold:
        cache = tempfile.mkdtemp(prefix="numba_cold_", dir=work)
        cold_run = run_child(["analyze", m, s, os.path.join(d, "out_cold")], env={**os.environ, "NUMBA_CACHE_DIR": cache})
        print(f"   analyze, cold numba cache: process {cold_run.get('process_wall_s', float('nan')):.1f} s", flush=True)
    ana = run_child(["analyze", m, s, os.path.join(d, "out")])
    print(f"   analyze: process {ana.get('process_wall_s', float('nan')):.1f} s (call {ana.get('wall_s', float('nan')):.1f} s), "
          f"peak RSS {ana.get('peak_rss_mb', float('nan')):.0f} MB, load {ana.get('loadavg_1_5_15_before')}"
          + (f"  ERROR {ana['error']}" if ana.get("error") else ""), flush=True)
    print(f"   stages: {json.dumps({k: round(v, 2) for k, v in (ana.get('timings_s') or {}).items()})}", flush=True)
    parse = run_child(["parse", m, s])
    print(f"   parse alone: master {parse.get('master_s', float('nan')):.1f} s, slave {parse.get('slave_s', float('nan')):.1f} s",
          flush=True)
    prof_path = None
    if profile:
        prof_path = os.path.join(RESULTS_DIR, f"pipeline_profile_{int(duration_s)}s.txt")
        run_child(["analyze", m, s, os.path.join(d, "out_prof"), "--profile", prof_path])
    stages = ana.get("timings_s") or {}
    stage_only = {k: v for k, v in stages.items() if k != "total" and v is not None}
    dominant = max(stage_only, key=stage_only.get) if stage_only else None
    ratio = (ana["process_wall_s"] / base["seconds"]
             if ana.get("process_wall_s") and not ana.get("error") and base.get("seconds") else None)
    shutil.rmtree(d, ignore_errors=True)
    return {"duration_s": duration_s, "pair": pair, "messages": msgs, "messages_total": total,
            "pymavlink_recv_match": base, "analyze": ana, "analyze_cold_numba_cache": cold_run,
            "parse_alone": parse, "dominant_stage": dominant,
            "analyze_process_over_pymavlink": ratio, "target_met": (ratio is not None and ratio <= 0.5),
            "profile_file": os.path.relpath(prof_path, ROOT) if prof_path else None}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 min log only")
    ap.add_argument("--long", action="store_true", help="also the 4 h log")
    ap.add_argument("--fix-rate", type=float, default=10.0, help="master /fix rate, Hz (velocity stays 200 Hz)")
    ap.add_argument("--profile-all", action="store_true",
                    help="cProfile the analyze at every length (default: the shortest only)")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    ap.add_argument("--profile", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        kind, rest = args.child[0], args.child[1:]
        if kind == "make":
            make_child(float(rest[0]), rest[1], float(rest[2]))
        elif kind == "count":
            count_child(*rest)
        elif kind == "pymavlink":
            pymavlink_child(*rest)
        elif kind == "parse":
            parse_child(*rest)
        else:
            analyze_child(*rest, args.profile)
        return 0
    lengths = [600.0] if args.quick else [600.0, 3600.0] + ([14400.0] if args.long else [])
    work = tempfile.mkdtemp(prefix="tapost_bench_pipeline_")
    results = {"benchmark": "bench_pipeline", "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
               "machine": {"python": platform.python_version(), "cpu_count": os.cpu_count(),
                           "platform": platform.platform()},
               "mode": "quick" if args.quick else ("long" if args.long else "default"),
               "config": {"scenario": "aircraft", "imu_rate_hz": RATE_HZ, "nav_rate_hz": RATE_HZ,
                          "master_fix_rate_hz": args.fix_rate, "max_lag_s": 2.0, "recording": True},
               "note": ("4 h not run (use --long)" if not args.long and not args.quick else ""),
               "runs": []}
    try:
        for i, dur in enumerate(lengths):
            try:
                results["runs"].append(bench_length(dur, work, args.fix_rate, profile=(i == 0 or args.profile_all),
                                                    cold=(i == 0)))
            except Exception as exc:  # say so in the figures
                results["runs"].append({"duration_s": dur, "error": f"{type(exc).__name__}: {exc}"})
                print(f"   FAILED: {type(exc).__name__}: {exc}", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    ok = [r for r in results["runs"] if "error" not in r and r["analyze"].get("process_wall_s")]
    if len(ok) >= 2:
        base_run = ok[0]
        results["scaling_vs_shortest"] = {
            f"{r['duration_s'] / 60:.0f} min": {
                "length_x": r["duration_s"] / base_run["duration_s"],
                "messages_x": round(r["messages_total"] / base_run["messages_total"], 2),
                **{k: round(v / base_run["analyze"]["timings_s"][k], 2)
                   for k, v in r["analyze"]["timings_s"].items() if base_run["analyze"]["timings_s"].get(k)}}
            for r in ok}
        per_msg = [r["analyze"]["process_wall_s"] / r["messages_total"] * 1e6 for r in ok]
        results["scaling_us_per_message"] = {f"{r['duration_s'] / 60:.0f} min": round(v, 3) for r, v in zip(ok, per_msg)}
    os.makedirs(RESULTS_DIR, exist_ok=True)
    from pipelines.report import json_safe, write_text_atomic

    write_text_atomic(RESULTS, json.dumps(json_safe(results), indent=2) + "\n")
    print(f"figures: {RESULTS}")
    for r in ok:
        a = r["analyze"]
        print(f"{r['duration_s'] / 60:5.0f} min  {r['messages_total']:>9d} msgs  analyze {a['process_wall_s']:7.1f} s  "
              f"pymavlink {r['pymavlink_recv_match']['seconds']:7.1f} s  ratio {r['analyze_process_over_pymavlink'] or float('nan'):.2f}  "
              f"peak {a.get('peak_rss_mb', 0):.0f} MB  dominant {r['dominant_stage']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
