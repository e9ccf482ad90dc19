"""Speed of the whole ``tapost analyze`` pipeline on long logs, against pymavlink's plain read loop.

Pair: master 200 Hz MCAP (Imu + velocity + fix), slave 200 Hz MAVLink tlog (HIGHRES_IMU + ATTITUDE +
GLOBAL_POSITION_INT), simulated by ``logtools.sim`` and written by the parser colleagues' writers
(``parsers.registry.write(path, log, "mcap" | "tlog")``). For each log length:

* wall time of each stage of analyze (parse, latency, compensate, alignment, report, recording)
  and of the whole analyze (report.json + report.html + recording.rrd), in a fresh process, with
  its peak resident memory (``resource.getrusage(RUSAGE_CHILDREN).ru_maxrss``);
* in the same run, pymavlink's plain ``recv_match()`` loop over the slave tlog (the baseline
  a user would write); target: the whole analyze in at most half that time;
* for the shortest length, a cProfile of the analyze: the functions that dominate.

    python benchmarks/bench_pipeline.py            # 10 min and 1 h
    python benchmarks/bench_pipeline.py --quick    # 10 min only
    python benchmarks/bench_pipeline.py --long     # also 4 h (slow: several minutes and GBs)

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
import subprocess
import sys
import tempfile
import time
from dataclasses import fields

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
RESULTS = os.path.join(ROOT, "benchmarks", "results", "bench_pipeline.json")
RATE_HZ = 200.0


def _overrides(cfg_type, duration_s: float) -> dict:
    """SimConfig overrides for a duration and 200 Hz streams, using the fields the config has."""
    names = {f.name for f in fields(cfg_type)}
    ov = {"duration_s": duration_s}
    for n in names:
        if n.endswith("rate_hz") and any(k in n for k in ("imu", "nav", "master", "slave", "att", "vel")):
            if "gps" not in n and "fix" not in n and "pos" not in n:
                ov[n] = RATE_HZ
    return {k: v for k, v in ov.items() if k in names}


def make_pair(duration_s: float, d: str, scenario: str = "aircraft") -> dict:
    from logtools import sim
    from parsers import registry

    cfg0 = sim.scenario_config(scenario)
    cfg = sim.scenario_config(scenario, **_overrides(type(cfg0), duration_s))
    t = time.perf_counter()
    pair = sim.simulate(cfg)
    t_sim = time.perf_counter() - t
    m, s = os.path.join(d, "master.mcap"), os.path.join(d, "slave.tlog")
    t = time.perf_counter()
    registry.write(m, pair.master, "mcap")
    registry.write(s, pair.slave, "tlog")
    t_write = time.perf_counter() - t
    truth = pair.truth.to_dict()
    return {"master": m, "slave": s, "simulate_s": t_sim, "write_s": t_write,
            "truth_latency_s": truth.get("latency_s"), "truth_drift_ppm": truth.get("drift_ppm"),
            "master_bytes": os.path.getsize(m), "slave_bytes": os.path.getsize(s),
            "imu_rows": {"master": len(pair.master.imu), "slave": len(pair.slave.imu)},
            "nav_rows": {"master": len(pair.master.nav), "slave": len(pair.slave.nav)}}


def count_messages(path: str) -> dict:
    from parsers import inspect_log

    inv = inspect_log(path)
    per = {s.name: int(s.count) for s in inv.streams}
    return {"total": int(sum(per.values())), "streams": per}


def pymavlink_loop(path: str) -> dict:
    """The baseline: pymavlink's plain recv_match() loop over the whole tlog."""
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
    return {"seconds": time.perf_counter() - t, "messages": n}


