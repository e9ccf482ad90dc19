"""Independent work in forked child processes, for the CLI's single-pair ``analyze`` on a POSIX machine with
more than one core:

* ``submit``: one stage beside another, the uncompensated alignment run beside the compensated one (they
  share nothing but their inputs, which the child has by fork, copy-on-write);
* ``prepare`` / ``call_prepared``: a child forked at the start that imports the modules of a later stage
  (the recording's: rerun's SDK, about 0.5 s of imports) while this process parses the logs, then runs
  that stage's call when it is sent (its arguments pickled through a pipe: 4.5 MB, 20 ms for the sample
  pair; so only for small inputs, see ``PREPARED_MAX_INPUT_BYTES``);
* ``start_prepared``: that call sent now and its answer read later (the recording beside the HTML report),
  or, without a prepared child, ``submit``;
* ``submit_awaiting``: a call that starts now and is sent one more object later (``Pending.send``), which it
  asks for when it needs it (the recording, forked while the IMU-to-IMU fit still runs, and sent the report
  once the fit is in).

The child sends its result (or its exception) back pickled through a pipe and exits; its large arrays travel
beside the pickle, through a shared-memory file the parent made before the fork (Linux's memfd), which the
parent maps instead of reading them through the pipe (``OOB_MIN_BYTES``). Anything that goes wrong with the
fork itself (no fork, one core, a child that dies) falls back to running the call in this process, so the
answer never depends on it. Batch workers and the Python API do not fork (a process with
threads of its own may not fork safely): ``analyze`` turns it on for its own process only.
"""
from __future__ import annotations

import gc
import importlib
import mmap
import os
import pickle
import signal
import sys
from typing import Any, Callable

from parsers.base import glibc as _libc  # (glibc, for its malloc controls; None elsewhere: their own policy)

#: "on": forking allowed (the CLI's analyze); "malloc": glibc's policy set here (a tapost command's process)
_ENABLED = {"on": False, "malloc": False}
#: name -> (pid, request write fd, result read fd, result memfd or -1)
_PREPARED: dict[str, tuple[int, int, int, int]] = {}

#: inputs (master + slave file bytes) up to which a prepared child is worth its pipe: the pickled analysis
#: is about 1.2x the logs' bytes and exists twice while the child reads it; up to 60 MB (about 15 minutes
#: of 200 Hz logs) that copy costs less than the 0.5 s of imports it saves, and it never adds to the
#: memory of the long logs, whose peak is the constraint
PREPARED_MAX_INPUT_BYTES = 60_000_000

#: master + slave file bytes above which ``analyze`` parses the larger log in a forked child while it parses
#: the other: on the 1 h pair 1.8-1.9 s against 3.1-3.4 s in turn (the child's InsLog comes back through shared
#: memory, OOB_MIN_BYTES). Below, both logs are parsed in one forked child while ``analyze`` imports the
#: analysis' modules (which a parse does not need): the sample pair
#: 1.051 -> 1.018 s (medians of 40 whole runs, alternated)
FORK_PARSE_MIN_INPUT_BYTES = PREPARED_MAX_INPUT_BYTES

#: master + slave IMU samples up to which ``analyze`` computes the IMU-to-IMU fit in a second forked child
#: beside the two alignment runs (the uncompensated one in the first child, two passes, the compensated one
#: here), rather than here after them: the fit's arrays (about 0.4 GB per hour of 200 Hz data for both
#: units) then sit beside the runs'. Up to about 1 h of 200 Hz logs; beyond, where the long logs' peak memory
#: is the constraint, the fit waits for the runs
FORK_IMU_TO_IMU_MAX_SAMPLES = 1_500_000

#: master + slave IMU samples up to which ``analyze`` runs the uncompensated alignment in a forked child beside
#: the compensated one here. The child's filter, histories and master series sit beside this process's
#: (0.3-0.5 GB per hour of 200 Hz logs): the 4 h pair's whole process tree peaked at 3.0 GB so, 2.5 GB with
#: the runs in turn. Up to about 1 h of 200 Hz logs, as the IMU-to-IMU fit; beyond, the runs in turn
FORK_ALIGNMENT_MAX_SAMPLES = FORK_IMU_TO_IMU_MAX_SAMPLES

