"""Work run in a thread beside the caller's (the CLI's ``analyze``, up to about 1 h of 200 Hz logs:
``estimate(..., overlap=True)``). numpy and the compiled kernels leave the GIL for their arrays' loops, so two
independent computations on large arrays share two cores. Nothing is shared but the arguments, which the
work does not change; every thread is waited for before the caller goes on (a fork beside a running thread
could copy a lock it holds)."""
from __future__ import annotations

import threading
from collections.abc import Callable


class Beside:
    """``fn(*args, **kwargs)`` started in a thread; ``result()`` waits, then returns or raises what ``fn``
    did; ``join()`` only waits."""

    def __init__(self, fn: Callable, *args, **kwargs):
        self._out: list = []
        self._err: list[BaseException] = []

        def run() -> None:
            try:
                self._out.append(fn(*args, **kwargs))
            except BaseException as exc:  # noqa: BLE001 - raised in the caller's thread, by result()
                self._err.append(exc)

        self._thread = threading.Thread(target=run, name="tapost-latency", daemon=True)
        self._thread.start()

    def join(self) -> None:
        self._thread.join()

    def result(self):
        self._thread.join()
        if self._err:
            raise self._err[0]
        return self._out[0]


def both(fn: Callable, first: tuple, second: tuple, threads: bool) -> tuple:
    """``(fn(*first), fn(*second))``, the second in a thread beside the first where ``threads``; the first's
    exception is raised before the second's, as in turn."""
    if not threads:
        return fn(*first), fn(*second)
    job = Beside(fn, *second)
    try:
        a = fn(*first)
    finally:
        job.join()
    return a, job.result()
