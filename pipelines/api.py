"""The Python API (DESIGN.md, "Python API"): what ``tapost analyze`` does, for notebooks and scripts.

```python
from pipelines import api                      # or: import tapost as api
log = api.load("flight.BIN::imu=IMU2")          # InsLog
an = api.analyze("master.mcap", "slave.tlog", max_lag="auto")   # in memory: nothing is written
an.report                    # the report.json dict (status, latency, alignment, warnings, notes, ...)
an.latency, an.alignment     # LatencyResult, {"uncompensated"|"compensated": AlignmentResult or None}
an.slave_on_master_clock     # InsLog: the slave's samples with stamps on the master's clock
an.frames()                  # dict of pandas DataFrames (rates, states, residuals, slave on master clock)
an.write("out/")             # the CLI's outputs: report.json, report.html, recording.rrd
```

Keyword options are the CLI's long options with ``_`` for ``-`` (``max_lag=0.5``, ``filter="kf-delay"``,
``lever_arm="0.1,0,0"``, ``no_recording=True``, ``no_html=True``, ``no_compare=True``, ``config="a.toml"``).
Paths are ``str`` (``PATH[::SELECTOR]`` for a log) or any ``os.PathLike`` (``pathlib.Path``: its text is read
as a str's, selector included). Unreadable input raises ``InputError``, and so does a wrong argument (a log
that is neither a path nor an InsLog, an output folder that is no path, a ``progress`` that is no
``progress(fraction, stage)`` callable), naming what was given and what is expected. An InsLog accessor
asked for a channel its log lacks (``quat_wxyz()`` where ``has_quat`` is False) raises
``MissingChannelError`` (an ``AnalysisError``, and a ``KeyError``). A latency the data cannot give does not
raise: ``an.ok`` is False, ``an.failure`` says why and ``an.report["status"]`` is "failed" (the CLI exits 1
there).
"""
from __future__ import annotations

from logtools.errors import AnalysisError, InputError, TapostError
from logtools.inslog import InsLog, MissingChannelError
from logtools.results import AlignmentResult, LatencyResult
from parsers import load as _load
from parsers.registry import path_arg
from pipelines import analyze as _analyze
from pipelines.analyze import Analysis, AnalyzeOptions

__all__ = ["load", "analyze", "options", "Analysis", "AnalyzeOptions", "InsLog", "LatencyResult",
           "AlignmentResult", "TapostError", "InputError", "AnalysisError", "MissingChannelError"]

#: keyword options: the CLI's long options (``tapost analyze --help``), dashes as underscores
OPTIONS = _analyze.CLI_KEYS + ("no_compare", "config")


def load(arg) -> InsLog:
    """Read one unit of a log, ``PATH[::SELECTOR]`` (a str, or an ``os.PathLike`` such as ``pathlib.Path``;
    ``tapost inspect PATH`` lists the selectors). An InsLog is returned as it is (``analyze`` takes either)."""
    if isinstance(arg, InsLog):
        return arg
    return _load(arg)  # (parsers.load takes a str or an os.PathLike, and says what else it was given)


def options(**opts) -> AnalyzeOptions:
    """The analysis options from keyword options named like the CLI's long options."""
    unknown = set(opts) - set(OPTIONS)
    if unknown:
        raise InputError(f"unknown option(s): {', '.join(sorted(unknown))}; known: {', '.join(OPTIONS)}")
    config_path = opts.pop("config", None)
    config = _analyze.read_config(path_arg(config_path, "config", selector=False)) if config_path else None
    no_compare = opts.pop("no_compare", None)
    if no_compare is not None and _analyze._flag("no_compare", no_compare):  # (None: not given, as the CLI's)
        opts["compare"] = False
    cli = {k: opts.get(k) for k in _analyze.CLI_KEYS}
    return _analyze.options_from(cli, config)[0]


def _log_arg(arg, role: str) -> str | InsLog:
    """``analyze``'s ``master``/``slave``: an InsLog as it is, a path as a str (a Path's text, so that the
    report records a str and large files are parsed in parallel as the CLI's are)."""
    return arg if isinstance(arg, InsLog) else path_arg(arg, f"the {role} log", inslog=True)


def analyze(master: str | InsLog, slave: str | InsLog, progress=None, **opts) -> Analysis:
    """Analyze one pair in memory: latency, compensation, both alignment runs (nothing is written).

    ``master``/``slave`` are ``PATH[::SELECTOR]`` strings, ``os.PathLike`` paths or InsLogs (``load``).
    ``progress`` is an optional ``progress(fraction, stage)`` callback. Wrong arguments raise InputError."""
    from pipelines.firstrun import announce_compiling

    master, slave = _log_arg(master, "master"), _log_arg(slave, "slave")
    progress = _analyze.progress_arg(progress)
    opts_ = options(**opts)
    announce_compiling()  # one line on stderr if numba compiles (the first run after installing)
    return _analyze.compute(master, slave, opts_, progress=progress)