#: master + slave IMU samples up to which ``analyze`` runs the latency's comparison methods (the seeds' and
#: cross-correlation) in a forked child while this process computes the tapost estimate (rather than after
#: it: about 2 s of the 1 h pair's 6-8 s latency stage). The child's arrays sit beside this process's: up to
#: about 1 h of 200 Hz logs, as for the IMU-to-IMU fit; beyond, the long logs' peak memory decides
FORK_COMPARE_MAX_SAMPLES = FORK_IMU_TO_IMU_MAX_SAMPLES

#: master + slave IMU samples up to which ``analyze``'s tapost latency makes its velocity pair in a thread
#: beside its rate fit (``estimate(..., overlap=True)``): the 1 h pair's latency stage 0.4-0.5 s shorter,
#: the same estimate to the bit. The two stages' arrays then sit side by side: up to about 1 h of 200 Hz
#: logs, as the forks above; beyond, the long logs' peak memory decides
THREAD_LATENCY_MAX_SAMPLES = FORK_IMU_TO_IMU_MAX_SAMPLES


#: a child's answer carries its arrays (numpy's pickle buffers, protocol 5) of this size and more out of band:
#: written into a memfd the parent made before the fork and mapped by the parent (copy-on-write, private), not
#: pickled into the pipe. The 1 h pair's master (104 MB) came back through the pipe in 0.5-0.7 s on a 2-core
#: machine (a pipe moves 64 KB per wake-up, and the pickle was copied once on each side); smaller buffers stay
#: in the pickle, where a page-aligned slot would cost more than it saves
OOB_MIN_BYTES = 1 << 20
_OOB_TAG = "tapost-parallel-oob-1"
_OOB_ALIGN = 64


#: the descriptors a child forked later closes (held there, one would keep another child's channel open):
#: the memfds of this process's children not yet answered, the pipes that will send a child its later object
#: (``submit_awaiting``) and a prepared child's request pipe
_CHILDREN_FDS: set[int] = set()


def _memfd() -> int:
    """An anonymous shared-memory file for a child's large arrays (-1 where the system has none: they go
    through the pipe)."""
    if not hasattr(os, "memfd_create"):
        return -1
    try:
        fd = os.memfd_create("tapost-answer", getattr(os, "MFD_CLOEXEC", 0))
    except OSError:
        return -1
    _CHILDREN_FDS.add(fd)
    return fd


def _in_child(own: int) -> None:
    """In a child just forked: the other children's descriptors closed (held here, a memfd would outlive its
    answer, a pipe would never see its end)."""
    for fd in _CHILDREN_FDS - {own}:
        _close(fd)
    _CHILDREN_FDS.clear()


def _child_done() -> None:
    """In a child that has answered, before it leaves by os._exit (no exit handlers): what it compiled of the
    generated code kept for later runs (pipelines.codecache, where the CLI installed it)."""
    cache = sys.modules.get("pipelines.codecache")
    if cache is not None:
        cache.save()


def enable(on: bool = True) -> None:
    """Allow forking in this process (the CLI's ``analyze``; its malloc policy is then tapost's too)."""
    _ENABLED["on"] = bool(on)


def own_malloc() -> None:
    """This process is a tapost command's own, not a Python API caller's: :func:`malloc_policy` may set
    glibc's policy in it (the CLI's ``restamp``, which forks nothing)."""
    _ENABLED["malloc"] = True


