"""Transfer alignment as ``tapost analyze`` runs it, on random pairs with what real installations have and
the seeds' scenarios do not: an arbitrary mounting, a lever arm of up to 2 m per axis, flexure.

Runs are drawn like ``bench_latency.py`` (scenario round robin, latency in [-1, 1] s, drift in +-100 ppm,
uniform random mounting, IMU rates 50-400 Hz, noise level 0.5/1/3, slave nav in 3/4), 60, 120 or 300 s
long, with a lever arm uniform in +-2 m per axis in 2/3 of the runs and seed 000's flexure in 1/2.
Each pair: the latency estimated (tapost), the slave compensated (restamp), then two alignments (kf,
the match the CLI picks):

* ``tapost``: the CLI's defaults (``--lever-arm auto --flexure auto``: the lever arm as states started
  from the latency's velocity fit; the latency fit's flexure model as states, or the alignment's own
  flexure check);
* ``rigid``: neither (``--lever-arm off --flexure off``), and the coarse mounting from the rates alone: what
  the CLI did before 2026-11-24.

``--one-axis N`` further pairs (default 30) whose rates turn about one axis only (cars with gentle turns on
a level road, ships that barely roll, aircraft with shallow S-turns; IMU-only slaves, lever arms, no
flexure): where the coarse mounting needs the specific forces too (set ``one-axis``).

Per set (lever arm / flexure / both / neither / one-axis) and variant: mounting error (the rotation between estimate
and truth, arcmin) RMS and worst, z = error / sqrt(sum of the three sigmas^2), the fraction with z <= 2 and
z > 3, the lever arm's error where estimated. The same z over only the axes the result reports
(``reported axes``: report.json's ``mounting_rpy_deg`` is null, with the reason, on an axis the data does
not determine): the whole-rotation z scores those too, at the prior the filter kept there.

    python benchmarks/bench_alignment_random.py [--runs 48] [--workers 2]

    python benchmarks/bench_alignment_random.py --real-errors [--board auto|on|off|oracle]

Writes ``benchmarks/results/alignment_random.json`` (``alignment_random_real_errors.json`` with
``--real-errors``; another ``--board`` than the CLI's default auto in the name, see ``default_out``); prints
markdown tables.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time
from datetime import datetime, timezone

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import bench_latency as bl  # noqa: E402

OUT = os.path.join(bl.RESULTS_DIR, "alignment_random.json")
OUT_REAL = os.path.join(bl.RESULTS_DIR, "alignment_random_real_errors.json")
VARIANTS = ("tapost", "rigid")
SETS = ("neither", "lever arm", "flexure", "both")


def draw(i: int, base_seed: int) -> dict:
    d = bl.draw_config(i, base_seed)
    rng = np.random.default_rng([base_seed, i, 31])
    d["set"] = "random"
    d["duration_s"] = float(rng.choice([60.0, 120.0, 300.0]))
    d["lever_arm_m"] = ([float(x) for x in rng.uniform(-2.0, 2.0, 3)] if rng.random() < 2.0 / 3.0
                        else [0.0, 0.0, 0.0])
    d["flexure"] = bool(rng.random() < 0.5)
    return d


def draw_one_axis(i: int, base_seed: int) -> dict:
    """A pair whose rates turn about one axis only: a car with gentle turns on a level road, a ship that
    barely rolls or pitches (0.2 deg), an aircraft with shallow S-turns; IMU-only slave, no flexure."""
    d = bl.draw_config(i, base_seed + 7)
    rng = np.random.default_rng([base_seed, i, 47])
    d["scenario"] = ("vehicle", "ship", "aircraft")[i % 3]
    d.update(set="one-axis", slave_nav=False, flexure=False, duration_s=float(rng.choice([120.0, 300.0])),
             lever_arm_m=[float(x) for x in rng.uniform(-2.0, 2.0, 3)])
    d["extra"] = dict(turn_amp_deg=float(rng.uniform(2.0, 20.0)), climb_amp_deg=0.0,
                      speed_var_m_s=float(rng.uniform(0.0, 2.0)))
    if d["scenario"] == "ship":
        d["extra"]["sway_amp_deg"] = (0.2, 0.2, 3.0)
    return d


def draw_nav_master(i: int, base_seed: int) -> dict:
    """A master INS that logs only its navigation solution (no IMU): every other pair one-axis (as
    ``draw_one_axis``), the rest random installations (as ``draw``)."""
    d = draw_one_axis(i, base_seed + 13) if i % 2 == 0 else draw(i, base_seed + 13)
    d.update(set="nav-master", master_nav_only=True)
    return d


def real_errors(d: dict, i: int, base_seed: int) -> dict:
    """The error sources of real boards (issue 22) added to a draw: the slave's accelerometer triad 0.5-2 deg
    off its gyro triad (random axis), the master's attitude with a first-order Markov error of 0.05-0.2 deg
    and 10-100 s correlation, the slave's IMU as 25 or 50 Hz snapshots with 0.05-0.3 m/s^2 / 0.05-0.3 deg/s
    of vibration near 97 Hz (aliased into the motion's band)."""
    rng = np.random.default_rng([base_seed, i, 53])
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    from logtools.conventions import dcm_from_rotvec, euler_from_dcm

    mis = np.degrees(euler_from_dcm(dcm_from_rotvec(np.radians(rng.uniform(0.5, 2.0)) * axis)))
    d = dict(d)
    d["extra"] = {**d.get("extra", {}),
                  "slave_accel_misalign_rpy_deg": tuple(float(x) for x in mis),
                  "master_att_markov_deg": float(rng.uniform(0.05, 0.2)),
                  "master_att_markov_tau_s": float(rng.uniform(10.0, 100.0)),
                  "slave_vibration_accel_m_s2": float(rng.uniform(0.05, 0.3)),
                  "slave_vibration_gyro_dps": float(rng.uniform(0.05, 0.3))}
    d["slave_imu_rate_hz"] = float(rng.choice([25.0, 50.0]))
    d["real_errors"] = True
    return d


def _imu_to_imu_row(pair, slave) -> dict:
    """alignment.imu_to_imu against its truth: per triad the error (deg) and z per axis."""
    from logtools.alignment.imu_to_imu import imu_to_imu

    res = imu_to_imu(pair.master, slave)
    out = {}
    for name, tr, truth in (("gyro", res.gyro, pair.truth.imu_to_imu_gyro_rpy_deg),
                            ("accel", res.accel, pair.truth.imu_to_imu_accel_rpy_deg)):
        if tr is None or truth is None:
            out[name] = dict(note=res.reasons.get(name, "not measured"))
            continue
        e = (np.asarray(tr.rpy_deg) - np.asarray(truth) + 180.0) % 360.0 - 180.0
        out[name] = dict(error_deg=[float(x) for x in e], z=[float(x) for x in np.abs(e) / np.asarray(tr.sigma_deg)],
                         rigid=tr.rigid)
    return out


def summarize_imu_to_imu(rows: list[dict]) -> dict:
    out = {}
    for name in ("gyro", "accel"):
        z = np.array([r["imu_to_imu"][name]["z"] for r in rows if "z" in r.get("imu_to_imu", {}).get(name, {})])
        e = np.array([r["imu_to_imu"][name]["error_deg"] for r in rows
                      if "z" in r.get("imu_to_imu", {}).get(name, {})])
        out[name] = dict(n=int(len(z)), not_measured=int(sum(1 for r in rows if "imu_to_imu" in r) - len(z)),
                         axes_within_2_sigma=float(np.mean(z <= 2.0)) if len(z) else None,
                         runs_all_axes_within_2_sigma=float(np.mean((z <= 2.0).all(axis=1))) if len(z) else None,
                         rms_error_arcmin=float(np.sqrt(np.mean(e ** 2)) * 60.0) if len(e) else None,
                         worst_z=float(z.max()) if len(z) else None)
    return out


def set_of(d: dict) -> str:
    if d.get("set") in ("one-axis", "nav-master"):
        return d["set"]
    lev = any(d["lever_arm_m"])
    return SETS[int(lev) + 2 * int(d["flexure"])]


def _rotation_arcmin(rpy_a, rpy_b) -> float:
    from logtools.conventions import dcm_from_euler

    d = dcm_from_euler(np.radians(rpy_a)).T @ dcm_from_euler(np.radians(rpy_b))
    return float(np.degrees(np.arccos(np.clip((np.trace(d) - 1.0) / 2.0, -1.0, 1.0))) * 60.0)


def _reported_axes_z(res, truth_rpy_deg) -> dict:
    """The same z over only the axes the result reports (report.json's mounting_rpy_deg, where an axis the
    data does not determine is null with its reason): the estimate with each null angle set to the truth's,
    its rotation from the truth over the root-sum-square of the reported axes' sigmas (equal to z when every
    axis is reported). What a user is told; the whole-rotation z also scores the null axes, at the prior
    the filter kept there."""
    from pipelines.report import alignment_section

    sec = alignment_section(res)
    shown = [k for k, x in enumerate(sec["mounting_rpy_deg"] or []) if x is not None]
    if not shown:
        return dict(reported_axes=[], z_reported=None)
    est = np.asarray(truth_rpy_deg, float).copy()
    est[shown] = np.asarray(res.mounting_rpy_deg, float)[shown]
    sig = float(np.linalg.norm(np.asarray(res.mounting_sigma_deg, float)[shown])) * 60.0
    return dict(reported_axes=shown, z_reported=_rotation_arcmin(est, truth_rpy_deg) / sig if sig > 0 else None)


def run_one(d: dict) -> dict:
    from logtools import sim
    from logtools.alignment import CONFIG, AlignmentOptions, run_alignment
    from logtools.compensate import compensate
    from logtools.latency import estimate
    from pipelines.analyze import AnalyzeOptions, _flexure_options, _lever_options, _resolve_match, board_options

    cfg = dataclasses.replace(bl.sim_config(d), lever_arm_m=tuple(d["lever_arm_m"]), **d.get("extra", {}))
    pair = sim.simulate(cfg)
    if d.get("master_nav_only"):  # the master logs its solution only
        from logtools.inslog import InsLog

        m = pair.master
        pair = dataclasses.replace(pair, master=InsLog(imu=m.imu.iloc[:0], nav=m.nav, meta=m.meta))
    row = dict(d, set=set_of(d))
    row["mount_rpy_deg"] = list(d["mount_rpy_deg"])
    try:
        lat = estimate(pair.master, pair.slave, max_lag_s=bl.MAX_LAG_S, compare=False)
        slave = compensate(pair.slave, lat, pair.master)
        if d.get("real_errors") and pair.master.has_gyro:
            row["imu_to_imu"] = _imu_to_imu_row(pair, slave)
        match, why = _resolve_match(pair.master, "auto")
        if match is None:
            raise RuntimeError(why)
    except Exception as exc:  # noqa: BLE001 - a benchmark row records the failure
        for v in VARIANTS:
            row[v] = dict(note=f"{type(exc).__name__}: {exc}"[:200])
        return row
    board_mode = d.get("board", "off")
    opts = AnalyzeOptions(board_errors="on" if board_mode == "oracle" else board_mode)
    board = board_options(opts)
    if board_mode == "oracle":  # the board's error states with the simulator's own Markov parameters
        ex = d.get("extra", {})
        board.update(master_att_err_deg=max(ex.get("master_att_markov_deg", 0.0), 1e-3),
                     master_att_err_tau_s=ex.get("master_att_markov_tau_s", 30.0))
    options = {"tapost": AlignmentOptions(**_lever_options(opts, lat), **_flexure_options(opts, lat), **board),
               "rigid": AlignmentOptions()}
    # rigid: the coarse mounting from the rates alone, as before
    configs = {"tapost": CONFIG, "rigid": dataclasses.replace(CONFIG, coarse_joint=False)}
    if d.get("widen"):  # the sigmas widened by the innovations' correlation time (issue 22)
        configs = {k: dataclasses.replace(c, innov_corr_min=2.0) for k, c in configs.items()}
    for v in VARIANTS:
        t0 = time.perf_counter()
        try:
            res = run_alignment(pair.master, slave, filter="kf", match=match, options=options[v], config=configs[v])
            err = _rotation_arcmin(res.mounting_rpy_deg, cfg.mount_rpy_deg)
            sig = float(np.linalg.norm(res.mounting_sigma_deg)) * 60.0
            lev_err = (None if res.lever_arm_m is None or res.lever_arm_sigma_m is None
                       else float(np.linalg.norm(np.subtract(res.lever_arm_m, cfg.lever_arm_m))))
            flex = ("latency model" if options[v].flexure is True
                    else "added" if any(n.startswith("flexure states added") for n in res.notes) else "none")
            row[v] = dict(error_arcmin=err, sigma_arcmin=sig, z=err / sig if sig > 0 else float("inf"),
                          lever_error_m=lev_err, flexure_states=flex, note="",
                          board_states=res.has_board_states,
                          **_reported_axes_z(res, cfg.mount_rpy_deg))
        except Exception as exc:  # noqa: BLE001
            row[v] = dict(note=f"{type(exc).__name__}: {exc}"[:200])
        row[f"runtime_{v}_s"] = time.perf_counter() - t0
    return row


def _reported_summary(ok: list[dict]) -> dict:
    """Coverage over the reported axes only (runs with at least one reported axis), and how many runs
    report some axis as not determined."""
    zr = np.array([x["z_reported"] for x in ok if x.get("z_reported") is not None])
    return dict(reported_within_2_sigma=float(np.mean(zr <= 2.0)) if len(zr) else None,
                reported_worst_z=float(zr.max()) if len(zr) else None,
                runs_with_null_axes=sum(1 for x in ok if len(x.get("reported_axes", (0, 1, 2))) < 3))


def summarize(rows: list[dict]) -> dict:
    out = {}
    for v in VARIANTS:
        ok = [r[v] for r in rows if "error_arcmin" in r.get(v, {})]
        e = np.array([x["error_arcmin"] for x in ok])
        z = np.array([x["z"] for x in ok])
        lev = np.array([x["lever_error_m"] for x in ok if x["lever_error_m"] is not None])
        out[v] = dict(n=len(ok), failed=len(rows) - len(ok),
                      rms_arcmin=float(np.sqrt(np.mean(e ** 2))) if len(e) else None,
                      worst_arcmin=float(e.max()) if len(e) else None,
                      within_2_sigma=float(np.mean(z <= 2.0)) if len(z) else None,
                      beyond_3_sigma=int(np.sum(z > 3.0)), worst_z=float(z.max()) if len(z) else None,
                      lever_error_rms_m=float(np.sqrt(np.mean(lev ** 2))) if len(lev) else None,
                      **_reported_summary(ok),
                      board_states=sum(1 for x in ok if x.get("board_states")),
                      flexure_states={k: sum(1 for x in ok if x["flexure_states"] == k)
                                      for k in ("latency model", "added", "none")})
    return out


def md_table(summary: dict, title: str) -> str:
    lines = [f"| {title} | n | mounting err RMS / worst (') | z <= 2 | z > 3 (worst z) | reported axes: z <= 2 "
             "(runs with a null axis) | lever arm err RMS (m) |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for v, s in summary.items():
        if not s["n"]:
            continue
        lev = "n/a" if s["lever_error_rms_m"] is None else f"{s['lever_error_rms_m']:.3f}"
        rep = ("n/a" if s.get("reported_within_2_sigma") is None
               else f"{100 * s['reported_within_2_sigma']:.0f} % ({s['runs_with_null_axes']})")
        lines.append(f"| {v} | {s['n']} | {s['rms_arcmin']:.3f} / {s['worst_arcmin']:.3f} | "
                     f"{100 * s['within_2_sigma']:.0f} % | {s['beyond_3_sigma']} ({s['worst_z']:.1f}) | {rep} | {lev} |")
    return "\n".join(lines)


def default_out(real: bool, board: str) -> str:
    """The results file: alignment_random[_real_errors].json with the CLI's default (board auto); else the
    board mode in the name (the white model, board off, on the real-error pairs: _real_white)."""
    if board == "auto":
        return OUT_REAL if real else OUT
    if real and board == "off":
        return os.path.join(bl.RESULTS_DIR, "alignment_random_real_white.json")
    return os.path.join(bl.RESULTS_DIR, f"alignment_random{'_real' if real else ''}_board_{board}.json")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=48)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--one-axis", type=int, default=30, help="further pairs whose rates turn about one axis")
    ap.add_argument("--nav-master", type=int, default=24,
                    help="further pairs whose master logs only its navigation solution (half of them one-axis)")
    ap.add_argument("--seed", type=int, default=2027)
    ap.add_argument("--out", default=None, help=f"default {OUT} ({OUT_REAL} with --real-errors); with --board "
                                                 "on|off|oracle the file name says so")
    ap.add_argument("--real-errors", action="store_true",
                    help="add real boards' error sources (see real_errors()) and check alignment.imu_to_imu")
    ap.add_argument("--widen", action="store_true",
                    help="alignment sigmas widened by the innovations' correlation time (AlignmentConfig.innov_corr_min)")
    ap.add_argument("--board", choices=("auto", "off", "on", "oracle"), default="auto",
                    help="tapost's --board-errors (default auto, as the CLI); oracle: on, with the simulator's "
                         "own Markov parameters")
    a = ap.parse_args(argv)
    a.out = a.out or default_out(a.real_errors, a.board)
    jobs = ([draw(i, a.seed) for i in range(a.runs)] + [draw_one_axis(a.runs + i, a.seed) for i in range(a.one_axis)]
            + [draw_nav_master(a.runs + a.one_axis + i, a.seed) for i in range(a.nav_master)])
    if a.real_errors:
        jobs = [real_errors(d, k, a.seed) for k, d in enumerate(jobs)]
    if a.widen:
        jobs = [dict(d, widen=True) for d in jobs]
    jobs = [dict(d, board=a.board) for d in jobs]
    t0 = time.time()
    rows = bl.run_pool(run_one, jobs, a.workers, every=8)
    rows.sort(key=lambda r: r["run"])
    summary = {"all": summarize([r for r in rows if r["set"] in SETS]),
               **{s: summarize([r for r in rows if r["set"] == s]) for s in SETS + ("one-axis", "nav-master")}}
    out = dict(benchmark="alignment_random", created_utc=datetime.now(timezone.utc).isoformat(timespec="seconds"),
               config=dict(runs=a.runs, seed=a.seed, max_lag_s=bl.MAX_LAG_S),
               machine=dict(python=platform.python_version(), cpus=os.cpu_count(), workers=a.workers),
               wall_time_s=time.time() - t0, summary=summary, rows=rows)
    out["config"]["widen"] = bool(a.widen)
    out["config"]["board"] = a.board
    if a.real_errors:
        out["config"]["real_errors"] = True
        out["imu_to_imu"] = summarize_imu_to_imu(rows)
    bl.write_json_atomic(a.out, out)
    for s, summ in summary.items():
        n = summ["tapost"]["n"] + summ["tapost"]["failed"]
        print(md_table(summ, f"{s} ({n} runs)"))
        print()
    if a.real_errors:
        for name, si in out["imu_to_imu"].items():
            print(f"imu_to_imu {name}: {si}")
    print(f"wrote {a.out} ({time.time() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
