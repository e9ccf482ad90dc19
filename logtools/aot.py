"""tapost's kernels compiled ahead of time into one extension module: numba's runtime never loads.

A process that runs numba-compiled kernels from numba's on-disk cache still pays numba's start-up: its import
(0.15 s), its typing and target contexts on the first call (0.3 s: numba imports most of itself then) and
each kernel's load (5-40 ms). On a 2-minute pair that is a third of the whole run. The same machine code can
be had without numba: ``numba.pycc`` compiles the kernels, with the argument types real runs pass, into a
plain CPython extension that needs only numpy to run.

* :func:`build` (run by the background warm-up, after the kernels compiled into numba's cache) exports every
  kernel the warm-up called, once per argument-type signature it was called with, into
  ``~/.cache/tapost/aot-<fingerprint>/``: the extension and ``table.json`` (which export serves which kernel
  at which argument types; the CPU it was compiled for).
* :func:`load` (``logtools.jit``, once per process in compiled mode) imports that extension when it was built
  for this installation (the kernel fingerprint), this CPU, this Python and this numpy.
* :class:`Kernel` stands in for a numba dispatcher: a call whose arguments' types (numpy dtype, dimensions,
  layout, writability; Python and numpy scalars; tuples of those) match an export runs the export;
  anything else (a type no warm-up passed, a damaged-file path, a format not warmed) makes numba's
  dispatcher, exactly as without this module, and rebinds every stand-in to its dispatcher first (numba
  compiles a kernel that calls another through its module's globals). The exports do not check their
  arguments' types (a mismatch would read memory as the wrong type), so the match here is exact.

Exports keep the kernels' numba options (``nogil`` releases the GIL around the call, as the dispatcher does)
and numba's defaults otherwise (no fastmath, Python's error model): the same machine code as numba's cache,
the same results bit for bit (tested). Where no C compiler is present, the build fails and says so in the
warm-up's log; runs then use numba's cache as before. ``TAPOST_AOT=0`` turns the extension off.
"""
from __future__ import annotations

import contextlib
import hashlib
import importlib.machinery
import importlib.util
import json
import os
import platform
import shutil
import sys
import tempfile
import threading
import time
import warnings

import numpy as np

__all__ = ["Kernel", "build", "load", "arg_key", "numba_key", "cpu_key", "aot_dir", "enabled"]

MODULE = "tapost_kernels"  #: the extension's name (its init function is PyInit_tapost_kernels)
TABLE = "table.json"

_ARRAY = np.ndarray
_GENERIC = np.generic


def enabled() -> bool:
    return os.environ.get("TAPOST_AOT", "1").strip() != "0"


def cpu_key() -> str:
    """The CPU the extension's code was compiled for (numba compiles for the host's instruction set): model
    and feature flags from /proc/cpuinfo, or the platform's processor name elsewhere."""
    text = ""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("model name", "flags", "Features", "CPU part")):
                    text += line
                if line.strip() == "" and text:
                    break
    except OSError:
        pass
    if not text and sys.platform == "darwin":  # (no /proc: the CPU's brand and features from sysctl)
        import subprocess

        for key in ("machdep.cpu.brand_string", "machdep.cpu.features", "hw.optional.arm64"):
            try:
                text += subprocess.run(["sysctl", "-n", key], capture_output=True, text=True, timeout=5).stdout
            except (OSError, subprocess.SubprocessError):
                pass
    # (the processor's name only where neither gave anything: on Linux it is `uname -p`, run in a subprocess,
    # a fork of the analysing process in every run, and it says nothing the model name and flags do not)
    text += platform.machine() + ("" if text else f"|{platform.processor()}")
    return hashlib.sha1(text.encode()).hexdigest()[:16]


def aot_dir(fingerprint: str) -> str:
    from logtools import jit

    return os.path.join(os.path.dirname(jit.stamp_path(fingerprint)), f"aot-{fingerprint}")


