"""``tapost analyze MASTER SLAVE``: parse both logs -> latency -> compensation -> transfer alignment
(uncompensated: slave stamps at face value; compensated) -> report.json, report.html, recording.rrd.

Every output is written atomically; report.json is written last, so its presence marks a finished
analysis. A step the data cannot support is skipped with its reason (report.json "skipped" and the
summary), never faked. A failed latency estimate (no overlap, no motion, NaNs) is exit 1 with the
reason in one line; report.json (and report.html) still record the failure.

Options come from the command line, else from ``--config FILE`` (TOML or JSON, same names as the
long options with ``_`` for ``-``, top level or under an ``[analyze]`` table), else the defaults.
"""
from __future__ import annotations

import argparse
import importlib
import inspect
import json
import math
import numbers
import os
import re
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from logtools.alignment.options import CONFIG as ALIGNMENT_CONFIG
from logtools.alignment.options import FILTERS, AlignmentOptions, FilterKind, accepts_flexure_model
from logtools.alignment.options import MATCHES as ALIGNMENT_MATCHES
from logtools.compensate import METHODS as COMPENSATIONS
from logtools.errors import AnalysisError, InputError
from logtools.inslog import InsLog
from logtools.results import LATENCY_METHODS, AlignmentResult, LatencyResult
from logtools.units_check import scale_findings
from parsers import load
from pipelines import report as rp
from pipelines import parallel
from pipelines.firstrun import input_bytes
from pipelines.progress import Progress, null_progress

MATCHES = ("auto",) + ALIGNMENT_MATCHES  # auto: vel+att when the master has both, else what it has
REPORT, HTML, RECORDING = "report.json", "report.html", "recording.rrd"


@dataclass(frozen=True)
class Numerics:
    """The numerical stages an analysis calls; None: logtools' own, imported on first use (so the CLI starts
    without loading numba). Orchestration tests hand in light stand-ins through ``use_numerics``."""

    estimate: Callable | None = None  # logtools.latency.estimate
    compensate: Callable | None = None  # logtools.compensate.compensate
    run_alignment: Callable | None = None  # logtools.alignment.run_alignment


_numerics = Numerics()


def use_numerics(numerics: Numerics) -> Numerics:
    """Make ``numerics`` the stages of every later analysis in this process (and in processes forked from
    it); returns the ones before, to restore."""
    global _numerics
    before, _numerics = _numerics, numerics
    return before


def numerics_stage(name: str) -> Callable:
    """The stage ``name`` ("estimate", "compensate", "run_alignment") in use (ImportError if logtools' own
    cannot be loaded)."""
    fn = getattr(_numerics, name)
    if fn is not None:
        return fn
    if name == "estimate":
        from logtools.latency import estimate as fn
    elif name == "compensate":
        from logtools.compensate import compensate as fn
    else:
        from logtools.alignment import run_alignment as fn
    return fn


def _kernels_compiled() -> bool:
    """This process runs the compiled kernels (logtools.jit). They release the GIL, so that a second thread can
    run beside them (the reference code's Python holds it: the latency's velocity pair in a thread beside its
    rate fit made the sample pair's first run 0.25-0.3 s slower instead of faster)."""
    from logtools import jit

    return jit.compiled()


@dataclass(frozen=True)
class AnalyzeOptions:
    """What ``tapost analyze`` does. ``max_lag_s=None`` searches the whole overlap (``--max-lag auto``)."""

    max_lag_s: float | None = 2.0
    filter: str = "kf"
    match: str = "auto"  # auto: vel+att when the master has both, else what it has
    compensation: str = "restamp"  # the slave's own samples, stamps corrected (nothing resampled)
    smoother: bool = False
    recording: bool = True
    html: bool = True  # report.html (report.json is always written)
    latency_method: str = "tapost"
    compare: bool = True  # also run the seeds' latency methods (report.json latency.methods)
    recording_max_rows: int = 100_000
    #: the search window was set by the user (CLI/config); when it was not and the two logs are on
    #: unrelated clocks (UNIX vs boot time), a face-value window means nothing and the whole overlap is
    #: searched instead (recorded in the report)
    max_lag_given: bool = False
    #: the slave's position in the master's body frame for the alignment: "auto" (estimated as filter
    #: states when velocity is matched, started from the latency's velocity fit), "X,Y,Z" in metres
    #: (known, not estimated) or "off" (not modelled)
    lever_arm: str = "auto"
    #: flexure states in the alignment: "auto" (when the latency fit found flexure, with its model; else
    #: seed 000's when the alignment's residuals call for them), "on" (that model, else seed 000's
    #: 0.05 deg / 2 1/s), "off"
    flexure: str = "auto"
    #: a consumer board's errors in the alignment: "on" (the master's attitude error as a first-order
    #: Markov process and the slave's accelerometer triad misalignment as states, the sigmas widened by the
    #: residuals' correlation time; for an autopilot's EKF or AHRS as the master), "off" (a
    #: navigation-grade master), "auto" (off unless that run's innovations are correlated in time; then on)
    board_errors: str = "auto"
    #: also write the slave on the master's clock: any of "csv", "parquet", "native" (pipelines.export)
    write_slave: tuple[str, ...] = ()
    name: str | None = None  #: the pair's name (tapost batch): the recording is "tapost: <name>"

    def __post_init__(self):
        parse_lever_arm(self.lever_arm)
        if self.flexure not in FLEXURE_MODES:
            raise InputError(f"--flexure takes {', '.join(FLEXURE_MODES)}, not {self.flexure!r}")
        if self.board_errors not in BOARD_MODES:
            raise InputError(f"--board-errors takes {', '.join(BOARD_MODES)}, not {self.board_errors!r}")
        for name, allowed in (("filter", FILTERS), ("match", MATCHES), ("compensation", COMPENSATIONS),
                              ("latency_method", LATENCY_METHODS)):
            if getattr(self, name) not in allowed:
                raise InputError(f"{name} must be one of {', '.join(allowed)}, not {getattr(self, name)!r}")
        if self.max_lag_s is not None and not (self.max_lag_s > 0 and np.isfinite(self.max_lag_s)):
            raise InputError(f"max lag must be a positive number of seconds or 'auto', not {self.max_lag_s!r}")
        if self.compensation == "split" and not FilterKind.parse(self.filter).splits_delay:
            # (S004's split shifts the slave by whole samples and leaves the rest to kf-split's delay state:
            # with another filter that rest, up to half a sample, stayed in the slave without a word)
            raise InputError(f"--compensation split leaves the delay under one sample to the kf-split filter's "
                             f"delay state; with --filter {self.filter} it would stay in the slave: use --filter "
                             "kf-split with it, or another compensation")


@dataclass
class PairOutcome:
    report: dict
    out_dir: str
    paths: dict[str, str | None]
    summary: list[str] = field(default_factory=list)
    exit_code: int = 0


# ---- options --------------------------------------------------------------------------------
def parse_max_lag(text) -> float | None:
    if text is None:
        return None
    if isinstance(text, (bool, np.bool_)):  # (true is no number of seconds: it was taken for 1 s)
        raise InputError(f"--max-lag takes seconds or 'auto', not {text!r}")
    if isinstance(text, str) and text.strip().lower() == "auto":
        return None
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise InputError(f"--max-lag takes seconds or 'auto', not {text!r}") from None
    if not (v > 0 and np.isfinite(v)):
        raise InputError(f"--max-lag must be positive, not {text!r}")
    return v


FLEXURE_MODES = ("auto", "on", "off")
BOARD_MODES = ("auto", "on", "off")


def parse_lever_arm(text) -> str | tuple[float, float, float]:
    """--lever-arm: 'auto', 'off', or X,Y,Z metres (``options_from`` joins a config file's list)."""
    t = str(text).strip().lower()
    if t in ("auto", "off"):
        return t
    try:
        xyz = tuple(float(x) for x in t.split(","))
    except ValueError:
        xyz = ()
    if len(xyz) != 3 or not all(np.isfinite(xyz)):
        raise InputError(f"--lever-arm takes auto, off or X,Y,Z in metres (master body frame), not {text!r}")
    return xyz


