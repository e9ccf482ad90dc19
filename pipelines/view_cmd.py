"""``tapost view DIR|FILE.rrd [--web [--bind ADDR]]``: open a recording in the rerun viewer.

* native (default): rerun's desktop viewer. It needs a display: on Linux without ``DISPLAY`` or
  ``WAYLAND_DISPLAY`` the command says in one line to use ``--web`` or to open report.html, and exits 1
  (it does not start the viewer, which would print its own log and a windowing error).
* ``--web``: the web viewer, for a browser on this machine (or another one with ``--bind``). The
  recording file itself is served over plain HTTP from this process (one file, read-only) and rerun
  serves only the viewer's static pages (``rerun --serve-web URL``): no gRPC proxy is started, which
  in rerun 0.41 busy-polls a core while idle. Both listen on 127.0.0.1 unless ``--bind ADDR`` says
  otherwise (``--bind 0.0.0.0``: every interface). The address to open is printed on one line.

Ctrl-C stops the viewer (the whole process group rerun starts) and exits 0. rerun's own output is
kept out of the terminal; when rerun fails, the last line it wrote is shown. On Linux the viewer also
ends when this process is killed outright (SIGKILL): rerun's binary is started directly (not through
the ``rerun`` command's Python wrapper, which would leave it a grandchild) with its parent-death signal
set (``prctl(PR_SET_PDEATHSIG, SIGTERM)``), so no viewer is left listening after us.

A folder is trusted as far as its report.json says: a recording.rrd there that report.json's
``outputs`` does not list (an analysis rerun into the same folder with ``--no-recording``, or one that
failed or skipped its recording) is from another run, and is refused with one line (exit 2). A folder
without report.json, or a .rrd file named directly, is opened as it is.
"""
from __future__ import annotations

import argparse
import http.server
import importlib.util
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import webbrowser
from urllib.parse import quote

from logtools.errors import InputError, TapostError


class NoDisplayError(TapostError):
    """The native viewer cannot open a window here (exit 1)."""

    exit_code = 1


class ViewerError(TapostError):
    """rerun's viewer did not start or stopped with an error (exit 1)."""

    exit_code = 1


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("target", help="an analyze output directory or a .rrd file")
    p.add_argument("--web", action="store_true",
                   help="serve the web viewer (open the printed address in a browser) instead of the native one")
    p.add_argument("--bind", default="127.0.0.1", metavar="ADDR",
                   help="with --web: the address to listen on (default 127.0.0.1, this machine only; "
                        "0.0.0.0 = every interface)")
    p.add_argument("--port", type=port_number, default=0,
                   help="with --web: the web viewer's port, 1..65535 (default, or 0: a free one)")


def port_number(text: str) -> int:
    """``--port``: 1..65535, or 0 for a free one (argparse says a bad one in one line, exit 2, before
    anything starts; rerun itself would refuse it with only its usage hint)."""
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} is no TCP port: give 1..65535 (or 0, the default: a free one)")
    return port


