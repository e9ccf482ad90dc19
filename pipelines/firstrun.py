"""Say on stderr when numba compiles tapost's kernels (the first run after installing, or a new kind of
pair), terminal or not: that run is otherwise silent for tens of seconds.

numba caches each compiled kernel next to its source file (``__pycache__/*.nbi|*.nbc``), so only the first
use of a kernel compiles; a cache hit raises no ``numba:compile`` event and prints nothing.
"""
from __future__ import annotations

import glob
import os
import sys

#: what the message says the compiling costs (measured: a fresh clone's first ``tapost analyze`` of the
#: sample pair against a warm one, on 2 cores)
COMPILE_ESTIMATE = "about 1 min on a 2-core machine"

_state = {"installed": False, "said": False}


def _say(stream) -> None:
    if _state["said"]:
        return
    _state["said"] = True
    try:
        stream.write(f"tapost: compiling numerical kernels on first use (once, {COMPILE_ESTIMATE}; "
                     "cached for later runs)...\n")
        stream.flush()
    except (OSError, ValueError):
        pass


def announce_compiling(stream=None) -> bool:
    """Print one line on ``stream`` (stderr) when numba first compiles a kernel in this process.
    Returns False when numba is not installed (nothing compiles then)."""
    if _state["installed"]:
        return True
    try:
        from numba.core import event
    except ImportError:
        return False

    class _Listener(event.Listener):
        def on_start(self, ev):
            _say(stream if stream is not None else sys.stderr)

        def on_end(self, ev):
            pass

    event.register("numba:compile", _Listener())
    _state["installed"] = True
    return True


#: the kernel every analysis compiles (the alignment filter's loop): no cache entry for it means this run
#: compiles, and says so before the slow imports
_PROBE = ("logtools", os.path.join("alignment", "__pycache__"), "kf._kf_loop-*.nbi")


def kernels_cached() -> bool:
    """True when numba's cache holds the alignment loop (next to the sources, or in NUMBA_CACHE_DIR).
    A file-system look only: imports nothing."""
    import importlib.util

    if os.environ.get("NUMBA_CACHE_DIR"):  # numba then caches there only
        pats = [os.path.join(os.environ["NUMBA_CACHE_DIR"], "**", _PROBE[2])]
    else:
        spec = importlib.util.find_spec(_PROBE[0])
        pats = [os.path.join(loc, _PROBE[1], _PROBE[2])
                for loc in ((spec.submodule_search_locations or []) if spec else [])]
    return any(glob.glob(p, recursive=True) for p in pats)


def early_notice(command: str | None, stream=None) -> None:
    """For a fresh ``tapost analyze`` or ``batch`` process: the compile line at once (before numpy, pandas,
    numba are imported) when the cache has no alignment kernel; later compiles are told by the listener."""
    if command in ("analyze", "batch") and not kernels_cached():
        _say(stream if stream is not None else sys.stderr)
