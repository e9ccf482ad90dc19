"""How much of a damaged log each reader keeps.

A 40 s simulated slave (aircraft, 200 Hz IMU) is written in every format the repository writes; each file
(for a ROS 2 bag its storage file) is damaged ``--copies`` times: ``--bytes`` random bytes inverted
(``flip``), or a run of ``--bytes`` bytes zeroed (``zero``) or replaced by random bytes (``garble``). Each
copy is read with ``parsers.load``; the figure is the share of the undamaged file's IMU samples it keeps
(-1 when the reader refuses the file: one line, exit 2 in the CLI).

    python benchmarks/bench_damage.py                      # 20 copies, 8 inverted bytes
    python benchmarks/bench_damage.py --kind zero --bytes 4096

Figures go to ``benchmarks/results/damage_<kind>_<bytes>.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
CASES = [("tlog", "s.tlog", {}), ("dataflash", "s.bin", {}), ("ulog", "s.ulg", {}), ("csv", "s.csv", {}),
         ("mcap", "s.mcap", {}), ("rosbag1", "s.bag", {}), ("rosbag1", "s_lz4.bag", {"compression": "lz4"}),
         ("rosbag2", "b2sql", {"storage": "sqlite3"}),
         ("rosbag2", "b2mcap", {"storage": "mcap"})]


def damage(orig: bytes, kind: str, n: int, rng) -> bytes:
    b = bytearray(orig)
    if kind == "flip":
        for _ in range(n):
            b[int(rng.integers(0, len(b)))] ^= 0xFF
    else:
        i = int(rng.integers(0, len(b) - n))
        b[i:i + n] = bytes(n) if kind == "zero" else rng.integers(0, 256, n).astype(np.uint8).tobytes()
    return bytes(b)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--copies", type=int, default=20)
    ap.add_argument("--bytes", type=int, default=8)
    ap.add_argument("--kind", choices=("flip", "zero", "garble"), default="flip")
    a = ap.parse_args(argv)
    from logtools import sim
    from logtools.errors import InputError
    from parsers import load, registry

    pair = sim.simulate(sim.scenario_config("aircraft", duration_s=40.0, seed=5))
    n_ref = len(pair.slave.imu)
    out: dict = {"copies": a.copies, "kind": a.kind, "bytes": a.bytes, "formats": {}}
    with tempfile.TemporaryDirectory() as d:
        for fmt, name, opts in CASES:
            src = os.path.join(d, name)
            registry.write(src, pair.slave, fmt, **opts)
            files = ([os.path.join(src, f) for f in os.listdir(src) if not f.endswith(".yaml")]
                     if os.path.isdir(src) else [src])
            target = max(files, key=os.path.getsize)
            orig = Path(target).read_bytes()
            kept = []
            for seed in range(a.copies):
                Path(target).write_bytes(damage(orig, a.kind, a.bytes, np.random.default_rng(seed)))
                try:
                    kept.append(len(load(src).imu) / n_ref)
                except InputError:
                    kept.append(-1.0)
            Path(target).write_bytes(orig)
            k = np.asarray(kept)
            row = {"file_mb": len(orig) / 1e6, "kept_min": float(k.min()), "kept_median": float(np.median(k)),
                   "copies_below_0.9": int((k < 0.9).sum()), "refused": int((k < 0).sum()), "kept": kept}
            out["formats"][name] = {"format": fmt, "options": opts, **row}
            print(f"{fmt:9s} {name:7s} kept min {row['kept_min']:6.3f} median {row['kept_median']:.3f}  "
                  f"below 0.9: {row['copies_below_0.9']}/{a.copies}  refused: {row['refused']}", flush=True)
    res = ROOT / "benchmarks" / "results" / f"damage_{a.kind}_{a.bytes}.json"
    res.write_text(json.dumps(out, indent=2) + "\n")
    print(f"-> {res.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
