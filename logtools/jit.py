"""Compiled kernels or reference code: one decision per process, made here.

tapost's sequential kernels (the alignment filter's loop, the strapdown, the record walkers of the
parsers, the flexure whitening) are numba-compiled and cached on disk. Compiling them all costs about a
minute on a 2-core machine, once per installation; a 2-minute pair needs none of that speed. So:

* ``compiled`` kernels run when numba's cache already holds them (the stamp below says so), or when the
  input is large enough that the reference code would cost more than compiling (``hint_input_bytes``);
* otherwise this process runs the **reference** code (the same algorithms in numpy and plain Python: the
  code paths that run without numba, tested equal to the compiled ones), and a background process
  compiles the kernels for the next runs (``pipelines/warmup.py``, low priority, once; it writes the stamp
  when every kernel is in the cache).

In compiled mode, where the warm-up also built the kernels ahead of time (logtools.aot), :func:`njit` returns
stand-ins that call that extension and load numba only for argument types it does not export.

``TAPOST_KERNELS=compiled|reference|auto`` (default auto) overrides the choice; ``TAPOST_WARMUP=0`` stops the
background compile. The decision is taken at the first call of :func:`compiled` (the kernel modules call
it when they are imported) and holds for the process.
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time

__all__ = ["compiled", "njit", "lazy", "hint_input_bytes", "mode", "stamp_path", "kernel_fingerprint",
           "write_stamp", "start_background_warmup", "warmup_running", "warmup_wanted", "LARGE_INPUT_BYTES",
           "cache_home"]

#: inputs (master + slave file bytes) from which the reference code costs more than compiling the kernels:
#: the reference alignment runs about 6x slower than the compiled loop (0.45 -> 2.9 s on the 2-minute,
#: 3.7 MB sample pair) and compiling costs about 45 s, so the break-even is near 60 MB of logs (about
#: 15 minutes of 200 Hz data); below it the first run is faster without compiling.
LARGE_INPUT_BYTES = 60_000_000

#: the modules that hold numba kernels (their sources' size and mtime invalidate numba's cache, and so
#: the stamp)
KERNEL_MODULES = ("logtools/strapdown.py", "logtools/alignment/kf.py", "logtools/alignment/model.py",
                  "logtools/alignment/imu_to_imu.py",
                  "logtools/latency/flexure.py", "parsers/mavlink_common.py", "parsers/mcap_ros.py",
                  "parsers/ulog.py", "parsers/csvtable.py", "parsers/rosbag1.py", "parsers/restamp_mavlink.py",
                  "parsers/restamp_csv.py", "parsers/ros_containers.py",
                  "parsers/restamp.py", "parsers/restamp_sqlite.py", "logtools/dsp.py",
                  "logtools/latency_seeds.py")

_state: dict = {"mode": None, "hint": None, "why": ""}


def _root() -> str:
    return os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _numba_install() -> str | None:
    """Where numba is installed, with its version file's and __init__'s sizes and mtimes (any other numba put
    there changes them); None without numba. Neither numba nor importlib.metadata is imported for it (the
    metadata lookup of numba's version cost about 10 ms of every run)."""
    import importlib.util

    try:
        spec = importlib.util.find_spec("numba")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.origin:
        return None
    where = os.path.dirname(spec.origin)
    parts = [where]
    for name in ("_version.py", "__init__.py"):
        try:
            st = os.stat(os.path.join(where, name))
        except OSError:
            continue
        parts.append(f"{name}:{st.st_size}:{st.st_mtime_ns}")
    return "|".join(parts)


def kernel_fingerprint() -> str:
    """numba's installation and the kernel sources' sizes and mtimes (what numba's cache is keyed on); "" without
    numba (no kernels to compile)."""
    numba_key = _numba_install()
    if numba_key is None:
        return ""
    h = hashlib.sha1()
    h.update(numba_key.encode())
    root = _root()
    h.update(root.encode())
    h.update(os.environ.get("NUMBA_CACHE_DIR", "").encode())
    for rel in KERNEL_MODULES:
        try:
            st = os.stat(os.path.join(root, rel))
        except OSError:
            continue
        h.update(f"{rel}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


def cache_home() -> str:
    """tapost's cache directory (``$XDG_CACHE_HOME/tapost``, else ``~/.cache/tapost``): the kernel stamps, the
    ahead-of-time extension, the parsers' cached tables."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "tapost")


def stamp_path(fingerprint: str | None = None) -> str:
    """The file that says every kernel of this installation is in numba's cache."""
    return os.path.join(cache_home(), f"kernels-{fingerprint or kernel_fingerprint()}.json")


def write_stamp(seconds: float) -> str:
    """Called by the warm-up when every kernel compiled (atomic write)."""
    path = stamp_path()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "w") as f:
        json.dump({"compiled_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                   "compile_s": round(seconds, 1), "python": sys.executable}, f)
    os.replace(tmp, path)
    return path


def _numba_importable() -> bool:
    import importlib.util

    return importlib.util.find_spec("numba") is not None


def hint_input_bytes(n: int | None) -> None:
    """The CLI's size of the inputs, before the kernel modules are imported (large inputs compile now)."""
    _state["hint"] = n


def _decide() -> tuple[str, str]:
    env = os.environ.get("TAPOST_KERNELS", "auto").strip().lower()
    if not _numba_importable():
        return "reference", "numba is not installed"
    if env in ("compiled", "reference"):
        return env, f"TAPOST_KERNELS={env}"
    if os.path.exists(stamp_path()):
        return "compiled", "kernels in numba's cache"
    hint = _state["hint"]
    if hint is not None and hint >= LARGE_INPUT_BYTES:
        return "compiled", f"large input ({hint / 1e6:.0f} MB): compiling pays off"
    return "reference", "kernels not compiled yet"


def mode() -> str:
    """"compiled" or "reference" (decided once per process)."""
    if _state["mode"] is None:
        _state["mode"], _state["why"] = _decide()
    return _state["mode"]


def why() -> str:
    mode()
    return _state["why"]


def compiled() -> bool:
    return mode() == "compiled"


def njit(fn=None, *, always: bool = False, **options):
    """``@njit`` / ``@njit(fastmath=False)``: numba.njit(cache=True, ...) in compiled mode, the function itself
    (valid Python) otherwise. ``always=True``: a kernel whose plain-Python run is far too slow to stand in
    (one called thousands of times inside an optimiser): in reference mode it is compiled on its first call
    (numba imported then, the compile announced on stderr), and never runs as Python."""
    options.pop("cache", None)

    def wrap(f):
        if compiled():
            table = aot_table()
            if table is not None:
                from logtools import aot

                return aot.kernel(f, options, table)
            from numba import njit as _njit

            disp = _njit(cache=True, **options)(f)
            _DISPATCHERS.append((disp, dict(options)))
            return disp
        if not always or not _numba_importable():
            return f
        box: list = []

        def first_call(*args):
            if not box:
                from numba import njit as _njit

                sys.stderr.write(f"tapost: compiling {f.__name__} (once; the reference code would take minutes)\n")
                sys.stderr.flush()
                box.append(_njit(cache=True, **options)(f))
            return box[0](*args)

        first_call.__name__, first_call.__doc__, first_call.py_func = f.__name__, f.__doc__, f
        return first_call

    return wrap(fn) if fn is not None else wrap


_DISPATCHERS: list = []  # (numba dispatcher, options) made in this process: what the warm-up exports


def dispatchers() -> list:
    return list(_DISPATCHERS)


def aot_table() -> dict | None:
    """The ahead-of-time compiled kernels of this installation (logtools.aot), loaded once; None without."""
    if "aot" not in _state:
        _state["aot"] = None
        if compiled():
            from logtools import aot

            _state["aot"] = aot.load(kernel_fingerprint())
    return _state["aot"]


def lazy(fn):
    """A getter of ``fn`` compiled on first use (numba imported then), or ``fn`` in reference mode."""
    box: list = []

    def get():
        if not box:
            box.append(njit(fn))
        return box[0]

    return get


# ---- the background warm-up -------------------------------------------------------------------------
def _lock_path() -> str:
    return stamp_path() + ".lock"


def _lock_is_live(path: str, max_age_s: float = 900.0) -> bool:
    try:
        with open(path) as f:
            pid = int(f.read().strip() or 0)
        age = time.time() - os.path.getmtime(path)
    except (OSError, ValueError):
        return False
    if age > max_age_s:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def warmup_running() -> bool:
    """A background warm-up of this installation is running (its lock is live)."""
    return _lock_is_live(_lock_path())


def warmup_wanted() -> bool:
    """A background compile may start (numba is there, TAPOST_WARMUP is not 0)."""
    return os.environ.get("TAPOST_WARMUP", "1") != "0" and _numba_importable()


def start_background_warmup(respect_kernels_env: bool = True) -> bool:
    """Start ``python -m pipelines.warmup`` detached at low priority, unless one runs or it is not wanted
    (TAPOST_WARMUP=0; a TAPOST_KERNELS choice, unless the caller decided in auto mode already).
    Returns True when one was started."""
    if not warmup_wanted():
        return False
    if respect_kernels_env and os.environ.get("TAPOST_KERNELS", "auto").strip().lower() != "auto":
        return False
    if os.path.exists(stamp_path()):
        return False
    lock = _lock_path()
    if _lock_is_live(lock):
        return False
    try:
        os.makedirs(os.path.dirname(lock), exist_ok=True)
        log = open(stamp_path() + ".log", "w")
        env = dict(os.environ, TAPOST_KERNELS="compiled", TAPOST_WARMUP="0")
        proc = subprocess.Popen([sys.executable, "-m", "pipelines.warmup", "--lock", lock],
                                stdin=subprocess.DEVNULL, stdout=log, stderr=log, env=env, cwd=_root(),
                                start_new_session=True, close_fds=True)
        log.close()
        with open(lock, "w") as f:
            f.write(str(proc.pid))
        return True
    except OSError:
        return False
