"""How much of a damaged log each reader keeps.

A 40 s simulated slave (aircraft, 200 Hz IMU) is written in every format the repository writes; each file
(for a ROS 2 bag its storage file) is damaged ``--copies`` times: ``--bytes`` random bytes inverted
(``flip``) or one random bit flipped in each (``bit``), or a run of ``--bytes`` bytes zeroed (``zero``) or
replaced by random bytes (``garble``). Each
copy is read with ``parsers.load``; the figure is the share of the undamaged file's IMU samples it keeps
(-1 when the reader refuses the file: one line, exit 2 in the CLI).

    python benchmarks/bench_damage.py                      # 20 copies, 8 inverted bytes
    python benchmarks/bench_damage.py --kind zero --bytes 4096

Figures go to ``benchmarks/results/damage_<kind>_<bytes>.json``.

``--latency``: each copy that reads is analysed against the simulated master (``logtools.latency.estimate``),
with the isolated-spike stage (``LatencyConfig.spikes``) on and off; the figures are each estimate's error
against the simulator's truth in its own sigmas (z: is a damaged copy's estimate still right within what
it claims?), its drift error (ppm), and how far the damage moved the latency from the undamaged file's
estimate, in that estimate's sigmas (a copy that lost part of its data moves within its larger sigma).
Figures go to ``benchmarks/results/damage_latency_<kind>_<bytes>.json``.
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
    elif kind == "bit":
        for _ in range(n):
            b[int(rng.integers(0, len(b)))] ^= 1 << int(rng.integers(0, 8))
    else:
        i = int(rng.integers(0, len(b) - n))
        b[i:i + n] = bytes(n) if kind == "zero" else rng.integers(0, 256, n).astype(np.uint8).tobytes()
    return bytes(b)


def written(d: str, name: str, slave, fmt: str, opts: dict) -> tuple[str, str, bytes]:
    """The slave written as ``name`` in ``d``: (its path, the file to damage (a ROS 2 bag's storage file), that
    file's bytes)."""
    from parsers import registry

    src = os.path.join(d, name)
    registry.write(src, slave, fmt, **opts)
    files = ([os.path.join(src, f) for f in os.listdir(src) if not f.endswith(".yaml")]
             if os.path.isdir(src) else [src])
    target = max(files, key=os.path.getsize)
    return src, target, Path(target).read_bytes()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--copies", type=int, default=20)
    ap.add_argument("--bytes", type=int, default=8)
    ap.add_argument("--kind", choices=("flip", "bit", "zero", "garble"), default="flip")
    ap.add_argument("--latency", action="store_true", help="the damaged copies' latency against the master")
    a = ap.parse_args(argv)
    if a.latency:
        return latency_main(a)
    from logtools import sim
    from logtools.errors import InputError
    from parsers import load

    pair = sim.simulate(sim.scenario_config("aircraft", duration_s=40.0, seed=5))
    n_ref = len(pair.slave.imu)
    out: dict = {"copies": a.copies, "kind": a.kind, "bytes": a.bytes, "formats": {}}
    with tempfile.TemporaryDirectory() as d:
        for fmt, name, opts in CASES:
            src, target, orig = written(d, name, pair.slave, fmt, opts)
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


def latency_main(a) -> int:
    from dataclasses import replace

    from logtools import sim
    from logtools.errors import AnalysisError, InputError
    from logtools.latency import LatencyConfig, estimate
    from parsers import load

    on = LatencyConfig()
    configs = {"spikes_on": on, "spikes_off": replace(on, spikes=replace(on.spikes, enabled=False))}
    pair = sim.simulate(sim.scenario_config("aircraft", duration_s=40.0, seed=5))
    truth = pair.truth

    def z_truth(r) -> tuple[float, float]:
        t_ref = pair.master.t0_s + r.t_mid_rel_s  # (the estimate's latency is the one at its window's middle)
        true = truth.latency_s + truth.drift_ppm * 1e-6 * (t_ref - truth.t_mid_s)
        return (r.latency_s - true) / r.sigma_s, r.drift_ppm - truth.drift_ppm

    out: dict = {"copies": a.copies, "kind": a.kind, "bytes": a.bytes, "formats": {}}
    with tempfile.TemporaryDirectory() as d:
        for fmt, name, opts in CASES:
            src, target, orig = written(d, name, pair.slave, fmt, opts)
            ref = {k: estimate(pair.master, load(src), compare=False, config=c) for k, c in configs.items()}
            rows = {k: {"z_truth": [], "drift_error_ppm": [], "moved_sigmas": [], "spike_warnings": 0}
                    for k in configs}
            refused = failed = 0
            for seed in range(a.copies):
                Path(target).write_bytes(damage(orig, a.kind, a.bytes, np.random.default_rng(seed)))
                try:
                    slave = load(src)
                except InputError:
                    refused += 1
                    continue
                for k, c in configs.items():
                    try:
                        r = estimate(pair.master, slave, compare=False, config=c)
                    except AnalysisError:
                        failed += k == "spikes_on"
                        continue
                    z, de = z_truth(r)
                    rows[k]["z_truth"].append(z)
                    rows[k]["drift_error_ppm"].append(de)
                    rows[k]["moved_sigmas"].append((r.latency_s - ref[k].latency_s) / ref[k].sigma_s)
                    rows[k]["spike_warnings"] += any("local sigmas" in w for w in r.quality["warnings"])
            Path(target).write_bytes(orig)
            z0, _ = z_truth(ref["spikes_on"])
            entry = {"format": fmt, "options": opts, "refused": refused, "analysis_failed": failed,
                     "undamaged": {"sigma_s": ref["spikes_on"].sigma_s, "z_truth": z0}}
            for k, row in rows.items():
                z = np.abs(np.asarray(row["z_truth"]))
                row.update({"analysed": int(len(z)), "max_abs_z": float(z.max()) if len(z) else None,
                            "within_2_sigma": float(np.mean(z <= 2.0)) if len(z) else None,
                            "beyond_3_sigma": int((z > 3.0).sum()),
                            "max_abs_drift_error_ppm": (float(np.max(np.abs(row["drift_error_ppm"])))
                                                        if len(z) else None)})
                entry[k] = row
            out["formats"][name] = entry
            e_on, e_off = entry["spikes_on"], entry["spikes_off"]
            print(f"{fmt:9s} {name:9s} analysed {e_on['analysed']}/{a.copies} (refused {refused}, failed {failed}); "
                  f"|z| vs truth at most {e_on['max_abs_z'] or 0:.2f}, {e_on['beyond_3_sigma']} beyond 3 sigma "
                  f"(spikes replaced in {e_on['spike_warnings']}); without the spike stage at most "
                  f"{e_off['max_abs_z'] or 0:.2f}, {e_off['beyond_3_sigma']} beyond 3 sigma", flush=True)
    res = ROOT / "benchmarks" / "results" / f"damage_latency_{a.kind}_{a.bytes}.json"
    res.write_text(json.dumps(out, indent=2) + "\n")
    print(f"-> {res.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
