"""Latency on the hard cases the main Monte Carlo does not draw: short logs, long slave dropouts, slave
stamps in whole milliseconds, and a slave INS whose velocity frame is rotated (a heading error).

Each set draws its runs like ``bench_latency.py`` (scenario round robin, latency in [-1, 1] s, drift in
+-100 ppm, uniform random mounting, IMU rates 50-400 Hz, noise level 0.5/1/3, flexure in 1/3) and changes
one thing:

* ``short``: 25, 30 or 40 s logs (1/3 with white stamp noise up to 0.2 of each IMU period);
* ``dropout``: 60-300 s logs, the slave silent for 20-45 % of the log in one stretch;
* ``ms-stamps``: the slave at 100, 125, 200 or 250 Hz (a whole number of ms per sample, as real IMUs
  run) read from a canonical CSV whose time is written in whole milliseconds (``%.3f``), half of the runs
  without drift (a fixed sampling phase: every stamp off by the same fraction of a millisecond);
* ``rotated-velocity``: the slave logs a nav velocity as an INS whose attitude is off by a heading error
  of 1-8 deg and a tilt of up to 0.5 deg would (R (v - g t) + g t), flexure in half of the runs;
* ``short-flexure``: 25-45 s logs, all with seed 000's flexure (without: the flexure model's likelihood
  asking for 4 blocks per unknown, as before 2026-11-24, which kept records under ~40 s from the Kalman stage);
* ``slow-vibrating``: the slave at 40, 50, 62.5 or 100 Hz, the whole vehicle shaking 0.003-0.012 deg per
  axis at 8 Hz to 0.4 of the slave's rate (a rigid-body vibration: the delay's information near the
  slave's Nyquist rate), no flexure (without: the slave gridded by a cubic spline at its stamps' fixed
  offset, ``PrepareConfig.band_limited_fraction`` infinite, as before 2026-12-05).

Every run is estimated twice: ``tapost`` and ``tapost-without`` (the remedy of that set switched off
through its configuration (``WITHOUT``, ``without_config``): 1-2 drift windows below 45 s as before; no stamp-resolution floor; no frame
rotation, the linear tilt model only; 4 blocks per unknown). The dropout set has no switch (its remedies are structural: the
band from the longest run, the overlap count from the valid samples, windows inside the runs of data).
Per set and variant: RMS, worst, within 1 ms, coverage of sigma (|error| <= 2 sigma).

    python benchmarks/bench_latency_hard.py [--runs-per-set 32] [--workers 2]

Writes ``benchmarks/results/latency_hard.json``; prints markdown tables.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from datetime import datetime, timezone

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bench_latency as bl  # noqa: E402

OUT = os.path.join(bl.RESULTS_DIR, "latency_hard.json")
SETS = ("short", "dropout", "ms-stamps", "rotated-velocity", "short-flexure", "slow-vibrating")
VARIANTS = ("tapost", "tapost-without")
G_NED = np.array([0.0, 0.0, 9.80665])


def draw(set_name: str, i: int, base_seed: int) -> dict:
    """Run i of a set: bench_latency's draw, then the set's change."""
    k = SETS.index(set_name)
    d = bl.draw_config(i, base_seed + 1000 * (k + 1))
    d["set"] = set_name
    rng = np.random.default_rng([base_seed, k, i, 7])
    if set_name == "short":
        d["duration_s"] = float(rng.choice([25.0, 30.0, 40.0]))
        if rng.random() < 1.0 / 3.0:
            d["master_jitter_s"] = float(rng.uniform(0.0, 0.2)) / d["master_imu_rate_hz"]
            d["slave_jitter_s"] = float(rng.uniform(0.0, 0.2)) / d["slave_imu_rate_hz"]
    elif set_name == "short-flexure":
        d["duration_s"] = float(rng.choice([25.0, 30.0, 35.0, 40.0, 45.0]))
        d["flexure"] = True
    elif set_name == "slow-vibrating":
        rate = float(rng.choice([40.0, 50.0, 62.5, 100.0]))
        d["slave_imu_rate_hz"] = rate
        d["flexure"] = False
        d["rigid_vibration_deg"] = [float(x) for x in rng.uniform(0.003, 0.012, 3)]
        d["rigid_vibration_hz"] = [float(x) for x in rng.uniform(8.0, 0.4 * rate, 3)]
    elif set_name == "dropout":
        dur = float(rng.uniform(60.0, 300.0))
        d["duration_s"] = dur
        length = float(rng.uniform(0.20, 0.45)) * dur
        d["slave_gaps_s"] = [[float(rng.uniform(0.1, 0.9 - length / dur)) * dur, length]]
    elif set_name == "ms-stamps":
        # real IMUs run at round rates: a whole number of ms per sample keeps the sampling phase fixed
        d["slave_imu_rate_hz"] = float(rng.choice([100.0, 125.0, 200.0, 250.0]))
        if i % 2 == 0:
            d["drift_ppm"] = 0.0
    else:
        d["slave_nav"] = True
        d["flexure"] = bool(i % 2 == 0)
        d["velocity_frame_rpy_deg"] = [float(rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.5, 0.5)),
                                       float(rng.choice([-1.0, 1.0]) * rng.uniform(1.0, 8.0))]
    return d


def _ms_csv_slave(slave):
    """The slave through a canonical CSV whose time column has whole milliseconds (rounded)."""
    from parsers import csv_canonical, registry

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "slave.csv")
        csv_canonical.write(path, slave, time_decimals=3)
        return registry.load(path)


def _rotated_velocity(slave, rpy_deg):
    """The slave's nav velocity as an INS off by the rotation R would log it: R (v - g t) + g t."""
    from logtools.conventions import dcm_from_euler
    from logtools.inslog import VEL, InsLog

    nav = slave.nav.copy()
    t = nav.index.to_numpy(float)
    v = nav[list(VEL)].to_numpy(float)
    gt = G_NED * (t - t[len(t) // 2])[:, None]
    R = dcm_from_euler(np.radians(rpy_deg))
    nav[list(VEL)] = (v - gt) @ R.T + gt
    return InsLog(imu=slave.imu, nav=nav, meta=slave.meta)


#: the configuration changes (section -> {field: value}) that switch each set's remedy off
WITHOUT = {
    "short": {"windows": {"windows3_min_s": 60.0}},
    "ms-stamps": {"uncertainty": {"stamp_resolution_floor": False}, "velocity": {"stamp_resolution_floor": False}},
    "rotated-velocity": {"velocity": {"frame_min_deg": float("inf"), "tilt_exact_deg": float("inf")}},
    "dropout": {},
    "short-flexure": {"flexure": {"ml_blocks_per_unknown": 4.0}},
    "slow-vibrating": {"prepare": {"band_limited_fraction": float("inf")}},
}


def without_config(set_name: str):
    """The default LatencyConfig with the set's remedy switched off (``WITHOUT``)."""
    from dataclasses import replace

    from logtools.latency import LatencyConfig

    cfg = LatencyConfig()
    for section, fields in WITHOUT[set_name].items():
        cfg = replace(cfg, **{section: replace(getattr(cfg, section), **fields)})
    return cfg


def run_one(d: dict) -> dict:
    from logtools import sim
    from logtools.latency import LatencyConfig, estimate

    pair = sim.simulate(bl.sim_config(d))
    master, slave = pair.master, pair.slave
    if d["set"] == "ms-stamps":
        slave = _ms_csv_slave(slave)
    elif d["set"] == "rotated-velocity":
        slave = _rotated_velocity(slave, d["velocity_frame_rpy_deg"])
    row = dict(d)
    row["mount_rpy_deg"] = list(d["mount_rpy_deg"])
    for variant in VARIANTS:
        config = without_config(d["set"]) if variant == "tapost-without" else LatencyConfig()
        t0 = time.perf_counter()
        try:
            res = estimate(master, slave, max_lag_s=bl.MAX_LAG_S, compare=False, config=config)
            truth = float(pair.truth.latency_at(res.t_mid_rel_s))
            row[variant] = dict(latency_s=float(res.latency_s), sigma_s=float(res.sigma_s),
                                error_s=float(res.latency_s) - truth, note="")
        except Exception as exc:  # noqa: BLE001 - a benchmark row records the failure
            row[variant] = dict(latency_s=float("nan"), sigma_s=float("nan"), error_s=float("nan"),
                                note=f"{type(exc).__name__}: {exc}"[:200])
        row[f"runtime_{variant}_s"] = time.perf_counter() - t0
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs-per-set", type=int, default=32)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--out", default=OUT)
    a = ap.parse_args(argv)
    jobs = [draw(s, i, a.seed) for s in SETS for i in range(a.runs_per_set)]
    t0 = time.time()
    rows = bl.run_pool(run_one, jobs, a.workers, every=16)
    rows.sort(key=lambda r: (SETS.index(r["set"]), r["run"]))
    summary = {s: bl.summarize([r for r in rows if r["set"] == s], VARIANTS) for s in SETS}
    out = dict(benchmark="latency_hard", created_utc=datetime.now(timezone.utc).isoformat(timespec="seconds"),
               config=dict(runs_per_set=a.runs_per_set, seed=a.seed, max_lag_s=bl.MAX_LAG_S, without=WITHOUT),
               machine=dict(python=platform.python_version(), cpus=os.cpu_count(), workers=a.workers),
               wall_time_s=time.time() - t0, summary=summary, rows=rows)
    bl.write_json_atomic(a.out, out)
    for s in SETS:
        print(bl.md_table(summary[s], f"{s} ({a.runs_per_set} runs)"))
        print()
    print(f"wrote {a.out} ({time.time() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
