"""Compile tapost's numba kernels into numba's on-disk cache, then write the stamp that tells later runs
to use them (logtools.jit).

Started in the background, at low priority, by the first ``tapost analyze``/``batch`` after installing
(which itself runs the reference code meanwhile); run it by hand to compile ahead, e.g. in a container
image:

    python -m pipelines.warmup          # about 1 min on 2 cores; prints what it compiles

It simulates a 30-second pair, writes it in the formats whose readers or native exports have kernels
(MCAP, ROS 1 bag, tlog, DataFlash, ULog, CSV, ROS 2 bag, a vendor CSV of ISO date-times), reads each back, exports each on a shifted
clock, and runs the whole analysis on the MCAP/tlog pair (and on a pair with flexure, and with the alignment's
other filters), so every kernel compiles with the argument types a real run passes. Then it compiles the
kernels it called once more, ahead of time, into one extension module that later runs call without loading
numba (logtools.aot; needs a C compiler, skipped with one line on stderr without).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time


def _say(quiet: bool, text: str) -> None:
    if not quiet:
        print(text, flush=True)


def warm(quiet: bool = False) -> float:
    """Compile every kernel (this process in compiled mode); returns the seconds it took."""
    os.environ["TAPOST_KERNELS"] = "compiled"
    os.environ["TAPOST_WARMUP"] = "0"
    os.environ["TAPOST_AOT"] = "0"  # (numba's dispatchers, whose signatures the ahead-of-time build exports)
    t0 = time.perf_counter()
    from logtools import jit, sim
    from parsers import load, registry
    from parsers.restamp import ClockShift
    from pipelines import analyze, export

    if not jit.compiled():
        raise SystemExit(f"tapost warmup: nothing to compile ({jit.why()})")
    cfg = sim.scenario_config("aircraft", duration_s=30.0)
    pair = sim.simulate(cfg)
    with tempfile.TemporaryDirectory(prefix="tapost-warmup-") as d:
        paths = {}
        for fmt, ext, log in (("mcap", "mcap", pair.master), ("rosbag1", "bag", pair.master),
                              ("tlog", "tlog", pair.slave),
                              ("dataflash", "bin", pair.slave), ("ulog", "ulg", pair.slave),
                              ("csv", "csv", pair.slave), ("rosbag2", "", pair.master)):
            path = os.path.join(d, f"{fmt}.{ext}" if ext else fmt)
            try:
                registry.write(path, log, fmt)
            except Exception as exc:  # noqa: BLE001 - a writer that cannot take this log: skip its reader
                _say(quiet, f"  {fmt}: not written ({exc})")
                continue
            paths[fmt] = path
            t = time.perf_counter()
            got = load(path)
            _say(quiet, f"  {fmt} reader: {time.perf_counter() - t:.1f} s")
            t = time.perf_counter()
            shift = ClockShift(0.01, 20.0, got.meta.t0_ns)
            export.write_native(path, os.path.join(d, f"shifted_{fmt}" + (f".{ext}" if ext else "")), fmt, shift,
                                got.meta.selector)
            _say(quiet, f"  {fmt} native export: {time.perf_counter() - t:.1f} s")
        # a vendor CSV of ISO 8601 date-times: their scan and their writer (parsers.csvtable._iso_cells,
        # parsers.restamp_csv._emit)
        import numpy as np

        iso = os.path.join(d, "iso.csv")
        sl = pair.slave
        t_ns = sl.meta.t0_ns + np.round(sl.t_imu_s() * 1e9).astype(np.int64)
        cells = np.datetime_as_string(t_ns.view("datetime64[ns]"), unit="ns")
        cols = np.column_stack([sl.gyro_rad_s(), sl.accel_m_s2()])
        with open(iso, "w") as fh:
            fh.write("Time (ISO 8601),Gyro X (rad/s),Gyro Y (rad/s),Gyro Z (rad/s),Accel X (m/s^2),Accel Y (m/s^2),"
                     "Accel Z (m/s^2)\n")
            fh.writelines(f"{c}Z," + ",".join(repr(float(v)) for v in row) + "\n" for c, row in zip(cells, cols))
        got = load(iso)
        export.write_native(iso, os.path.join(d, "shifted_iso.csv"), got.meta.format,
                            ClockShift(0.01, 20.0, got.meta.t0_ns), got.meta.selector)
        _say(quiet, "  vendor CSV of ISO date-times: read and exported")
        if "rosbag2" in paths:  # the page scan that reads a damaged .db3 (parsers.restamp_sqlite.recover)
            from parsers import restamp_sqlite

            for f in sorted(os.listdir(paths["rosbag2"])):
                if f.endswith(".db3"):
                    restamp_sqlite.recover(os.path.join(paths["rosbag2"], f))
        if "ulog" in paths:  # the resync past damage in the middle of a ULog (parsers.ulog.walk_resyncing)
            import numpy as np

            from parsers import ulog

            buf = np.fromfile(paths["ulog"], np.uint8)
            ulog.kernel("_chain_at")(buf, 16, ulog._KNOWN_TYPES, ulog._MAX_MSG_SIZE, np.full(1 << 16, -1, np.int64),
                                     ulog.RESYNC_CHAIN)
        t = time.perf_counter()
        opts = analyze.options_from({k: None for k in analyze.CLI_KEYS})[0]
        analyze.compute(paths["mcap"], paths["tlog"], opts)
        _say(quiet, f"  latency, compensation, alignment: {time.perf_counter() - t:.1f} s")
        # the other paths' kernels and argument types (the ahead-of-time build exports what ran here): a pair
        # with flexure (the latency fit's flexure whitening), the alignment's other filters and options
        t = time.perf_counter()
        flex = sim.simulate(sim.scenario_config("aircraft", duration_s=30.0, flexure=True))
        fm, fs = os.path.join(d, "flex_master.mcap"), os.path.join(d, "flex_slave.tlog")
        registry.write(fm, flex.master, "mcap")
        registry.write(fs, flex.slave, "tlog")
        analyze.compute(fm, fs, opts)
        for variant in ({"filter": "kf-split"}, {"filter": "kf-delay", "smoother": True, "board_errors": "on"},
                        {"filter": "ahinf"}, {"filter": "hinf", "match": "vel", "compensation": "interp"}):
            cli = {k: None for k in analyze.CLI_KEYS}
            cli.update(variant)
            analyze.compute(paths["mcap"], paths["tlog"], analyze.options_from(cli)[0])
        _say(quiet, f"  flexure pair, other filters and options: {time.perf_counter() - t:.1f} s")
    return time.perf_counter() - t0


def build_ahead(quiet: bool = False) -> str | None:
    """The kernels this process compiled, exported into one extension module (logtools.aot): later runs call
    them without loading numba. Its failure (no C compiler, a numba without pycc) is said and harmless: runs
    use numba's cache then."""
    from logtools import aot, jit

    fingerprint = jit.kernel_fingerprint()
    if aot.built(fingerprint):  # (built for these sources and this CPU already)
        return aot.aot_dir(fingerprint)
    try:
        return aot.build(jit.dispatchers(), fingerprint, log=lambda t: _say(quiet, t))
    except Exception as exc:  # noqa: BLE001 - any failure leaves numba's cache in use, as before
        first = str(exc).splitlines()[0] if str(exc) else ""
        why = ("no working C compiler" if "compiler" in first.lower() else f"{type(exc).__name__}: {first}")
        print(f"tapost warmup: the kernels' ahead-of-time extension was not built ({why}); runs use numba's "
              "cache, about 0.4 s slower each", file=sys.stderr, flush=True)
        return None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m pipelines.warmup", description=__doc__.split("\n\n")[0])
    p.add_argument("--lock", help="lock file to remove when done (the background start's)")
    p.add_argument("--quiet", action="store_true")
    a = p.parse_args(argv)
    if a.lock and hasattr(os, "nice"):
        try:
            os.nice(19)  # in the background: never in the way of the user's own run
        except OSError:
            pass
    try:
        _say(a.quiet, "tapost: compiling the numerical kernels into numba's cache...")
        seconds = warm(a.quiet)
        from logtools import jit

        path = jit.write_stamp(seconds)
        build_ahead(a.quiet)
        _say(a.quiet, f"tapost: kernels compiled in {seconds:.0f} s; later runs use them ({path})")
        return 0
    finally:
        if a.lock:
            try:
                os.unlink(a.lock)
            except OSError:
                pass


if __name__ == "__main__":
    # the process ends at once once its files are written and its lock removed: the interpreter's teardown of
    # numba's compiler (0.55-0.7 s of a core) would otherwise run beside the user's next tapost
    from pipelines.cli import flush_std_streams

    code = main()
    flush_std_streams()
    os._exit(code)