def read_config(path: str) -> dict:
    """TOML or JSON config -> {option: value}; top level or an ``analyze`` table."""
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except OSError as exc:
        raise InputError(f"cannot read config: {exc.strerror}", path) from None
    if raw.startswith(b"\xef\xbb\xbf"):  # (a UTF-8 byte order mark, as some editors write: not the file's text)
        raw = raw[3:]
    import tomllib  # (here alone: only a run with --config reads one)

    try:
        data = json.loads(raw) if raw.lstrip()[:1] in (b"{",) else tomllib.loads(raw.decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        try:  # (a JSON array starts as a TOML table header does)
            data = json.loads(raw) if raw.lstrip()[:1] == b"[" else None
        except ValueError:
            data = None
        if data is None:
            raise InputError(f"config is neither valid TOML nor JSON: {str(exc).splitlines()[0]}", path) from None
    if not isinstance(data, dict):
        raise InputError(f"config must hold a table of options (TOML) or a JSON object, not a {type(data).__name__}",
                         path)
    if isinstance(data.get("analyze"), dict):
        data = {**{k: v for k, v in data.items() if k != "analyze"}, **data["analyze"]}
    config = {str(k).replace("-", "_"): v for k, v in data.items()}
    try:  # (every value checked here, so that a bad one is said with the file's name)
        options_from({}, config)
    except InputError as exc:
        raise InputError(exc.problem, path) from None
    return config


_CONFIG_KEYS = {"max_lag", "filter", "match", "compensation", "smoother", "no_recording", "recording",
                "no_html", "html",
                "latency_method", "compare", "out", "recording_max_rows", "lever_arm", "flexure", "board_errors",
                "write_slave"}


#: the analysis options add_arguments defines (argparse dests), as options_from takes them
CLI_KEYS = ("max_lag", "filter", "match", "compensation", "smoother", "no_recording", "no_html", "latency_method",
            "compare", "lever_arm", "flexure", "board_errors", "write_slave")


def cli_values(ns: argparse.Namespace) -> dict:
    """The analysis options of parsed arguments (None: not given)."""
    return {k: getattr(ns, k, None) for k in CLI_KEYS}


def options_from(cli: dict, config: dict | None = None) -> tuple[AnalyzeOptions, str | None]:
    """Merge CLI values (None = not given) over config values over defaults -> (options, out dir)."""
    config = dict(config or {})
    unknown = set(config) - _CONFIG_KEYS
    if unknown:
        raise InputError(f"unknown config option(s): {', '.join(sorted(unknown))}; "
                         f"known: {', '.join(sorted(_CONFIG_KEYS))}")
    merged = {**config, **{k: v for k, v in cli.items() if v is not None}}
    kw: dict = {}
    if "max_lag" in merged:
        kw["max_lag_s"] = parse_max_lag(merged["max_lag"])
        kw["max_lag_given"] = True
    for k in ("filter", "match", "compensation", "latency_method", "flexure", "board_errors"):
        if k in merged:
            kw[k] = str(merged[k])
    flags = {k: _flag(k, merged[k]) for k in ("smoother", "compare", "recording", "no_recording", "html", "no_html")
             if k in merged}
    for k in ("smoother", "compare", "recording", "html"):
        if k in flags:
            kw[k] = flags[k]
    if flags.get("no_recording"):
        kw["recording"] = False
    if flags.get("no_html"):
        kw["html"] = False
    if kw.get("filter") in FILTERS and FilterKind.parse(kw["filter"]).splits_delay and "compensation" not in kw:
        kw["compensation"] = "split"  # S004: integer-sample lag applied, the residual left to the delay state
    if "write_slave" in merged:
        from pipelines.export import KINDS, parse_kinds

        kw["write_slave"] = parse_kinds(merged["write_slave"])
        if not kw["write_slave"] and cli.get("write_slave") is not None:  # (--write-slave= from an empty variable)
            raise InputError(f"--write-slave names nothing to write ({', '.join(KINDS)}, comma-separated)")
    if "recording_max_rows" in merged:
        kw["recording_max_rows"] = _whole_rows("recording_max_rows", merged["recording_max_rows"])
    if "lever_arm" in merged:
        la = merged["lever_arm"]
        kw["lever_arm"] = ",".join(str(x) for x in la) if isinstance(la, (list, tuple)) else str(la)
    out = merged.get("out")
    if out is not None and not isinstance(out, (str, os.PathLike)):
        raise InputError(f"out takes a folder path, not {out!r}")
    if isinstance(out, str) and not out.strip():
        raise InputError("out is an empty path: give a folder, or leave it out for tapost_out/")
    return AnalyzeOptions(**kw), out


def _flag(key: str, value) -> bool:
    """A switch's value: true or false (TOML, JSON, Python), or 0 or 1; anything else is refused (the string
    "false" is not taken for true)."""
    if isinstance(value, (bool, np.bool_)) or (isinstance(value, numbers.Integral) and value in (0, 1)):
        return bool(value)
    raise InputError(f"{key} takes true or false, not {value!r}")


def _whole_rows(key: str, value) -> int:
    if not isinstance(value, (bool, float)):
        try:
            n = int(value)
        except (TypeError, ValueError):
            n = 0
        if n >= 1:
            return n
    raise InputError(f"{key} takes a whole number of rows (at least 1), not {value!r}")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from pipelines.cli import output_path

    p.add_argument("master", help="master log, PATH[::SELECTOR]")
    p.add_argument("slave", help="slave log, PATH[::SELECTOR]")
    p.add_argument("-o", "--out", default=None, type=output_path, help="output directory (default tapost_out/)")
    p.add_argument("--max-lag", default=None, metavar="S|auto",
                   help="latency search half-width in seconds (default 2), or 'auto' for the whole overlap")
    p.add_argument("--filter", default=None, choices=FILTERS, help="alignment filter (default kf)")
    p.add_argument("--match", default=None, choices=MATCHES,
                   help="alignment measurements (default auto: vel+att when the master has both)")
    p.add_argument("--compensation", default=None, choices=COMPENSATIONS,
                   help="how the slave is put on the master's clock (default restamp: the slave's own "
                        "samples with corrected stamps; split with --filter kf-split)")
    p.add_argument("--smoother", action="store_const", const=True, default=None,
                   help="run the RTS smoother after the filter")
    p.add_argument("--latency-method", default=None, choices=LATENCY_METHODS,
                   help="method whose estimate is used (default tapost)")
    p.add_argument("--no-compare", dest="compare", action="store_const", const=False, default=None,
                   help="do not also run the other latency methods")
    p.add_argument("--no-recording", action="store_const", const=True, default=None,
                   help="do not write recording.rrd")
    p.add_argument("--no-html", action="store_const", const=True, default=None,
                   help="do not write report.html (report.json is always written)")
    p.add_argument("--lever-arm", default=None, metavar="auto|off|X,Y,Z",
                   help="slave position in the master body frame (FRD, m) for the alignment: auto (default: "
                        "estimated where velocity is matched), off, or known X,Y,Z")
    p.add_argument("--flexure", default=None, choices=FLEXURE_MODES,
                   help="flexure states in the alignment: auto (default: with the latency fit's flexure "
                        "model when it found one, else when the residuals call for them), on, off")
    p.add_argument("--board-errors", default=None, choices=BOARD_MODES,
                   help="on: the master is a consumer-grade EKF/AHRS (an autopilot): its attitude error "
                        "(correlated in time) and the slave's accelerometer triad misalignment become "
                        "alignment states and the sigmas honest for them; off: a navigation-grade master; "
                        "auto (default): off, then on where that run's innovations are correlated in time")
    p.add_argument("--write-slave", default=None, metavar="csv|parquet|native[,...]",
                   help="also write the slave on the master's clock next to the report "
                        "(slave_on_master_clock.*: canonical CSV, Parquet, and/or the slave's own format)")
    p.add_argument("--config", default=None, metavar="FILE", help="TOML or JSON file with the same options")


# ---- the pipeline -----------------------------------------------------------------------------
def _span(t: np.ndarray) -> tuple[float, float]:
    return (float(t[0]), float(t[-1])) if len(t) else (np.nan, np.nan)


def _overlap_s(master: InsLog, slave: InsLog) -> float:
    """How long the master's streams and the slave's IMU overlap on their stamps as they are (s; <= 0 or NaN:
    not at all)."""
    m0, m1 = master.span_s()
    s0, s1 = _span(slave.t_imu_s())
    return min(m1, s1) - max(m0, s0)


def _resolve_match(master: InsLog, requested: str) -> tuple[str | None, str | None]:
    """(match, None) or (None, reason it cannot be done)."""
    has_att, has_vel = master.has_quat, master.has_vel
    if requested == "auto":
        if has_att and has_vel:
            return "vel+att", None
        if has_vel:
            return "vel", None
        if has_att:
            return "att", None
        return None, "alignment needs the master's attitude and/or velocity (the master log has neither)"
    need = {"vel": ("velocity",), "att": ("attitude",), "vel+att": ("velocity", "attitude")}[requested]
    missing = [n for n in need if not {"velocity": has_vel, "attitude": has_att}[n]]
    if missing:
        return None, f"match {requested} needs the master's {' and '.join(missing)} (not in the master log)"
    return requested, None


def alignment_options(slave: InsLog, opts: AnalyzeOptions, lat: LatencyResult | None) -> AlignmentOptions:
    """The alignment's options for this pair: the split's residual delay, the lever arm, the flexure model
    (each helper below gives its AlignmentOptions fields)."""
    return AlignmentOptions(**_filter_options(slave, opts), **_lever_options(opts, lat), **_flexure_options(opts, lat),
                            **board_options(opts))


def board_options(opts: AnalyzeOptions) -> dict:
    """AlignmentOptions' board_errors field from ``--board-errors``."""
    return {"board_errors": {"on": True, "off": False}.get(opts.board_errors, "auto")}


def _filter_options(slave: InsLog, opts: AnalyzeOptions) -> dict:
    """AlignmentOptions fields: for S004's split, the residual latency the compensation left."""
    if not FilterKind.parse(opts.filter).splits_delay:
        return {}
    from logtools.compensate import split_residual_s

    residual = split_residual_s(slave)
    return {} if residual is None else {"delay_s": residual}


def _lever_options(opts: AnalyzeOptions, lat: LatencyResult | None) -> dict:
    """AlignmentOptions' lever-arm fields: a known one as given; in auto mode estimated, from the latency's
    velocity fit when that fit agreed with the rates (else from zero)."""
    mode = parse_lever_arm(opts.lever_arm)
    if mode == "off":
        return {}
    if isinstance(mode, tuple):
        return {"lever_arm_m": mode}
    out: dict = {"estimate_lever_arm": True}
    vf = (lat.quality or {}).get("velocity_fit") if lat is not None else None
    if isinstance(vf, dict) and vf.get("agrees") and vf.get("lever_arm_m") is not None:
        la = np.asarray(vf["lever_arm_m"], float)
        if la.shape == (3,) and np.all(np.isfinite(la)):
            out["lever_arm_m"] = tuple(float(x) for x in la)
    return out


def _flexure_options(opts: AnalyzeOptions, lat: LatencyResult | None) -> dict:
    """AlignmentOptions' flexure fields: the model the latency's rate fit found (sigma per axis, beta) where
    it is a structure's flexure (``accepts_flexure_model``); else, with ``--flexure auto`` the alignment adds
    seed 000's when its residuals call for it, with ``--flexure on`` always."""
    if opts.flexure == "off":
        return {}
    fm = (lat.quality or {}).get("flexure_model") if lat is not None else None
    if (isinstance(fm, dict) and fm.get("sigma_deg") is not None and fm.get("beta_1_s") is not None
            and accepts_flexure_model(fm["sigma_deg"], fm["beta_1_s"], ALIGNMENT_CONFIG)):
        return {"flexure": True, "flex_sigma_deg": tuple(float(x) for x in fm["sigma_deg"]),
                "flex_beta": float(fm["beta_1_s"])}
    if opts.flexure == "on":  # seed 000's flexure (eq 8)
        return {"flexure": True, "flex_sigma_deg": ALIGNMENT_CONFIG.flex_auto_sigma_deg,
                "flex_beta": ALIGNMENT_CONFIG.flex_auto_beta_1_s}
    return {"flexure": "auto"}


def _alignment(master: InsLog, slave: InsLog, run: str, opts: AnalyzeOptions, progress,
               lat: LatencyResult | None = None, board_decided=None, board_follow=None,
               beside=None) -> AlignmentResult | str:
    """One alignment run, or the reason it could not be done (str). ``board_decided``, ``board_follow``,
    ``beside``: see run_alignment (passed where the alignment takes them)."""
    if not (slave.has_gyro and slave.has_accel):
        return "alignment needs the slave's IMU (angular rate and specific force)"
    match, why = _resolve_match(master, opts.match)
    if why:
        return why
    if not _overlap_s(master, slave) > 0:
        hint = " (clocks unrelated? the compensated run uses the estimated latency)" if run == "uncompensated" else ""
        return f"no time overlap between the master and the slave on {run} stamps{hint}"
    try:
        run_alignment = numerics_stage("run_alignment")
    except ImportError as exc:
        return f"alignment is not available in this installation ({exc})"
    takes = inspect.signature(run_alignment).parameters
    hook = {k: v for k, v in (("board_decided", board_decided), ("board_follow", board_follow), ("beside", beside))
            if v is not None and k in takes}
    try:
        return run_alignment(master, slave, filter=opts.filter, match=match, smoother=opts.smoother,
                             progress=progress, options=alignment_options(slave, opts, lat), **hook)
    except AnalysisError as exc:
        return exc.problem


def _import_numerics() -> None:
    """The numerical stages' modules imported (the latency's: 0.28 s of scipy and logtools modules), where
    this process would wait for the master's parse in its child; an import that fails here fails again where
    its stage needs it, and is reported there."""
    for name in ("estimate", "compensate", "run_alignment"):
        try:
            numerics_stage(name)
        except ImportError:
            return


def _prepare_master(master: InsLog) -> None:
    """logtools' alignment's per-master preparation done once (``prepare_master``) before the runs fork;
    nothing for an alignment put in with ``use_numerics``."""
    if _numerics.run_alignment is not None:
        return
    try:
        from logtools.alignment.run import prepare_master
    except ImportError:
        return  # (the runs say it)
    prepare_master(master)


class _BoardDecision:
    """--board-errors auto: the compensated run's decision on the board's states, for the uncompensated run
    in its forked child (which takes the same model): sent through a pipe once the compensated run's first
    filter has decided (run_alignment's ``board_decided``), read by the child after its own first filter
    (``board_follow``), which then runs the filter with the states, if they join, on its own preparation.
    The end of file (this process gone) reads as "without them"; a run that fell back to this process
    (no fork) reads the decision kept here."""

    def __init__(self) -> None:
        self._r, self._w = os.pipe()
        self._home = os.getpid()
        self.on: bool | None = None

    def after_fork(self) -> None:
        """In this process once the child is forked (or not): the read end is the child's alone."""
        os.close(self._r)

    def send(self, on: bool) -> None:
        """The decision, once (later calls are ignored)."""
        if self.on is not None:
            return
        self.on = bool(on)
        try:
            os.write(self._w, b"1" if on else b"0")
        except OSError:
            pass  # (the child is gone: its result is read, or not, at result())
        finally:
            os.close(self._w)

    def __call__(self) -> bool:
        if os.getpid() == self._home:  # (the run fell back to this process: the decision is known by then)
            return bool(self.on)
        os.close(self._w)  # (the child's copy: the end of file must come when this process's closes)
        with os.fdopen(self._r, "rb") as fh:
            return fh.read(1) == b"1"


def _uncompensated_options(opts: AnalyzeOptions, compensated: bool) -> AnalyzeOptions:
    """The uncompensated run's options. With ``--board-errors auto`` the compensated run decides: the delay
    left in the uncompensated slave correlates its innovations by itself, which says nothing of the master's
    board (rerun with the board's states when the compensated run took them, see compute)."""
    if opts.board_errors == "auto" and compensated:
        return replace(opts, board_errors="off")
    return opts


#: the modules of the outputs (write_outputs) and what they import (rerun's SDK alone is about 0.4 s), done
#: ahead: in the recording's prepared child, or while this process waits. pandas is the recording's too where
#: it is written here: pyarrow, under rerun, imports it on the first array it converts (to ask whether that is
#: a pandas object), and nothing before the recording needs it on the analysis' own path. pyarrow.compute is
#: the recording's too: rerun's bar chart (the latency cost) builds its tensor with pyarrow's
#: ``ListArray.from_arrays``, which imports it (with dateutil): 35-50 ms of CPU in the recording's call, on the
#: run's last stretch where the alignment's children still run, unless the prepared child has it already
OUTPUT_MODULES = {"html": ("pipelines.html",),
                  "recording": ("pipelines.recording", "rerun", "rerun.blueprint", "pyarrow.compute"),
                  "recording_here": ("pandas",)}
#: what the recording's prepared child does after its imports (module, function): pandas refused there
#: (``pipelines.recording.without_pandas``: pyarrow, under rerun, would import it only to ask whether the
#: arrays it converts are pandas objects). The same recording (``rerun rrd compare``)
RECORDING_CHILD_SETUP = ("pipelines.recording", "without_pandas")


def _import_output_modules(opts: AnalyzeOptions) -> None:
    """The output stage's imports, done while this process would wait for the alignment's forked children
    (the 1 h pair: 2-3 s of waiting; its recording then starts 0.4 s sooner). Not the recording's where a
    prepared child holds them (``parallel.prepare``); an import that fails here fails again where it is
    used, and is reported there."""
    names = list(OUTPUT_MODULES["html"]) if opts.html else []
    if opts.recording and not parallel.is_prepared("recording"):
        names += OUTPUT_MODULES["recording"] + OUTPUT_MODULES["recording_here"]
    for name in names:
        try:
            importlib.import_module(name)
        except ImportError:
            return


def _has_board_states(res) -> bool:
    return isinstance(res, AlignmentResult) and res.has_board_states


def _as_the_latency_read(master: InsLog, slave: InsLog, an: rp.Analysis, opts: AnalyzeOptions
                         ) -> tuple[InsLog, InsLog | None, InsLog]:
    """(master, compensated slave, slave at face value) for the alignment and the IMU-to-IMU fit: the logs with
    the samples the latency replaced as corrupt (``latency.quality.replaced_samples``, ``logtools.latency.spikes``)
    replaced there too (one gyro sample 0.54 rad/s off put a simulated pair's mounting sigma at 26 arcmin and its
    lever arm 0.7 m off; 0.018 arcmin and 4 mm without it); else the logs themselves. The outputs (report
    plots, recording, exports) keep the logs' own values."""
    replaced = (an.latency.quality or {}).get("replaced_samples") if an.latency is not None else None
    if not replaced or an.slave_comp is None:
        return master, an.slave_comp, an.slave_face_value()
    from logtools.latency.spikes import mend

    master_m, slave_m = mend(master, slave, replaced)
    try:
        comp = numerics_stage("compensate")(slave_m, an.latency, master_m, method=opts.compensation)
    except AnalysisError:  # (it compensated the slave as logged: the logs themselves then)
        return master, an.slave_comp, an.slave_face_value()
    return master_m, comp, slave_m.rebased(master_m.meta.t0_ns)


def _velocity_mended(master: InsLog) -> tuple[InsLog, str | None]:
    """The master with its isolated corrupt velocity samples (``AlignmentConfig.vel_spike_sigmas``,
    ``vel_spike_min_m_s``) replaced by their neighbours' mean, for the alignment, and the warning that says so;
    else the master itself and None."""
    if not master.has_vel:
        return master, None
    from logtools.inslog import VEL
    from logtools.latency.spikes import Spikes, instants, isolated_samples, replaced_rows

    t = master.t_nav_s()
    rows, off = isolated_samples(t, master.nav_columns.values(VEL), ALIGNMENT_CONFIG.vel_spike_sigmas,
                                 ALIGNMENT_CONFIG.vel_spike_min_m_s)
    if not len(rows):
        return master, None
    return (replaced_rows(master, {VEL: Spikes(rows, np.zeros(len(rows)))}, stream="nav"),
            f"master: {len(rows)} velocity sample(s) (at {instants(t, rows, master.t0_s)}; up to "
            f"{float(off.max()):.3g} m/s) off their neighbours and back within one sample, replaced by their "
            "neighbours' mean for the alignment (corrupt values?)")


def _wants_imu_to_imu(master: InsLog, slave: InsLog) -> bool:
    """The contract: the IMU-to-IMU rotation only where both units log an IMU."""
    return bool((master.has_gyro or master.has_accel) and (slave.has_gyro or slave.has_accel))


def _imu_to_imu_sections(master: InsLog, an: rp.Analysis, align_sections: dict, extra: dict,
                         fit=None, slave_comp: InsLog | None = None) -> None:
    """``alignment.imu_to_imu`` and ``alignment.consistency`` (DESIGN.md) where both units log an IMU: the
    slave's triads against the master's, on the compensated slave (``fit``: already computed, while the
    forked child ran; ``slave_comp``: the compensated slave as the latency read it, ``_as_the_latency_read``); a
    disagreement with the compensated nav-referenced mounting beyond 3 combined sigma is a warning naming the
    likely cause."""
    slave = an.slave_comp if slave_comp is None else slave_comp
    if not _wants_imu_to_imu(master, an.slave):
        return
    from logtools.alignment.imu_to_imu import consistency, imu_to_imu

    if slave is None:
        align_sections["imu_to_imu"] = {"gyro_rpy_deg": None, "gyro_sigma_deg": None, "accel_rpy_deg": None,
                                        "accel_sigma_deg": None,
                                        "reasons": {"gyro": "no compensated slave (latency or compensation "
                                                            "failed)", "accel": "no compensated slave"}}
        return
    res = fit if fit is not None else imu_to_imu(master, slave)
    align_sections["imu_to_imu"] = res.section()
    comp = align_sections.get("compensated")
    mount = sig = lever = lever_sig = None
    board = False
    if isinstance(comp, AlignmentResult):
        sec = rp.alignment_section(comp)
        mount, sig = sec["mounting_rpy_deg"], sec["mounting_sigma_deg"]
        lever, lever_sig = sec.get("lever_arm_m"), sec.get("lever_arm_sigma_m")
        board = _has_board_states(comp)  # the filter carried the master's error
    cons = consistency(mount, sig, res, board_states=board, lever_m=lever, lever_sigma_m=lever_sig)
    warning = cons.pop("warning")
    align_sections["consistency"] = cons
    for text in (warning, cons.get("lever_arm_note")):
        if text:
            extra.setdefault("warnings", []).append({"stage": "alignment", "text": text})


def _fmt_ms(x: float | None) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x * 1e3:+.3f} ms"


