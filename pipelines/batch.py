"""``tapost batch CAMPAIGN [-o DIR] [--jobs N] [--scheduler ADDRESS]``: analyze every pair of a campaign.

CAMPAIGN is
  * a folder. Pairs are found by name (case-insensitive), in this order:
      1. one subfolder per pair: ``<name>/master[.ext]`` + ``<name>/slave[.ext]`` (a file or a
         bag directory; pair name = the subfolder's name);
      2. flat files: ``<name>.master.<ext>`` + ``<name>.slave.<ext>`` (pair name = ``<name>``);
      3. the folder itself holding one ``master[.ext]`` + ``slave[.ext]`` (pair name = the folder's).
    A master without its slave (or two candidates) is a failed row saying so.
  * a manifest CSV with a header ``master,slave[,options][,name]``: paths relative to the manifest's
    folder (``PATH[::SELECTOR]`` allowed), ``options`` = analyze options as on the command line
    (e.g. ``--max-lag auto --filter hinf``), ``name`` defaults to ``pairNNN``.

Outputs in DIR (default ``tapost_batch``): ``<pair>/report.json|report.html|recording.rrd`` (as
``tapost analyze``), ``<pair>/done.json`` written last (status, reason, summary row and the inputs'
fingerprint), ``summary.csv`` + ``summary.parquet`` (one row per pair, sorted by pair) and
``index.html`` linking each report. Beside the numbers, each row carries ``input_damage`` (an input's
damage warnings: the pair was analysed on the readable part; index.html shows "ok (damaged input)"),
``warnings`` (how many) and ``worst_warning`` (damage first, then skipped steps, then the rest; notes
are not warnings), and ``latency_at_s`` / ``latency_at_utc``: the instant ``latency_s`` is quoted at
(the middle of the analysed window, master seconds as logged, and UTC when the master is on UNIX time). Every file is written atomically (temp + rename); inputs are
only read. A broken pair is a failed row with its reason, never a crashed batch.

Rerunning skips a pair whose ``done.json`` matches the current inputs and options (size and mtime of
the inputs) and whose report.json is valid (or that failed on the same inputs). Ctrl-C (SIGINT)
stops submitting work, lets the running pairs finish their atomic writes, writes the summary of
what is done and exits 130; the next run completes the rest.
"""
from __future__ import annotations

import argparse
import collections
import concurrent.futures as cf
import csv
import dataclasses
import glob
import hashlib
import html
import io
import json
import multiprocessing as mp
import os
import re
import shlex
import signal
import sys
import threading
import time
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace

from logtools.errors import InputError, TapostError
from pipelines import report as rp
from pipelines.report import input_damage, latency_instant, report_warnings, warning_severity  # noqa: F401 (batch's API)

DONE = "done.json"
SUMMARY_COLUMNS = (
    "pair", "status", "input_damage", "exit_code", "latency_s", "sigma_s", "drift_ppm",
    "latency_at_s", "latency_at_utc",
    "mount_unc_roll_deg", "mount_unc_pitch_deg", "mount_unc_yaw_deg",
    "mount_comp_roll_deg", "mount_comp_pitch_deg", "mount_comp_yaw_deg",
    "mount_comp_sigma_roll_deg", "mount_comp_sigma_pitch_deg", "mount_comp_sigma_yaw_deg",
    "lever_comp_x_m", "lever_comp_y_m", "lever_comp_z_m",
    "warnings", "worst_warning", "reason", "master", "slave", "report",
)
#: text columns of the summary (the rest are numbers)
TEXT_COLUMNS = ("pair", "status", "input_damage", "latency_at_utc", "worst_warning", "reason", "master", "slave",
                "report")


@dataclass(frozen=True)
class PairJob:
    """One pair to analyze; paths absolute, ``options`` = analyze CLI flags, ``problem`` = known broken."""

    name: str
    master: str
    slave: str
    out_dir: str
    options: tuple[str, ...] = ()
    problem: str = ""


# ---- discovery ------------------------------------------------------------------------------
_SAFE = re.compile(r"[^A-Za-z0-9._-]+")