# ---- argument types --------------------------------------------------------------------------------------
def arg_key(x) -> str | None:
    """The type numba's dispatcher would give ``x``, as a short string; None for a type no export takes."""
    if isinstance(x, _ARRAY):
        fl = x.flags
        layout = "C" if fl.c_contiguous else "F" if fl.f_contiguous else "A"
        return f"a{x.dtype.str}{x.ndim}{layout}{'w' if fl.writeable else 'r'}"
    if isinstance(x, bool):
        return "bool"
    if isinstance(x, int):
        return "int64" if -(1 << 63) <= x < (1 << 63) else None
    if isinstance(x, float):
        return "float64"
    if isinstance(x, _GENERIC):
        return x.dtype.name if x.dtype.kind in "biuf" else None
    if isinstance(x, tuple):
        parts = [arg_key(e) for e in x]
        return None if None in parts else "(" + ",".join(parts) + ")"
    if x is None:
        return "none"
    return None


def numba_key(t) -> str | None:
    """:func:`arg_key` of a value numba types as ``t`` (build side); None for a type no export takes."""
    from numba.core import types
    from numba.np import numpy_support

    if isinstance(t, types.Array):
        if not t.aligned or t.layout not in "CFA":
            return None
        try:
            dt = numpy_support.as_dtype(t.dtype)
        except Exception:  # noqa: BLE001 - a dtype numpy has no name for: not exported
            return None
        if dt.kind not in "biuf":
            return None
        return f"a{dt.str}{t.ndim}{t.layout}{'w' if t.mutable else 'r'}"
    if isinstance(t, types.Boolean):
        return "bool"
    if isinstance(t, (types.Integer, types.Float)):
        return str(t)
    if isinstance(t, types.BaseTuple) and not isinstance(t, types.NamedTuple):
        parts = [numba_key(e) for e in t.types]
        return None if None in parts else "(" + ",".join(parts) + ")"
    if isinstance(t, types.NoneType):
        return "none"
    return None


def kernel_name(py_func) -> str:
    return f"{py_func.__module__}:{py_func.__qualname__}"


# ---- the stand-in ----------------------------------------------------------------------------------------
class Kernel:
    """A kernel served by the extension's exports, numba's dispatcher for any other argument types."""

    def __init__(self, py_func, options: dict, exports: dict):
        self.py_func = py_func
        self.options = options
        self._exports = exports  # argument-types key -> exported function
        self._dispatcher = None
        self.__name__, self.__qualname__ = py_func.__name__, py_func.__qualname__
        self.__module__, self.__doc__, self.__wrapped__ = py_func.__module__, py_func.__doc__, py_func

    def __call__(self, *args, **kwargs):
        if kwargs:  # (keyword arguments: numba's dispatcher, which binds them)
            return self.dispatcher()(*args, **kwargs)
        key = ",".join(map(_key_or_miss, args))
        ex = self._exports.get(key)
        if ex is not None:
            return ex(*args)
        if key not in self._exports:
            ex = self._exports[key] = _widening(key, self._exports)  # (None: numba's dispatcher)
            if ex is not None:
                return ex(*args)
        return self.dispatcher()(*args)

    def dispatcher(self):
        """numba's dispatcher of this kernel (numba loads, and every stand-in becomes its dispatcher)."""
        if self._dispatcher is None:
            _materialise()
        return self._dispatcher

    def __reduce__(self):
        """Pickled by name, as a function is (a process that unpickles it has its own stand-in)."""
        return _by_name, (self.py_func.__module__, self.py_func.__qualname__)

    def __repr__(self) -> str:
        return f"<tapost kernel {kernel_name(self.py_func)}: {len(self._exports)} exported signature(s)>"


def _by_name(module: str, qualname: str):
    import importlib

    obj = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    return obj


def _widening(key: str, exports: dict):
    """An export whose argument types take the call's without a conversion that could change anything: a
    contiguous array where the export takes any layout ('A'), a writable array where it takes a read-only one
    (the compiled code then never writes it). numba's dispatcher would compile these types anew; the machine
    code differs only in how it indexes, so the results are the same. None when no export takes them."""
    if "(" in key or "?" in key:  # (tuples: exact types only)
        return None
    got = key.split(",")
    for other, ex in list(exports.items()):
        if ex is None:
            continue
        want = other.split(",")
        if len(want) == len(got) and all(a == e or _array_takes(e, a) for a, e in zip(got, want)):
            return ex
    return None


def _array_takes(e: str, a: str) -> bool:
    return e[:1] == "a" == a[:1] and e[:-2] == a[:-2] and e[-2] in ("A", a[-2]) and e[-1] in ("r", a[-1])


def _key_or_miss(x) -> str:
    k = arg_key(x)
    return "?" if k is None else k