#: warnings printed in the summary (all of them are in report.json and report.html)
SUMMARY_WARNINGS = 8


#: the alignment's note of residuals beyond its noise model (``alignment.run``), its factor
_RESIDUALS_X = re.compile(r"^residuals ([0-9.]+)x larger than the noise model")


def summary_lines(rep: dict, paths: dict[str, str | None]) -> list[str]:
    """The short human summary printed on stdout."""
    m, s, lat = rep["master"], rep["slave"], rep["latency"]
    out = [f"master  {m['path']} [{m['format']}, {m['clock']} clock, {m['duration_s'] or 0:.1f} s]",
           f"slave   {s['path']} [{s['format']}, {s['clock']} clock, {s['duration_s'] or 0:.1f} s]"]
    if rep.get("latency_search"):
        out.append(f"latency search: {rep['latency_search']}")
    if "failed" in lat:
        out.append(f"latency FAILED: {lat['failed']}")
    else:
        sig = lat["sigma_s"]
        q = lat.get("quality") or {}
        aided = q.get("accel_aided") is True
        flex = q.get("flexure_model")
        how = (f", flexure model {max(flex['sigma_deg']):.3g} deg / beta {flex['beta_1_s']:.3g} 1/s"
               if isinstance(flex, dict) else "")
        vel = q.get("velocity_fit")
        if isinstance(vel, dict) and vel.get("fused"):  # velocity matching fused with the rates
            how += " + velocity"
        elif isinstance(vel, dict) and not vel.get("agrees"):
            how += f", velocity alone {_fmt_ms(vel['latency_s'])} (disagrees, not used)"
        big = abs(lat["latency_s"]) >= 10.0  # unrelated clocks: the offset between them, in seconds
        head = f"{lat['latency_s']:+.6f} s" if big else f"{lat['latency_s'] * 1e3:+.3f} ms"
        drift = f"drift {lat['drift_ppm']:+.2f} ppm" if lat["drift_ppm"] is not None else "drift not estimated"
        out.append(f"latency {head} +/- {sig * 1e3 if sig is not None else float('nan'):.3f} ms (1 sigma), {drift}  "
                   f"[{lat['method']}{' gyro+accel' if aided else ''}{how}, "
                   f"window {lat['window_s'][1] - lat['window_s'][0]:.1f} s]")
        # (the seeds' methods assume the units' axes aligned: said beside their figures, which a mounting
        # rotation makes meaningless)
        others = [f"{k} {_fmt_ms(v['latency_s'])}" + (" (axes assumed aligned)" if "axes assumed aligned" in
                                                     str(v.get("note", "")) else "")
                  for k, v in lat.get("methods", {}).items() if k != lat["method"]]
        if others:
            out.append("        other methods: " + ", ".join(others))
        if q.get("too_little_motion"):
            what = ("noise large against the motion" if q.get("low_motion_cause") == "noise"
                    else "too little motion")
            out.append(f"        {what}: this latency and its sigma are doubtful (see the warnings)")
    for run in rp.RUNS:
        a = rep["alignment"].get(run, {})
        if "skipped" in a:
            out.append(f"mounting ({run}): skipped: {a['skipped']}")
            continue
        if all(x is None for x in (a.get("mounting_rpy_deg") or [None])):
            out.append(f"mounting ({run}, {a['filter']}/{a['match']}): not determined"
                       + (f" ({', '.join(n for n in a.get('notes', []) if 'not determined' in n)})"
                          if any('not determined' in n for n in a.get('notes', [])) else ""))
            continue
        rpy = " ".join(f"{x:+.4f}" if x is not None else "n/a" for x in a["mounting_rpy_deg"])
        sig = " ".join(f"{x * 60:.3g}'" if x is not None else "n/a" for x in a["mounting_sigma_deg"])
        conv = (f"{a['converged_s']:.1f} s" if a.get("converged_s") is not None
                else "settled" if a.get("still_converging") is False else "not converged")
        out.append(f"mounting ({run}, {a['filter']}/{a['match']}): roll pitch yaw = {rpy} deg "
                   f"+/- {sig} (arcmin, 1 sigma), {conv}")
        far = next((m.group(1) for n in a.get("notes", []) if run == "uncompensated"
                    for m in [_RESIDUALS_X.search(n)] if m), None)
        if far is not None:  # (a 1.2 s delay left in put a mounting 160 deg off at a sigma of 0.5 deg)
            out.append(f"        residuals {far}x its noise model: the delay left in distorts this run; its mounting "
                       "and sigma show what the delay does, not the mounting")
        if a.get("mounting_not_determined"):
            out.append(f"        not determined (n/a): {', '.join(a['mounting_not_determined'])}: not observable "
                       "with this motion (the value would be its prior)")
        if any(n.startswith("board error states added") for n in a.get("notes", [])):
            out.append("        with the board's error states (the master's attitude error, the slave's accelerometer "
                       "triad): --board-errors auto found the innovations correlated without them")
        la, ls = a.get("lever_arm_m"), a.get("lever_arm_sigma_m")
        if la is not None and None not in la:
            tail = ((" +/- " + " ".join(f"{x:.3f}" for x in ls) + " m (1 sigma)") if ls and None not in ls
                    else " m (given)")
            out.append(f"        lever arm x y z = {' '.join(f'{x:+.3f}' for x in la)}{tail}")
    out += _imu_to_imu_lines(rep["alignment"])
    for k, v in rep.get("skipped", {}).items():
        if k == "recording":
            out.append(f"skipped recording: {v}")
    warns, notes = rep.get("warnings", []), rep.get("notes", [])
    out.append(f"status {rep.get('status', '?')}: {len(warns)} warning(s), {len(notes)} note(s)"
               + (" (notes in report.json)" if notes else ""))
    for w in warns[:SUMMARY_WARNINGS]:
        out.append(f"  warning [{w['stage']}] {w['text']}")
    if len(warns) > SUMMARY_WARNINGS:
        out.append(f"  ... {len(warns) - SUMMARY_WARNINGS} more warning(s) in report.json")
    from pipelines.export import summary_from_report

    out += summary_from_report(rep)
    if any(paths.values()):
        out.append("outputs " + ", ".join(p for p in paths.values() if p))
    return out


