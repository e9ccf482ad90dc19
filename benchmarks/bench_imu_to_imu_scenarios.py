"""The IMU-to-IMU rotations (``alignment.imu_to_imu``) on the simulator's four scenarios, any mounting.

Monte Carlo against simulated truth: ``logtools.sim`` pairs of each scenario ("ship", "aircraft", "vehicle",
"multirotor"; its own IMU grades and motion), 90 s, a random mounting (roll and yaw anywhere, pitch within
+-80 deg), the master's IMU at 100, 200 or 400 Hz and the slave's at 100, 200 or 250 Hz (its samples at the
simulator's random phase), a seed per run; the slave on the master's clock (no latency, no drift: this
measures the triads, not the latency). Per triad (gyro, accelerometers) and scenario: the rotation error (deg, the angle
of R_est R_true^T, against the simulator's ``imu_to_imu_*_rpy_deg``) RMS and worst, the Euler axes within 2
and 3 sigma, the median of each run's largest sigma, and the band check's outcome (the slow and the fast part
of the motion fitted apart: one rotation, not one rotation, or not compared because a band's rotation is not
determined).

Two variants on the same pairs:
* ``tapost``: the defaults;
* ``bands_unguarded``: a band's rotation taken as determined whatever the two units share in it
  (``band_min_canonical_z`` = 0), as before 2026-12-07. (The other half of that day's change, the low-pass's
  noise counted in each band, has no switch.)

    python benchmarks/bench_imu_to_imu_scenarios.py [--runs 12] [--seed 5]

Figures go to ``benchmarks/results/imu_to_imu_scenarios.json``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from logtools import sim  # noqa: E402
from logtools.alignment import imu_to_imu as ii  # noqa: E402
from logtools.conventions import dcm_from_euler, dcm_from_quat  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "imu_to_imu_scenarios.json"
SCENARIOS = ("ship", "aircraft", "vehicle", "multirotor")
VARIANTS = {"tapost": ii.DEFAULT, "bands_unguarded": replace(ii.DEFAULT, band_min_canonical_z=0.0)}


def score(tr: ii.TriadRotation | None, truth_rpy_deg) -> dict:
    if tr is None or truth_rpy_deg is None:
        return {"measured": False}
    r_true = dcm_from_euler(np.radians(truth_rpy_deg))
    d = dcm_from_quat(np.asarray(tr.quat_wxyz)) @ r_true.T
    angle = float(np.degrees(np.arccos(np.clip((np.trace(d) - 1.0) / 2.0, -1.0, 1.0))))
    de = (np.asarray(tr.rpy_deg) - np.asarray(truth_rpy_deg) + 180.0) % 360.0 - 180.0
    if tr.gimbal:  # (the canonical triple at the gimbal lock: the angle is the figure, the axes are not)
        de = np.full(3, np.nan)
    z = np.abs(de) / np.maximum(np.asarray(tr.sigma_deg), 1e-12)
    band = "one rotation" if tr.rigid else ("not one rotation" if tr.rigid is False else "not compared")
    return {"measured": True, "error_deg": angle, "z": z.tolist(), "sigma_deg": list(tr.sigma_deg), "band": band,
            "band_z": tr.band_z, "band_unchecked": tr.band_unchecked}


def summary(rows: list[dict]) -> dict:
    got = [r for r in rows if r["measured"]]
    out: dict = {"runs": len(rows), "not_measured": len(rows) - len(got)}
    if not got:
        return out
    err = np.array([g["error_deg"] for g in got])
    z = np.array([g["z"] for g in got]).reshape(-1)
    z = z[np.isfinite(z)]
    out.update(rms_error_deg=float(np.sqrt(np.mean(err ** 2))), worst_error_deg=float(err.max()),
               axes_within_2_sigma=float(np.mean(z <= 2.0)) if len(z) else None,
               axes_within_3_sigma=float(np.mean(z <= 3.0)) if len(z) else None,
               median_largest_sigma_deg=float(np.median([max(g["sigma_deg"]) for g in got])),
               bands={k: sum(g["band"] == k for g in got) for k in ("one rotation", "not one rotation", "not compared")})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=12, help="pairs per scenario")
    ap.add_argument("--seed", type=int, default=5)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    rows = []
    for sc in SCENARIOS:
        for k in range(args.runs):
            mount = (float(rng.uniform(-180, 180)), float(rng.uniform(-80, 80)), float(rng.uniform(-180, 180)))
            rates = (float(rng.choice([100.0, 200.0, 400.0])), float(rng.choice([100.0, 200.0, 250.0])))
            cfg = sim.scenario_config(sc, duration_s=90.0, seed=k, mount_rpy_deg=mount, latency_s=0.0, drift_ppm=0.0,
                                      master_imu_rate_hz=rates[0], slave_imu_rate_hz=rates[1])
            pair = sim.simulate(cfg)
            slave = pair.slave.rebased(pair.master.meta.t0_ns)
            row = {"scenario": sc, "seed": k, "mount_rpy_deg": list(mount), "imu_rates_hz": list(rates)}
            for name, config in VARIANTS.items():
                res = ii.imu_to_imu(pair.master, slave, config=config)
                row[name] = {"gyro": score(res.gyro, pair.truth.imu_to_imu_gyro_rpy_deg),
                             "accel": score(res.accel, pair.truth.imu_to_imu_accel_rpy_deg)}
            rows.append(row)
            print(f"  {sc} {k}: accel error {row['tapost']['accel'].get('error_deg', float('nan')):.3f} deg, "
                  f"band {row['tapost']['accel'].get('band')}", flush=True)
    out = {"benchmark": "bench_imu_to_imu_scenarios", "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
           "config": {"runs_per_scenario": args.runs, "seed": args.seed, "duration_s": 90.0},
           "summary": {v: {sc: {t: summary([r[v][t] for r in rows if r["scenario"] == sc]) for t in ("gyro", "accel")}
                           for sc in SCENARIOS} for v in VARIANTS},
           "rows": rows}
    print("| variant | scenario | triad | RMS error (deg) | worst | axes within 2 / 3 sigma | median largest sigma "
          "(deg) | bands: one rotation / not one / not compared |")
    print("|---|---|---|---:|---:|---:|---:|---:|")
    for v in VARIANTS:
        for sc in SCENARIOS:
            for t in ("gyro", "accel"):
                s = out["summary"][v][sc][t]
                if "rms_error_deg" not in s:
                    print(f"| {v} | {sc} | {t} | not measured ({s['not_measured']}) | | | | |")
                    continue
                b = s["bands"]
                print(f"| {v} | {sc} | {t} | {s['rms_error_deg']:.3f} | {s['worst_error_deg']:.3f} | "
                      f"{100 * s['axes_within_2_sigma']:.0f} % / {100 * s['axes_within_3_sigma']:.0f} % | "
                      f"{s['median_largest_sigma_deg']:.3g} | {b['one rotation']} / {b['not one rotation']} / "
                      f"{b['not compared']} |")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {RESULTS} ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
