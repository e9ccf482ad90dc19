"""The ``tapost`` command line (DESIGN.md, "CLI contract").

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and ``run(args) -> int``.
Known failures (``TapostError``) become one line on stderr and the error's exit code
(0 success, 1 analysis failed, 2 bad usage or unreadable input); ``--debug`` shows tracebacks.
"""
from __future__ import annotations

import argparse
import errno
import gc
import importlib
import os
import signal
import sys

from logtools import __version__
from logtools.errors import TapostError, os_error_path

COMMANDS = {
    "inspect": ("pipelines.inspect_cmd", "list a log's channels, rates, durations, clocks, selectors"),
    "analyze": ("pipelines.analyze", "latency + compensation + transfer alignment for one pair"),
    "batch": ("pipelines.batch", "analyze every pair of a campaign folder or manifest"),
    "restamp": ("pipelines.restamp_cmd", "write a slave log on the master's clock from a finished report"),
    "simulate": ("pipelines.simulate_cmd", "write a synthetic master/slave pair with truth.json"),
    "view": ("pipelines.view_cmd", "open a recording in the rerun viewer"),
}


#: BLAS threads of a tapost process (set before numpy is imported; a value the user set is kept). The
#: numerics' matrices are small (tens of columns) and ``analyze`` already runs two stages at once in
#: forked processes, ``batch`` one pair per core: BLAS threads of their own only wait on each other.
#: Measured with OpenBLAS on 2 cores: the sample pair 0.90x the wall time and 0.81x the CPU of 2 threads,
#: the same report to the last digit; the test suite (two workers) from 312 s to 193 s
BLAS_THREADS = "1"
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
#: numpy's madvise(MADV_HUGEPAGE) on its arrays of 4 MB and more, off in a tapost process (numpy's own
#: switch, read when numpy is imported; a value the user set is kept). Every stage allocates and frees
#: arrays of the logs' length, and each first touch of a 2 MB huge page zeroes all of it in the kernel; in a
#: virtual machine whose freed memory goes back to the host (virtio-balloon free page reporting: Firecracker,
#: cloud hypervisors), huge pages come from freshly returned blocks and the host backs them again. Measured on
#: such a 2-core VM, whole `tapost analyze` processes of the 1 h pair: 16.5-17.4 s wall with 5.4-6.8 s of
#: system time, against 14.0-14.4 s with 2.4 s; the same user time and peak RSS, report.json the same to the
#: bit; the sample pair and the 4 h pair unchanged within their scatter (benchmarks/README.md)
NUMPY_HUGEPAGES = "0"
NUMPY_HUGEPAGE_VARIABLE = "NUMPY_MADVISE_HUGEPAGE"
#: the garbage collector's thresholds in a tapost process and its children (Python's are 700, 10, 10). A run
#: imports numpy and scipy, and its recording's child rerun: millions of long-lived objects, which every full
#: collection scans (40-50 ms each, several per run of the sample pair, most of them while those imports run).
#: With the young generation collected every 100 000 allocations instead of 700, a short run makes none or
#: one; reference cycles are still collected. Measured on 2 cores, whole processes alternated: the sample
#: pair 1.09 -> 1.00 s (medians of 6), the 1 h pair the same wall time and peak memory (9.1-9.4 s,
#: 0.84-0.86 GB) either way
GC_THRESHOLDS = (100_000, 10, 10)
#: numpy's submodules that scipy's array-API layer (scipy 1.15 and later) imports in every process that
#: imports scipy: it asks numpy for each of its public names, and numpy imports those submodules on demand
#: (f2py also pulls in charset_normalizer). tapost's log commands use none of these, so they are registered as
#: lazy modules (importlib.util.LazyLoader: loaded on first attribute access) before scipy is imported. Not
#: numpy.char (some parsers use it): nothing the analysis touches goes through a lazy module, whose first
#: access is not thread-safe before Python 3.12. Nor numpy.ma or numpy.strings, which pandas loads wherever it
#: is imported: deferring them in the analysing process too measured no difference (0.749 and 0.746 s).
#: Measured on 2 cores: importing scipy.linalg, fft and ndimage 0.19-0.20 -> 0.13-0.16 s
NUMPY_DEFERRED_SUBMODULES = ("f2py", "testing", "ctypeslib", "polynomial", "rec")


