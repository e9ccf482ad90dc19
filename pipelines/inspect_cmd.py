"""``tapost inspect LOG``: what a log holds and the selectors that pick each unit.

Works on every format's :class:`parsers.base.Inventory`: one row per stream (name, kind, count,
rate, start on the stream's own clock, duration, clock), then the ready-to-use selectors, warnings
(damage, gaps...) and notes. ``--json`` prints the same as one JSON object (schema
``tapost.inventory/1``; non-finite numbers become null).

``tapost inspect PATH::SELECTOR`` also loads what the selector picks and shows it (channels, clock,
stamp source, warnings), so a selector can be checked before an analysis; a selector naming something
the log does not hold is the usual one-line error (exit 2).
"""
from __future__ import annotations

import argparse
import json
import math
from dataclasses import asdict

from logtools.inslog import InsLog
from parsers import inspect_log, load, parse_log_arg
from parsers.base import Inventory

SCHEMA = "tapost.inventory/1"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", help="log file or bag/session directory, optionally PATH::SELECTOR")
    p.add_argument("--json", action="store_true", help="machine-readable output (one JSON object)")
    p.add_argument("--fields", action="store_true", help="also list each stream's fields")


def _finite(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def is_time_series(s) -> bool:
    """False for a stream whose records do not spread over time (one record, or every stamp equal:
    PX4 topics logged once, or stamped 0), whose rate and duration mean nothing."""
    return s.count > 1 and math.isfinite(s.duration_s) and s.duration_s > 0


def inventory_dict(inv: Inventory) -> dict:
    """The JSON form of an inventory (what ``--json`` prints); each stream says ``time_series``."""
    d = _finite(asdict(inv))
    for sd, s in zip(d["streams"], inv.streams):
        sd["time_series"] = is_time_series(s)
    return {"schema": SCHEMA, **d}


def format_inventory(inv: Inventory, *, fields: bool = False) -> list[str]:
    """The text form, one line per item."""
    out = [f"{inv.path}: {inv.format}"]
    w = max([32] + [len(s.name) for s in inv.streams])
    out.append(f"  {'stream':<{w}} {'kind':<6} {'count':>8} {'rate_hz':>8} {'start_s':>16} {'dur_s':>9} clock")
    for s in inv.streams:
        if is_time_series(s):
            rate = f"{s.rate_hz:>8.2f}" if math.isfinite(s.rate_hz) else f"{'-':>8}"
            dur, clock = f"{s.duration_s:>9.2f}", s.clock
        else:  # not a time series: no rate, no duration
            rate, dur = f"{'-':>8}", f"{'-':>9}"
            clock = (f"{s.clock}; not a time series ("
                     + ("one record" if s.count == 1 else "no records" if s.count == 0
                        else f"all {s.count} records share one stamp") + ")")
        out.append(f"  {s.name:<{w}} {s.kind:<6} {s.count:>8d} {rate} {s.start_s:>16.3f} {dur} {clock}")
        if fields and s.fields:
            out.append(f"  {'':<{w}}   fields: {', '.join(s.fields)}")
    if not inv.streams:
        out.append("  (no streams)")
    if inv.selectors and any(inv.selectors):
        out.append("  selectors (use as PATH::SELECTOR):")
        for sel in inv.selectors:
            out.append(f"    {inv.path}::{sel}" if sel else f"    {inv.path}   (no selector needed)")
    for warning in inv.warnings:  # (a note riding in the warnings with its "note:" prefix is said as one)
        out.append(f"  {warning}" if warning.startswith("note:") else f"  warning: {warning}")
    for n in inv.notes:
        out.append(f"  note: {n}")
    return out


def selection_dict(log: InsLog) -> dict:
    """What a selector picked: the loaded unit's meta in brief."""
    m = log.meta
    return _finite({"selector": m.selector, "clock": m.clock, "stamp_source": m.stamp_source, "t0_ns": m.t0_ns,
                    "duration_s": log.duration_s,
                    "channels": {k: {"rate_hz": c.rate_hz, "count": c.count, "source": c.source}
                                 for k, c in m.channels.items()},
                    "warnings": list(m.warnings)})


def format_selection(sel: dict) -> list[str]:
    out = [f"  selected ({sel['selector'] or 'default'}): clock {sel['clock']}, {sel['duration_s']:.2f} s, "
           f"stamps: {sel['stamp_source']}"]
    for k, c in sel["channels"].items():
        rate = f"{c['rate_hz']:.2f}" if c["rate_hz"] is not None else "-"
        out.append(f"    {k:<6} {c['count']:>8d} samples {rate:>8} Hz  from {c['source']}")
    # (a note rides in a log's warnings with a "note:" prefix; report.json files it under notes)
    out += [f"    {w}" if w.startswith("note:") else f"    warning: {w}" for w in sel["warnings"]]
    return out


def run(args: argparse.Namespace) -> int:
    path, selector = parse_log_arg(args.log)
    inv = inspect_log(path)
    sel = selection_dict(load(args.log)) if "::" in args.log else None
    if args.json:
        d = inventory_dict(inv)
        if sel is not None:
            d["selection"] = sel
        print(json.dumps(d, indent=2))
        return 0
    lines = format_inventory(inv, fields=getattr(args, "fields", False))
    if sel is not None:
        lines += format_selection(sel)
    print("\n".join(lines))
    return 0
