"""One independent stage in a forked child process, for the CLI's single-pair ``analyze`` on a POSIX
machine with more than one core: the uncompensated alignment run beside the compensated one (they share
nothing but their inputs, which the child has by fork, copy-on-write).

The child sends its result (or its exception) back pickled through a pipe and exits; anything that goes
wrong with the fork itself (no fork, one core, a child that dies) falls back to running the call in this
process, so the answer never depends on it. Batch workers and the Python API do not fork (a process with
threads of its own may not fork safely): ``analyze`` turns it on for its own process only.
"""
from __future__ import annotations

import os
import pickle
import sys
from typing import Any, Callable

_ENABLED = {"on": False}


def enable(on: bool = True) -> None:
    """Allow forking in this process (the CLI's ``analyze``)."""
    _ENABLED["on"] = bool(on)


def available() -> bool:
    return (_ENABLED["on"] and hasattr(os, "fork") and (os.cpu_count() or 1) > 1
            and os.environ.get("TAPOST_FORK", "1") != "0")


class Pending:
    """A call running in a forked child (``result()`` waits), or done in this process."""

    def __init__(self, fn: Callable, args: tuple, kwargs: dict):
        self._fn, self._args, self._kwargs = fn, args, kwargs
        self._pid: int | None = None
        self._rfd: int | None = None
        self._done = False
        self._value: Any = None
        if available():
            self._start()

    def _start(self) -> None:
        try:
            rfd, wfd = os.pipe()
            sys.stdout.flush()
            sys.stderr.flush()
            pid = os.fork()
        except OSError:
            return
        if pid == 0:  # the child: compute, send, leave without running the parent's exit handlers
            code = 0
            try:
                os.close(rfd)
                try:
                    payload = pickle.dumps((True, self._fn(*self._args, **self._kwargs)), protocol=5)
                except BaseException as exc:  # noqa: BLE001 - the parent re-raises it
                    payload = pickle.dumps((False, exc), protocol=5)
                with os.fdopen(wfd, "wb") as fh:
                    fh.write(payload)
            except BaseException:  # noqa: BLE001
                code = 1
            finally:
                os._exit(code)
        os.close(wfd)
        self._pid, self._rfd = pid, rfd

    def result(self) -> Any:
        if self._done:
            return self._value
        ok, value = None, None
        if self._pid is not None:
            try:
                with os.fdopen(self._rfd, "rb") as fh:
                    data = fh.read()
                os.waitpid(self._pid, 0)
                if data:
                    ok, value = pickle.loads(data)
            except (OSError, EOFError, pickle.UnpicklingError):
                ok = None
        if ok is None:  # no fork, or the child died: the same call here
            ok, value = True, self._fn(*self._args, **self._kwargs)
        self._done, self._value = True, value
        if not ok:
            raise value
        return value


def submit(fn: Callable, *args, **kwargs) -> Pending:
    """Start ``fn(*args, **kwargs)`` in a forked child where allowed, else later in this process."""
    return Pending(fn, args, kwargs)