#: a pair with this many rows in its four tables (IMU and navigation of both units; about 1.7 h of 200 Hz)
#: or more has its arrays of MMAP_THRESHOLD_BYTES and more mmapped (glibc's threshold fixed, not raised up
#: to 32 MB as large blocks are freed), so that a freed one goes back to the system at once. Measured on
#: the 4 h pair (11.5 M rows): peak RSS 2.64 -> 2.48 GB; on the 1 h pair (2.9 M rows), where it is not
#: applied, it would cost 1.10x the wall time (every (n, 3) temporary mmapped and faulted in anew)
LARGE_PAIR_ROWS = 5_000_000
MMAP_THRESHOLD_BYTES = 16 << 20
M_MMAP_THRESHOLD = -3  # mallopt's parameters (malloc.h)
M_TRIM_THRESHOLD = -1
#: below LARGE_PAIR_ROWS, in the CLI's process: glibc's mmap threshold fixed at its largest (32 MB) and its
#: trim threshold at 1 GB, so that a stage's freed arrays (the 1 h pair's (n, 3) float64 columns, 17 MB) are
#: reused from the heap, not unmapped and faulted in anew by the next allocation (glibc's own policy raises
#: the mmap threshold only as large blocks are freed, and trims the heap top beyond twice that); the heap is
#: still trimmed between stages (``release_freed_memory``). Measured on the 1 h pair (2.9 M rows), whole
#: processes: minor page faults 1.42-1.53 M -> 0.79-0.93 M, system time 3.2-3.4 -> 2.1-2.7 s of 21-22 s of
#: CPU, the main process's peak RSS 756-772 -> 756-789 MB
SMALL_PAIR_MMAP_BYTES = 32 << 20
SMALL_PAIR_TRIM_BYTES = 1 << 30
GLIBC_TRIM_THRESHOLD_BYTES = 128 << 10  # (glibc's default)
#: master + slave file bytes up to which the CLI's analyze takes the small-pair policy from its start, for
#: the parse too (its rows are not known before it): the 1 h pair is 274 MB (2.9 M rows); a pair found to
#: have LARGE_PAIR_ROWS rows or more after its parse gets the large-pair policy then
SMALL_PAIR_MAX_INPUT_BYTES = 400_000_000


def small_pair_malloc(input_bytes: int | None) -> None:
    """The small-pair malloc policy (:func:`malloc_policy`) from now on, where the inputs' bytes are known
    and at most SMALL_PAIR_MAX_INPUT_BYTES (the CLI's analyze, before its parse: its rows not known yet)."""
    if input_bytes is not None and input_bytes <= SMALL_PAIR_MAX_INPUT_BYTES:
        malloc_policy(0)  # (no rows known: below LARGE_PAIR_ROWS)


def _fork() -> int:
    """os.fork with SIGINT held through it: a Ctrl-C landing in the interpreter's at-fork handlers (logging's
    lock release) was printed as an ignored exception with a traceback, and lost; held, it arrives just
    after the fork, where the command's one-line handler takes it (tests/test_first_hour.py).

    The garbage collector's objects are frozen first (``gc.freeze``, as Python's documentation advises
    before a fork without exec): the collections of both processes then skip the millions of objects the
    imports made (a child's would have written into every one's header, copying its pages), and they are
    still freed when their last reference goes; only a reference cycle among them stays. The sample pair,
    whole processes alternated (frozen before the first fork only: 24 and 30 pairs): CPU 1.042 -> 1.009 s and
    1.073 -> 1.042 s, wall 0.605 -> 0.596 s and 0.630 -> 0.625 s; before every fork (24 pairs): CPU 1.140 ->
    1.118 s, wall 0.669 -> 0.660 s. A simulated 1 h pair: the same CPU and peak memory (13.3 s, 696 MB), the
    same report.json."""
    gc.freeze()
    hold = hasattr(signal, "pthread_sigmask")
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT}) if hold else None
    try:
        return os.fork()
    finally:
        if hold:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


def malloc_policy(rows: int) -> None:
    """glibc's malloc policy for a pair of ``rows`` rows, unless the user set one (``MALLOC_MMAP_THRESHOLD_``
    or ``MALLOC_TRIM_THRESHOLD_``): from LARGE_PAIR_ROWS rows on, MMAP_THRESHOLD_BYTES as its fixed mmap
    threshold; below, in the CLI's own process (``enable``, ``own_malloc``: not a Python API caller's),
    SMALL_PAIR_MMAP_BYTES and SMALL_PAIR_TRIM_BYTES (freed arrays reused from the heap)."""
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "MALLOC_TRIM_THRESHOLD_" in os.environ:
        return
    if rows < LARGE_PAIR_ROWS and not (_ENABLED["on"] or _ENABLED["malloc"]):
        return
    libc = _libc()
    if libc is None:
        return
    if rows >= LARGE_PAIR_ROWS:
        libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
        libc.mallopt(M_TRIM_THRESHOLD, GLIBC_TRIM_THRESHOLD_BYTES)  # (as glibc's own, were it set before)
    else:
        libc.mallopt(M_MMAP_THRESHOLD, SMALL_PAIR_MMAP_BYTES)
        libc.mallopt(M_TRIM_THRESHOLD, SMALL_PAIR_TRIM_BYTES)


