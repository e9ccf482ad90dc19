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
import re
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import numpy as np

from logtools import __version__
from logtools.conventions import dcm_from_euler, dcm_from_quat
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
                mat = dcm_from_euler(np.radians(res.mounting_rpy_deg))
                q = res.mounting_quat_wxyz  # the exact rotation, where the triple is the gimbal lock's canonical one
                if q is not None and np.abs(dcm_from_quat(np.asarray(q, float)) - mat).max() > 1e-9:
                    mat = dcm_from_quat(np.asarray(q, float))
                return mat, f"alignment ({run})"
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


#: what the summary and report.html say beside a rotation whose Euler angles are the gimbal lock's canonical
#: triple (``imu_to_imu``'s ``*_gimbal_lock``)
GIMBAL_LOCK_SAID = ("gimbal lock: the pitch lies within its uncertainty of +-90 deg, where roll and yaw turn about "
                    "one axis and cannot be told apart; shown with roll 0 and the combined turn as yaw; the rotation "
                    "itself is {quat} in report.json")


LATENCY_KEYS = ("latency_s", "sigma_s", "drift_ppm", "method", "window_s", "quality", "methods")


def latency_section(lat: LatencyResult) -> dict:
    return {
        "latency_s": _num(lat.latency_s),
        "sigma_s": _num(lat.sigma_s),
        "drift_ppm": _num(lat.drift_reported_ppm),  # (null where not estimated: quality.drift_not_estimated)
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
        # the exact rotation (mounting_rpy_deg is the canonical triple at the gimbal lock); null where an
        # axis is not determined (it would hold the prior there)
        "mounting_quat_wxyz": None if undetermined else _vec(res.mounting_quat_wxyz),
        "gyro_bias_dph": _vec(res.gyro_bias_dph),
        "accel_bias_mg": _vec(res.accel_bias_mg),
        "gyro_bias_sigma_dph": _vec(res.gyro_bias_sigma_dph),
        "accel_bias_sigma_mg": _vec(res.accel_bias_sigma_mg),
        "converged_s": _num(res.converged_s),
        # the sigma still fell at the end of the run (AlignmentConfig.settle_fall_ratio): more data would tighten it
        "still_converging": res.still_converging,
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
    # the other states likewise: an axis whose sigma did not shrink from its prior holds the prior, not an
    # estimate (DESIGN.md: null, never the prior); which ones in ``states_not_determined``, the note says why
    prior_held = []
    for state, key in (("gyro_bias", "gyro_bias_dph"), ("accel_bias", "accel_bias_mg"), ("lever_arm", "lever_arm_m")):
        vals = sec.get(key)
        if vals is None or res.lever_arm_sigma_m is None and state == "lever_arm":  # (a lever arm as given)
            continue
        axes = [i for i, ax in enumerate("xyz") if res.observability.get(f"{state}_{ax}") is False]
        if axes:
            sec[key] = [None if i in axes else x for i, x in enumerate(vals)]
            prior_held += [f"{state}_{'xyz'[i]}" for i in axes]
    if res.observability.get("delay") is False and sec.get("delay_s") is not None:
        sec["delay_s"] = None
        prior_held.append("delay")
    if prior_held:
        sec["states_not_determined"] = prior_held
    return sec


def alignment_skipped(reason: str, filter: str, match: str, *, applies: bool = True) -> dict:
    """A run not done, and why. ``applies=False``: the run has no meaning for this pair (the uncompensated run
    of logs on different clocks): not counted in ``skipped``, said as a note."""
    # (the contract's RESULT keys all present, null: a reader of mounting_rpy_deg gets null, not a KeyError)
    return {"skipped": reason, "filter": filter, "match": match, "mounting_rpy_deg": None, "mounting_sigma_deg": None,
            "gyro_bias_dph": None, "accel_bias_mg": None, "converged_s": None, "residual_rms": {},
            **({} if applies else {"not_applicable": True})}


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
        if "skipped" in sec and not sec.get("not_applicable"):
            skipped[f"alignment.{run}"] = sec["skipped"]
    status = "failed" if "failed" in lat else ("partial" if skipped else "ok")
    reasons = clock_step_reasons(lat, master, slave)
    if reasons and status == "ok":
        status = "partial"
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
    if reasons:
        rep["status_reason"] = "; ".join(reasons)
    if extra:
        rep.update(json_safe(extra))
    rep = json_safe(rep)
    add_findings(rep)
    return rep


def _ms(x: float) -> str:
    """Seconds as signed milliseconds, to 0.1 ms (0.01 below 10 ms)."""
    return f"{x * 1e3:+.1f} ms" if abs(x) >= 0.01 else f"{x * 1e3:+.2f} ms"


def clock_step_words(step: dict) -> str:
    """``latency.quality.clock_step`` in words: the step, where, the latency either side."""
    t_rel, t_abs = _num(step.get("t_rel_s")), _num(step.get("t_s"))
    size, sig = _num(step.get("step_s")) or 0.0, _num(step.get("sigma_s"))
    before, after = _num(step.get("latency_before_s")), _num(step.get("latency_after_s"))
    where = (f" near {t_rel:.1f} s into the master log" if t_rel is not None else "") + (
        f" (stamp {t_abs:.3f} s)" if t_abs is not None else "")
    return (f"the latency steps by {_ms(size)}" + (f" +- {abs(sig) * 1e3:.2g} ms" if sig is not None else "")
            + f"{where}, a clock step or reset in one log: one latency and drift do not describe the pair"
            + (f"; before {_ms(before)}, after {_ms(after)}" if before is not None and after is not None else "")
            + "; analyse the parts apart")


def clock_step_reasons(lat: dict, master: InsLog, slave: InsLog) -> list[str]:
    """Why the status is not "ok" although every step ran: a clock step in the latency (its windows), or a
    log split at a clock step back or reset by its parser (only one part analysed)."""
    from parsers.assemble import CLOCK_STEP_WORDS

    out = []
    step = (lat.get("quality") or {}).get("clock_step") if "failed" not in lat else None
    if isinstance(step, dict):
        out.append(clock_step_words(step))
    for role, log in (("master", master), ("slave", slave)):
        if any(CLOCK_STEP_WORDS in w for w in log.meta.warnings):
            out.append(f"the {role} log's clock steps back or resets (see its warnings): only one part of it "
                       "was analysed")
    return out


# ---- warnings and notes ------------------------------------------------------------------------
#: a parser's line that says what was chosen, not what is wrong (they share ``meta.warnings``)
_NOTE_STARTS = ("note:", "no selector given", "selected ")
_NOTE_CONTAINS = (": picked ", "position from GPS")
#: an alignment note that is a warning: the estimate is doubtful or not an estimate at all
_ALIGN_WARN_CONTAINS = ("did not follow the data", "not determined", "not observable",
                        "larger than the noise model", "far beyond its prior", "updates skipped")
#: ``name (source): text`` lines of the parsers' stream checks (gaps, duplicates, NaNs...)
_STREAM_LINE = re.compile(r"^(\w+) \(([^()]*)\): (.+)$")


def _is_parse_note(text: str) -> bool:
    return text.startswith(_NOTE_STARTS) or any(c in text for c in _NOTE_CONTAINS)


def _merge_stream_lines(lines: list[str]) -> list[str]:
    """One line per problem: ``gyro (IMU): 1 gap(s)...`` on five channels -> ``1 gap(s)...: gyro (IMU),
    accel (IMU), ...``. Other lines are kept (exact repeats dropped), in their first order."""
    order: list[str] = []
    chans: dict[str, list[str]] = {}
    for text in lines:
        m = _STREAM_LINE.match(text)
        key = m.group(3) if m else text
        if key not in chans:
            order.append(key)
            chans[key] = []
        if m:
            chans[key].append(f"{m.group(1)} ({m.group(2)})")
    out = []
    for key in order:
        c = chans[key]
        out.append(key if not c else (f"{c[0]}: {key}" if len(c) == 1 else f"{key}: {', '.join(c)}"))
    return out


def _latency_flag_words(q: dict) -> list[str]:
    """The latency quality flags that limit the result, said in words."""
    out = []
    if q.get("too_little_motion"):
        snr, dps = _num(q.get("motion_snr")), _num(q.get("motion_dps"))
        fig = ", ".join(x for x in ((f"signal/noise {snr:.3g}" if snr is not None else ""),
                                    (f"motion {dps:.3g} deg/s" if dps is not None else "")) if x)
        if q.get("low_motion_cause") == "noise":  # (the motion is there: the noise drowns it)
            out.append(f"the sensors' noise is large against the motion ({fig}; vibration?): the latency and its "
                       "sigma are doubtful")
        else:
            out.append(f"too little motion for a reliable latency ({fig}): the estimate and its sigma are doubtful")
    if q.get("periodic"):
        alts = ", ".join(f"{x:+.4f} s" for x in (q.get("periodic_alternatives_s") or [])[:4] if _num(x) is not None)
        out.append("the motion repeats: other lags fit almost as well" + (f" ({alts})" if alts else "")
                   + "; the sigma covers their spread")
    step = q.get("clock_step")
    if isinstance(step, dict):
        out.append(clock_step_words(step))
    elif q.get("windows_disagree"):  # (a clock step says why, and more)
        chi = _num(q.get("window_chi2_red"))
        out.append("the latency differs between parts of the log beyond their sigmas"
                   + (f" (reduced chi-square {chi:.3g})" if chi is not None else ""))
    vf = q.get("velocity_fit")
    if q.get("velocity_disagrees") and isinstance(vf, dict):
        v = _num(vf.get("latency_s"))
        out.append("the velocities alone give a different latency"
                   + (f" ({v * 1e3:+.3f} ms)" if v is not None else "") + ": not used")
    return out


def findings(rep: dict) -> tuple[list[dict], list[dict]]:
    """(warnings, notes) of a report, each ``[{stage, text}]``: warnings say what may be wrong with the
    data or the results; notes say what was chosen or done. Warnings are deduplicated."""
    warns: list[dict] = []
    notes: list[dict] = []

    def add(kind: list[dict], stage: str, text: str) -> None:
        item = {"stage": stage, "text": str(text)}
        if item not in kind:
            kind.append(item)

    parsed: dict[str, tuple[list[str], list[str]]] = {}
    for role in ("master", "slave"):
        sec = rep.get(role) or {}
        ws, ns = [], []
        for w in sec.get("warnings", []) or []:
            (ns if _is_parse_note(w) else ws).append(w)
        parsed[role] = (_merge_stream_lines(ws), [n[5:].strip() if n.startswith("note:") else n for n in ns])
    for i, kind in ((0, warns), (1, notes)):
        m_list, s_list = parsed["master"][i], parsed["slave"][i]
        for text in m_list:  # the same line on both sides (one file, two units): said once
            add(kind, "parse", f"{'master and slave' if text in s_list else 'master'}: {text}")
        for text in s_list:
            if text not in m_list:
                add(kind, "parse", f"slave: {text}")
    if rep.get("latency_search"):
        add(notes, "latency", f"searched the {rep['latency_search']}")
    lat = rep.get("latency") or {}
    if "failed" in lat:
        add(warns, "latency", f"latency failed: {lat['failed']}")
    q = lat.get("quality") or {}
    for w in q.get("warnings", []) or []:
        add(warns, "latency", w)
    for w in _latency_flag_words(q):
        add(warns, "latency", w)
    if "failed" not in lat and lat.get("sigma_s") is None and lat.get("latency_s") is not None:
        add(warns, "latency", "the latency's sigma could not be determined")
    comp = rep.get("compensation") or {}
    if comp.get("skipped"):
        add(warns, "compensation", f"compensation skipped: {comp['skipped']}")
    al = rep.get("alignment") or {}
    why = [(al.get(run) or {}).get("skipped") for run in RUNS]
    if why[0] is not None and why[0] == why[1]:
        add(warns, "alignment", f"alignment skipped (both runs): {why[0]}")
    for run in RUNS:
        sec = al.get(run) or {}
        if "skipped" in sec:
            if why[0] != why[1] and not ("failed" in lat and run == "compensated"):
                add(notes if sec.get("not_applicable") else warns, "alignment",
                    f"{run} alignment skipped: {sec['skipped']}")
            continue
        for n in sec.get("notes", []) or []:
            bad = any(c in n for c in _ALIGN_WARN_CONTAINS)
            # the uncompensated run shows what the delay does: its trouble is expected, a note
            add(warns if bad and run == "compensated" else notes, "alignment", f"{run}: {n}")
        if sec.get("mounting_rpy_deg") and None in sec["mounting_rpy_deg"] and run == "compensated":
            add(warns, "alignment", f"{run}: the mounting was not determined")
        if run == "compensated" and sec.get("converged_s") is None:
            sig = sec.get("mounting_sigma_deg") or []
            at = ("" if not sig or None in sig else
                  " at " + "/".join(f"{60 * x:.2g}" for x in sig) + "' (roll/pitch/yaw)")
            if sec.get("still_converging") is False:  # settled above the thresholds: what the pair allows
                add(notes, "alignment", f"{run}: the mounting's sigma settled{at}, above the convergence "
                    "thresholds of a navigation-grade pair (converged_s null)")
            else:
                add(warns, "alignment", f"{run}: the mounting's sigma did not converge: it still fell over the "
                    f"last part of the log{at} (more motion or a longer log would tighten it)")
    for step, why in (rep.get("skipped") or {}).items():
        if not (step == "latency" or step.startswith("alignment.")):
            add(warns, "outputs", f"{step} skipped: {why}")
    # warnings a stage put in the report itself (the IMU-to-IMU consistency, an export's damage)
    for w in list(rep.get("warnings") or []):  # already set: by a stage, or by an earlier call (deduplicated)
        add(warns, w["stage"], w["text"])
    return warns, notes


def add_findings(rep: dict) -> dict:
    """Set the report's top-level ``warnings`` and ``notes`` (DESIGN.md) from its sections."""
    rep["warnings"], rep["notes"] = findings(rep)
    return rep


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


# ---- readings of a finished report (report.html and the batch's summary) --------------------------------
#: warnings that say an input file is damaged (truncated, corrupt): the worst kind, shown beside the status
_DAMAGE = re.compile(r"damag|truncat|corrupt|cut short|incomplete frame|bad crc|undecodable|bad bytes", re.I)


def warning_severity(stage: str, text: str) -> int:
    """3 a damaged input, 2 a step skipped or failed, 1 any other warning (notes are not warnings)."""
    if _DAMAGE.search(text):
        return 3
    if stage.startswith("skipped"):
        return 2
    return 1


def report_warnings(rep: dict) -> list[tuple[str, str]]:
    """Every warning of a report as (stage, text), notes left out.

    Uses the top-level ``warnings`` list of the report contract when the report has one; otherwise
    gathers them from the inputs' sections (their "note: ..." lines are notes), the latency quality
    and the skipped steps. A step that was skipped is a warning either way."""
    out: list[tuple[str, str]] = []
    top = rep.get("warnings")
    if isinstance(top, list):
        for w in top:
            if isinstance(w, dict):
                out.append((str(w.get("stage") or ""), str(w.get("text") or "")))
            else:
                out.append(("", str(w)))
    else:
        for role in ("master", "slave"):
            for w in (rep.get(role) or {}).get("warnings") or []:
                if not str(w).lower().startswith("note:"):
                    out.append((role, str(w)))
        for w in ((rep.get("latency") or {}).get("quality") or {}).get("warnings") or []:
            out.append(("latency", str(w)))
    seen = [t for _, t in out]
    for k, v in (rep.get("skipped") or {}).items():
        # (the contract's list says each skipped step in its own words, the reason quoted: counted once)
        if not any(str(v) in t for t in seen):
            out.append((f"skipped {k}", f"{k}: {v}"))
    return out


def input_damage(rep: dict) -> str:
    """The inputs' damage warnings as one line ("slave: truncated tlog: ..."), or "" when none."""
    parts = []
    for role in ("master", "slave"):
        parts += [f"{role}: {w}" for w in (rep.get(role) or {}).get("warnings") or [] if _DAMAGE.search(str(w))]
    if not parts and isinstance(rep.get("warnings"), list):  # the contract's list, stage naming the input
        parts = [f"{w.get('stage')}: {w.get('text')}" for w in rep["warnings"]
                 if isinstance(w, dict) and _DAMAGE.search(str(w.get("text")))]
    return "; ".join(parts)


def latency_instant(rep: dict) -> tuple[float | None, str | None]:
    """The instant ``latency_s`` is quoted at (the middle of the analysed window): absolute master
    seconds as logged (UNIX or boot), and as UTC (ISO 8601) when the master is on UNIX time."""
    lat, m = rep.get("latency") or {}, rep.get("master") or {}
    t = None
    if isinstance(lat.get("t_mid_rel_s"), (int, float)) and isinstance(m.get("t0_ns"), int):
        t = m["t0_ns"] * 1e-9 + lat["t_mid_rel_s"]
    elif isinstance(lat.get("window_s"), list) and None not in lat["window_s"][:2] and len(lat["window_s"]) >= 2:
        t = 0.5 * (lat["window_s"][0] + lat["window_s"][1])
    if t is None or lat.get("latency_s") is None:
        return None, None
    utc = None
    if m.get("clock") == "epoch":
        utc = _dt.datetime.fromtimestamp(t, _dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"
    return t, utc
