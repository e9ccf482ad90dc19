"""``tapost analyze MASTER SLAVE``: (foundation stage) load both logs and say what was read."""
from __future__ import annotations

import argparse

from parsers import load


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("master", help="master log, PATH[::SELECTOR]")
    p.add_argument("slave", help="slave log, PATH[::SELECTOR]")
    p.add_argument("-o", "--out", default="tapost_out", help="output directory")


def run(args: argparse.Namespace) -> int:
    for role, arg in (("master", args.master), ("slave", args.slave)):
        log = load(arg)
        m = log.meta
        print(f"{role}: {m.source_path} [{m.format}] clock={m.clock} t0_ns={m.t0_ns} "
              f"duration={log.duration_s:.1f}s channels="
              + ", ".join(f"{k}:{v.rate_hz:.0f}Hz x{v.count}" for k, v in m.channels.items()))
    print("analyze: latency and alignment stages are not implemented yet; stopped after loading.")
    return 0