def _safe_name(name: str) -> str:
    return _SAFE.sub("_", name).strip("._") or "pair"


def _role_entries(folder: str, role: str) -> list[str]:
    out = []
    for e in sorted(os.listdir(folder)):
        low = e.lower()
        if not e.startswith(".") and (low == role or low.startswith(role + ".")):
            out.append(os.path.join(folder, e))
    return out


def discover_folder(campaign: str, out_root: str) -> list[PairJob]:
    """Pairs of a campaign folder (naming rule in the module docstring)."""
    jobs: list[PairJob] = []
    out_abs = os.path.abspath(out_root)
    for e in sorted(os.listdir(campaign)):
        d = os.path.join(campaign, e)
        if e.startswith(".") or not os.path.isdir(d) or os.path.abspath(d) == out_abs:
            continue
        ms, ss = _role_entries(d, "master"), _role_entries(d, "slave")
        if not ms and not ss:
            continue
        name = _safe_name(e)
        problem = ""
        if len(ms) != 1 or len(ss) != 1:
            problem = (f"expected one master.* and one slave.* in {d}, found "
                       f"{len(ms)} master ({', '.join(map(os.path.basename, ms)) or '-'}) and "
                       f"{len(ss)} slave ({', '.join(map(os.path.basename, ss)) or '-'})")
        jobs.append(PairJob(name, ms[0] if ms else "", ss[0] if ss else "", os.path.join(out_root, name),
                            problem=problem))
    flat: dict[str, dict[str, list[str]]] = {}
    for e in sorted(os.listdir(campaign)):
        m = re.match(r"^(?P<name>.+?)\.(?P<role>master|slave)(\..*)?$", e, re.IGNORECASE)
        p = os.path.join(campaign, e)
        if m and not e.startswith(".") and os.path.abspath(p) != out_abs:
            flat.setdefault(m["name"], {"master": [], "slave": []})[m["role"].lower()].append(p)
    taken = {j.name for j in jobs}
    for stem, roles in sorted(flat.items()):
        name = _safe_name(stem)
        if name in taken:
            name = f"{name}_flat"
        ms, ss = roles["master"], roles["slave"]
        problem = ""
        if len(ms) != 1 or len(ss) != 1:
            problem = (f"expected one {stem}.master.* and one {stem}.slave.*, found {len(ms)} and {len(ss)}")
        jobs.append(PairJob(name, ms[0] if ms else "", ss[0] if ss else "", os.path.join(out_root, name),
                            problem=problem))
    # the campaign folder itself holding one pair (``tapost batch sample_logs/``)
    ms, ss = _role_entries(campaign, "master"), _role_entries(campaign, "slave")
    ms = [p for p in ms if os.path.abspath(p) != out_abs]
    if len(ms) == 1 and len(ss) == 1:
        name = _safe_name(os.path.basename(os.path.abspath(campaign)))
        name = f"{name}_root" if name in {j.name for j in jobs} else name
        jobs.append(PairJob(name, ms[0], ss[0], os.path.join(out_root, name)))
    return jobs


