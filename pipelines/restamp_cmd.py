"""``tapost restamp SLAVE --from DIR/report.json [-o OUT] [--format native|csv|parquet]``.

The slave log put on the master's clock with a finished analysis' latency and drift (report.json
``latency``: ``latency_s``, ``drift_ppm``, ``t_mid_rel_s`` with ``master.t0_ns``), without analysing
again. The slave is read with the report's selector unless one is given (``SLAVE::SELECTOR``), so that
its clock is the one the latency was measured on. Default output: next to the report,
``slave_on_master_clock.<ext>``. The report is not changed.
"""
from __future__ import annotations

import argparse
import json
import os

from logtools.errors import InputError
from parsers import load
from parsers.registry import detect, parse_log_arg
from parsers.restamp import ClockShift
from pipelines import export, parallel
from pipelines.firstrun import input_bytes
from pipelines.report import log_section


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("slave", help="slave log, PATH[::SELECTOR] (default selector: the report's)")
    p.add_argument("--from", dest="report", required=True, metavar="DIR/report.json",
                   help="report.json of a finished analysis of this slave (or its folder)")
    from pipelines.cli import output_path

    p.add_argument("-o", "--out", default=None, metavar="OUT", type=output_path,
                   help="output file (folder for folder formats); default next to the report")
    p.add_argument("--format", default="native", metavar="native|csv|parquet[,...]",
                   help="native (the slave's own format, default), csv or parquet; comma-separated for several")
    p.add_argument("--force", action="store_true",
                   help="apply the report's correction to a log whose channels are not the report's slave's")


def read_report(path: str) -> dict:
    if os.path.isdir(path):
        path = os.path.join(path, "report.json")
    try:
        with open(path, encoding="utf-8") as fh:
            rep = json.load(fh)
    except OSError as exc:
        raise InputError(f"cannot read the report: {exc.strerror}", path) from None
    except ValueError as exc:
        raise InputError(f"not a JSON report: {exc}", path) from None
    if not isinstance(rep, dict) or not str(rep.get("schema", "")).startswith("tapost.report/"):
        raise InputError("not a tapost report.json (no schema tapost.report/...)", path)
    # (what restamp reads of a hand-edited or damaged report; the values themselves: ClockShift.from_report)
    for key, sec in (("latency", rep.get("latency")), ("master", rep.get("master")), ("slave", rep.get("slave")),
                     ("latency.quality", (rep.get("latency") or {}).get("quality")
                      if isinstance(rep.get("latency"), dict) else None)):
        if sec is not None and not isinstance(sec, dict):
            raise InputError(f"the report's {key} is not an object ({type(sec).__name__})", path)
    return rep


#: channels' rates within this fraction are the same log's (a rate is measured over the log's whole span: a
#: copy cut short or with a gap keeps it within a fraction of a percent; another unit or stream setting does not)
SAME_RATE_FRACTION = 0.02


def not_the_reports_slave(rep_slave: dict, here: dict) -> tuple[str, str]:
    """(why the log described by ``here`` (``pipelines.report.log_section``) is not the one the report's slave
    section ``rep_slave`` describes, how it differs from it otherwise), each "" where nothing says so: a
    channel's other source or rate (beyond SAME_RATE_FRACTION), or stamps that do not overlap the report's, is
    another log; another start, length, count or set of channels is the same log cut, extended, damaged or
    read differently. What the report does not give (a hand-written one) is not compared."""
    other, differs = [], []
    chans, mine = rep_slave.get("channels"), here.get("channels") or {}
    if isinstance(chans, dict) and chans:
        if set(chans) != set(mine):  # (a reader that takes one more channel than the report's did: differs)
            differs.append(f"channels {', '.join(sorted(mine)) or 'none'} where the report's slave had "
                         f"{', '.join(sorted(chans))}")
        for name in sorted(set(chans) & set(mine)):
            a, b = chans[name] if isinstance(chans[name], dict) else {}, mine[name]
            if a.get("source") is not None and a.get("source") != b.get("source"):
                other.append(f"{name} from {b.get('source')}, the report's from {a.get('source')}")
            ra, rb = a.get("rate_hz"), b.get("rate_hz")
            if isinstance(ra, (int, float)) and rb is not None and ra > 0 and abs(rb / ra - 1) > SAME_RATE_FRACTION:
                other.append(f"{name} at {rb:.4g} Hz, the report's at {ra:.4g} Hz")
            elif isinstance(a.get("count"), int) and a["count"] != b.get("count"):
                differs.append(f"{b.get('count')} {name} samples, the report's {a['count']}")
    s0, d0 = rep_slave.get("start_s"), rep_slave.get("duration_s")
    s1, d1 = here.get("start_s"), here.get("duration_s")
    if all(isinstance(x, (int, float)) for x in (s0, d0, s1, d1)):
        if s1 > s0 + d0 or s0 > s1 + d1:
            other.append(f"its stamps ({s1:.3f}..{s1 + d1:.3f} s) do not overlap the report's slave's "
                         f"({s0:.3f}..{s0 + d0:.3f} s)")
        elif abs(s1 - s0) > 1e-3 or abs(d1 - d0) > 1e-3:
            differs.append(f"it spans {s1:.3f}..{s1 + d1:.3f} s, the report's slave {s0:.3f}..{s0 + d0:.3f} s")
    return "; ".join(other), "; ".join(differs)