def _imu_to_imu_lines(align: dict) -> list[str]:
    """Summary lines of ``alignment.imu_to_imu`` / ``consistency`` (none when the section is absent)."""
    ii = align.get("imu_to_imu")
    if not ii:
        return []
    out = []
    for name, label in (("gyro", "gyro triad"), ("accel", "accel triad")):
        rpy, sig = ii.get(f"{name}_rpy_deg"), ii.get(f"{name}_sigma_deg")
        if rpy is None:
            out.append(f"imu-to-imu {label}: not measured: {ii.get('reasons', {}).get(name, 'unknown')}")
        else:
            out.append(f"imu-to-imu {label}: roll pitch yaw = {' '.join(f'{x:+.4f}' for x in rpy)} deg +/- "
                       f"{' '.join(f'{x * 60:.3g}' + chr(39) for x in sig)} (arcmin, 1 sigma)"
                       + (f"; {rp.GIMBAL_LOCK_SAID.format(quat=f'{name}_quat_wxyz')}"
                          if ii.get(f"{name}_gimbal_lock") else ""))
    cons = align.get("consistency")
    if cons and cons.get("note"):
        out.append(("WARNING: " if cons.get("agrees") is False else "") + "mounting vs imu-to-imu: " + cons["note"])
    if cons and cons.get("lever_arm_agrees") is False and cons.get("lever_arm_note"):
        out.append("WARNING: " + cons["lever_arm_note"])
    return out