def discover_manifest(manifest: str, out_root: str) -> list[PairJob]:
    """Pairs of a manifest CSV (``master,slave[,options][,name]``; paths relative to its folder)."""
    base = os.path.dirname(os.path.abspath(manifest))
    try:
        with open(manifest, newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            rows = list(reader)
            header = [(h or "").strip().lower() for h in (reader.fieldnames or [])]
    except UnicodeDecodeError:
        raise InputError("not a manifest CSV (not UTF-8 text): a campaign is a folder of pairs or a manifest CSV "
                         "master,slave[,options][,name]", manifest) from None
    except (OSError, csv.Error) as exc:
        raise InputError(f"cannot read manifest: {exc}", manifest) from None
    if not rows:
        raise InputError("manifest has no pairs (header master,slave[,options][,name] then one row per pair)",
                         manifest)
    if "master" not in header or "slave" not in header:
        raise InputError("manifest header must name the columns master and slave", manifest)

    def resolve(p: str) -> str:
        path, sep, sel = p.strip().partition("::")
        if path and not os.path.isabs(path):
            path = os.path.join(base, path)
        return path + (sep + sel if sep else "")

    jobs, seen = [], set()
    for i, row in enumerate(rows, 1):
        # (fields beyond the header's columns: csv puts them in a list under None; the row's columns are then
        # shifted, and its name too)
        extra = row.pop(None, None) or []
        row = {(k or "").strip().lower(): (v or "").strip() for k, v in row.items()}
        name = _safe_name(f"pair{i:03d}" if extra else (row.get("name") or f"pair{i:03d}"))
        if name in seen:
            name = f"{name}_{i}"
        seen.add(name)
        problem = ""
        try:
            opts = _config_from(base, tuple(shlex.split(row.get("options", ""))))
        except ValueError as exc:
            opts, problem = (), f"bad options in manifest row {i}: {exc}"
        if any(a in ("-o", "--out") or a.startswith(("--out=", "-o=")) for a in opts):
            problem = (f"manifest row {i}: -o is no per-pair option (each pair's outputs go to the campaign's "
                       "output folder, in a folder of the pair's name: give the name column)")
        if not row.get("master") or not row.get("slave"):
            problem = f"manifest row {i} lacks a master or a slave path"
        if extra:
            problem = (f"manifest row {i} has {len(row) + len(extra)} fields for the header's {len(row)} columns: "
                       "quote a field that holds commas (a selector such as \"FILE::imu=IMU,nav=XKF1\")")
        jobs.append(PairJob(name, resolve(row.get("master", "")), resolve(row.get("slave", "")),
                            os.path.join(out_root, name), opts, problem))
    return jobs


def _config_from(base: str, opts: tuple[str, ...]) -> tuple[str, ...]:
    """A manifest row's options with a relative ``--config FILE`` taken from the manifest's folder ``base``, as
    its master and slave paths are (it was taken from where batch ran)."""
    out = list(opts)
    for i, a in enumerate(out):
        if a == "--config" and i + 1 < len(out):
            if out[i + 1] and not os.path.isabs(out[i + 1]):
                out[i + 1] = os.path.join(base, out[i + 1])
        elif a.startswith("--config="):
            path = a[len("--config="):]
            if path and not os.path.isabs(path):
                out[i] = "--config=" + os.path.join(base, path)
    return tuple(out)


def discover(campaign: str, out_root: str) -> list[PairJob]:
    if os.path.isdir(campaign):
        jobs = discover_folder(campaign, out_root)
        if not jobs:
            raise InputError("no pairs found (expected <name>/master.* + <name>/slave.* subfolders, "
                             "<name>.master.* + <name>.slave.* files, or one master.* + slave.* here)", campaign)
        return jobs
    if os.path.isfile(campaign):
        return discover_manifest(campaign, out_root)
    raise InputError("no such campaign folder or manifest", campaign)


# ---- one pair (runs in a worker) ------------------------------------------------------------
def _stat_sig(arg: str) -> list:
    path = arg.partition("::")[0]
    try:
        if os.path.isdir(path):
            parts = []
            for f in sorted(glob.glob(os.path.join(path, "**"), recursive=True)):
                if os.path.isfile(f):
                    st = os.stat(f)
                    parts.append([os.path.relpath(f, path), st.st_size, st.st_mtime_ns])
            return [arg, parts]
        st = os.stat(path)
        return [arg, st.st_size, st.st_mtime_ns]
    except OSError:
        return [arg, None]


def fingerprint(job: PairJob) -> str:
    """Hash of the inputs (path, size, mtime) and options: a done pair is redone when it changes."""
    blob = json.dumps([_stat_sig(job.master), _stat_sig(job.slave), list(job.options), rp.SCHEMA])
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def read_done(job: PairJob) -> dict | None:
    """The done marker if it is valid for the current inputs and its outputs are complete."""
    try:
        with open(os.path.join(job.out_dir, DONE), encoding="utf-8") as fh:
            done = json.load(fh)
    except (OSError, ValueError):
        return None
    if not isinstance(done, dict) or done.get("fingerprint") != fingerprint(job):
        return None
    if done.get("status") == "ok" and not rp.is_complete(os.path.join(job.out_dir, "report.json")):
        return None
    return done


def _clean_temps(out_dir: str) -> None:
    for f in glob.glob(os.path.join(out_dir, ".*.tmp")):
        try:
            os.remove(f)
        except OSError:
            pass


def _v(x, i):
    try:
        return x[i]
    except (TypeError, IndexError, KeyError):
        return None


def display_status(status: str, damage: str | None) -> str:
    """The status as index.html and the batch's printout show it: never a bare "ok" on a damaged input."""
    return f"{status} (damaged input)" if damage and isinstance(damage, str) and status != "failed" else status


def row_from_report(job: PairJob, rep: dict | None, status: str, exit_code: int, reason: str) -> dict:
    row = {c: None for c in SUMMARY_COLUMNS}
    row.update(pair=job.name, status=status, exit_code=exit_code, reason=reason, master=job.master,
               slave=job.slave)
    if rep:
        lat = rep.get("latency", {})
        row.update(latency_s=lat.get("latency_s"), sigma_s=lat.get("sigma_s"), drift_ppm=lat.get("drift_ppm"),
                   report=os.path.join(job.name, "report.html" if (rep.get("outputs") or {}).get("html")
                                       else "report.json"))
        for run, tag in (("uncompensated", "unc"), ("compensated", "comp")):
            a = rep.get("alignment", {}).get(run, {})
            for i, ax in enumerate(("roll", "pitch", "yaw")):
                row[f"mount_{tag}_{ax}_deg"] = _v(a.get("mounting_rpy_deg"), i)
                if tag == "comp":
                    row[f"mount_comp_sigma_{ax}_deg"] = _v(a.get("mounting_sigma_deg"), i)
            if tag == "comp":
                for i, ax in enumerate("xyz"):
                    row[f"lever_comp_{ax}_m"] = _v(a.get("lever_arm_m"), i)
        if not reason and rep.get("skipped"):
            row["reason"] = "; ".join(f"{k}: {v}" for k, v in rep["skipped"].items())
        row["latency_at_s"], row["latency_at_utc"] = latency_instant(rep)
        warns = report_warnings(rep)
        row["warnings"] = len(warns)
        if warns:
            stage, text = max(warns, key=lambda w: warning_severity(*w))  # the first of the worst kind
            row["worst_warning"] = f"{stage}: {text}" if stage and not text.startswith(stage.split()[-1]) else text
        row["input_damage"] = input_damage(rep) or None
    return row


def run_pair(job: PairJob) -> dict:
    """Analyze one pair into ``job.out_dir``; never raises for a broken pair (failed row instead).

    Returns {"row": summary row, "ran": bool (False = outputs were already complete)}."""
    done = read_done(job)
    if done is not None:
        return {"row": done["row"], "ran": False}
    try:
        os.makedirs(job.out_dir, exist_ok=True)
    except OSError as exc:  # (a file in its place, no permission): a failed row, the other pairs go on
        reason = f"{job.out_dir}: cannot create the pair's output folder: {exc.strerror}"
        return {"row": rp.json_safe(row_from_report(job, None, "failed", 2, reason)), "ran": True}
    _clean_temps(job.out_dir)
    try:
        os.remove(os.path.join(job.out_dir, DONE))  # stale marker: this pair is being redone
    except FileNotFoundError:
        pass
    t = time.perf_counter()
    rep, status, code, reason = None, "ok", 0, ""
    if job.problem:
        status, code, reason = "failed", 2, job.problem
    else:
        try:
            from pipelines import analyze

            ns = _parse_options(job.options)
            config = analyze.read_config(ns.config) if ns.config else None
            opts, _ = analyze.options_from(analyze.cli_values(ns), config)
            if hasattr(opts, "name"):  # names the pair's recording "tapost: <pair>"
                opts = replace(opts, name=job.name)
            out = analyze.analyze_pair(job.master, job.slave, job.out_dir, opts)
            rep = out.report
            status = "ok" if rep.get("status") == "ok" else "partial"
        except TapostError as exc:
            status, code, reason = "failed", exc.exit_code, str(exc)
            rep = _load_json(os.path.join(job.out_dir, "report.json"))
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception as exc:  # a bug in a step: this pair fails, the batch goes on
            status, code, reason = "failed", 1, f"internal error: {type(exc).__name__}: {exc}"
    row = row_from_report(job, rep, status, code, reason)
    marker = {"status": status, "exit_code": code, "reason": reason, "fingerprint": fingerprint(job),
              "row": row, "seconds": time.perf_counter() - t, "finished_utc": rp.now_utc()}
    rp.write_text_atomic(os.path.join(job.out_dir, DONE), json.dumps(rp.json_safe(marker), indent=2))
    return {"row": rp.json_safe(row), "ran": True}


def _load_json(path: str) -> dict | None:
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except (OSError, ValueError):
        return None


class _OptParser(argparse.ArgumentParser):
    def error(self, message: str):
        raise InputError(f"bad analyze options: {message}")


def _parse_options(options: tuple[str, ...]) -> argparse.Namespace:
    from pipelines import analyze

    p = _OptParser(prog="options", add_help=False)
    analyze.add_arguments(p)
    from pipelines.cli import glue_vector_values

    return p.parse_args(["MASTER", "SLAVE", *glue_vector_values(list(options))])


# ---- outputs --------------------------------------------------------------------------------
def write_summary(out_root: str, rows: list[dict]) -> dict[str, str]:
    """summary.csv, summary.parquet and index.html (atomic), rows sorted by pair."""
    import pandas as pd

    from parsers.atomic import atomic_path

    rows = sorted(rows, key=lambda r: r["pair"])
    df = pd.DataFrame([{c: r.get(c) for c in SUMMARY_COLUMNS} for r in rows], columns=list(SUMMARY_COLUMNS))
    for c in SUMMARY_COLUMNS:
        if c.endswith(("_s", "_ppm", "_deg")):
            df[c] = pd.to_numeric(df[c], errors="coerce").astype("float64")
    for c in ("exit_code", "warnings"):
        df[c] = pd.to_numeric(df[c], errors="coerce").astype("Int64")
    for c in TEXT_COLUMNS:
        df[c] = df[c].astype("string")
    paths = {k: os.path.join(out_root, f) for k, f in
             (("csv", "summary.csv"), ("parquet", "summary.parquet"), ("index", "index.html"))}
    buf = io.StringIO()
    df.to_csv(buf, index=False)  # full precision (round-trips exactly)
    rp.write_text_atomic(paths["csv"], buf.getvalue())
    with atomic_path(paths["parquet"]) as tmp:
        df.to_parquet(tmp, index=False)
    rp.write_text_atomic(paths["index"], index_html(df))
    return paths


def index_html(df) -> str:
    import pandas as pd

    e = html.escape

    def cell(v, spec=".3f"):
        try:
            if v is None or v != v:
                return "&ndash;"
        except (TypeError, ValueError):
            return "&ndash;"
        return f"{v:{spec}}" if isinstance(v, float) else e(str(v))

    n_ok = int((df["status"] == "ok").sum())
    n_part = int((df["status"] == "partial").sum())
    n_fail = int((df["status"] == "failed").sum())
    n_dmg = int(df["input_damage"].notna().sum())
    rows = []
    for r in df.itertuples(index=False):
        link = f'<a href="{e(str(r.report))}">{e(str(r.pair))}</a>' if isinstance(r.report, str) else e(str(r.pair))
        lat = "&ndash;" if r.latency_s != r.latency_s else f"{r.latency_s * 1e3:+.3f}"
        sig = "&ndash;" if r.sigma_s != r.sigma_s else f"{r.sigma_s * 1e3:.3f}"
        mount = " / ".join(cell(getattr(r, f"mount_comp_{a}_deg")) for a in ("roll", "pitch", "yaw"))
        dmg = r.input_damage if isinstance(r.input_damage, str) else ""
        status = display_status(str(r.status), dmg)
        at = (e(r.latency_at_utc) if isinstance(r.latency_at_utc, str)
              else ("&ndash;" if pd.isna(r.latency_at_s) else f"{r.latency_at_s:.3f} s"))
        nw = 0 if pd.isna(r.warnings) else int(r.warnings)
        worst = e(r.worst_warning) if isinstance(r.worst_warning, str) else ""
        warn = f"{nw}" + (f": {worst}" if worst else "")
        cls = "damaged" if dmg and r.status != "failed" else str(r.status)
        rows.append(f"<tr class={e(cls)}><td>{link}</td><td>{e(status)}</td>"
                    f"<td class=n>{lat}</td><td class=n>{sig}</td><td class=n>{cell(r.drift_ppm, '+.2f')}</td>"
                    f"<td class=n>{at}</td><td class=n>{mount}</td><td>{warn}</td>"
                    f"<td>{cell(r.reason) if isinstance(r.reason, str) else ''}</td></tr>")
    return (
        "<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>tapost batch summary</title><style>"
        "body{font-family:Helvetica,Arial,sans-serif;margin:24px;color:#1d2733}"
        "table{border-collapse:collapse;font-size:13px}th,td{border:1px solid #dde3ea;padding:4px 8px}"
        "th{background:#eef2f6}td.n{text-align:right;font-family:Menlo,Consolas,monospace}"
        "tr.failed td{background:#fdecea}tr.partial td,tr.damaged td{background:#fff6e5}</style></head><body>"
        f"<h1>tapost batch summary</h1><p>{len(df)} pairs: {n_ok} ok, {n_part} partial, {n_fail} failed"
        + (f"; {n_dmg} with a damaged input (analysed on its readable part)" if n_dmg else "") + ". "
        "Also as <a href=summary.csv>summary.csv</a> and summary.parquet.</p>"
        "<table><tr><th>pair</th><th>status</th><th>latency (ms)</th><th>1&sigma; (ms)</th><th>drift (ppm)</th>"
        "<th>latency quoted at (window middle, master clock)</th>"
        "<th>mounting r/p/y, compensated (deg)</th><th>warnings: worst</th><th>reason / skipped steps</th></tr>"
        + "".join(rows) + "</table></body></html>\n")


# ---- scheduling -----------------------------------------------------------------------------
def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _result_or_failure(job: PairJob, fut) -> dict:
    """A worker's result; a worker that died (killed, out of memory) becomes a failed row."""
    try:
        return fut.result()
    except Exception as exc:
        return {"row": row_from_report(job, None, "failed", 1, f"worker failed: {type(exc).__name__}: {exc}"),
                "ran": True}


class _SigintLatch:
    """Ctrl-C raises KeyboardInterrupt as usual and is also remembered: an interrupt that lands where
    Python swallows exceptions (a finaliser, a weakref callback: "Exception ignored in ...") still
    stops the batch before its next pair (``check``) and at its end."""

    def __init__(self) -> None:
        self.requested = False
        self._old = None

    def __enter__(self) -> _SigintLatch:
        if threading.current_thread() is threading.main_thread() and \
                signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            self._old = signal.signal(signal.SIGINT, self._handler)
        return self

    def _handler(self, signum, frame) -> None:
        self.requested = True
        raise KeyboardInterrupt

    def check(self) -> None:
        if self.requested:
            raise KeyboardInterrupt

    def __exit__(self, *exc) -> None:
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)


