"""``tapost simulate SCENARIO -o DIR [options]``: a synthetic master/slave pair plus truth.json.

Writes ``DIR/master.<ext>``, ``DIR/slave.<ext>`` (through ``parsers.registry.write``; the extension is
the format module's first) and ``DIR/truth.json`` (atomically). Default formats: MCAP for the master
and tlog for the slave when those writers exist, canonical CSV otherwise.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys

from logtools.conventions import G0_M_S2
from logtools.errors import InputError
from parsers.assemble import LIMITS

DEFAULT_FORMATS = {"master": ("mcap", "csv"), "slave": ("tlog", "csv")}


def _floats(text: str, n: int, what: str, limit: float | None = None, unit: str = "") -> tuple[float, ...]:
    """``n`` comma-separated finite numbers, each within +-``limit`` where one is given."""
    try:
        vals = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise InputError(f"simulate: {what} needs {n} comma-separated numbers, got {text!r}") from None
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise InputError(f"simulate: {what} needs {n} comma-separated finite numbers, got {text!r}")
    if limit is not None and any(abs(v) > limit for v in vals):
        raise InputError(f"simulate: {what} beyond +-{limit:g} {unit} ({text}): the readers would drop such samples "
                         "as impossible values")
    return vals


#: the largest biases and lever arm simulate writes: a tenth of what the readers take for a corrupt value
#: (parsers.assemble.LIMITS: 175 rad/s, 5000 m/s^2), and a lever arm of a large ship's
MAX_GYRO_BIAS_DPH = math.degrees(LIMITS["gyro"] / 10) * 3600
MAX_ACCEL_BIAS_MG = LIMITS["accel"] / 10 / G0_M_S2 * 1000
MAX_LEVER_ARM_M = 500.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="ship, aircraft, vehicle or multirotor")
    from pipelines.cli import output_path

    p.add_argument("-o", "--out", required=True, type=output_path, help="output directory")
    p.add_argument("--duration", type=float, metavar="S", help="seconds (default 120)")
    p.add_argument("--seed", type=int, metavar="N", help="random seed (default 0)")
    p.add_argument("--latency", type=float, metavar="S", help="slave stamps late by S seconds")
    p.add_argument("--drift", type=float, metavar="PPM", help="slave clock rate error (ppm)")
    p.add_argument("--mount", metavar="R,P,Y",
                   help="mounting roll,pitch,yaw in deg (v_slave = R v_master); negative first value: "
                        "--mount=-1,0,0")
    p.add_argument("--lever-arm", metavar="X,Y,Z", help="slave position in the master body frame (m)")
    p.add_argument("--flexure", action="store_true", help="second-order Markov flexure (seed 000)")
    p.add_argument("--slave-clock", choices=("epoch", "boot"),
                   help="slave stamps on the epoch clock (default) or seconds since boot")
    p.add_argument("--master-rate", type=float, metavar="HZ", help="master IMU rate (default 200)")
    p.add_argument("--master-nav-rate", type=float, metavar="HZ", help="master nav rate (default 100)")
    p.add_argument("--slave-rate", type=float, metavar="HZ", help="slave IMU rate (default 200)")
    p.add_argument("--slave-nav-rate", type=float, metavar="HZ", help="slave nav rate (default 50)")
    p.add_argument("--no-slave-nav", action="store_true", help="the slave logs IMU only")
    p.add_argument("--gyro-bias", metavar="X,Y,Z", help="slave gyro bias (deg/h)")
    p.add_argument("--accel-bias", metavar="X,Y,Z", help="slave accel bias (mg)")
    p.add_argument("--noiseless", action="store_true", help="no sensor/nav errors, noise or jitter")
    p.add_argument("--master-format", metavar="FMT", help="default mcap if writable, else csv")
    p.add_argument("--slave-format", metavar="FMT", help="default tlog if writable, else csv")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="any SimConfig field, e.g. --set heave_amp_m=1 --set slave_jitter_s=1e-4")


def _default_format(role: str) -> str:
    from parsers.registry import format_by_name

    for name in DEFAULT_FORMATS[role]:
        try:
            if hasattr(format_by_name(name), "write"):
                return name
        except InputError:
            continue
    return "csv"


def _parse_set(items: list[str]) -> dict:
    from logtools.sim import SimConfig

    types = {f.name: f for f in dataclasses.fields(SimConfig)}
    out: dict = {}
    for item in items:
        key, sep, val = item.partition("=")
        key = key.strip()
        if not sep or key not in types:
            raise InputError(f"simulate: --set needs FIELD=VALUE with a SimConfig field, got {item!r}")
        default = types[key].default
        try:
            if isinstance(default, bool):
                if val.lower() not in ("1", "0", "true", "false", "yes", "no"):
                    raise ValueError(val)
                out[key] = val.lower() in ("1", "true", "yes")
            elif isinstance(default, int) and not isinstance(default, bool):
                out[key] = int(val)
            elif isinstance(default, float):
                out[key] = float(val)
            elif key == "slave_gaps_s":
                out[key] = tuple(tuple(float(x) for x in g) for g in json.loads(val))
            elif isinstance(default, tuple):
                out[key] = tuple(float(x) for x in val.split(","))
            elif default is None:
                out[key] = None if val.lower() in ("", "none") else float(val)
            else:
                out[key] = val
        except (ValueError, TypeError, json.JSONDecodeError):
            raise InputError(f"simulate: bad value for {key}: {val!r}") from None
    return out


def config_from_args(args: argparse.Namespace):
    from logtools import sim

    ov: dict = {}
    simple = {"duration": "duration_s", "seed": "seed", "latency": "latency_s", "drift": "drift_ppm",
              "slave_clock": "slave_clock", "master_rate": "master_imu_rate_hz",
              "master_nav_rate": "master_nav_rate_hz", "slave_rate": "slave_imu_rate_hz",
              "slave_nav_rate": "slave_nav_rate_hz"}
    for arg, fld in simple.items():
        v = getattr(args, arg)
        if v is not None:
            ov[fld] = v
    if args.mount is not None:
        ov["mount_rpy_deg"] = _floats(args.mount, 3, "--mount")
    if args.lever_arm is not None:
        ov["lever_arm_m"] = _floats(args.lever_arm, 3, "--lever-arm", MAX_LEVER_ARM_M, "m")
    if args.gyro_bias is not None:
        ov["slave_gyro_bias_dph"] = _floats(args.gyro_bias, 3, "--gyro-bias", MAX_GYRO_BIAS_DPH, "deg/h")
    if args.accel_bias is not None:
        ov["slave_accel_bias_mg"] = _floats(args.accel_bias, 3, "--accel-bias", MAX_ACCEL_BIAS_MG, "mg")
    if args.flexure:
        ov["flexure"] = True
    if args.no_slave_nav:
        ov["slave_nav"] = False
    ov.update(_parse_set(args.set))
    # a slower master IMU than its nav default: keep nav <= IMU unless asked explicitly
    base = sim.scenario_config(args.scenario)
    for imu, nav in (("master_imu_rate_hz", "master_nav_rate_hz"), ("slave_imu_rate_hz", "slave_nav_rate_hz")):
        if imu in ov and nav not in ov and ov[imu] < getattr(base, nav):
            ov[nav] = ov[imu]
    cfg = sim.scenario_config(args.scenario, **ov)
    return cfg.noiseless() if args.noiseless else cfg


def _as_written(truth, role: str, log, path: str, fmt: str):
    """(truth, note): ``truth`` for the stamps of ``path`` as a reader sees them. A log simulated on UNIX time
    that its format can only put on UNIX time through records it does not hold (a DataFlash log without GPS
    records: a slave without nav) is written on its time since boot; truth.json then gives the latency
    with that clock's offset in it (as for ``--slave-clock boot``), measured on the file read back."""
    import numpy as np

    from parsers import registry

    if log.meta.clock != "epoch" or not len(log.imu):
        return truth, ""
    try:
        back = registry.load(path)
    except InputError:  # (not readable as a whole: the truth as simulated; analyze says what is wrong)
        return truth, ""
    if back.meta.clock == "epoch" or not len(back.imu):
        return truth, ""
    n = min(len(back.imu), len(log.imu))
    t_sim = log.meta.t0_ns + np.round(log.t_imu_s()[:n] * 1e9).astype(np.int64)
    t_back = back.meta.t0_ns + np.round(back.t_imu_s()[:n] * 1e9).astype(np.int64)
    off = int(np.round(np.median((t_back - t_sim).astype(float))))  # (the format's stamp resolution: < 1 us)
    sign = 1 if role == "slave" else -1  # (latency = slave stamp - master stamp)
    truth = dataclasses.replace(truth, latency_s=truth.latency_s + sign * off * 1e-9,
                                clock_offset_s=truth.clock_offset_s + sign * off * 1e-9,
                                clock_offset_ns=truth.clock_offset_ns + sign * off,
                                **{f"{role}_clock": back.meta.clock,
                                   f"{role}_t0_ns": int(getattr(truth, f"{role}_t0_ns") + off)})
    return truth, (f"the {role} was simulated on UNIX time, but {os.path.basename(path)} is on its boot clock "
                   f"(a {fmt} log puts its stamps on UNIX time only through records this one does not hold, such "
                   f"as DataFlash's GPS records without nav): truth.json's latency includes that clock's offset "
                   f"({off * 1e-9:+.6f} s)")


