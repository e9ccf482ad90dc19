"""Container work that releases the GIL (zstd/lz4/bz2 (de)compression, CRC-32 of large buffers),
done a few items ahead in worker threads while the calling thread walks or writes records in order.

Reading or writing an MCAP file or a ROS 1 bag is chunk after chunk of "decompress, check, walk" or
"lay out, compress, check, write"; the (de)compression and the CRC are most of the time and run
outside the GIL, so on a machine with two or more cores they overlap with the walk or the layout of
the neighbouring chunks. Results are handed back in input order and an exception raised by the work
of an item is raised where that item is consumed, as if the work had been done inline; with one core
(or ``TAPOST_IO_THREADS=1``) nothing runs in threads.
"""
from __future__ import annotations

import concurrent.futures as cf
import os
import threading
from collections import deque
from typing import Callable, Iterable, Iterator, TypeVar

T = TypeVar("T")
R = TypeVar("R")

#: worker threads: the container work is memory-bound beyond a few threads, and a batch runs several
#: analyses at once (each with its own process), so at most 4
MAX_THREADS = 4
#: items in flight per worker (the memory held ahead is about this many chunks per worker)
AHEAD_PER_WORKER = 2

_POOL: list[cf.ThreadPoolExecutor] = []
_LOCK = threading.Lock()


def _forget_pool_in_child() -> None:  # a forked worker (a batch's process pool) has none of the threads
    global _LOCK
    _POOL.clear()
    _LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool_in_child)


def workers() -> int:
    """Worker threads to use: ``TAPOST_IO_THREADS`` if set, else the cores (at most MAX_THREADS)."""
    env = os.environ.get("TAPOST_IO_THREADS", "").strip()
    if env.isdigit() and int(env) >= 1:
        return min(int(env), 32)
    return max(1, min(MAX_THREADS, os.cpu_count() or 1))


def _pool() -> cf.ThreadPoolExecutor:
    with _LOCK:
        if not _POOL:
            _POOL.append(cf.ThreadPoolExecutor(max_workers=workers(), thread_name_prefix="tapost-io"))
        return _POOL[0]


def beside(fn: Callable[..., R], *args) -> cf.Future:
    """``fn(*args)`` started in a worker thread while the caller goes on (run here, now, with one worker):
    its ``result()`` where the caller needs it (and waited for by ``drain`` where the caller leaves early)."""
    if workers() < 2:
        fut: cf.Future = cf.Future()
        try:
            fut.set_result(fn(*args))
        except BaseException as exc:  # noqa: BLE001 - raised by result(), where an inline call would raise it
            fut.set_exception(exc)
        return fut
    return _pool().submit(fn, *args)


def ordered(fn: Callable[[T], R], items: Iterable[T], ahead: int | None = None) -> Iterator[R]:
    """``fn(item)`` for every item, in order, up to ``ahead`` items computed ahead in worker threads.
    Leaving the loop early waits for the work in flight (it may touch buffers the caller frees next)."""
    n = workers()
    if n <= 1:
        for it in items:
            yield fn(it)
        return
    ahead = ahead or AHEAD_PER_WORKER * n
    pool = _pool()
    src = iter(items)
    q: deque = deque()
    try:
        for it in src:
            q.append(pool.submit(fn, it))
            if len(q) >= ahead:
                break
        while q:
            fut = q.popleft()
            nxt = next(src, _END)
            if nxt is not _END:
                q.append(pool.submit(fn, nxt))
            yield fut.result()
    finally:
        drain(q)


class Prefetch:
    """``fn(key)`` of the keys a scan will ask for, computed ahead in threads; ``get(key)`` hands the
    result back (or raises what the work raised). A key not planned, or asked for out of order, is
    computed inline. Use as a context manager: leaving it waits for the work in flight."""

    def __init__(self, fn: Callable[[T], R], keys: Iterable[T], ahead: int | None = None):
        self._fn = fn
        self._keys = iter(keys)
        self._n = workers()
        self._ahead = ahead or AHEAD_PER_WORKER * self._n
        self._futs: dict = {}
        self._fill()

    def _fill(self) -> None:
        if self._n <= 1:
            return
        pool = _pool()
        while len(self._futs) < self._ahead:
            k = next(self._keys, _END)
            if k is _END:
                return
            self._futs[k] = pool.submit(self._fn, k)

    def get(self, key: T) -> R:
        fut = self._futs.pop(key, None)
        if fut is None:
            return self._fn(key)
        self._fill()
        return fut.result()

    def close(self) -> None:
        drain(list(self._futs.values()))
        self._futs.clear()

    def __enter__(self) -> "Prefetch":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def drain(futs) -> None:
    """Cancel what has not started and wait for what has (its exceptions dropped)."""
    for f in futs:
        f.cancel()
    for f in futs:
        try:
            f.result()
        except BaseException:  # noqa: BLE001 - the caller is already leaving (or handled its own item)
            pass


_END = object()