def _run_local(jobs: list[PairJob], n: int, on_result, latch: _SigintLatch | None = None) -> None:
    """Serial (n = 1, in this process) or ``n`` worker processes, at most ``n`` pairs in flight so
    that an interrupt stops at once: the running pairs finish their (atomic) writes, no new one starts.
    A worker that dies (a crash in a native library on a pair's input, the kernel's out-of-memory killer)
    breaks its pool: the pairs then in flight run again one at a time in a pool of their own (the one that
    kills its worker again is a failed row), and the rest go on in a new pool."""
    check = latch.check if latch is not None else (lambda: None)
    if n <= 1:
        for j in jobs:
            check()
            on_result(j, run_pair(j))
        check()
        return
    ctx = mp.get_context(os.environ.get("TAPOST_MP_START", "spawn"))
    todo = collections.deque(jobs)
    while todo:
        for j in _run_pool(todo, n, ctx, on_result, check):  # (in flight when a worker died)
            on_result(j, _run_alone(j, ctx))
            check()


def _run_pool(todo: collections.deque, n: int, ctx, on_result, check) -> list[PairJob]:
    """The pairs of ``todo`` (taken from it) in a pool of ``n`` workers until it is done or broken; the pairs
    in flight when a worker died (their results unknown), or []."""
    inflight: dict = {}
    with cf.ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=_ignore_sigint) as ex:
        def fill() -> None:
            while len(inflight) < n and todo:
                j = todo.popleft()
                inflight[ex.submit(run_pair, j)] = j

        try:
            fill()
            while inflight:
                done, _ = cf.wait(list(inflight), return_when=cf.FIRST_COMPLETED)
                if any(isinstance(f.exception(), BrokenProcessPool) for f in done):
                    return list(inflight.values())
                for f in done:
                    j = inflight.pop(f)
                    on_result(j, _result_or_failure(j, f))
                check()
                fill()
        except KeyboardInterrupt:
            print(f"tapost batch: interrupted; waiting for {len(inflight)} running pair(s) to finish their "
                  "writes (Ctrl-C again to abandon them)", file=sys.stderr)
            for f in cf.as_completed(list(inflight)):
                j = inflight.pop(f)
                on_result(j, _result_or_failure(j, f))
            raise
    return []