class Analysis(rp.Analysis):
    """One analysed pair, in memory (DESIGN.md, "Python API"): the two logs, the latency, the slave on the
    master's clock, both alignment runs; ``report`` is the report.json dict, ``frames()`` the data as pandas
    DataFrames, ``write(dir)`` the CLI's outputs. Made by ``compute`` (``pipelines.api.analyze``)."""

    def __init__(self, master: InsLog, slave: InsLog, options: "AnalyzeOptions", master_arg: str = "",
                 slave_arg: str = ""):
        super().__init__(master=master, slave=slave)
        self.options = options
        self.master_arg = master_arg or master.meta.source_path
        self.slave_arg = slave_arg or slave.meta.source_path
        self.failure: str | None = None  # why the latency could not be estimated (None: it was)
        self.extra: dict = {}  # report.json's further sections (compensation, latency_search, ...)
        self.align_sections: dict[str, dict | AlignmentResult] = {}
        self.timings_s: dict[str, float] = {}
        self.skipped_steps: dict[str, str] = {}  # output steps that could not be done (recording)
        self._report: dict | None = None

    # -- results ------------------------------------------------------------------------------
    @property
    def slave_on_master_clock(self) -> InsLog | None:
        """The compensated slave: its samples with stamps on the master's clock (None if latency failed)."""
        return self.slave_comp

    @property
    def ok(self) -> bool:
        """True when the latency was estimated (the CLI's exit 0)."""
        return self.latency is not None

    @property
    def report(self) -> dict:
        """The report.json dict (outputs none until ``write``)."""
        if self._report is None:
            self._report = self.build_report({**self.timings_s, "report": 0.0, "recording": 0.0}, {})
        return self._report

    def build_report(self, timings: dict, paths: dict[str, str | None]) -> dict:
        lat_section = (self.latency if self.latency is not None
                       else rp.latency_failed(self.failure or "unknown", self.options.latency_method))
        options = {**asdict(self.options), "master": self.master_arg, "slave": self.slave_arg}
        extra = {**self.extra, "mounting_for_plots": self.mounting()[1],
                 "outputs": {k: (os.path.basename(v) if v else None) for k, v in paths.items()}}
        r = rp.build_report(self.master, self.slave, latency=lat_section, alignment=self.align_sections,
                            timings_s={k: timings.get(k, 0.0) for k in rp.TIMING_KEYS}, options=options,
                            extra=extra)
        if self.skipped_steps:
            r["skipped"].update(self.skipped_steps)
            if r["status"] == "ok":
                r["status"] = "partial"
            rp.add_findings(r)
        return r

    def frames(self) -> dict:
        """The analysis as pandas DataFrames (see ``pipelines.frames``)."""
        from pipelines.frames import analysis_frames

        return analysis_frames(self)

    def summary(self) -> str:
        """The short summary ``tapost analyze`` prints."""
        return "\n".join(summary_lines(self.report, {}))

    def write(self, out_dir, progress=None) -> "PairOutcome":
        """Write the CLI's outputs in ``out_dir`` (a str or ``os.PathLike``; report.json last; see
        ``write_outputs``). A wrong argument raises InputError naming it (``progress_arg``)."""
        from parsers.registry import path_arg

        return write_outputs(self, path_arg(out_dir, "the output folder", selector=False), progress_arg(progress))


def progress_arg(progress):
    """``progress``: None, or a callable that takes ``(fraction, stage)``; else InputError saying so."""
    if progress is None:
        return None
    if not callable(progress):
        given = f"{type(progress).__name__} {progress!r}"
        raise InputError("progress must be None or a callable progress(fraction, stage); got "
                         + (given if len(given) <= 80 else given[:77] + "..."))
    try:
        sig = inspect.signature(progress)
    except (TypeError, ValueError):  # (a builtin without a signature: taken on trust)
        return progress
    try:
        sig.bind(0.5, "stage")
    except TypeError as exc:
        name = getattr(progress, "__qualname__", type(progress).__name__)
        raise InputError(f"progress must take two arguments, progress(fraction, stage); {name}{sig} "
                         f"does not ({exc})") from None
    return progress


def _arg_path(arg) -> str:
    return arg.meta.source_path if isinstance(arg, InsLog) else str(arg).partition("::")[0]


def stream_relation(master: InsLog, slave: InsLog) -> str | None:
    """"same" where both sides are the same stream: of the same file with the same resolved selector, or the
    same angular rates and navigation sources (of one file read on two clocks; of any files at the same
    stamps: a unit's folder and the session that defaults to it, a plain copy). "one imu" where they read one
    IMU stream with different navigation sources (two EKF lanes of one log against one IMU). Else None: a
    pair (a copy restamped, its stamps shifted, is one: the export's round trip)."""
    same_file = _same_file(master, slave)
    if same_file and master.meta.selector == slave.meta.selector:
        return "same"
    if not _one_imu(master, slave, same_file):
        return None
    return "same" if _nav_sources(master) == _nav_sources(slave) else "one imu"


def same_stream(master: InsLog, slave: InsLog) -> bool:
    """Both sides are the same stream (``stream_relation``): nothing to compare."""
    return stream_relation(master, slave) == "same"


def same_imu(master: InsLog, slave: InsLog) -> str | None:
    """What to say where both sides read one IMU stream with different navigation sources
    (``stream_relation``), else None."""
    return _one_imu_text(master) if stream_relation(master, slave) == "one imu" else None


def _one_imu_text(master: InsLog) -> str:
    """The warning of a pair that reads one IMU stream on both sides: the latency is then that stream against
    itself, 0 by construction; the alignment compares the two navigation sources."""
    src = master._channel("gyro").source if master._channel("gyro") is not None else "IMU"
    return (f"master and slave read the same IMU stream ({src}): the latency compares it with itself (0 by "
            "construction); the alignment compares their navigation sources. For the latency between two units, "
            "give two IMUs (`tapost inspect FILE` lists them)")


def _same_file(master: InsLog, slave: InsLog) -> bool:
    try:
        return os.path.samefile(master.meta.source_path, slave.meta.source_path)
    except OSError:
        return os.path.abspath(master.meta.source_path) == os.path.abspath(slave.meta.source_path)


def _nav_sources(log: InsLog) -> tuple:
    return tuple(getattr(log._channel(k), "source", None) for k in ("att", "vel", "pos"))


def _one_imu(master: InsLog, slave: InsLog, same_file: bool) -> bool:
    """The same angular rates on both sides: of the same file, or at the same stamps."""
    if not (master.has_gyro and slave.has_gyro and master.n_imu == slave.n_imu and master.n_imu):
        return False
    if not np.array_equal(master.gyro_rad_s(), slave.gyro_rad_s(), equal_nan=True):
        return False
    return same_file or bool(np.array_equal(master.t_imu_s() * 1e9 + master.meta.t0_ns,
                                            slave.t_imu_s() * 1e9 + slave.meta.t0_ns))


def _skip_reason(exc: BaseException) -> str:
    """Why an output was skipped: ``Type: message``, and the file and line that raised it where that file is
    neither tapost's nor the Python installation's (a stray ``attr.py`` in the working directory, run as the
    attrs package rerun imports, made "FileNotFoundError: [Errno 2] No such file or directory: 'analyze'"
    out of the recording, naming nothing the user could find)."""
    import site
    import traceback

    text = f"{type(exc).__name__}: {exc}"
    frames = traceback.extract_tb(exc.__traceback__) if exc.__traceback__ is not None else []
    if not frames:
        return text
    if frames[-1].filename.startswith("<"):  # (frozen or generated code)
        return text
    where = os.path.abspath(frames[-1].filename)
    ours = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # (the folder of pipelines/, logtools/)
    homes = {os.path.abspath(p) for p in (sys.prefix, sys.base_prefix, sys.exec_prefix, ours,
                                           *site.getsitepackages(), site.getusersitepackages())}
    if any(where == h or where.startswith(h + os.sep) for h in homes):
        return text
    return f"{text} (raised in {where}, line {frames[-1].lineno}: a file there named like a library shadows it?)"


def _parse_child_sets_up_nothing() -> bool:
    """A parse in a forked child costs no kernel set-up there: the reference code, or the compiled kernels
    served by the ahead-of-time extension (loaded here first: the child's by fork). Kernels served from numba's
    cache (no C compiler, ``TAPOST_AOT=0``) would set numba up in the child again (0.4-0.5 s of CPU,
    docs/performance.md), beside this process's own."""
    from logtools import jit

    return not jit.compiled() or jit.aot_table() is not None


