"""The accelerometer triad's IMU-to-IMU rotation on vibrating mounts with MEMS gyros and long lever arms.

Monte Carlo against simulated truth: pairs of IMUs on one rigid body (random smooth manoeuvres, a rigid-body
angular vibration of 8-25 Hz on every axis, a translational one of 10-25 Hz), the slave's accelerometers on
a lever arm of 0.3-2 m in a random direction, its triads rotated by a random rotation; the master at 200 or
400 Hz, the slave at the same rate or half of it with its stamps at a random phase between the master's;
white noise of MEMS units (gyros 1-4 mrad/s a sample, accelerometers 0.02-0.05 m/s^2) and slave biases. Every
signal is evaluated exactly at each unit's own stamps (no interpolation in the generator).

On the same pairs, three variants of ``imu_to_imu`` (``ImuToImuConfig``):
* ``tapost``: the defaults (five-point angular acceleration, the rates interpolated onto the common stamps
  by four points, the gyro noise's moment taken out of the lever-arm regressors' moments: errors in
  variables);
* ``linear_regressors``: the same with the rates interpolated linearly;
* ``no_eiv``: the defaults with the noise left in (``regressor_noise_max_frac`` = 2: never applied);
* ``before``: the three-point difference, linear interpolation, the noise left in (the code before
  2026-12-04's evening).
Per variant: the rotation error (deg, the angle of R_est R_true^T) RMS and worst, the axes within 2 and 3
sigma, the runs beyond 3 sigma on some axis, the lever arm's error RMS (m), the triads not measured.

    python benchmarks/bench_imu_to_imu_vibration.py [--runs 60] [--seed 11]

Figures go to ``benchmarks/results/imu_to_imu_vibration.json``.
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
from logtools.alignment import imu_to_imu as ii  # noqa: E402
from logtools.conventions import dcm_from_quat, euler_from_dcm, skew  # noqa: E402
from logtools.inslog import InsLog, LogMeta  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "imu_to_imu_vibration.json"
VARIANTS = {"tapost": ii.DEFAULT,
            "linear_regressors": replace(ii.DEFAULT, lever_interp_points=2),
            "no_eiv": replace(ii.DEFAULT, regressor_noise_max_frac=2.0),
            "before": replace(ii.DEFAULT, regressor_noise_max_frac=2.0, lever_derivative_points=3,
                              lever_interp_points=2)}


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return dcm_from_quat(q / np.linalg.norm(q))


def make_pair(rng: np.random.Generator) -> tuple[InsLog, InsLog, dict]:
    dur = float(rng.uniform(60.0, 120.0))
    m_hz = float(rng.choice([200.0, 400.0]))
    s_hz = m_hz if rng.random() < 0.5 else m_hz / 2
    # (frequency Hz, amplitude, phase) per axis: smooth manoeuvres, then the rigid-body vibration
    slow = [[(rng.uniform(0.05, 1.5), rng.uniform(0.05, 0.4), rng.uniform(0, 2 * np.pi)) for _ in range(4)]
            for _ in range(3)]
    vib_w = [(rng.uniform(8.0, min(25.0, m_hz / 8)), rng.uniform(0.02, 0.15), rng.uniform(0, 2 * np.pi))
             for _ in range(3)]
    f_slow = [[(rng.uniform(0.05, 1.5), rng.uniform(0.2, 1.5), rng.uniform(0, 2 * np.pi)) for _ in range(4)]
              for _ in range(3)]
    vib_f = [(rng.uniform(10.0, min(25.0, m_hz / 8)), rng.uniform(0.2, 1.0), rng.uniform(0, 2 * np.pi))
             for _ in range(3)]
    d = rng.normal(size=3)
    lever = d / np.linalg.norm(d) * rng.uniform(0.3, 2.0)
    r_true = _random_rotation(rng)

    def motion(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        w, dw, f = np.zeros((len(t), 3)), np.zeros((len(t), 3)), np.zeros((len(t), 3))
        f[:, 2] = -9.81
        for i in range(3):
            for fr, a, ph in slow[i] + [vib_w[i]]:
                w[:, i] += a * np.sin(2 * np.pi * fr * t + ph)
                dw[:, i] += a * 2 * np.pi * fr * np.cos(2 * np.pi * fr * t + ph)
            for fr, a, ph in f_slow[i] + [vib_f[i]]:
                f[:, i] += a * np.sin(2 * np.pi * fr * t + ph)
        return w, dw, f

    tm = np.arange(0.0, dur, 1.0 / m_hz)
    ts = np.arange(0.0, dur, 1.0 / s_hz) + rng.uniform(0.0, 1.0 / m_hz)
    ts = ts[ts < dur]
    wm, _dwm, fm = motion(tm)
    ws, dws, fs = motion(ts)
    f_lever = fs + np.einsum("kij,j->ki", skew(dws) + skew(ws) @ skew(ws), lever)
    g_sig_m, g_sig_s = rng.uniform(1e-3, 4e-3), rng.uniform(1e-3, 4e-3)
    a_sig_m, a_sig_s = rng.uniform(0.02, 0.05), rng.uniform(0.02, 0.05)
    master = InsLog.from_arrays(LogMeta("master.csv", "csv"), tm, wm + rng.normal(0, g_sig_m, wm.shape),
                                fm + rng.normal(0, a_sig_m, fm.shape))
    slave = InsLog.from_arrays(LogMeta("slave.csv", "csv"), ts,
                               ws @ r_true.T + rng.normal(0, g_sig_s, ws.shape) + rng.normal(0, 0.002, 3),
                               f_lever @ r_true.T + rng.normal(0, a_sig_s, fs.shape) + rng.normal(0, 0.05, 3))
    truth = {"duration_s": dur, "master_hz": m_hz, "slave_hz": s_hz, "lever_m": lever.tolist(),
             "rpy_deg": np.degrees(euler_from_dcm(r_true)).tolist(), "gyro_noise_rad_s": [g_sig_m, g_sig_s],
             "accel_noise_m_s2": [a_sig_m, a_sig_s], "vib_rad_s": [v[1] for v in vib_w],
             "vib_hz": [v[0] for v in vib_w]}
    return master, slave, {"r": r_true, "lever": lever, "row": truth}


def score(tr: ii.TriadRotation | None, truth: dict) -> dict:
    if tr is None:
        return {"measured": False}
    r_est = dcm_from_quat(np.asarray(tr.quat_wxyz))
    d = r_est @ truth["r"].T
    angle = float(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))))
    de = (np.asarray(tr.rpy_deg) - truth["row"]["rpy_deg"] + 180.0) % 360.0 - 180.0  # per Euler angle
    z = np.abs(de) / np.maximum(np.asarray(tr.sigma_deg), 1e-12)
    lev = None if tr.lever_arm_m is None else float(np.linalg.norm(np.asarray(tr.lever_arm_m) - truth["lever"]))
    return {"measured": True, "error_deg": angle, "z": z.tolist(), "sigma_deg": list(tr.sigma_deg),
            "lever_error_m": lev}


def summary(rows: list[dict], name: str) -> dict:
    got = [r[name] for r in rows if r[name]["measured"]]
    err = np.array([g["error_deg"] for g in got])
    z = np.array([g["z"] for g in got]).reshape(-1, 3)
    lev = np.array([g["lever_error_m"] for g in got if g["lever_error_m"] is not None])
    return {"runs": len(rows), "not_measured": len(rows) - len(got),
            "rms_error_deg": float(np.sqrt(np.mean(err ** 2))) if len(err) else None,
            "median_error_deg": float(np.median(err)) if len(err) else None,
            "worst_error_deg": float(err.max()) if len(err) else None,
            "axes_within_2_sigma": float(np.mean(z <= 2)) if len(z) else None,
            "axes_within_3_sigma": float(np.mean(z <= 3)) if len(z) else None,
            "runs_beyond_3_sigma": int(np.sum(z.max(axis=1) > 3)) if len(z) else 0,
            "worst_z": float(z.max()) if len(z) else None,
            "lever_rms_error_m": float(np.sqrt(np.mean(lev ** 2))) if len(lev) else None}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=60)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    rows = []
    t0 = time.perf_counter()
    for i in range(args.runs):
        master, slave, truth = make_pair(rng)
        row = {"run": i, **truth["row"]}
        for name, cfg in VARIANTS.items():
            row[name] = score(ii.imu_to_imu(master, slave, config=cfg).accel, truth)
        rows.append(row)
        if (i + 1) % 10 == 0:
            print(f"  {i + 1}/{args.runs} runs, {time.perf_counter() - t0:.0f} s", flush=True)
    out = {"benchmark": "bench_imu_to_imu_vibration", "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
           "config": {"runs": args.runs, "seed": args.seed}, "summary": {n: summary(rows, n) for n in VARIANTS},
           "rows": rows}
    print("| variant | not measured | RMS error (deg) | median | worst | axes within 2 / 3 sigma | runs beyond 3 "
          "sigma (worst z) | lever arm RMS error (m) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for n, s in out["summary"].items():
        print(f"| {n} | {s['not_measured']} | {s['rms_error_deg']:.3f} | {s['median_error_deg']:.3f} | "
              f"{s['worst_error_deg']:.3f} | {100 * s['axes_within_2_sigma']:.0f} % / {100 * s['axes_within_3_sigma']:.0f} % "
              f"| {s['runs_beyond_3_sigma']} ({s['worst_z']:.1f}) | {s['lever_rms_error_m']:.3f} |")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out} ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