def _run_alone(job: PairJob, ctx) -> dict:
    """One pair in a worker of its own: its result, or a failed row where that worker dies too."""
    with cf.ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_ignore_sigint) as ex:
        fut = ex.submit(run_pair, job)
        if isinstance(fut.exception(), BrokenProcessPool):
            reason = ("the process analysing this pair died (a crash in a native library or compiled code on its "
                      "input, or the system's out-of-memory killer); the other pairs ran")
            return {"row": row_from_report(job, None, "failed", 1, reason), "ran": True}
        return _result_or_failure(job, fut)


def _run_dask(jobs: list[PairJob], address: str, on_result) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise InputError("--scheduler needs dask.distributed (pip install 'tapost[dask]')") from None
    try:
        client = Client(address, timeout="20s")
    except (OSError, TimeoutError) as exc:
        raise InputError(f"cannot connect to the Dask scheduler: {exc}", address) from None
    except (ValueError, TypeError) as exc:  # (distributed's parse of the address: "missing port number")
        raise InputError(f"not a Dask scheduler address ({exc}): give tcp://HOST:PORT", address) from None
    try:
        futs = client.map(run_pair, jobs, pure=False, key=[f"tapost-{j.name}-{fingerprint(j)}" for j in jobs])
        by_key = {f.key: j for f, j in zip(futs, jobs)}
        for f in as_completed(futs):
            on_result(by_key[f.key], _result_or_failure(by_key[f.key], f))
    finally:
        client.close()