def set_numpy_environment() -> None:
    """BLAS_THREADS and NUMPY_HUGEPAGES for this process and its children, where the user has not chosen
    (before numpy loads: after, the variables do nothing)."""
    for name in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, BLAS_THREADS)
    os.environ.setdefault(NUMPY_HUGEPAGE_VARIABLE, NUMPY_HUGEPAGES)


def defer_numpy_submodules() -> None:
    """NUMPY_DEFERRED_SUBMODULES as lazy modules (after ``set_numpy_environment``: this imports numpy).
    Only an optimisation: whatever fails leaves numpy as it is."""
    try:
        import importlib.util

        import numpy
    except ImportError:
        return
    for sub in NUMPY_DEFERRED_SUBMODULES:
        name = f"numpy.{sub}"
        if name in sys.modules:
            continue
        try:
            spec = importlib.util.find_spec(name)
            if spec is None or spec.loader is None:
                continue
            spec.loader = importlib.util.LazyLoader(spec.loader)
            module = importlib.util.module_from_spec(spec)
            sys.modules[name] = module
            spec.loader.exec_module(module)
            setattr(numpy, sub, module)
        except Exception:  # noqa: BLE001 - numpy loads it the usual way then
            sys.modules.pop(name, None)


def preload_numpy_ma() -> None:
    """numpy.ma loaded now, in analyze's process before it forks: the process loads it anyway (scipy's
    array-API layer asks numpy for every public name), and its children loaded it each on their own (the parse
    child through ``np.unique``, which asks ``np.ma.is_masked``; the recording child through rerun's colour
    conversion): about 11 ms of CPU each. The sample pair, whole processes alternated (24 pairs, twice): CPU
    1.023 -> 1.002 s and 1.055 -> 1.042 s, wall 0.611 -> 0.602 s and 0.636 -> 0.623 s."""
    try:
        import numpy

        numpy.ma.is_masked  # noqa: B018 - (numpy 2 loads the submodule on this first access)
    except (ImportError, AttributeError):
        pass


#: the commands whose analysis imports scipy (fft, linalg, ndimage) in every run
SCIPY_COMMANDS = ("analyze", "batch", "simulate")


class _DocAsIs:
    """Stands in for scipy's docstring scraper in ``keep_scipy_docstrings``: the docstring as it is."""

    def __init__(self, f, *args, **kwargs):
        self._doc = getattr(f, "__doc__", None) or ""

    def __getitem__(self, section):
        return []  # (a section the caller appends to, then drops)

    def __str__(self) -> str:
        return "\n" + self._doc  # (the caller drops the first line, the signature)


def keep_scipy_docstrings() -> None:
    """scipy 1.15 and later rewrite the docstring of every function they mark with its array-API capabilities
    (``scipy._lib._array_api.xp_capabilities``) while the module is imported: the docstring is parsed by
    numpydoc's scraper and written back with a table appended. That is about 50 ms of every analyze (about
    200 functions in scipy.fft, linalg, ndimage, special), for docstrings a command never shows. In this
    process the decorator still records each function's capabilities and leaves its docstring as it is.
    The same for scipy's batching decorator (``scipy._lib._util._apply_over_batch``), which scrapes the
    docstrings of about 70 scipy.linalg functions to append a note on batched arguments: 20-40 ms of the
    imports the latency stage waits for (measured in a fresh process after the parse: the analysis' imports
    0.108-0.17 s -> 0.087-0.11 s). Each checked on a probe function first (:func:`_scraper_as_is`)."""

    def capabilities_kept(decorator) -> bool:
        def probe():
            """Probe.

            Text.
            """

        doc = probe.__doc__
        decorator(capabilities_table={})(probe)
        return probe.__doc__ == doc

    def batching_kept(decorator) -> bool:
        def probe(a):
            """Probe.

            Text.
            """
            return a

        doc = probe.__doc__
        wrapped = decorator(("a", 1))(probe)
        return wrapped.__doc__ == doc and list(wrapped([1.0, 2.0])) == [1.0, 2.0]

    _scraper_as_is("scipy._lib._array_api", "xp_capabilities", capabilities_kept)
    _scraper_as_is("scipy._lib._util", "_apply_over_batch", batching_kept)