def run(args: argparse.Namespace) -> int:
    kinds = export.parse_kinds(args.format, "--format")
    if not kinds:
        raise InputError("--format names nothing to write (native, csv or parquet)")
    if args.out and len(kinds) > 1:
        raise InputError("-o names one file: give one --format with it (or omit -o)")
    rep = read_report(args.report)
    report_path = args.report if not os.path.isdir(args.report) else os.path.join(args.report, "report.json")
    try:
        shift = ClockShift.from_report(rep)
    except ValueError as exc:
        raise InputError(str(exc), report_path) from None
    path, sel = parse_log_arg(args.slave)
    # freed arrays reused from the heap, not faulted in anew (the native exports' column and chunk buffers:
    # a 1 h MCAP slave's export 0.47 -> 0.40 s; pipelines.parallel.malloc_policy), in tapost's own process
    parallel.small_pair_malloc(input_bytes("restamp", [path]))
    slave_rep = rep.get("slave") or {}
    if not sel and slave_rep.get("format"):  # (before the report's selector is tried on another format's file)
        fmt = detect(path).NAME
        if fmt != slave_rep["format"]:
            raise InputError(f"the report's slave is {slave_rep['format']}, this log is {fmt}", path)
    arg = args.slave if sel else (f"{path}::{slave_rep['selector']}" if slave_rep.get("selector") else path)
    slave = load(arg)
    notes = []
    if slave_rep.get("format") and slave_rep["format"] != slave.meta.format:
        raise InputError(f"the report's slave is {slave_rep['format']}, this log is {slave.meta.format}", path)
    if slave_rep.get("path") and os.path.basename(slave_rep["path"]) != os.path.basename(path):
        notes.append(f"note: the report's slave was {slave_rep['path']}")
    if slave_rep.get("clock") and slave_rep["clock"] != slave.meta.clock:
        raise InputError(f"the report's slave was read on the {slave_rep['clock']} clock, this one on "
                         f"{slave.meta.clock}: give the report's selector ({slave_rep.get('selector')})", path)
    other, differs = not_the_reports_slave(slave_rep, log_section(slave))
    if other and not args.force:
        raise InputError(f"not the log this report analysed: {other} (--force applies its correction anyway)",
                         path)
    if other or differs:
        notes.append(f"warning: this log differs from the report's slave: {'; '.join(filter(None, [other, differs]))}; "
                     "the report's latency and drift applied as they are")
    out_dir = os.path.dirname(os.path.abspath(report_path))
    # the report's master is an input too: never written over (its path as analyze was given it: from where
    # analyze ran, unknown here, so as it reads from here and from the report's folder)
    m = str((rep.get("master") or {}).get("path") or "").partition("::")[0]
    masters = tuple(x for x in ((m, os.path.join(out_dir, m)) if m else ()) if os.path.exists(x))
    entries = export.write_slave(kinds, out_dir, slave, shift, out_path=args.out, inputs=masters)
    sec = export.report_section(entries, shift)
    caveat = export.clock_step_caveat((rep.get("latency") or {}).get("quality"))
    if caveat:
        notes.append(f"warning: {caveat}")
    for line in notes + export.summary_from_report({"slave_on_master_clock": sec}):
        print(line)
    failed = [e for e in entries if e.failed]
    if failed:
        raise InputError("; ".join(f"{e.kind}: {e.failed}" for e in failed))
    return 0