def run_batch(campaign: str, out_root: str, *, jobs: int = 1, scheduler: str | None = None,
              log=None, write_slave: str | None = None, no_html: bool = False) -> tuple[list[dict], dict[str, int]]:
    """Analyze every pair; returns (rows sorted by pair, counts {"ran", "skipped", "failed"}).
    ``write_slave`` (csv,parquet,native) is added to every pair's options that do not set it, and with
    ``no_html`` ``--no-html`` to every pair's (both are part of a pair's options, so of its fingerprint)."""
    log = log or (lambda msg: print(msg, file=sys.stderr))
    pair_jobs = discover(campaign, out_root)
    if write_slave:
        from pipelines.export import parse_kinds

        kinds = ",".join(parse_kinds(write_slave))
        pair_jobs = [j if any(o.startswith("--write-slave") for o in j.options)
                     else dataclasses.replace(j, options=tuple(j.options) + ("--write-slave", kinds))
                     for j in pair_jobs]
    if no_html:
        pair_jobs = [j if "--no-html" in j.options else dataclasses.replace(j, options=tuple(j.options) + ("--no-html",))
                     for j in pair_jobs]
    try:
        os.makedirs(out_root, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder: {exc.strerror}", out_root) from None
    rows: dict[str, dict] = {}
    counts = {"ran": 0, "skipped": 0, "failed": 0}
    total = len(pair_jobs)

    def on_result(job: PairJob, res: dict) -> None:
        rows[job.name] = res["row"]
        counts["ran" if res["ran"] else "skipped"] += 1
        if res["row"]["status"] == "failed":
            counts["failed"] += 1
        log(f"[{len(rows)}/{total}] {job.name}: {display_status(res['row']['status'], res['row'].get('input_damage'))}"
            + ("" if res["ran"] else " (already done)")
            + (f" - {res['row']['reason']}" if res["row"]["status"] == "failed" else ""))

    # pairs already complete are not even sent to a worker
    todo = []
    for j in pair_jobs:
        done = read_done(j)
        if done is not None:
            on_result(j, {"row": done["row"], "ran": False})
        else:
            todo.append(j)
    try:
        with _SigintLatch() as latch:
            if scheduler:
                _run_dask(todo, scheduler, on_result)
            else:
                _run_local(todo, max(1, int(jobs)), on_result, latch)
            latch.check()
    finally:
        final = [rows.get(j.name) or row_from_report(j, None, "pending", -1, "not run (interrupted)")
                 for j in pair_jobs]
        write_summary(out_root, final)
    return sorted(final, key=lambda r: r["pair"]), counts


# ---- CLI ------------------------------------------------------------------------------------
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("campaign", help="campaign folder or manifest CSV (master,slave[,options][,name])")
    from pipelines.cli import output_path

    p.add_argument("-o", "--out", default="tapost_batch", type=output_path,
                   help="output directory (default tapost_batch/)")
    p.add_argument("--jobs", type=int, default=1, help="pairs analyzed in parallel (processes)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the pairs on a Dask cluster (e.g. tcp://host:8786)")
    p.add_argument("--write-slave", default=None, metavar="csv|parquet|native[,...]",
                   help="also write each pair's slave on the master's clock (see tapost analyze)")
    p.add_argument("--no-html", action="store_true",
                   help="skip each pair's report.html (report.json is always written; index.html still is)")


def scheduler_address(text: str | None) -> str | None:
    """``--scheduler``: None (not given), else ``[tcp://]HOST:PORT`` with a port 1..65535, checked before any
    pair runs (an empty one ran the campaign here; a port beyond 65535 waited 20 s for a connection)."""
    if text is None:
        return None
    addr = text.strip()
    scheme, _sep, rest = addr.rpartition("://")
    if scheme == "inproc" and rest:  # (a scheduler in this process: dask's LocalCluster(processes=False))
        return addr
    host, colon, port = rest.rpartition(":")
    if not (host and colon and port.isdigit() and 1 <= int(port) <= 65535):
        raise InputError("not a Dask scheduler address (a host and a port 1..65535): give tcp://HOST:PORT",
                         text if text.strip() else "--scheduler ''")
    return addr


def run(args: argparse.Namespace) -> int:
    if args.jobs < 1:
        raise InputError("--jobs must be at least 1")
    args.scheduler = scheduler_address(args.scheduler)
    if args.scheduler is not None and args.jobs != 1:  # (said, not silently dropped)
        print(f"tapost: --jobs {args.jobs} is not used with --scheduler: the cluster's workers run the pairs",
              file=sys.stderr)
    rows, counts = run_batch(args.campaign, args.out, jobs=args.jobs, scheduler=args.scheduler,
                             write_slave=args.write_slave, no_html=args.no_html)
    n_ok = sum(r["status"] in ("ok", "partial") for r in rows)
    print(f"{len(rows)} pairs: {n_ok} analyzed, {counts['failed']} failed; "
          f"{counts['ran']} run now, {counts['skipped']} already done")
    for r in rows:
        lat = f"{r['latency_s'] * 1e3:+.3f} ms" if isinstance(r.get("latency_s"), (int, float)) else "-"
        status = display_status(r["status"], r.get("input_damage"))
        print(f"  {r['pair']:<24} {status:<8} {lat:>12}  {r.get('reason') or r.get('input_damage') or ''}")
    print(f"summary: {os.path.join(args.out, 'summary.csv')}, {os.path.join(args.out, 'index.html')}")
    return 0