def release_freed_memory() -> None:
    """Hand the heap's free pages back to the system (glibc's ``malloc_trim``; elsewhere nothing), between
    stages. glibc keeps arrays below its mmap threshold (which it raises up to 32 MB as large blocks are
    freed: a 4 h log's 23 MB columns) in the heap, where the pages of a stage's freed temporaries would
    stay resident among live arrays."""
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)


def available() -> bool:
    return (_ENABLED["on"] and hasattr(os, "fork") and (os.cpu_count() or 1) > 1
            and os.environ.get("TAPOST_FORK", "1") != "0")


_UNSENT = object()


class Later:
    """What a ``submit_awaiting`` call is given as ``later``: ``later()`` returns the object the caller sends
    (``Pending.send``), waiting for it; raises EOFError where the caller ended without sending one. In a
    child, a thread reads it (one pickle from ``fh``) from the start, so that the sender never waits for the
    call to ask (the report of a 1 h pair is larger than a pipe holds)."""

    def __init__(self, fh=None, value: Any = _UNSENT):
        self._value, self._reader = value, None
        if fh is not None:
            import threading

            self._reader = threading.Thread(target=self._read, args=(fh,), daemon=True)
            self._reader.start()

    def _read(self, fh) -> None:
        try:
            self._value = pickle.load(fh)
        except Exception:  # noqa: BLE001 - nothing sent (the caller ended, or abandoned the call)
            pass

    def __call__(self) -> Any:
        if self._reader is not None:
            self._reader.join()
            self._reader = None
        if self._value is _UNSENT:
            raise EOFError("nothing was sent")
        return self._value


class Pending:
    """A call running in a forked child (``result()`` waits), or done in this process."""

    def __init__(self, fn: Callable, args: tuple, kwargs: dict, awaiting: bool = False):
        self._fn, self._args, self._kwargs = fn, args, kwargs
        self._pid: int | None = None
        self._rfd: int | None = None
        self._memfd = -1
        self._done = False
        self._value: Any = None
        self._awaiting = awaiting
        self._later_w = -1  # (the pipe's end that sends the child its later object)
        self._sent: Any = _UNSENT
        if available():
            self._start()

    def _start(self) -> None:
        try:
            rfd, wfd = os.pipe()
        except OSError:
            return
        later_r = later_w = -1
        if self._awaiting:
            try:
                later_r, later_w = os.pipe()
            except OSError:
                _close(rfd, wfd)
                return
        memfd = _memfd()
        try:
            sys.stdout.flush()
            sys.stderr.flush()
            pid = _fork()
        except OSError:
            _close(rfd, wfd, memfd, later_r, later_w)
            return
        if pid == 0:  # the child: compute, send, leave without running the parent's exit handlers
            code = 0
            try:
                os.close(rfd)
                _close(later_w)
                _close_prepared()  # a prepared child must see its end of file when the parent closes it
                _in_child(memfd)
                kwargs = self._kwargs
                if self._awaiting:
                    kwargs = {**kwargs, "later": Later(os.fdopen(later_r, "rb"))}
                _answer(self._fn, self._args, kwargs, wfd, memfd)
            except BaseException:  # noqa: BLE001
                code = 1
            finally:
                os._exit(code)
        os.close(wfd)
        _close(later_r)
        if later_w >= 0:
            _CHILDREN_FDS.add(later_w)  # (a child forked later closes it: else this child would never see its end)
        self._pid, self._rfd, self._memfd, self._later_w = pid, rfd, memfd, later_w

    def send(self, value: Any) -> None:
        """The later object of a ``submit_awaiting`` call (once): to its child, or kept for the call here."""
        self._sent = value
        if self._later_w < 0:
            return
        _send_later(self._later_w, value)
        self._later_w = -1

    def _here(self) -> Any:
        if self._awaiting:
            return self._fn(*self._args, **self._kwargs, later=Later(value=self._sent))
        return self._fn(*self._args, **self._kwargs)

    def result(self) -> Any:
        if self._done:
            return self._value
        ok, value = None, None
        if self._pid is not None:
            _close(self._later_w)  # (never sent: the child's later() raises EOFError, raised here)
            self._later_w = -1
            try:
                ok, value = _read_answer(self._rfd, memfd=self._memfd)
                os.waitpid(self._pid, 0)
            except (OSError, EOFError, ValueError, pickle.UnpicklingError):
                ok = None
            finally:
                _close(self._memfd)
                self._memfd = -1
        if ok is None:  # no fork, or the child died: the same call here
            ok, value = True, self._here()
        self._done, self._value = True, value
        if not ok:
            raise value
        return value

    def abandon(self) -> None:
        """The answer is not wanted, but the child ends on its own (it may have files to tidy): a later object
        not yet sent never comes (its ``later()`` raises EOFError), its answer is not read."""
        if self._done:
            return
        self._done = True
        if self._pid is not None:
            _let_go(self._pid, self._later_w, self._rfd, self._memfd)
            self._later_w = -1

    def cancel(self) -> None:
        """The result is not wanted (the stage beside it failed): the child is ended and reaped."""
        if self._done:
            return
        self._done = True
        if self._pid is not None:
            try:
                os.kill(self._pid, signal.SIGKILL)
            except OSError:
                pass
            _close(self._rfd, self._memfd, self._later_w)
            self._later_w = -1
            try:
                os.waitpid(self._pid, 0)
            except OSError:
                pass