def _parse_both(master_arg: str, slave_arg: str) -> tuple[InsLog, InsLog]:
    """Both logs parsed, the master first (its error first)."""
    return load(master_arg), load(slave_arg)


def parse_pair(master_arg: str | InsLog, slave_arg: str | InsLog, prog=null_progress,
               meanwhile: Callable[[], None] | None = None, there=None) -> tuple[InsLog, InsLog]:
    """Both logs loaded (an InsLog given is taken as it is). Where forking is allowed (the CLI's analyze) and
    the files are large (``parallel.FORK_PARSE_MIN_INPUT_BYTES``), the larger file is parsed in a forked child
    while this process parses the other, then calls ``meanwhile`` (work of a later stage) before it takes the
    child's answer (its arrays mapped, not copied: ``parallel.OOB_MIN_BYTES``). The larger file there: this
    process has ``meanwhile`` to do besides (the 1 h pair's 165 MB slave tlog in the child, 2.1 s with its
    imports, against the 109 MB master MCAP and 0.3 s of imports here). A bad master is reported before a bad
    slave either way.

    ``there``: both logs' parse already started in a forked child (``_parse_both``; ``run``, for inputs below
    ``parallel.FORK_PARSE_MIN_INPUT_BYTES``): ``meanwhile`` is called, then its answer taken. On the sample
    pair the parse (0.09 s, with the parsers' imports) then runs beside this process's imports of the
    analysis' modules (0.09 s) on the core the recording's prepared child shares: 1.051 -> 1.018 s (medians of
    40 whole runs, alternated)."""
    prog(0.0, "parse master")
    if there is not None:
        if meanwhile is not None:
            meanwhile()
        return there.result()
    if isinstance(master_arg, str) and isinstance(slave_arg, str) and parallel.available():
        m_bytes, s_bytes = (input_bytes("analyze", [a]) or 0 for a in (master_arg, slave_arg))
        if m_bytes + s_bytes > parallel.FORK_PARSE_MIN_INPUT_BYTES:
            master_there = m_bytes >= s_bytes
            pending = parallel.submit(load, master_arg if master_there else slave_arg)
            if master_there:
                prog(0.08, "parse slave")
            try:
                here = load(slave_arg if master_there else master_arg)
            except BaseException as exc:
                if master_there and isinstance(exc, Exception):
                    pending.result()  # (raises the master's error, if it has one)
                else:
                    pending.cancel()
                raise
            if not master_there:
                prog(0.08, "parse slave")
            if meanwhile is not None:
                meanwhile()
            other = pending.result()
            return (other, here) if master_there else (here, other)
    master = master_arg if isinstance(master_arg, InsLog) else load(master_arg)
    prog(0.08, "parse slave")
    return master, slave_arg if isinstance(slave_arg, InsLog) else load(slave_arg)


def compute(master_arg: str | InsLog, slave_arg: str | InsLog, opts: AnalyzeOptions | None = None,
            progress=None, when_aligned: Callable[[Analysis], None] | None = None, there=None) -> Analysis:
    """Parse (or take) both logs -> latency -> compensation -> both alignment runs, in memory.

    ``when_aligned(an)`` is called where the IMU-to-IMU fit still runs in a forked child once both alignment
    runs are in ``an``, or sooner, once the compensated run is, where the uncompensated one still runs in its
    child and the compensated run gives the mounting (``an.alignment`` then holds the compensated run alone
    during the call; the CLI starts its recording there: ``start_recording``, which gets the other run later).

    Raises InputError (unreadable input, the same stream on both sides: exit 2). A latency the data
    cannot give is not raised: ``Analysis.failure`` says why (the CLI's exit 1)."""
    opts = opts or AnalyzeOptions()
    prog = progress if progress is not None else null_progress
    scaled = getattr(prog, "scaled", None)
    sub = (lambda lo, hi, st: scaled(lo, hi, st)) if scaled else (lambda lo, hi, st: null_progress)
    tim: dict[str, float] = {}
    t_all = time.perf_counter()

    # -- parse
    t = time.perf_counter()
    master, slave = parse_pair(master_arg, slave_arg, prog, meanwhile=_import_numerics, there=there)
    parallel.malloc_policy(master.n_imu + master.n_nav + slave.n_imu + slave.n_nav)
    parallel.release_freed_memory()  # (each stage's freed temporaries: not carried into the next stage)
    tim["parse"] = time.perf_counter() - t
    relation = stream_relation(master, slave)  # (one comparison of the rates for both checks)
    if relation == "same":
        raise InputError("master and slave are the same stream (the same angular rates; nothing to compare); "
                         "give two logs, or two units of one log with selectors "
                         "(e.g. FILE::imu=IMU and FILE::imu=IMU2; `tapost inspect FILE` lists them)",
                         _arg_path(slave_arg))
    an = Analysis(master, slave, opts,
                  master_arg if isinstance(master_arg, str) else "", slave_arg if isinstance(slave_arg, str) else "")
    extra = an.extra
    units = scale_findings(master, slave)  # (a unit mix-up: said as a warning, and in a failure's line)
    extra.setdefault("warnings", []).extend({"stage": "parse", "text": u} for u in units)
    if relation == "one imu":
        extra["warnings"].append({"stage": "parse", "text": _one_imu_text(master)})

    # -- latency
    t = time.perf_counter()
    failure: str | None = None
    missing = [role for role, log in (("master", master), ("slave", slave)) if not (log.has_gyro or log.has_quat)]
    if missing:
        failure = f"latency needs angular rate or attitude from both units; the {' and '.join(missing)} has neither"
    else:
        try:
            estimate = numerics_stage("estimate")
        except ImportError as exc:
            raise AnalysisError(f"latency estimation is not available in this installation ({exc})") from None
        max_lag = opts.max_lag_s
        clocks = (master.meta.clock, slave.meta.clock)
        if not opts.max_lag_given and max_lag is not None and set(clocks) == {"epoch", "boot"}:
            max_lag = None
            extra["latency_search"] = (f"whole overlap: the master is on {clocks[0]} time and the slave on "
                                       f"{clocks[1]} time, so their stamps cannot be compared at face value")
        try:
            # the comparison methods in a forked child beside the headline (CLI, logs up to about 1 h); an
            # estimate put in with use_numerics may not take the argument
            n_imu = master.n_imu + slave.n_imu
            takes = inspect.signature(estimate).parameters
            beside = ({"beside": parallel.submit} if parallel.available() and opts.compare
                      and n_imu <= parallel.FORK_COMPARE_MAX_SAMPLES and "beside" in takes else {})
            if (parallel.available() and n_imu <= parallel.THREAD_LATENCY_MAX_SAMPLES and "overlap" in takes
                    and _kernels_compiled()):
                beside["overlap"] = True  # (the velocity pair in a thread beside the rate fit)
            an.latency = estimate(master, slave, method=opts.latency_method, max_lag_s=max_lag,
                                  compare=opts.compare, progress=sub(0.15, 0.45, "latency"), **beside)
        except AnalysisError as exc:
            failure = exc.problem
            face = slave.rebased(master.meta.t0_ns)
            m0, m1 = master.span_s()
            s0, s1 = face.span_s()
            if (max_lag is not None and "--max-lag" not in failure
                    and (master.meta.clock != slave.meta.clock or min(m1, s1) <= max(m0, s0))):
                failure += (f" (clocks look unrelated: master {master.meta.clock}, slave {slave.meta.clock}, "
                            "no overlap at face value; try --max-lag auto)")
            from parsers.mavlink_tlog import RECEIVE_CHOSEN

            received = [role for role, log in (("master", master), ("slave", slave))
                        if log.meta.stamp_source == RECEIVE_CHOSEN]
            if received and "receive stamps" not in failure:  # (a telemetry link delivers its messages in
                # bursts: their receive stamps are no clock; said once, where the estimate's own line has not)
                failure += (f"; the {' and '.join(received)}'s stamps are the tlog's receive stamps (time=receive), "
                            "which a telemetry link gives in bursts: time=message reads the messages' own time "
                            "fields")
    if failure and units:
        failure += f"; but {'; '.join(units)}"
    if failure:  # (a log read as another format than its name says: another file than the one meant?)
        from parsers.registry import NAMED_OTHERWISE

        renamed = [f"the {role} {w}" for role, log in (("master", master), ("slave", slave))
                   for w in log.meta.warnings if NAMED_OTHERWISE in w]
        if renamed:
            failure += "; " + "; ".join(renamed)
    an.failure = failure
    disagrees = _chosen_method_disagrees(an.latency)
    if disagrees:
        extra["warnings"].append({"stage": "latency", "text": disagrees})
    parallel.release_freed_memory()
    tim["latency"] = time.perf_counter() - t

    # -- compensation and alignment
    t = time.perf_counter()
    if an.latency is not None:
        prog(0.45, "compensate")
        try:
            compensate = numerics_stage("compensate")
            an.slave_comp = compensate(slave, an.latency, master, method=opts.compensation)
            extra["compensation"] = {"method": opts.compensation, "applied_latency_s": an.latency.latency_s,
                                     "applied_drift_ppm": an.latency.drift_ppm}
        except ImportError as exc:
            extra["compensation"] = {"method": opts.compensation, "skipped": f"not available ({exc})"}
        except AnalysisError as exc:
            extra["compensation"] = {"method": opts.compensation, "skipped": exc.problem}
    tim["compensate"] = time.perf_counter() - t
    t = time.perf_counter()
    master_al, slave_comp_al, face = _as_the_latency_read(master, slave, an, opts)
    master_al, said = _velocity_mended(master_al)
    if said:
        extra.setdefault("warnings", []).append({"stage": "alignment", "text": said})
    runs = {"uncompensated": (face, sub(0.5, 0.7, "alignment (uncompensated)")),
            "compensated": (slave_comp_al, sub(0.7, 0.9, "alignment (compensated)"))}
    run_opts = {"uncompensated": _uncompensated_options(opts, an.slave_comp is not None), "compensated": opts}
    pending = {}
    decision: _BoardDecision | None = None
    n_imu = master_al.n_imu + an.slave.n_imu
    forked = (runs["uncompensated"][0] is not None and runs["compensated"][0] is not None and parallel.available()
              and n_imu <= parallel.FORK_ALIGNMENT_MAX_SAMPLES)
    imu_fit = None
    if forked and _wants_imu_to_imu(master_al, an.slave) and n_imu <= parallel.FORK_IMU_TO_IMU_MAX_SAMPLES:
        # the IMU-to-IMU fit in a forked child beside the two runs (the uncompensated one in a second child, the
        # compensated one here), when the logs are short enough for its arrays to sit beside theirs
        # (parallel.FORK_IMU_TO_IMU_MAX_SAMPLES); else here once the runs are done. Forked first: it is the
        # stage's longest part (5 s of the 1 h pair's 11 s of CPU) and needs none of the runs' master series
        from logtools.alignment.imu_to_imu import imu_to_imu

        imu_fit = parallel.submit(imu_to_imu, master_al, slave_comp_al)
    if forked:
        # the two runs share nothing but their inputs: the uncompensated one in a forked child (CLI only),
        # the master's series prepared before (the child shares them instead of preparing its own). That
        # child starts its flexure pass in a child of its own beside its rigid pass (run_alignment's
        # ``beside``): the delay left in the uncompensated slave makes the flexure pass follow almost always,
        # and the run's three passes are the alignment stage's critical path (the sample pair's first run:
        # 0.72 s of Python passes; with the kernels compiled, 0.15 s, while this process, done with the
        # compensated run, only starts the recording: 0.765 -> 0.744 s, medians of 16 whole runs)
        _prepare_master(master_al)
        if run_opts["uncompensated"] is not opts and _numerics.run_alignment is None:
            # --board-errors auto: the compensated run decides the board's states; the uncompensated one
            # follows its decision in the child (the filter with them, if they join, on the child's own
            # preparation, beside the compensated run's second filter; not rerun here after the children:
            # a consumer board's 1 h pair spent 4.8 s so at the stage's end)
            decision = _BoardDecision()
            pending["uncompensated"] = parallel.submit(_alignment, master_al, face, "uncompensated", opts,
                                                       null_progress, an.latency, None, decision, parallel.submit)
            decision.after_fork()
        else:
            pending["uncompensated"] = parallel.submit(_alignment, master_al, face, "uncompensated",
                                                       run_opts["uncompensated"], null_progress, an.latency,
                                                       beside=parallel.submit)
    for run, (slog, p) in runs.items():
        if slog is None:
            why = ("latency failed" if an.latency is None
                   else f"compensation failed: {extra.get('compensation', {}).get('skipped', 'unknown')}")
            pending[run] = why
        elif run not in pending:
            p(0.0, "")
            decided = decision.send if decision is not None and run == "compensated" else None
            try:
                pending[run] = _alignment(master_al, slog, run, run_opts[run], p, an.latency, decided)
            finally:
                if decided is not None:
                    decided(False)  # (no decision made: the run failed, or never reached it; else ignored)
    if forked:
        _import_output_modules(opts)  # (this process would wait for the children here)
    early = (when_aligned is not None and isinstance(imu_fit, parallel.Pending)
             and isinstance(pending.get("uncompensated"), parallel.Pending)
             and _gives_the_mounting(pending.get("compensated")))
    if early:
        # the recording started now, while the uncompensated run still runs in its child: it logs the series
        # (rotated by the compensated run's mounting, which the plots use whatever the other run gives) and
        # that run's states, and gets the uncompensated run's with the report (pipelines.recording.Rest). On
        # the sample pair this process waited here 0.1 s with a core free, and the recording was the run's
        # last 0.15 s
        an.alignment["compensated"] = pending["compensated"]
        when_aligned(an)
        an.alignment.clear()  # (filled below, in the runs' order)
    for run in runs:
        res = pending[run]
        if isinstance(res, parallel.Pending):
            res = res.result()
        if run == "uncompensated" and run_opts[run] is not opts:
            # --board-errors auto added the board's states to the compensated run: the uncompensated one
            # with the same model, so that the two differ by the compensation alone (in its child, following
            # the decision; else here, now); and without them where the compensated run's filter with them
            # did not follow the data and the run without them stands
            board = _has_board_states(pending.get("compensated"))
            if decision is not None:  # (the child followed the decision)
                if decision.on and not board:
                    res = _alignment(master_al, face, run, run_opts[run], null_progress, an.latency)
            elif board and isinstance(res, AlignmentResult):
                res = _alignment(master_al, face, run, replace(opts, board_errors="on"), null_progress, an.latency)
        if isinstance(res, AlignmentResult):
            an.alignment[run] = res
            an.align_sections[run] = res
        else:
            an.alignment[run] = None
            # a master and a slave whose stamps do not overlap at face value (UNIX time against time since
            # boot, or two units' boot clocks) have nothing to align uncompensated: the run does not apply
            # there, which is no shortcoming of the analysis
            applies = not (run == "uncompensated" and face is not None and not _overlap_s(master_al, face) > 0)
            an.align_sections[run] = rp.alignment_skipped(res, opts.filter, opts.match, applies=applies)
    if "logtools.alignment.run" in sys.modules:  # the runs are done: their master series go
        sys.modules["logtools.alignment.run"].forget_master(master_al)
    parallel.release_freed_memory()
    if when_aligned is not None and isinstance(imu_fit, parallel.Pending) and not early:
        when_aligned(an)
    _imu_to_imu_sections(master_al, an, an.align_sections, extra,
                         imu_fit.result() if isinstance(imu_fit, parallel.Pending) else None, slave_comp_al)
    parallel.release_freed_memory()
    tim["alignment"] = time.perf_counter() - t
    tim["total"] = time.perf_counter() - t_all
    an.timings_s = tim
    return an