_KERNELS: list[Kernel] = []
_HOOKS: list = []  # called once when numba first loads (the CLI's compile announcement)
_LOCK = threading.RLock()  # (kernels run in threads: one materialisation)


def on_numba_load(hook) -> None:
    _HOOKS.append(hook)


def _materialise() -> None:
    """numba's dispatchers for every stand-in made so far, and the stand-ins in tapost's modules' globals
    replaced by them (a kernel compiled now calls its callees through those globals)."""
    with _LOCK:
        from numba import njit

        fresh = [k for k in _KERNELS if k._dispatcher is None]
        if not fresh:
            return
        for hook in list(_HOOKS):
            _HOOKS.remove(hook)
            hook()
        made = {id(k): njit(cache=True, **k.options)(k.py_func) for k in fresh}
        _rebind({id(k): made.get(id(k), k._dispatcher) for k in _KERNELS})
        for k in fresh:
            k._dispatcher = made[id(k)]


def _rebind(by_id: dict) -> None:
    """Every stand-in in the globals of tapost's modules and of the kernels' own modules -> its dispatcher."""
    owners = {k.py_func.__module__ for k in _KERNELS}
    for name, mod in list(sys.modules.items()):
        if mod is None or not (name in owners or name.startswith(("logtools", "parsers", "pipelines"))):
            continue
        d = getattr(mod, "__dict__", None)
        if not d:
            continue
        for attr, val in list(d.items()):
            if type(val) is Kernel and by_id.get(id(val)) is not None:
                d[attr] = by_id[id(val)]


# ---- loading ---------------------------------------------------------------------------------------------
_LOADED: dict = {}


def load(fingerprint: str) -> dict | None:
    """``{kernel name: {argument-types key: export}}`` from this installation's extension; None when there is
    none for this fingerprint and CPU (or ``TAPOST_AOT=0``, or it does not import)."""
    if fingerprint in _LOADED:
        return _LOADED[fingerprint]
    table = None
    meta = _meta(fingerprint) if enabled() and fingerprint else None
    if meta is not None:
        try:
            path = os.path.join(aot_dir(fingerprint), meta["file"])
            loader = importlib.machinery.ExtensionFileLoader(MODULE, path)
            spec = importlib.util.spec_from_file_location(MODULE, path, loader=loader)
            mod = importlib.util.module_from_spec(spec)
            loader.exec_module(mod)
            table = {name: {key: getattr(mod, sym) for key, sym in rows} for name, rows in meta["kernels"].items()}
        except (OSError, ValueError, KeyError, ImportError, AttributeError, TypeError):
            table = None
    _LOADED[fingerprint] = table
    return table


def _meta(fingerprint: str) -> dict | None:
    """The table of this installation's extension, when it was built for this CPU, this Python and this numpy
    (its C API: an upgraded numpy needs it built again); else None."""
    try:
        with open(os.path.join(aot_dir(fingerprint), TABLE)) as f:
            meta = json.load(f)
    except (OSError, ValueError):
        return None
    same = (isinstance(meta, dict) and meta.get("cpu") == cpu_key()
            and meta.get("python") == sys.implementation.cache_tag and meta.get("numpy") == np.__version__)
    return meta if same else None


def built(fingerprint: str) -> bool:
    """This installation's extension exists for this CPU, Python and numpy and was built by these sources
    (whether or not TAPOST_AOT is 0)."""
    meta = _meta(fingerprint)
    return (meta is not None and meta.get("builder") == _builder()
            and os.path.isfile(os.path.join(aot_dir(fingerprint), str(meta.get("file")))))


def _builder() -> str:
    """This module's and the warm-up's sources (what decides which signatures are exported): a changed one
    builds the extension anew."""
    from logtools import jit

    h = hashlib.sha1()
    for rel in ("logtools/aot.py", "pipelines/warmup.py"):
        try:
            st = os.stat(os.path.join(jit._root(), rel))
            h.update(f"{rel}:{st.st_size}:{st.st_mtime_ns}".encode())
        except OSError:
            pass
    return h.hexdigest()[:16]


def kernel(py_func, options: dict, table: dict) -> Kernel:
    """The stand-in for ``py_func``: its exports, or none (a kernel only other kernels call, or one no
    warm-up ran: numba loads when it is first called from Python)."""
    k = Kernel(py_func, options, table.get(kernel_name(py_func)) or {})
    _KERNELS.append(k)
    return k