def has_display(environ=None) -> bool:
    """False on Linux (and other X11/Wayland systems) without DISPLAY or WAYLAND_DISPLAY."""
    env = os.environ if environ is None else environ
    if sys.platform == "darwin" or sys.platform.startswith("win"):
        return True
    return bool(env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"))


#: the first bytes of a rerun recording file (RRF0-RRF2 across rerun's versions: the stream header's magic)
RRD_MAGIC = b"RRF"


def _unlisted_recording(folder: str, name: str) -> str | None:
    """Why the analysis whose report.json is in ``folder`` has no recording ``name`` (with what to do, where
    something helps), or None where it lists it or there is no readable report.json to say (the folder is
    then taken as it is)."""
    try:
        with open(os.path.join(folder, "report.json"), encoding="utf-8") as fh:
            rep = json.load(fh)
    except (OSError, ValueError):
        return None
    if not isinstance(rep, dict) or not isinstance(rep.get("outputs"), dict):
        return None  # (no tapost report, or one from before report.json listed its outputs)
    if rep["outputs"].get("recording") == name:
        return None

    def section(key: str) -> dict:
        return rep[key] if isinstance(rep.get(key), dict) else {}

    if section("options").get("recording") is False:
        return "the analysis ran with --no-recording; analyze again without it to write one"
    if section("skipped").get("recording"):
        return f"its recording was skipped: {section('skipped')['recording']}"
    if rep.get("status") == "failed" or "failed" in section("latency"):
        return "a failed analysis (no latency) writes none"
    return "analyze again to write one"


def recording_path(target: str) -> str:
    path = os.path.join(target, "recording.rrd") if os.path.isdir(target) else target
    if os.path.isdir(target):
        why = _unlisted_recording(target, "recording.rrd")
        if why is not None:
            if os.path.lexists(path):
                raise InputError(f"left from another run, not this analysis' recording: the report.json beside "
                                 f"it lists no recording ({why})", path)
            raise InputError(f"no recording: its report.json lists none ({why})", target)
    if not os.path.isfile(path):
        raise InputError("no recording found (expected a .rrd file or a folder holding recording.rrd)", target)
    try:
        with open(path, "rb") as fh:
            head = fh.read(4)
    except OSError as exc:
        raise InputError(f"cannot read the recording: {exc.strerror}", path) from None
    if head[:3] != RRD_MAGIC:
        raise InputError("not a rerun recording (an .rrd file starts with RRF; tapost writes DIR/recording.rrd)", path)
    return path


def rerun_cli() -> list[str]:
    binary = _rerun_binary()
    if binary:
        return [binary]
    exe = shutil.which("rerun")
    return [exe] if exe else [sys.executable, "-m", "rerun"]


def _rerun_binary() -> str | None:
    """Linux: the binary the ``rerun`` command runs (rerun_cli's Python wrapper runs it as its child, which
    a parent-death signal given to the wrapper would not reach): ``RERUN_CLI_PATH`` as the wrapper honours
    it, else the one in this Python's rerun_cli package (the version of the rerun SDK that wrote the
    recording). None elsewhere or where there is none: the ``rerun`` command then."""
    if not sys.platform.startswith("linux"):
        return None
    path = os.environ.get("RERUN_CLI_PATH")
    if not path:
        try:
            spec = importlib.util.find_spec("rerun_cli")
        except (ImportError, ValueError):
            spec = None
        if spec is None or not spec.origin:
            return None
        path = os.path.join(os.path.dirname(spec.origin), "rerun")
    return path if os.path.isfile(path) and os.access(path, os.X_OK) else None


def _die_with_parent():
    """Linux: a ``preexec_fn`` that has the child sent SIGTERM when this process ends, however it ends
    (``prctl(PR_SET_PDEATHSIG)``, kept across exec; tied to the thread that starts the child, which here
    waits for it), and ends the child at once if we are gone already. None elsewhere or where libc's
    prctl cannot be had. Resolved here, so that the forked child only makes the one call."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        from parsers.base import libc

        prctl = libc().prctl
        prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
        prctl.restype = ctypes.c_int
    except (ImportError, OSError, AttributeError):
        return None
    parent = os.getpid()
    pr_set_pdeathsig = 1

    def preexec() -> None:
        prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)
        if os.getppid() != parent:  # (we died before the call)
            os._exit(1)

    return preexec


def free_port(host: str) -> int:
    fam = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(fam, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class _OneFileHandler(http.server.BaseHTTPRequestHandler):
    """Serves one file at ``/<name>`` (GET/HEAD, CORS open so that the viewer's page may fetch it)."""

    file_path = ""
    url_name = ""

    def _head(self, size: int) -> None:
        self.send_response(200)
        self.send_header("Content-Type", "application/octet-stream")
        self.send_header("Content-Length", str(size))
        self.send_header("Access-Control-Allow-Origin", "*")
        self.end_headers()

    def do_HEAD(self) -> None:  # noqa: N802 (http.server's naming)
        if self.path.split("?")[0] != "/" + self.url_name:
            self.send_error(404)
            return
        self._head(os.path.getsize(self.file_path))

    def do_GET(self) -> None:  # noqa: N802
        if self.path.split("?")[0] != "/" + self.url_name:
            self.send_error(404)
            return
        try:
            with open(self.file_path, "rb") as fh:
                self._head(os.fstat(fh.fileno()).st_size)
                shutil.copyfileobj(fh, self.wfile, 1 << 20)
        except (BrokenPipeError, ConnectionResetError):
            pass

    def log_message(self, *args) -> None:  # quiet: no line per request
        pass


def serve_file(path: str, host: str, port: int = 0) -> tuple[http.server.ThreadingHTTPServer, str]:
    """Start a thread serving ``path`` read-only on ``host``; returns (server, the file's URL path)."""
    name = quote(os.path.basename(path))
    handler = type("Handler", (_OneFileHandler,), {"file_path": os.path.abspath(path), "url_name": name})

    class Server(http.server.ThreadingHTTPServer):
        address_family = socket.AF_INET6 if ":" in host else socket.AF_INET
        daemon_threads = True

    srv = Server((host, port), handler)
    threading.Thread(target=srv.serve_forever, name="tapost-view-file", daemon=True).start()
    return srv, name


def _url_host(bind: str) -> str:
    """The host a browser should use for an address we listen on."""
    if bind in ("0.0.0.0", "::", ""):
        return socket.getfqdn() or "localhost"
    return f"[{bind}]" if ":" in bind else bind


_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def _last_line(path: str) -> str:
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            lines = [_ANSI.sub("", ln).strip() for ln in fh]
    except OSError:
        return ""
    lines = [ln for ln in lines if ln]
    return lines[-1] if lines else ""


def _stop(proc: subprocess.Popen) -> None:
    """Stop rerun and the viewer binary it starts as a child (its own process group)."""
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except (ProcessLookupError, PermissionError, AttributeError):
        proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError, AttributeError):
            proc.kill()
        proc.wait(5)


class _Stop(Exception):
    """SIGTERM / SIGHUP while the viewer runs."""


def _raise_stop(signum, frame) -> None:
    raise _Stop(signum)


def _run_viewer(cmd: list[str], *, on_started=None) -> int:
    """Run rerun with its output in a temporary file; Ctrl-C (or SIGTERM, SIGHUP) stops it and the
    viewer binary it starts, then returns 0: rerun runs in its own session, so it must not outlive us."""
    old = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, getattr(signal, "SIGHUP", None)):
            if sig is not None:
                old[sig] = signal.signal(sig, _raise_stop)
    try:
        return _run_viewer_inner(cmd, on_started)
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