#: a chosen latency method (``--latency-method``) is said to disagree with tapost's own estimate beyond this many
#: combined sigmas (the seeds' methods assume aligned axes and a fixed search grid: 56 sigma off on a pair
#: mounted at 90 deg yaw; where they hold, within 1-2)
METHOD_DISAGREES_SIGMAS = 5.0


def _chosen_method_disagrees(lat: LatencyResult | None) -> str | None:
    """What to say where the headline latency is another method's than tapost's and tapost's own estimate
    (run beside it, ``--compare``) is more than METHOD_DISAGREES_SIGMAS combined sigmas away."""
    if lat is None or lat.method == "tapost":
        return None
    own = (lat.methods or {}).get("tapost")
    if own is None or not (np.isfinite(own.latency_s) and np.isfinite(own.sigma_s)):
        return None
    sig = math.hypot(lat.sigma_s, own.sigma_s)
    d = lat.latency_s - own.latency_s
    if not (sig > 0 and abs(d) > METHOD_DISAGREES_SIGMAS * sig):
        return None
    return (f"the chosen method {lat.method} gives {lat.latency_s * 1e3:+.3f} ms, {abs(d) / sig:.0f} sigma from "
            f"tapost's own estimate ({own.latency_s * 1e3:+.3f} +/- {own.sigma_s * 1e3:.3f} ms); the seeds' "
            "methods assume aligned axes and a drift of 0 (docs/latency.md)")


def _gives_the_mounting(res) -> bool:
    """Whether the compensated run's result ``res`` is the mounting the outputs use (``Analysis.mounting``
    takes the compensated run's where its angles are finite)."""
    return isinstance(res, AlignmentResult) and bool(np.all(np.isfinite(res.mounting_rpy_deg)))


def start_recording(an: Analysis, out_dir: str):
    """The recording of ``an`` started now, in the child prepared for it (``parallel.prepare``) or a forked
    one, its series logged while this process still works (the 1 h pair: while the IMU-to-IMU fit ends, where
    one core was idle for 0.3-0.5 s); its report comes later, from ``write_outputs(..., recording=...)``.
    None where it is not wanted or forking is not allowed (write_outputs then does it all)."""
    opts = an.options
    if not (opts.recording and an.latency is not None and parallel.available()):
        return None
    try:
        from pipelines.recording import write_recording

        os.makedirs(out_dir, exist_ok=True)
    except (ImportError, OSError):
        return None  # (write_outputs meets it again and says so)
    job = parallel.start_prepared_awaiting("recording", write_recording, os.path.join(out_dir, RECORDING), an,
                                           max_rows=opts.recording_max_rows)
    return StartedRecording(job, frozenset(run for run, res in an.alignment.items() if res is not None))


class StartedRecording:
    """A recording ``start_recording`` started: its child's call (``parallel.start_prepared_awaiting``)
    and the alignment runs it was started with; ``write_outputs`` sends the report with the other runs
    (``pipelines.recording.Rest``)."""

    def __init__(self, job, runs_sent: frozenset[str]) -> None:
        self.job, self.runs_sent = job, runs_sent

    def send(self, rest) -> None:
        self.job.send(rest)

    def result(self):
        return self.job.result()

    def abandon(self) -> None:
        self.job.abandon()