def _scraper_as_is(module_name: str, decorator: str, works) -> None:
    """``module_name``'s docstring scraper (its ``FunctionDoc``) replaced by :class:`_DocAsIs` where
    ``works(module.<decorator>)`` says the decorator still does its job with it (on a probe function); when
    it says not, or raises (not the decorator known), or the module has another layout, scipy's own scraper
    stays."""
    try:
        module = importlib.import_module(module_name)
    except Exception:  # noqa: BLE001 - no scipy, or another layout: nothing to do
        return
    real, deco = getattr(module, "FunctionDoc", None), getattr(module, decorator, None)
    if real is None or not callable(deco):
        return
    module.FunctionDoc = _DocAsIs
    try:
        ok = bool(works(deco))
    except Exception:  # noqa: BLE001 - not the decorator known
        ok = False
    if not ok:
        module.FunctionDoc = real


def output_path(text: str) -> str:
    """An output path argument (``-o``): an empty one (a script's unset variable) is refused, not taken for
    the default folder or the current one."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty output path: give a folder or file name (or leave -o out)")
    return text


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2 (argparse's own code for usage errors)
        self.exit(2, f"tapost: {message} (see '{self.prog} --help')\n")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; with ``command`` only that subcommand's module is imported (its options parsed), the
    others are listed by name and help (importing every command's module cost 0.4 s per run)."""
    p = _Parser(prog="tapost", description="Latency and transfer alignment between two INS logs.")
    p.add_argument("--version", action="version", version=f"tapost {__version__}")
    p.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name, (modname, help_text) in COMMANDS.items():
        sp = sub.add_parser(name, help=help_text, description=help_text)
        if command is None or name == command:
            mod = importlib.import_module(modname)
            mod.add_arguments(sp)
            sp.set_defaults(_run=mod.run)
    return p


def command_of(argv: list[str]) -> str | None:
    """The subcommand an argument list names (the first argument that is not an option)."""
    return next((a for a in argv if not a.startswith("-")), None)


#: options whose value is a list of numbers that may start with a minus sign ("-0.5,0.2,1")
VECTOR_OPTIONS = ("--lever-arm",)


def glue_vector_values(argv: list[str]) -> list[str]:
    """``--lever-arm -0.5,0.2,1`` as ``--lever-arm=-0.5,0.2,1`` (argparse takes a value starting with '-'
    for an option unless it is one number)."""
    out, i = [], 0
    while i < len(argv):
        a = argv[i]
        nxt = argv[i + 1] if i + 1 < len(argv) else ""
        if a in VECTOR_OPTIONS and len(nxt) > 1 and nxt[0] == "-" and nxt[1] in "0123456789.":
            out.append(f"{a}={nxt}")
            i += 2
            continue
        out.append(a)
        i += 1
    return out


_INTERRUPTED = [False]


def _on_sigint(signum, frame) -> None:
    _INTERRUPTED[0] = True
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    if argv is None and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        # (a fresh process: Ctrl-C remembered, for what an import turns it into: numba's C extension
        # reports it as "ImportError: numba._devicearray failed to import")
        signal.signal(signal.SIGINT, _on_sigint)
    try:
        return _main(argv)
    except KeyboardInterrupt:  # (Ctrl-C while the command's modules load, before _main's own handler)
        print("tapost: interrupted", file=sys.stderr)
        return 130
    except Exception:
        if _INTERRUPTED[0]:  # the same Ctrl-C, become another exception on its way out of an import
            print("tapost: interrupted", file=sys.stderr)
            return 130
        raise


