"""What a fresh ``tapost`` process says about its numerical kernels, on stderr, terminal or not.

``logtools.jit`` decides per process whether the numba-compiled kernels run (they are in numba's cache,
or the input is large enough for compiling to pay off) or the reference code does (the first runs after
installing, while a background process compiles the kernels). The line comes before numpy, pandas or
numba are imported, so that a run is never silent for long:

* reference code, kernels compiling in the background: ``tapost: first run after installing: ...``;
* compiled kernels not in the cache yet (a large input): ``tapost: compiling numerical kernels ...``,
  and a numba ``numba:compile`` listener says the same once when a compile starts later (a new kind of
  pair, a format not read before).
"""
from __future__ import annotations

import atexit
import os
import sys

#: what compiling costs (measured: ``python -m pipelines.warmup`` on a fresh clone, quiet 2-core machine)
COMPILE_ESTIMATE = "about 1 min on a 2-core machine"

#: the commands whose inputs are logs (their size decides whether compiling pays off)
LOG_COMMANDS = ("analyze", "batch", "restamp", "inspect", "simulate")

_state = {"installed": False, "said": False}


def _write(stream, text: str) -> None:
    try:
        stream.write(text + "\n")
        stream.flush()
    except (OSError, ValueError):
        pass


def _say(stream) -> None:
    if _state["said"]:
        return
    _state["said"] = True
    _write(stream, f"tapost: compiling numerical kernels on first use (once, {COMPILE_ESTIMATE}; "
                   "cached for later runs)...")


def announce_compiling(stream=None) -> bool:
    """Print one line on ``stream`` (stderr) when numba first compiles a kernel in this process.
    Returns False when this process runs no compiled kernels (nothing compiles then)."""
    if _state["installed"]:
        return True
    from logtools import jit

    if not jit.compiled():
        return False
    if jit.aot_table() is not None:  # (kernels compiled ahead of time: numba loads only if one is missing)
        from logtools import aot

        aot.on_numba_load(lambda: _listen(stream))
    else:
        _listen(stream)
    _state["installed"] = True
    return True


def _listen(stream) -> None:
    from numba.core import event

    class _Listener(event.Listener):
        def on_start(self, ev):
            _say(stream if stream is not None else sys.stderr)

        def on_end(self, ev):
            pass

    event.register("numba:compile", _Listener())


def input_bytes(command: str | None, args: list[str]) -> int | None:
    """The size of the logs a command line names (``PATH[::SELECTOR]`` arguments, or a campaign folder's
    files); None when it names none. A file-system look only."""
    if command not in LOG_COMMANDS:
        return None
    total, seen = 0, False
    for a in args:
        if a.startswith("-") or a == command:
            continue
        path = a.split("::", 1)[0]
        if os.path.isfile(path):
            total += os.path.getsize(path)
            seen = True
        elif os.path.isdir(path):
            for base, _dirs, files in os.walk(path):
                for f in files:
                    try:
                        total += os.path.getsize(os.path.join(base, f))
                        seen = True
                    except OSError:
                        pass
    return total if seen else None


#: tapost's packages (under ``logtools.jit._root()``), byte-compiled in the background during a first run that
#: finds them not compiled yet
PACKAGES = ("logtools", "parsers", "pipelines")
#: a module the analysis imports late (its byte code missing: the packages were not compiled at install)
LATE_MODULE = os.path.join("logtools", "alignment", "kf.py")


def compile_bytecode_in_background() -> bool:
    """Byte-compile tapost's packages in a detached low-priority process, where that was not done at install
    (``pip install -e`` does not; a regular ``pip install`` does), for the runs after this one: the modules
    this run does not import (batch, simulate, ...) too. It was measured to shorten the first run itself
    (the sample pair 1.62-1.72 -> 1.52-1.55 s on 2 cores); once the run's own forked children kept the other
    core busy, it no longer did (1.60 s either way, 2026-12-07). Not where Python is told to write no byte
    code. Returns True when started."""
    if sys.dont_write_bytecode or os.environ.get("PYTHONDONTWRITEBYTECODE"):
        return False
    import importlib.util
    import subprocess

    from logtools import jit

    root = jit._root()
    try:
        if os.path.exists(importlib.util.cache_from_source(os.path.join(root, LATE_MODULE))):
            return False
        subprocess.Popen([sys.executable, "-m", "compileall", "-q", *(os.path.join(root, p) for p in PACKAGES)],
                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         start_new_session=True, close_fds=True,
                         preexec_fn=(lambda: os.nice(19)) if hasattr(os, "nice") else None)
        return True
    except (OSError, ValueError, NotImplementedError):
        return False


def early_notice(command: str | None, args: list[str] | None = None, stream=None) -> str:
    """For a fresh process: decide the kernels (logtools.jit, from the inputs' size) and say at once what
    that means; start the background compile where the reference code runs. Returns the mode."""
    from logtools import jit

    jit.hint_input_bytes(input_bytes(command, list(args or [])))
    mode = jit.mode()
    auto = os.environ.get("TAPOST_KERNELS", "auto").strip().lower() == "auto"
    out = stream if stream is not None else sys.stderr
    if command in ("analyze", "batch"):
        if mode == "reference" and jit.why() == "kernels not compiled yet":
            compile_bytecode_in_background()
            if command == "analyze" and not jit.warmup_running() and jit.warmup_wanted():
                # one pair: the compile starts when this run ends, so that it does not share the machine
                # with it (two vCPUs are often one core's two threads); a batch starts it at once
                atexit.register(jit.start_background_warmup, respect_kernels_env=False)
                started = True
            else:
                started = jit.start_background_warmup()
            if started or jit.warmup_running():
                _write(out, "tapost: first run after installing: the fast numerical kernels compile in the "
                            f"background (once, {COMPILE_ESTIMATE}); this run uses the reference code")
            else:
                _write(out, "tapost: the numerical kernels are not compiled yet: this run uses the reference "
                            f"code ('python -m pipelines.warmup' compiles them, {COMPILE_ESTIMATE})")
        elif jit.why().startswith("large input"):  # compiling pays off here: it starts now
            _say(out)
    if auto:  # the processes this one starts (batch workers) take the same kernels
        os.environ["TAPOST_KERNELS"] = mode
    return mode