def analyze_child(master: str, slave: str, out: str, profile: str | None) -> None:
    """Run in a fresh process: one analyze, timings and peak memory as JSON on stdout."""
    from pipelines.analyze import AnalyzeOptions, analyze_pair

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
        st = pstats.Stats(prof, stream=buf).sort_stats("cumulative")
        st.print_stats(25)
        rows = []
        for (fn, line, name), (cc, nc, tt, ct, _) in sorted(st.stats.items(), key=lambda kv: -kv[1][3])[:40]:
            rows.append({"function": f"{os.path.relpath(fn, ROOT) if fn.startswith(ROOT) else os.path.basename(fn)}:{line}:{name}",
                         "cumulative_s": round(ct, 3), "self_s": round(tt, 3), "calls": nc})
        tot = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[:15]
        self_rows = [{"function": f"{os.path.basename(fn)}:{line}:{name}", "self_s": round(tt, 3), "calls": nc}
                     for (fn, line, name), (cc, nc, tt, ct, _) in tot]
        with open(profile, "w") as fh:
            json.dump({"by_cumulative": rows, "by_self": self_rows}, fh, indent=1)
    res = {"wall_s": wall, "error": err,
           "timings_s": rep["timings_s"] if rep else None,
           "latency_s": rep["latency"].get("latency_s") if rep else None,
           "sigma_s": rep["latency"].get("sigma_s") if rep else None,
           "status": rep.get("status") if rep else "failed",
           "skipped": rep.get("skipped") if rep else None,
           "outputs_bytes": {f: os.path.getsize(os.path.join(out, f)) for f in os.listdir(out)
                             if not f.startswith(".")} if os.path.isdir(out) else {},
           "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
    print("BENCH_JSON " + json.dumps(res))


def run_child(master: str, slave: str, out: str, profile: str | None) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--child", master, slave, out]
    if profile:
        cmd += ["--profile", profile]
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    for line in p.stdout.splitlines():
        if line.startswith("BENCH_JSON "):
            res = json.loads(line[len("BENCH_JSON "):])
            res["process_wall_s"] = wall  # including interpreter start and imports
            return res
    return {"error": f"child failed (rc {p.returncode}): {p.stderr.strip().splitlines()[-1:] }",
            "process_wall_s": wall}


def bench_length(duration_s: float, work: str, profile: bool) -> dict:
    d = os.path.join(work, f"{int(duration_s)}s")
    os.makedirs(d, exist_ok=True)
    print(f"-- {duration_s / 60:.0f} min: simulating and writing", flush=True)
    pair = make_pair(duration_s, d)
    msgs = {"master": count_messages(pair["master"]), "slave": count_messages(pair["slave"])}
    print(f"   messages: master {msgs['master']['total']}, slave {msgs['slave']['total']}", flush=True)
    base = pymavlink_loop(pair["slave"])
    print(f"   pymavlink recv_match loop over the slave tlog: {base['seconds']:.1f} s "
          f"({base['messages']} messages)", flush=True)
    prof_path = os.path.join(d, "profile.json") if profile else None
    ana = run_child(pair["master"], pair["slave"], os.path.join(d, "out"), None)
    print(f"   analyze: {ana.get('wall_s', float('nan')):.1f} s, peak RSS {ana.get('peak_rss_mb', float('nan')):.0f} MB"
          + (f"  ERROR {ana['error']}" if ana.get("error") else ""), flush=True)
    prof = None
    if profile:
        run_child(pair["master"], pair["slave"], os.path.join(d, "out_prof"), prof_path)
        try:
            with open(prof_path) as fh:
                prof = json.load(fh)
        except (OSError, ValueError):
            prof = None
    stages = (ana.get("timings_s") or {})
    stage_only = {k: v for k, v in stages.items() if k != "total" and v is not None}
    dominant = max(stage_only, key=stage_only.get) if stage_only else None
    ratio = ana["wall_s"] / base["seconds"] if ana.get("wall_s") and base["seconds"] else None
    return {"duration_s": duration_s, "pair": pair, "messages": msgs,
            "messages_total": msgs["master"]["total"] + msgs["slave"]["total"],
            "pymavlink_recv_match": base, "analyze": ana, "dominant_stage": dominant,
            "analyze_over_pymavlink": ratio, "target_met": (ratio is not None and ratio <= 0.5),
            "profile": prof}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 min log only")
    ap.add_argument("--long", action="store_true", help="also the 4 h log")
    ap.add_argument("--child", nargs=3, metavar=("MASTER", "SLAVE", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--profile", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--work", default=None, help="folder for the generated logs (default: a temp dir)")
    args = ap.parse_args()
    if args.child:
        analyze_child(*args.child, args.profile)
        return 0
    lengths = [600.0] if args.quick else [600.0, 3600.0] + ([14400.0] if args.long else [])
    work = args.work or tempfile.mkdtemp(prefix="tapost_bench_")
    results = {"benchmark": "bench_pipeline", "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
               "machine": {"python": platform.python_version(), "cpu_count": os.cpu_count(),
                           "platform": platform.platform()},
               "mode": "quick" if args.quick else ("long" if args.long else "default"),
               "note": ("4 h not run (use --long)" if not args.long and not args.quick else ""),
               "runs": []}
    for i, dur in enumerate(lengths):
        try:
            results["runs"].append(bench_length(dur, work, profile=(i == 0)))
        except Exception as exc:  # missing writer / simulator: say so in the figures
            results["runs"].append({"duration_s": dur, "error": f"{type(exc).__name__}: {exc}"})
            print(f"   FAILED: {type(exc).__name__}: {exc}", flush=True)
    os.makedirs(os.path.dirname(RESULTS), exist_ok=True)
    from pipelines.report import write_text_atomic, json_safe

    write_text_atomic(RESULTS, json.dumps(json_safe(results), indent=2) + "\n")
    print(f"figures: {RESULTS}")
    for r in results["runs"]:
        if "error" in r:
            continue
        a = r["analyze"]
        print(f"{r['duration_s'] / 60:5.0f} min  {r['messages_total']:>9d} msgs  analyze {a.get('wall_s', 0):7.1f} s  "
              f"pymavlink {r['pymavlink_recv_match']['seconds']:7.1f} s  ratio {r['analyze_over_pymavlink'] or float('nan'):.2f}  "
              f"peak {a.get('peak_rss_mb', 0):.0f} MB  dominant {r['dominant_stage']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