def write_outputs(an: Analysis, out_dir: str, progress=None, recording=None) -> PairOutcome:
    """Write an analysis's outputs in ``out_dir``: report.html (unless ``--no-html``), recording.rrd
    (unless ``--no-recording``), then report.json last, so its presence marks a finished analysis. Every
    file is written atomically. Returns the outcome (report, paths, summary, exit code). ``recording``: the
    recording already started in ``out_dir`` (``start_recording``, which starts one only where this writes
    one), sent its report here."""
    opts = an.options
    prog = progress if progress is not None else null_progress
    t_out = time.perf_counter()
    tim = {k: v for k, v in an.timings_s.items() if k != "total"}
    _refuse_an_input_folder(out_dir, (an.master.meta.source_path, an.slave.meta.source_path))
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder: {exc.strerror}", out_dir) from None
    paths = {"report": os.path.join(out_dir, REPORT),
             "html": os.path.join(out_dir, HTML) if opts.html else None,
             "recording": os.path.join(out_dir, RECORDING) if opts.recording else None}
    an.skipped_steps = {}

    # -- the recording: sent its report where it started already (start_recording: the CLI, logs up to about
    # 1 h), else started first, beside the HTML: in the child prepared for it (small inputs), else in a forked
    # child where this process may fork, else here after the HTML
    t = time.perf_counter()
    if opts.recording and an.latency is not None:
        prog(0.9, "recording")
        try:
            rep = an.build_report({**tim, "report": 0.0, "recording": 0.0}, paths)
            if recording is not None:
                from pipelines.recording import Rest

                # (StartedRecording: a run it started without is logged now)
                sent = getattr(recording, "runs_sent", frozenset())
                recording.send(Rest(rep, {run: res for run, res in an.alignment.items() if run not in sent}))
            else:
                from pipelines.recording import write_recording

                recording = parallel.start_prepared("recording", write_recording, paths["recording"], an, rep,
                                                    max_rows=opts.recording_max_rows)
        except (ImportError, OSError, RuntimeError, ValueError) as exc:
            an.skipped_steps["recording"] = _skip_reason(exc)
            paths["recording"] = None
    elif opts.recording:
        paths["recording"] = None
    tim["recording"] = time.perf_counter() - t

    # -- html
    t = time.perf_counter()
    prog(0.93, "report")
    if opts.html:
        rep = an.build_report({**tim, "report": 0.0, "recording": 0.0,
                               "total": an.timings_s.get("total", 0.0) + time.perf_counter() - t_out}, paths)
        from pipelines.html import write_html

        write_html(paths["html"], rep, an)
    tim["report"] = time.perf_counter() - t

    # -- the recording's end (its time beyond the HTML's)
    t = time.perf_counter()
    if recording is not None:
        prog(0.96, "recording")
        try:
            try:
                an.extra["recording"] = recording.result()
            except ModuleNotFoundError as exc:
                from pipelines.recording import refused_pandas, write_recording

                if not refused_pandas(exc):
                    raise
                # (the prepared child refuses pandas, which this rerun needs after all: written here)
                an.extra["recording"] = write_recording(paths["recording"], an, an.build_report(
                    {**tim, "report": 0.0, "recording": 0.0}, paths), max_rows=opts.recording_max_rows)
        except (ImportError, OSError, RuntimeError, ValueError) as exc:
            an.skipped_steps["recording"] = _skip_reason(exc)
            paths["recording"] = None
    tim["recording"] += time.perf_counter() - t

    # -- the slave on the master's clock (--write-slave, pipelines.export), before report.json lists it
    if opts.write_slave and an.latency is not None:
        from pipelines.export import attach_to_analysis

        t = time.perf_counter()
        attach_to_analysis(opts.write_slave, out_dir, an.slave, an.master, an.latency, paths, an.extra)
        tim["export"] = time.perf_counter() - t

    # -- report.json last, with what an earlier run left in the folder said (a report.html that is not this
    # report's is a trap): in this report alone (another write of the same analysis finds its own folder)
    t = time.perf_counter()
    tim["total"] = an.timings_s.get("total", 0.0) + time.perf_counter() - t_out
    rep = an.build_report(tim, paths)
    stale = _left_from_an_earlier_run(out_dir, paths)
    if stale:
        rep["warnings"] = rep.get("warnings", []) + [
            {"stage": "outputs", "text": f"{name} in {out_dir} is left from an earlier run (this analysis did not "
             "write it): delete it, or write it again"} for name in stale]
        rp.add_findings(rep)
    rp.write_report(paths["report"], rep)
    tim["report"] += time.perf_counter() - t
    an._report = rep
    prog.done() if hasattr(prog, "done") else None
    outcome = PairOutcome(report=rep, out_dir=out_dir, paths=paths, summary=summary_lines(rep, paths),
                          exit_code=0 if an.latency is not None else 1)
    return outcome


def _refuse_an_input_folder(out_dir: str, sources) -> None:
    """InputError where ``out_dir`` is or lies in an input folder (a log read from a folder: a ROS 2 bag, an
    NGIMU unit or session; or the ROS 2 bag a storage file given alone lies in): inputs are never changed,
    and files written into a bag's folder are files of that bag."""
    out = os.path.realpath(out_dir)
    for src in sources:
        if not src:
            continue
        folder = src if os.path.isdir(src) else os.path.dirname(src)
        if not (os.path.isdir(src) or os.path.isfile(os.path.join(folder, "metadata.yaml"))):
            continue
        real = os.path.realpath(folder)
        if out == real or out.startswith(real + os.sep):
            raise InputError(f"the output folder is inside the input folder {folder} (a ROS 2 bag or a sensor's "
                             "folder, which the outputs would change): give another -o", out_dir)


def _left_from_an_earlier_run(out_dir: str, paths: dict) -> list[str]:
    """tapost's own output names in ``out_dir`` (report.html, recording.rrd, slave_on_master_clock.*) that this
    run did not write (``paths``): an analysis rerun into a folder with --no-html, --no-recording or without
    --write-slave leaves the earlier ones, which report.json does not list."""
    from pipelines.export import BASENAME

    written = {os.path.basename(str(v)) for v in paths.values() if v}
    try:
        names = os.listdir(out_dir)
    except OSError:
        return []
    return sorted(n for n in names if n not in written
                  and (n in (HTML, RECORDING) or n.startswith(BASENAME + ".")) and not n.endswith(".tmp"))


def analyze_pair(master_arg: str, slave_arg: str, out_dir: str, opts: AnalyzeOptions | None = None,
                 progress=None) -> PairOutcome:
    """Run the whole analysis of one pair and write its outputs in ``out_dir`` (``compute`` then
    ``write_outputs``; used by batch).

    Raises InputError (unreadable input, exit 2) before anything is written, AnalysisError (exit 1)
    when the latency cannot be estimated (after writing report.json/report.html with the failure).
    """
    an = compute(master_arg, slave_arg, opts, progress)
    outcome = write_outputs(an, out_dir, progress)
    if an.latency is None:
        raise AnalysisError(f"latency failed: {an.failure} (report: {outcome.paths['report']})")
    return outcome


def run(args: argparse.Namespace) -> int:
    config = read_config(args.config) if args.config else None
    opts, out = options_from({**cli_values(args), "out": args.out}, config)
    progress = Progress()
    size = input_bytes("analyze", [args.master, args.slave])
    parallel.small_pair_malloc(size)  # (freed arrays reused from the heap, for the parse too)
    if opts.recording:  # the recording's imports in a child, beside the parse (small inputs: pipelines.parallel)
        if size is not None and size <= parallel.PREPARED_MAX_INPUT_BYTES:
            parallel.prepare("recording", OUTPUT_MODULES["recording"], setup=RECORDING_CHILD_SETUP)
    out_dir = out or "tapost_out"
    # (before the work; a bad path or selector is said by the parse, in its order)
    _refuse_an_input_folder(out_dir, [str(a).partition("::")[0] for a in (args.master, args.slave)])
    there = None
    if (parallel.available() and size is not None and size <= parallel.FORK_PARSE_MIN_INPUT_BYTES
            and _parse_child_sets_up_nothing()):
        # both logs parsed in a forked child while this process imports the analysis' modules (parse_pair)
        there = parallel.submit(_parse_both, args.master, args.slave)
    before_numerics = getattr(args, "_before_numerics", None)  # (the CLI's: cli.keep_scipy_docstrings)
    if before_numerics is not None:
        before_numerics()
    started: list = []  # the recording, started while the IMU-to-IMU fit ends

    def aligned(a: Analysis) -> None:
        job = start_recording(a, out_dir)
        if job is not None:
            started.append(job)

    try:
        an = compute(args.master, args.slave, opts, progress=progress, when_aligned=aligned, there=there)
        outcome = write_outputs(an, out_dir, progress, recording=started[0] if started else None)
    finally:
        progress.done()
        parallel.release("recording")  # not used (no latency, an error): the child exits
        for job in started:
            job.abandon()  # (not sent its report, an error: it ends, its file removed; else nothing)
    print("\n".join(outcome.summary))
    sys.stdout.flush()
    if not an.ok:
        raise AnalysisError(f"latency failed: {an.failure} (report: {outcome.paths['report']})")
    return 0
