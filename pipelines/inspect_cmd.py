"""``tapost inspect LOG``: what a log holds and the selectors that pick each unit."""
from __future__ import annotations

import argparse
import json
from dataclasses import asdict

from parsers import inspect_log


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", help="log file or bag directory")
    p.add_argument("--json", action="store_true", help="machine-readable output")


def run(args: argparse.Namespace) -> int:
    inv = inspect_log(args.log)
    if args.json:
        print(json.dumps(asdict(inv), indent=2))
        return 0
    print(f"{inv.path}: {inv.format}")
    print(f"  {'stream':<32} {'kind':<6} {'count':>8} {'rate_hz':>8} {'start_s':>16} {'dur_s':>9} clock")
    for s in inv.streams:
        print(f"  {s.name:<32} {s.kind:<6} {s.count:>8d} {s.rate_hz:>8.2f} {s.start_s:>16.3f} "
              f"{s.duration_s:>9.2f} {s.clock}")
    if inv.selectors and any(inv.selectors):
        print("  selectors (use as PATH::SELECTOR):")
        for sel in inv.selectors:
            print(f"    {inv.path}::{sel}")
    for w in inv.warnings:
        print(f"  warning: {w}")
    for n in inv.notes:
        print(f"  note: {n}")
    return 0