def submit(fn: Callable, *args, **kwargs) -> Pending:
    """Start ``fn(*args, **kwargs)`` in a forked child where allowed, else later in this process."""
    return Pending(fn, args, kwargs)


def _send_later(fd: int, value: Any) -> None:
    """``value`` pickled to a child's later pipe, which is then closed."""
    try:
        payload = pickle.dumps(value, protocol=5)
        with os.fdopen(fd, "wb", closefd=False) as fh:
            fh.write(payload)
    except (OSError, TypeError, AttributeError, pickle.PickleError):
        pass  # (the child died: the call runs here at result(); an object that does not pickle: its later()
        #       raises EOFError)
    finally:
        _close(fd)


def submit_awaiting(fn: Callable, *args, **kwargs) -> Pending:
    """Start ``fn(*args, later=..., **kwargs)`` now as ``submit`` does; ``later()`` in the call waits for the
    object the caller sends with the Pending's ``send`` (where the call runs in this process, at ``result()``,
    ``later()`` returns it at once)."""
    return Pending(fn, args, kwargs, awaiting=True)


def _answer(fn: Callable, args: tuple, kwargs: dict, wfd: int, memfd: int = -1) -> None:
    """In a child: run the call and write (True, its value) or (False, its exception), pickled, to ``wfd``; its
    arrays of OOB_MIN_BYTES and more into ``memfd`` (where there is one), the pickle then wrapped with their
    places there (:func:`_read_answer` maps them). Then, the answer written, :func:`_child_done`."""
    try:
        payload = _dumps((True, fn(*args, **kwargs)), memfd)
    except BaseException as exc:  # noqa: BLE001 - the parent re-raises it
        payload = pickle.dumps((False, exc), protocol=5)
    with os.fdopen(wfd, "wb") as fh:
        fh.write(payload)
    _child_done()