def run(args: argparse.Namespace) -> int:
    from logtools import sim
    from parsers import registry
    from parsers.atomic import atomic_path

    cfg = config_from_args(args)
    fmts = {"master": args.master_format or _default_format("master"),
            "slave": args.slave_format or _default_format("slave")}
    mods = {role: registry.format_by_name(f) for role, f in fmts.items()}
    for role, mod in mods.items():
        if not hasattr(mod, "write"):
            raise InputError(f"simulate: format {mod.NAME} cannot be written (--{role}-format)")
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise InputError("output exists and is not a directory", args.out)
    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output directory: {exc.strerror or exc}", args.out) from None
    targets = [f"{role}{mods[role].EXTENSIONS[0]}" for role in ("master", "slave")] + ["truth.json"]
    there = [name for name in targets if os.path.lexists(os.path.join(args.out, name))]
    if there:  # (said: a folder of real logs given by mistake is not changed unnoticed)
        print(f"note: {', '.join(there)} in {args.out} existed and are replaced", file=sys.stderr)
    pair = sim.simulate(cfg)
    paths = {}
    for role, log in (("master", pair.master), ("slave", pair.slave)):
        path = os.path.join(args.out, f"{role}{mods[role].EXTENSIONS[0]}")
        try:
            registry.write(path, log, fmts[role])
        except OSError as exc:
            raise InputError(f"cannot write: {exc.strerror or exc}", path) from None
        paths[role] = path
    truth_obj = pair.truth
    for role, log in (("master", pair.master), ("slave", pair.slave)):
        truth_obj, said = _as_written(truth_obj, role, log, paths[role], fmts[role])
        if said:
            print(f"note: {said}")
    truth = truth_obj.to_dict()
    truth["files"] = {"master": os.path.basename(paths["master"]), "slave": os.path.basename(paths["slave"]),
                      "master_format": fmts["master"], "slave_format": fmts["slave"]}
    tpath = os.path.join(args.out, "truth.json")
    with atomic_path(tpath) as tmp, open(tmp, "w") as fh:
        json.dump(truth, fh, indent=2)
        fh.write("\n")
    print(f"{cfg.scenario}: {cfg.duration_s:g} s, latency {truth['latency_s']:.6f} s, drift "
          f"{cfg.drift_ppm:g} ppm, mount {list(cfg.mount_rpy_deg)} deg")
    print(f"  master: {paths['master']} ({fmts['master']}, {len(pair.master.imu)} imu, {len(pair.master.nav)} nav)")
    print(f"  slave:  {paths['slave']} ({fmts['slave']}, {len(pair.slave.imu)} imu, {len(pair.slave.nav)} nav)")
    print(f"  truth:  {tpath}")
    return 0