def _run_viewer_inner(cmd: list[str], on_started) -> int:
    env = {**os.environ, "RERUN_ANALYTICS": os.environ.get("RERUN_ANALYTICS", "0")}
    with tempfile.NamedTemporaryFile("w+", prefix="tapost-view-", suffix=".log", delete=False) as log:
        log_path = log.name
    try:
        with open(log_path, "w") as out:
            proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, env=env,
                                    start_new_session=True, preexec_fn=_die_with_parent())
        try:
            time.sleep(0.5)
            if proc.poll() is None and on_started is not None:
                on_started()
            code = proc.wait()
        except (KeyboardInterrupt, _Stop):
            _stop(proc)
            print("tapost view: stopped", file=sys.stderr)
            return 0
        if code not in (0, -signal.SIGTERM, 128 + signal.SIGTERM):
            why = _last_line(log_path) or f"exit code {code}"
            raise ViewerError(f"the rerun viewer failed: {why}")
        return 0
    finally:
        try:
            os.remove(log_path)
        except OSError:
            pass


def run(args: argparse.Namespace) -> int:
    path = recording_path(args.target)
    if not getattr(args, "web", False):
        if not has_display():
            report = os.path.join(os.path.dirname(os.path.abspath(path)), "report.html")
            raise NoDisplayError(f"no display here (DISPLAY and WAYLAND_DISPLAY are unset): use "
                                 f"'tapost view --web {args.target}' and open the address it prints in a browser, "
                                 f"or open {report}")
        return _run_viewer(rerun_cli() + [path])
    bind = args.bind or "127.0.0.1"
    try:
        srv, name = serve_file(path, bind)
        web_port = args.port or free_port(bind)
    except OSError as exc:
        raise InputError(f"cannot listen on {bind}: {exc.strerror or exc}") from None
    host = _url_host(bind)
    rrd_url = f"http://{host}:{srv.server_address[1]}/{name}"
    page = f"http://{host}:{web_port}/?url={quote(rrd_url, safe='')}"

    def started() -> None:
        print(f"tapost view: web viewer at {page} (listening on {bind}; Ctrl-C to stop)", flush=True)
        if has_display():
            webbrowser.open(page)

    try:
        return _run_viewer(rerun_cli() + ["--serve-web", "--bind", bind, "--web-viewer-port", str(web_port),
                                          rrd_url], on_started=started)
    finally:
        srv.shutdown()
        srv.server_close()
