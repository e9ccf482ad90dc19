"""Speed of the native export (the slave on the master's clock) against parsing the same file.

A 1 h slave at 200 Hz (IMU 200 Hz; attitude, velocity, position 50 Hz) is written in each format by the
repository's writers (tlog, DataFlash, ULog, canonical CSV, MCAP with ROS 2 messages, ROS 1 bag, ROS 2
bags with sqlite3 and with mcap storage). In the same run, for each file:
* parse: ``parsers.registry.load`` (file -> InsLog, what ``tapost analyze`` does with a slave);
* export: the native writer (``pipelines.export.write_native``: every record copied, the time fields
  rewritten with a ClockShift of 37.2 ms and 30 ppm), into a path where no earlier output lies (the previous
  repetition's output is deleted before the timing: replacing it made the export pay for the deletion of a
  347 MB file, 0.02-0.06 s of the file system's work);
* the ratio export / parse (the target: at most 1);
* the CSV and Parquet exports from the parsed InsLog;
* with ``--library-read``, once: the format's own library reading every message of the same file (pymavlink's
  ``recv_match`` loop for tlog and DataFlash, pyulog's ``ULog``, pandas' ``read_csv``, the ``mcap`` reader's
  ``iter_messages``, rosbags' ``AnyReader.messages`` without deserialising), opening included, imports not:
  what the export costs against reading the file with the tool a user has (context for the target, which
  compares with tapost's own parse).
Both run with numpy's environment of a ``tapost`` process (``pipelines.cli.set_numpy_environment``: one
BLAS thread, no huge pages), its garbage collector's thresholds (``pipelines.cli.GC_THRESHOLDS``) and the
malloc policy ``tapost restamp`` and ``tapost analyze`` set for such a file
(``pipelines.parallel.small_pair_malloc``: freed arrays reused from the heap). Parse and export run
``--repeat`` times interleaved, after one warm-up run of each (numba caches loaded): the figures are the
best of each and the median of the ratios of neighbouring runs (this 2-core machine's run-to-run scatter
is +-30 %). Both run the compiled kernels
(``TAPOST_KERNELS=compiled`` unless set), as every run after the first does.

    python benchmarks/bench_export.py            # 1 h logs
    python benchmarks/bench_export.py --quick    # 10 min logs
    python benchmarks/bench_export.py --library-read   # and the formats' own libraries' read loops (+3 min)

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
import gc  # noqa: E402

from pipelines.cli import GC_THRESHOLDS, set_numpy_environment  # noqa: E402

set_numpy_environment()  # numpy's threads and pages as in a tapost process (before numpy loads)
gc.set_threshold(*GC_THRESHOLDS)  # (as a tapost process's)
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


def library_read(case: str, path: Path) -> tuple[float, int]:
    """Seconds and messages of one pass of the format's own library over every message of ``path``: the file
    opened (its index read, where the library reads one) and every message read; the library imported
    before the clock starts."""
    import time

    if case in ("tlog", "dataflash"):
        from pymavlink import mavutil

        t, n = time.perf_counter(), 0
        conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
        while conn.recv_match() is not None:
            n += 1
        return time.perf_counter() - t, n
    if case == "ulog":
        from pyulog import ULog

        t = time.perf_counter()
        u = ULog(str(path))
        return time.perf_counter() - t, sum(len(d.data["timestamp"]) for d in u.data_list)
    if case == "csv":
        import pandas as pd

        t = time.perf_counter()
        frame = pd.read_csv(path)
        return time.perf_counter() - t, len(frame)
    if case == "mcap":
        from mcap.reader import make_reader

        with open(path, "rb") as fh:
            t = time.perf_counter()
            n = sum(1 for _ in make_reader(fh).iter_messages())
        return time.perf_counter() - t, n
    from rosbags.highlevel import AnyReader

    t = time.perf_counter()
    with AnyReader([path]) as reader:
        n = sum(1 for _ in reader.messages())
    return time.perf_counter() - t, n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 min logs instead of 1 h")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--formats", default=",".join(FORMATS))
    ap.add_argument("--library-read", action="store_true",
                    help="also time the format's own library reading every message (once per format)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_parse_ulog_csv import synthetic_log

    from parsers import registry
    from parsers.restamp import ClockShift
    from pipelines import export, parallel

    parallel.own_malloc()  # (this process as a tapost command's own: its malloc policy set below, as theirs)

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
            parallel.small_pair_malloc(int(_size_mb(src) * 1e6))  # (as tapost restamp: every file here is small)
            dst = d / f"exported_{name}"
            parsed = registry.load(str(src))  # warm-up (numba caches)
            export.write_native(str(src), str(dst), fmt, shift, parsed.meta.selector)
            ratios, tp, te = [], [], []
            for _ in range(args.repeat):  # parse and export interleaved: each ratio from neighbouring runs
                t_p, parsed = best_of(lambda: registry.load(str(src)), 1)
                _remove(dst)  # (the previous run's output: its deletion is the file system's work, not the export's)
                t_e, st = best_of(lambda: export.write_native(str(src), str(dst), fmt, shift, parsed.meta.selector), 1)
                tp.append(t_p)
                te.append(t_e)
                ratios.append(t_e / t_p)
            t_parse, t_exp = min(tp), min(te)
            row = {"format": fmt, "options": opts, "file_mb": _size_mb(src), "records": st.records, "parse_s": t_parse,
                   "export_native_s": t_exp, "ratio_export_over_parse": t_exp / t_parse,
                   "ratio_median_of_pairs": float(np.median(ratios)), "ratios_of_pairs": ratios,
                   "imu_samples": int(len(parsed.imu))}
            if args.library_read:
                t_lib, n_lib = library_read(case, src)
                row.update(library_read_s=t_lib, library_read_messages=n_lib, export_over_library_read=t_exp / t_lib)
            if fmt == "tlog":  # CSV/Parquet from the parsed slave, once
                t_csv, _ = best_of(lambda: export.write_slave(("csv",), str(d), parsed, shift), 1)
                t_pq, _ = best_of(lambda: export.write_slave(("parquet",), str(d), parsed, shift), 1)
                out["csv_export_s"], out["parquet_export_s"] = t_csv, t_pq
            out["formats"][case] = row
            print(f"{case:16s} {row['file_mb']:8.1f} MB  parse {t_parse:7.2f} s  export {t_exp:7.2f} s  "
                  f"ratio {row['ratio_export_over_parse']:.2f} (median of pairs {row['ratio_median_of_pairs']:.2f}: "
                  + ", ".join(f"{r:.2f}" for r in ratios) + ")"
                  + (f"  library read {row['library_read_s']:7.2f} s" if "library_read_s" in row else ""),
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