def _main(argv: list[str] | None) -> int:
    fresh = argv is None  # a fresh process (the console script, python -m), not a call from Python
    argv = list(sys.argv[1:] if argv is None else argv)
    command = command_of(argv)
    if fresh:  # numpy's threads and pages before it loads; decide the kernels from the inputs' size, say at once
        set_numpy_environment()  # what that means, and on any compile
        gc.set_threshold(*GC_THRESHOLDS)
        from pipelines.firstrun import LOG_COMMANDS, announce_compiling, early_notice

        if command in LOG_COMMANDS:  # (before the modules that make dataclasses are imported)
            from pipelines import codecache

            codecache.install()

        early_notice(command, argv)
        if command in LOG_COMMANDS:
            defer_numpy_submodules()
            if command in SCIPY_COMMANDS and command != "analyze":  # (analyze: once it has forked, below)
                keep_scipy_docstrings()
            announce_compiling()
        if command == "analyze":  # one pair in this process: its independent stages may fork
            from pipelines import parallel

            parallel.enable()
            preload_numpy_ma()
        elif command == "restamp":  # (its malloc policy is tapost's: pipelines.restamp_cmd)
            from pipelines import parallel

            parallel.own_malloc()
    parser = build_parser(command if command in COMMANDS else None)
    args = parser.parse_args(glue_vector_values(argv))
    if fresh and command == "analyze":
        # once the children that import no scipy are forked (the recording's, the parse's): the import of
        # scipy's array-API layer here (25-35 ms) delayed them, and the parse's answer is waited for (the
        # sample pair 0.642-0.643 -> 0.624-0.633 s, medians of 24 and 30 whole runs, alternated)
        args._before_numerics = keep_scipy_docstrings
    if not getattr(args, "_run", None):
        parser.print_help(sys.stderr)
        return 2
    debug = args.debug or bool(os.environ.get("TAPOST_DEBUG"))
    try:
        return int(args._run(args) or 0)
    except TapostError as exc:
        if debug:  # the traceback, and the same exit code as without --debug
            import traceback

            traceback.print_exc()
        print(f"tapost: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("tapost: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0
    except Exception as exc:  # a bug (or the system refusing a file): still one line
        if debug:
            import traceback

            traceback.print_exc()
        if isinstance(exc, OSError) and exc.errno in SYSTEM_REFUSALS:
            # the system refused a file (an output's path taken by a folder, a full or read-only disk, no
            # permission): what the user can act on, named by the path they know
            where = os_error_path(exc)
            print(f"tapost: {where}: {exc.strerror}" if where is not None else f"tapost: {exc.strerror}",
                  file=sys.stderr)
            return 2
        print(f"tapost: internal error: {type(exc).__name__}: {exc}"
              + ("" if debug else " (rerun with --debug for details)"), file=sys.stderr)
        return 1


#: errno values of an OSError that are the system refusing a file the user named or the place it goes
#: (said as one line with exit 2), not a bug of tapost's
SYSTEM_REFUSALS = frozenset(getattr(errno, n) for n in (
    "EACCES", "EPERM", "ENOSPC", "EDQUOT", "EROFS", "EISDIR", "ENOTDIR", "EEXIST", "ENAMETOOLONG", "ENOENT",
    "ENOTEMPTY", "EMFILE", "ENFILE", "EFBIG", "EIO", "ELOOP", "EXDEV") if hasattr(errno, n))


def flush_std_streams() -> None:
    """stdout and stderr flushed before a process ends without the interpreter's teardown (``os._exit``)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # (a closed pipe: nothing more can be said on it)
            pass


def script() -> None:
    """The ``tapost`` command (its console script, ``python -m pipelines.cli``): :func:`main`, then the process
    ends at once. By then the outputs are written and closed; stdout and stderr are flushed and the exit
    handlers run here (logging's, rerun's, the background compile's start), and only the interpreter's own
    teardown of its modules is skipped (numba's LLVM, scipy, pandas, rerun: 0.33-0.37 s at the end of every
    ``analyze`` on a 2-core machine, a sixth of the sample pair's run). Where a thread of this process other
    than this one still runs, or this Python has no ``atexit._run_exitfuncs``, it ends as usual."""
    import atexit
    import threading

    code = main()
    flush_std_streams()
    run_exit_handlers = getattr(atexit, "_run_exitfuncs", None)
    others = [t for t in threading.enumerate() if t is not threading.current_thread() and not t.daemon]
    if run_exit_handlers is None or others:
        sys.exit(code)
    run_exit_handlers()
    flush_std_streams()  # (what the handlers said)
    os._exit(int(code) & 0xFF)


if __name__ == "__main__":
    script()
