"""report.json: the machine-readable result of one analyzed pair (DESIGN.md, "report.json contract").

Schema "tapost.report/1" (``pipelines/report_schema.json``). Keys are extended, never renamed.
A step the data could not support is recorded, never faked: a failed latency estimate is
``latency = {"failed": reason, latency_s: null, ...}``; a skipped alignment run is
``{"skipped": reason, "filter": .., "match": ..}``. JSON never holds NaN or Infinity (``null`` instead).
"""
from __future__ import annotations

import datetime as _dt
import json
import math
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import numpy as np

from logtools import __version__
from logtools.conventions import dcm_from_euler
from logtools.inslog import InsLog
from logtools.results import AlignmentResult, LatencyResult
from parsers.atomic import atomic_path

SCHEMA = "tapost.report/1"
RUNS = ("uncompensated", "compensated")
TIMING_KEYS = ("parse", "latency", "compensate", "alignment", "report", "recording", "total")


@dataclass
class Analysis:
    """Everything the outputs (report.json, report.html, recording.rrd) are drawn from.

    ``slave_comp`` is the slave on the master's clock after compensation (None if latency failed);
    ``alignment`` maps run name ("uncompensated", "compensated") to its result, or None if skipped.
    All times are master-relative seconds (``master.meta.t0_ns``).
    """

    master: InsLog
    slave: InsLog
    slave_comp: InsLog | None = None
    latency: LatencyResult | None = None
    alignment: dict[str, AlignmentResult | None] = field(default_factory=dict)

    def slave_face_value(self) -> InsLog:
        """The slave with its stamps taken at face value, expressed on the master's origin."""
        return self.slave.rebased(self.master.meta.t0_ns)

    def mounting(self) -> tuple[np.ndarray, str]:
        """(R, source) with ``v_slave = R @ v_master``: best available estimate, identity if none."""
        for run in ("compensated", "uncompensated"):
            res = self.alignment.get(run)
            if res is not None and all(np.isfinite(res.mounting_rpy_deg)):
                return dcm_from_euler(np.radians(res.mounting_rpy_deg)), f"alignment ({run})"
        if self.latency is not None and self.latency.mounting_rpy_deg is not None:
            rpy = np.asarray(self.latency.mounting_rpy_deg, float)
            if np.all(np.isfinite(rpy)):
                return dcm_from_euler(np.radians(rpy)), "latency (angular-rate fit)"
        return np.eye(3), "none (identity assumed)"