def _dumps(answer: tuple, memfd: int) -> bytes:
    """``answer`` pickled; its large buffers written into ``memfd`` at aligned offsets and the pickle wrapped
    as (_OOB_TAG, their (offset, size), the file's size, the pickle), where there are any (else, or where the
    file cannot take them, the plain pickle)."""
    if memfd < 0:
        return pickle.dumps(answer, protocol=5)
    big: list[memoryview] = []

    def out_of_band(buf: pickle.PickleBuffer) -> bool:  # (True: in the pickle)
        try:
            raw = buf.raw()
        except BufferError:  # (neither C- nor Fortran-contiguous)
            return True
        if raw.nbytes < OOB_MIN_BYTES:
            return True
        big.append(raw)
        return False

    payload = pickle.dumps(answer, protocol=5, buffer_callback=out_of_band)
    if not big:
        return payload
    layout, end = [], 0
    for raw in big:
        layout.append((end, raw.nbytes))
        end = -(-(end + raw.nbytes) // _OOB_ALIGN) * _OOB_ALIGN
    try:
        os.ftruncate(memfd, max(end, 1))
        for (off, size), raw in zip(layout, big):
            done = 0
            while done < size:
                done += os.pwrite(memfd, raw[done:], off + done)
    except OSError:  # (no room for them: all through the pipe)
        return pickle.dumps(answer, protocol=5)
    return pickle.dumps((_OOB_TAG, layout, end, payload), protocol=5)


def _read_answer(rfd: int, closefd: bool = True, memfd: int = -1) -> tuple[bool | None, Any]:
    """In the parent: what :func:`_answer` wrote, or (None, None) when nothing came. Arrays it put in ``memfd``
    are mapped from there (private, copy-on-write: writing into one touches neither the file nor a child forked
    later), not copied."""
    with os.fdopen(rfd, "rb", closefd=closefd) as fh:
        data = fh.read()
    if not data:
        return None, None
    answer = pickle.loads(data)
    if type(answer) is tuple and len(answer) == 4 and answer[0] == _OOB_TAG:
        _, layout, size, payload = answer
        shared = mmap.mmap(memfd, size, flags=mmap.MAP_PRIVATE, prot=mmap.PROT_READ | mmap.PROT_WRITE)
        whole = memoryview(shared)  # (the arrays hold views of it: the map lasts as long as the last of them)
        answer = pickle.loads(payload, buffers=[whole[off:off + n] for off, n in layout])
    return answer


def _close(*fds: int) -> None:
    for fd in fds:
        if fd is None or fd < 0:
            continue
        _CHILDREN_FDS.discard(fd)
        try:
            os.close(fd)
        except OSError:
            pass


def _let_go(pid: int, *fds: int) -> None:
    """A child left to end on its own: this process's ends of its pipes and its memfd closed, the child reaped
    if it has ended already (else it is when this process ends)."""
    _close(*fds)
    try:
        os.waitpid(pid, os.WNOHANG)
    except OSError:
        pass


def _close_prepared() -> None:
    for _pid, w, r, mfd in list(_PREPARED.values()):
        _close(w, r, mfd)
    _PREPARED.clear()


def prepare(name: str, modules: tuple[str, ...], setup: tuple[str, str] | None = None) -> bool:
    """Fork a child that imports ``modules`` now, calls ``setup`` (module, function; an optimisation: what
    fails there is ignored) and then waits for one call (``call_prepared(name, ...)``); where forking is not
    allowed, nothing (the call will run here). Returns whether a child started."""
    if not available() or name in _PREPARED:
        return False
    try:
        req_r, req_w = os.pipe()
        res_r, res_w = os.pipe()
    except OSError:
        return False
    memfd = _memfd()
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        pid = _fork()
    except OSError:
        _close(req_r, req_w, res_r, res_w, memfd)
        return False
    if pid == 0:  # the child: import, wait for the call (or the end of file), answer, leave
        code = 0
        try:
            os.close(req_w)
            os.close(res_r)
            _close_prepared()
            _in_child(memfd)
            for m in modules:
                importlib.import_module(m)
            if setup is not None:
                try:
                    getattr(importlib.import_module(setup[0]), setup[1])()
                except Exception:  # noqa: BLE001 - the call runs without it
                    pass
            fh = os.fdopen(req_r, "rb")
            try:
                fn, args, kwargs, awaiting = pickle.load(fh)
            except EOFError:  # (released unused)
                pass
            else:
                if awaiting:  # (the later object follows the call on the same pipe)
                    kwargs = {**kwargs, "later": Later(fh)}
                _answer(fn, args, kwargs, res_w, memfd)
        except BaseException:  # noqa: BLE001 - an interrupt, a broken pipe: the parent runs the call itself
            code = 1
        finally:
            os._exit(code)
    os.close(req_r)
    os.close(res_w)
    _PREPARED[name] = (pid, req_w, res_r, memfd)
    return True


def call_prepared(name: str, fn: Callable, *args, **kwargs) -> Any:
    """``fn(*args, **kwargs)`` in the child ``prepare(name, ...)`` started (its exception re-raised here),
    or in this process when there is none or it failed (so the answer never depends on it)."""
    if name not in _PREPARED:
        return fn(*args, **kwargs)
    return start_prepared(name, fn, *args, **kwargs).result()


class _Sent:
    """A call sent to a prepared child (``result()`` waits for its answer), run here instead where the
    child cannot take it or dies. An awaiting one (``start_prepared_awaiting``) keeps the pipe open for
    ``send``."""

    def __init__(self, entry: tuple[int, int, int, int], fn: Callable, args: tuple, kwargs: dict,
                 awaiting: bool = False):
        self._pid, req_w, self._res_r, self._memfd = entry
        self._call = (fn, args, kwargs)
        self._awaiting, self._value_sent, self._req_w = awaiting, _UNSENT, -1
        self._sent = self._done = False
        try:
            payload = pickle.dumps((fn, args, kwargs, awaiting), protocol=5)
            with os.fdopen(req_w, "wb", closefd=False) as fh:
                fh.write(payload)
            self._sent = True
        except (OSError, TypeError, AttributeError, pickle.PickleError):
            pass  # not picklable, or the child died: the same call here, at result()
        finally:
            if self._sent and awaiting:
                self._req_w = req_w
                _CHILDREN_FDS.add(req_w)  # (a child forked later closes it)
            else:
                _close(req_w)

    def send(self, value: Any) -> None:
        """The later object of an awaiting call (once): to the child, or kept for the call here."""
        self._value_sent = value
        if self._req_w >= 0:
            _send_later(self._req_w, value)
            self._req_w = -1

    def abandon(self) -> None:
        """As ``Pending.abandon``: the child ends on its own, its answer not read."""
        if self._done:
            return
        self._done = True
        _let_go(self._pid, self._req_w, self._res_r, self._memfd)
        self._req_w = self._memfd = -1

    def result(self) -> Any:
        ok, value = None, None
        self._done = True
        _close(self._req_w)  # (never sent: the child's later() raises EOFError, raised here)
        self._req_w = -1
        try:
            if self._sent:
                ok, value = _read_answer(self._res_r, closefd=False, memfd=self._memfd)
        except (OSError, EOFError, ValueError, pickle.PickleError):
            ok = None
        finally:
            _close(self._res_r, self._memfd)
            self._memfd = -1
            try:
                os.waitpid(self._pid, 0)
            except OSError:
                pass
        if ok is None:
            fn, args, kwargs = self._call
            if self._awaiting:
                kwargs = {**kwargs, "later": Later(value=self._value_sent)}
            return fn(*args, **kwargs)
        if not ok:
            raise value
        return value


def start_prepared(name: str, fn: Callable, *args, **kwargs) -> "Pending | _Sent":
    """``fn(*args, **kwargs)`` started now, beside what this process does next: in the child
    ``prepare(name, ...)`` started, else in a forked child (:func:`submit`), else (forking not allowed) in this
    process when ``result()`` is asked for. ``result()`` waits and returns or re-raises as the call did."""
    entry = _PREPARED.pop(name, None)
    if entry is None:
        return submit(fn, *args, **kwargs)
    return _Sent(entry, fn, args, kwargs)


def start_prepared_awaiting(name: str, fn: Callable, *args, **kwargs) -> "Pending | _Sent":
    """``start_prepared`` for a call that takes ``later`` (``submit_awaiting``): the object given to the
    answer's ``send`` reaches the call when it asks for it."""
    entry = _PREPARED.pop(name, None)
    if entry is None:
        return submit_awaiting(fn, *args, **kwargs)
    return _Sent(entry, fn, args, kwargs, awaiting=True)


def is_prepared(name: str) -> bool:
    """Whether a child ``prepare(name, ...)`` started is waiting for its call."""
    return name in _PREPARED


def release(name: str) -> None:
    """Let a prepared child go unused (it sees its end of file and exits)."""
    entry = _PREPARED.pop(name, None)
    if entry is None:
        return
    _let_go(*entry)