# ---- building --------------------------------------------------------------------------------------------
@contextlib.contextmanager
def _as_numba_compiles(options_of: dict):
    """numba.pycc compiles every export with one set of flags and for the CPU model's generic features; while
    this holds, each kernel gets its own ``nogil`` (the CPython wrapper then releases the GIL around the call,
    as numba's dispatcher does) and the code the host's own features (what numba's JIT compiles for: a
    virtual machine may lack features its CPU model implies)."""
    import numba.pycc.compiler as pc
    from numba.core import codegen as cg

    plain, plain_features = pc.compile_extra, cg.AOTCPUCodegen._customize_tm_features

    def compile_extra(typingctx, targetctx, func, args, return_type, flags, locals, library=None, **kw):
        if options_of.get(id(func), {}).get("nogil"):
            flags = flags.copy()
            flags.release_gil = True
        return plain(typingctx, targetctx, func, args, return_type, flags, locals, library=library, **kw)

    pc.compile_extra = compile_extra
    cg.AOTCPUCodegen._customize_tm_features = lambda self: self._get_host_cpu_features()
    try:
        yield
    finally:
        pc.compile_extra, cg.AOTCPUCodegen._customize_tm_features = plain, plain_features


def build(dispatchers, fingerprint: str, log=None) -> str:
    """Export every compiled signature of ``dispatchers`` (``(dispatcher, options)`` pairs, numba's) into
    this installation's extension; returns its folder. Raises when the compile fails (no C compiler...)."""
    with warnings.catch_warnings():  # ("pending deprecation" since numba 0.57, with no replacement yet: said in docs)
        warnings.simplefilter("ignore")
        from numba.pycc import CC

    say = log or (lambda text: None)
    t0 = time.perf_counter()
    out = aot_dir(fingerprint)
    work = tempfile.mkdtemp(prefix="tapost-aot-", dir=os.path.dirname(out) if os.path.isdir(
        os.path.dirname(out)) else None)
    try:
        cc = CC(MODULE)
        cc.output_dir = work
        cc.target_cpu = "host"  # (numba's cache compiles for the host too; the table records which CPU)
        cc.verbose = False
        rows: dict[str, list] = {}
        options_of: dict[int, dict] = {}
        n = 0
        for disp, options in dispatchers:
            name = kernel_name(disp.py_func)
            for sig in disp.nopython_signatures:
                keys = [numba_key(a) for a in sig.args]
                if None in keys:  # (an argument type no call could match: left to numba)
                    continue
                key = ",".join(keys)
                if any(k == key for k, _ in rows.get(name, ())):  # (a kernel made twice: each signature once)
                    continue
                sym = f"k{n}"
                n += 1
                cc.export(sym, sig)(disp.py_func)
                options_of[id(disp.py_func)] = options
                rows.setdefault(name, []).append([key, sym])
        if not n:
            raise RuntimeError("no kernel to export")
        with _as_numba_compiles(options_of):
            cc.compile()
        so = [f for f in os.listdir(work) if f.startswith(MODULE) and f.endswith(tuple(
            importlib.machinery.EXTENSION_SUFFIXES))]
        if len(so) != 1:
            raise RuntimeError(f"the compile left {so or 'no extension'}")
        meta = {"file": so[0], "cpu": cpu_key(), "python": sys.implementation.cache_tag, "builder": _builder(),
                "numpy": np.__version__,
                "fingerprint": fingerprint, "exports": n, "compile_s": round(time.perf_counter() - t0, 1),
                "kernels": rows}
        with open(os.path.join(work, TABLE), "w") as f:
            json.dump(meta, f, indent=0)
        if os.path.isdir(out):
            shutil.rmtree(out, ignore_errors=True)
        os.replace(work, out)  # (the folder appears whole or not at all)
        work = None
        _remove_stale(out)
        say(f"  {n} kernel signatures compiled ahead of time in {time.perf_counter() - t0:.0f} s ({out})")
        return out
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)


def _remove_stale(keep: str) -> None:
    """Other installations' or earlier sources' extensions in the same cache folder, unused for a week."""
    base = os.path.dirname(keep)
    for name in os.listdir(base):
        path = os.path.join(base, name)
        if name.startswith("aot-") and path != keep and os.path.isdir(path):
            try:
                if time.time() - os.path.getmtime(path) > 7 * 86400:
                    shutil.rmtree(path, ignore_errors=True)
            except OSError:
                pass