# ---- JSON hygiene ----------------------------------------------------------------------------
def json_safe(obj: Any) -> Any:
    """Plain JSON types only: numpy -> python, NaN/inf -> None, tuples -> lists, keys -> str."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return [json_safe(v) for v in obj.tolist()]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if obj is None or isinstance(obj, str):
        return obj
    return str(obj)


def _num(x: Any) -> float | None:
    if x is None:
        return None
    try:
        f = float(x)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _vec(v: Any) -> list[float | None] | None:
    return None if v is None else [_num(x) for x in v]


# ---- sections --------------------------------------------------------------------------------
def log_section(log: InsLog) -> dict:
    """master/slave section: where the data came from, its clock, channels and warnings."""
    m = log.meta
    a, b = log.span_s()
    return {
        "path": m.source_path,
        "format": m.format,
        "selector": m.selector,
        "clock": m.clock,
        "stamp_source": m.stamp_source,
        "t0_ns": int(m.t0_ns),
        "start_s": _num(m.t0_ns * 1e-9 + a) if math.isfinite(a) else None,
        "duration_s": _num(log.duration_s),
        "channels": {name: {"rate_hz": _num(ch.rate_hz), "count": int(ch.count), "source": ch.source}
                     for name, ch in m.channels.items()},
        "contents": {"gyro": log.has_gyro, "accel": log.has_accel, "quat": log.has_quat,
                     "vel": log.has_vel, "pos": log.has_pos},
        "warnings": list(m.warnings),
    }


LATENCY_KEYS = ("latency_s", "sigma_s", "drift_ppm", "method", "window_s", "quality", "methods")


def latency_section(lat: LatencyResult) -> dict:
    return {
        "latency_s": _num(lat.latency_s),
        "sigma_s": _num(lat.sigma_s),
        "drift_ppm": _num(lat.drift_ppm),
        "method": lat.method,
        "window_s": _vec(lat.window_s),
        "quality": json_safe(dict(lat.quality)),
        "methods": {name: {"latency_s": _num(me.latency_s), "sigma_s": _num(me.sigma_s),
                           **({"note": me.note} if me.note else {})}
                    for name, me in lat.methods.items()},
        "mounting_rpy_deg": _vec(lat.mounting_rpy_deg),
        "t_mid_rel_s": _num(lat.t_mid_rel_s),
        "windows": int(len(lat.window_latency_s)),
    }


def latency_failed(reason: str, method: str = "tapost") -> dict:
    """The latency section when the estimate failed: every number null, the reason stated."""
    return {"failed": reason, "latency_s": None, "sigma_s": None, "drift_ppm": None, "method": method,
            "window_s": None, "quality": {}, "methods": {}}


def _undetermined_mounting(res: AlignmentResult) -> dict[str, str]:
    """Mounting axes the data did not determine (their sigma never shrank from the prior): axis -> reason."""
    return {ax: "not observable with this motion: its sigma did not shrink from the prior, so the value "
                "would be the prior, not an estimate"
            for ax in ("roll", "pitch", "yaw") if res.observability.get(f"mounting_{ax}") is False}


def alignment_section(res: AlignmentResult) -> dict:
    """One run's section. A mounting axis the data did not determine is null (DESIGN.md: never the prior),
    its reason in ``mounting_not_determined``."""
    undetermined = _undetermined_mounting(res)
    mount = _vec(res.mounting_rpy_deg)
    if mount is not None:
        mount = [None if ax in undetermined else x for ax, x in zip(("roll", "pitch", "yaw"), mount)]
    sec = {
        "filter": res.filter,
        "match": res.match,
        "mounting_rpy_deg": mount,
        "mounting_sigma_deg": _vec(res.mounting_sigma_deg),
        "gyro_bias_dph": _vec(res.gyro_bias_dph),
        "accel_bias_mg": _vec(res.accel_bias_mg),
        "gyro_bias_sigma_dph": _vec(res.gyro_bias_sigma_dph),
        "accel_bias_sigma_mg": _vec(res.accel_bias_sigma_mg),
        "converged_s": _num(res.converged_s),
        "residual_rms": {k: _num(v) for k, v in res.residual_rms.items()},
        "delay_s": _num(res.delay_s),
        "delay_sigma_s": _num(res.delay_sigma_s),
        "lever_arm_m": _vec(res.lever_arm_m),
        "lever_arm_sigma_m": _vec(res.lever_arm_sigma_m),
        "observability": {k: bool(v) for k, v in res.observability.items()},
        "notes": list(res.notes),
        "states": list(res.history_names),
    }
    if undetermined:
        sec["mounting_not_determined"] = undetermined
    return sec


def alignment_skipped(reason: str, filter: str, match: str) -> dict:
    return {"skipped": reason, "filter": filter, "match": match}


def now_utc() -> str:
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def build_report(
    master: InsLog,
    slave: InsLog,
    *,
    latency: LatencyResult | dict,
    alignment: dict[str, AlignmentResult | dict],
    timings_s: dict[str, float],
    options: dict | None = None,
    extra: dict | None = None,
) -> dict:
    """Assemble the report dict. ``latency``/``alignment`` values are results or ready sections
    (``latency_failed(..)``, ``alignment_skipped(..)``)."""
    lat = latency_section(latency) if isinstance(latency, LatencyResult) else dict(latency)
    align = {run: (alignment_section(r) if isinstance(r, AlignmentResult) else dict(r))
             for run, r in alignment.items()}
    skipped = {}
    if "failed" in lat:
        skipped["latency"] = lat["failed"]
    for run, sec in align.items():
        if "skipped" in sec:
            skipped[f"alignment.{run}"] = sec["skipped"]
    status = "failed" if "failed" in lat else ("partial" if skipped else "ok")
    rep = {
        "schema": SCHEMA,
        "tapost_version": __version__,
        "created_utc": now_utc(),
        "status": status,
        "master": log_section(master),
        "slave": log_section(slave),
        "latency": lat,
        "alignment": align,
        "skipped": skipped,
        "options": json_safe(options or {}),
        "timings_s": {k: _num(v) for k, v in timings_s.items()},
    }
    if extra:
        rep.update(json_safe(extra))
    return json_safe(rep)


# ---- IO and validation ------------------------------------------------------------------------
def dumps(report: dict) -> str:
    return json.dumps(json_safe(report), indent=2, allow_nan=False) + "\n"


def write_text_atomic(path: str, text: str) -> None:
    """Write a text file atomically (temp file + rename), with the usual permissions."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)


def write_report(path: str, report: dict) -> None:
    """Write report.json atomically (temp file + rename)."""
    write_text_atomic(path, dumps(report))


def load_schema() -> dict:
    """The JSON Schema (draft 2020-12) of "tapost.report/1", shipped as package data."""
    return json.loads(resources.files("pipelines").joinpath("report_schema.json").read_text("utf-8"))


def validate(report: dict) -> None:
    """Raise ``jsonschema.ValidationError`` if ``report`` does not follow the schema."""
    import jsonschema

    jsonschema.Draft202012Validator(load_schema()).validate(report)


def is_complete(path: str) -> bool:
    """True if ``path`` holds a parseable report of this schema (used by batch to skip work)."""
    try:
        with open(path, encoding="utf-8") as fh:
            rep = json.load(fh)
    except (OSError, ValueError):
        return False
    return isinstance(rep, dict) and rep.get("schema") == SCHEMA
