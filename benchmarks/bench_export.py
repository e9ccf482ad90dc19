"""Speed of the native export (the slave on the master's clock) against parsing the same file.

A 1 h slave at 200 Hz (IMU 200 Hz; attitude, velocity, position 50 Hz) is written in each format by the
repository's writers (tlog, DataFlash, ULog, canonical CSV, MCAP with ROS 2 messages, ROS 1 bag, ROS 2
bags with sqlite3 and with mcap storage). In the same run, for each file:
* parse: ``parsers.registry.load`` (file -> InsLog, what ``tapost analyze`` does with a slave);
* export: the native writer (``pipelines.export.write_native``: every record copied, the time fields
  rewritten with a ClockShift of 37.2 ms and 30 ppm);
* the ratio export / parse (the target: at most 1);
* the CSV and Parquet exports from the parsed InsLog.
Both run with numpy's environment of a ``tapost`` process (``pipelines.cli.set_numpy_environment``: one
BLAS thread, no huge pages). Parse and export run ``--repeat`` times interleaved, after one warm-up run of
each (numba caches loaded): the figures are the best of each and the median of the ratios of neighbouring
runs (this 2-core machine's run-to-run scatter is +-30 %). Both run the compiled kernels
(``TAPOST_KERNELS=compiled`` unless set), as every run after the first does.

    python benchmarks/bench_export.py            # 1 h logs
    python benchmarks/bench_export.py --quick    # 10 min logs

Figures go to ``benchmarks/results/export.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("TAPOST_KERNELS", "compiled")  # a warm installation's speed (see logtools.jit)
sys.path.insert(0, str(ROOT))
from pipelines.cli import set_numpy_environment  # noqa: E402

set_numpy_environment()  # numpy's threads and pages as in a tapost process (before numpy loads)
import numpy as np  # noqa: E402
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_parse_ulog_csv import best_of  # noqa: E402 (one timing helper for the parse and export benchmarks)
RESULTS = ROOT / "benchmarks" / "results" / "export.json"
#: case -> (reader format, file or folder name, writer options)
FORMATS = {"tlog": ("tlog", "slave.tlog", {}), "dataflash": ("dataflash", "slave.bin", {}),
           "ulog": ("ulog", "slave.ulg", {}), "csv": ("csv", "slave.csv", {}),
           "mcap": ("mcap", "slave.mcap", {}), "rosbag1": ("rosbag1", "slave.bag", {}),
           "rosbag2-sqlite3": ("rosbag2", "slave_bag2_sqlite3", {"storage": "sqlite3"}),
           "rosbag2-mcap": ("rosbag2", "slave_bag2_mcap", {"storage": "mcap"})}


def _size_mb(path: Path) -> float:
    return (sum(f.stat().st_size for f in path.iterdir()) if path.is_dir() else path.stat().st_size) / 1e6


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 min logs instead of 1 h")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--formats", default=",".join(FORMATS))
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_parse_ulog_csv import synthetic_log

    from parsers import registry
    from parsers.restamp import ClockShift
    from pipelines import export

    duration = 600.0 if args.quick else 3600.0
    log = synthetic_log(duration)
    shift = ClockShift(0.0372, 30.0, log.meta.t0_ns + int(duration / 2 * 1e9))
    out: dict = {"duration_s": duration, "imu_hz": 200.0, "nav_hz": 50.0, "repeat": args.repeat,
                 "python": platform.python_version(), "machine": platform.machine(), "cpus": os.cpu_count(),
                 "formats": {}}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        for case in args.formats.split(","):
            fmt, name, opts = FORMATS[case]
            src = d / name
            registry.write(str(src), log, fmt, **opts)
            dst = d / f"exported_{name}"
            parsed = registry.load(str(src))  # warm-up (numba caches)
            export.write_native(str(src), str(dst), fmt, shift, parsed.meta.selector)
            ratios, tp, te = [], [], []
            for _ in range(args.repeat):  # parse and export interleaved: each ratio from neighbouring runs
                t_p, parsed = best_of(lambda: registry.load(str(src)), 1)
                t_e, st = best_of(lambda: export.write_native(str(src), str(dst), fmt, shift, parsed.meta.selector), 1)
                tp.append(t_p)
                te.append(t_e)
                ratios.append(t_e / t_p)
            t_parse, t_exp = min(tp), min(te)
            row = {"format": fmt, "options": opts, "file_mb": _size_mb(src), "records": st.records, "parse_s": t_parse,
                   "export_native_s": t_exp, "ratio_export_over_parse": t_exp / t_parse,
                   "ratio_median_of_pairs": float(np.median(ratios)), "ratios_of_pairs": ratios,
                   "imu_samples": int(len(parsed.imu))}
            if fmt == "tlog":  # CSV/Parquet from the parsed slave, once
                t_csv, _ = best_of(lambda: export.write_slave(("csv",), str(d), parsed, shift), 1)
                t_pq, _ = best_of(lambda: export.write_slave(("parquet",), str(d), parsed, shift), 1)
                out["csv_export_s"], out["parquet_export_s"] = t_csv, t_pq
            out["formats"][case] = row
            print(f"{case:16s} {row['file_mb']:8.1f} MB  parse {t_parse:7.2f} s  export {t_exp:7.2f} s  "
                  f"ratio {row['ratio_export_over_parse']:.2f} (median of pairs {row['ratio_median_of_pairs']:.2f})",
                  flush=True)
            _remove(src)
            _remove(dst)
    if not args.quick and args.formats == ",".join(FORMATS):  # (a subset does not replace the full table)
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps(out, indent=2) + "\n")
        print(f"-> {RESULTS.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
