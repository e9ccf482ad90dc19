"""The code of the methods that dataclasses and attrs generate, compiled once and kept on disk (tapost's
command-line processes only; the Python API leaves Python as it is).

``@dataclass`` writes each class's ``__init__``, ``__repr__``, ``__eq__``, ``__hash__`` (and, frozen,
``__setattr__``/``__delattr__``) as Python source and compiles it while the class's module is imported;
attrs does the same for rerun's classes, rosbags for the message classes of a log's definitions. A ``tapost
analyze`` of the sample pair made about 100 dataclasses (tapost's configurations and results, the parsers')
and rerun about 160 attrs methods: 45-65 ms of compiling in the analysing process, 23 ms in the recording's
child, about 10 ms in the parse's, every run, for the same text. Here those modules' ``exec``/``compile`` is
given the code object compiled before for exactly that text (and file name, mode and future flags), from
``<cache>/codecache-<interpreter>-<bytecode magic>.marshal``; other text is compiled as Python does. The same
code object as Python compiles (the interpreter's bytecode, named in the file), so the same classes.

A text joins the table once a second process has compiled it (the first notes it as seen once, in a small
file beside it): some texts are new in every process (attrs' ``__hash__`` holds a hash of its class's name,
which Python salts per process: 17 of rerun's), and the table would grow by them at every run. Both files
are written (atomically, merged with what another process wrote meanwhile) at the end of a process that
compiled text the table did not hold, a forked child's too (``pipelines.parallel``). Only an optimisation:
a table that cannot be read or written, or a module of another layout, leaves Python compiling as it does.
Measured on 2 cores, whole processes of the sample pair alternated: CPU 1.22 -> 1.13 s, wall 0.72 -> 0.68 s
(medians of 24).
"""
import __future__

import builtins
import hashlib
import importlib.util
import marshal
import os
import sys

#: the most entries a written table keeps (one per generated text; a run of ``analyze`` uses about 1 000):
#: above it, one written after code changes keeps those its process used
MAX_ENTRIES = 3000
#: the most keys of texts seen once that are kept (the latest)
MAX_SEEN = 4000
#: ``TAPOST_CODE_CACHE=0``: compile as Python does
ENV = "TAPOST_CODE_CACHE"

_CODES: dict = {}
_USED: set = set()
_NEW: set = set()
_STATE: dict = {"path": None}


def table_path() -> str:
    from logtools.jit import cache_home

    tag = sys.implementation.cache_tag or sys.implementation.name
    return os.path.join(cache_home(), f"codecache-{tag}-{importlib.util.MAGIC_NUMBER.hex()}.marshal")


def _read(path: str, kind: type):
    """The marshalled ``kind`` (dict: the table; list: the keys seen once) at ``path``; empty where it cannot
    be read."""
    try:
        with open(path, "rb") as fh:
            value = marshal.loads(fh.read())
    except (OSError, EOFError, ValueError, TypeError):
        return kind()
    return value if type(value) is kind else kind()


def _write(path: str, value) -> None:
    from parsers.atomic import atomic_path

    data = marshal.dumps(value)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)


def _future_flags(module) -> int:
    """The ``from __future__`` features of ``module``, which a ``compile`` called from it inherits."""
    flags = 0
    for name in __future__.all_feature_names:
        feature = getattr(__future__, name)
        if getattr(module, name, None) is feature:
            flags |= feature.compiler_flag
    return flags


def _compiled(source: str, filename: str, mode: str, flags: int):
    key = hashlib.blake2b(f"{flags}\0{sys.flags.optimize}\0{mode}\0{filename}\0{source}".encode(),
                          digest_size=16).digest()  # (-O: the code Python compiles then differs)
    code = _CODES.get(key)
    if code is None:
        code = compile(source, filename, mode, flags=flags, dont_inherit=True)
        _CODES[key] = code
        _NEW.add(key)
    _USED.add(key)
    return code


def _exec_with(flags: int):
    """``exec``, the code of a source text from the table (compiled with the caller's future ``flags``)."""

    def cached_exec(source, globals=None, locals=None, /, *args, **kwargs):
        if type(source) is str and not args and not kwargs:
            source = _compiled(source, "<string>", "exec", flags)
        return builtins.exec(source, globals, locals, *args, **kwargs)

    return cached_exec


def _eval_with(flags: int):
    """``eval``, the code of a source text from the table (the caller's future ``flags``)."""

    def cached_eval(source, globals=None, locals=None, /):
        if type(source) is str:
            source = _compiled(source, "<string>", "eval", flags)
        return builtins.eval(source, globals, locals)

    return cached_eval


def _compile_with(flags: int):
    """``compile``, its code from the table (the caller's future ``flags``)."""

    def cached_compile(source, filename, mode, *args, **kwargs):
        if type(source) is str and type(filename) is str and not args and not kwargs:
            return _compiled(source, filename, mode, flags)
        return builtins.compile(source, filename, mode, *args, **kwargs)

    return cached_compile


_CACHED = {"exec": _exec_with, "eval": _eval_with, "compile": _compile_with}


#: modules that compile generated source through a builtin looked up in their globals, and which one: served
#: from the table (where imported already, at ``install``; else from their first line on, their own classes
#: too: :class:`_Finder`): dataclasses, typing (a string annotation, as rosbags' message classes have them),
#: collections (namedtuple's ``__new__``), attrs (rerun's classes, in the recording's child) and rosbags' type
#: store (the message classes it generates for each ROS message definition of a log)
MODULE_BUILTINS = {"dataclasses": "exec", "typing": "compile", "collections": "eval", "attr._make": "compile",
                   "rosbags.typesys.store": "exec"}


class _Finder:
    """A meta path finder for the MODULE_BUILTINS modules: their spec as the other finders give it, its
    loader putting the cached builtin into the module's namespace before the module's code runs."""

    def find_spec(self, name, path=None, target=None):
        what = MODULE_BUILTINS.get(name)
        if what is None:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(name, path, target)
            if spec is not None:
                break
        else:
            return None
        loader = spec.loader
        if loader is None or not hasattr(loader, "exec_module") or not hasattr(loader, "get_code"):
            return spec
        spec.loader = _Loader(loader, what)
        return spec


class _Loader:
    """The real loader, the module's code run with the cached builtin in its namespace."""

    def __init__(self, loader, what: str) -> None:
        self._loader, self._what = loader, what

    def __getattr__(self, name):  # (get_code, get_source, is_package, ...: the real loader's)
        return getattr(self._loader, name)

    def create_module(self, spec):
        return self._loader.create_module(spec)

    def exec_module(self, module) -> None:
        code = self._loader.get_code(module.__name__)
        module.__loader__ = self._loader  # (the module's loader is the real one once it runs)
        if module.__spec__ is not None:
            module.__spec__.loader = self._loader
        # its compiles get the future flags its source declares (attrs: annotations), read from its code
        module.__dict__[self._what] = _CACHED[self._what](code.co_flags & _FUTURE_MASK if code is not None else 0)
        if code is None:
            self._loader.exec_module(module)
        else:
            exec(code, module.__dict__)


_FUTURE_MASK = 0
for _name in __future__.all_feature_names:
    _FUTURE_MASK |= getattr(__future__, _name).compiler_flag


def install() -> bool:
    """The table loaded and the MODULE_BUILTINS modules' builtin served from it (a ``tapost`` command's process,
    first thing); False where it is off (``TAPOST_CODE_CACHE=0``) or has no cache directory."""
    if os.environ.get(ENV, "1") == "0" or _STATE["path"] is not None:
        return False
    try:
        path = table_path()
    except Exception:  # noqa: BLE001 - no cache directory to be had
        return False
    code_type = type(install.__code__)
    _CODES.update((k, v) for k, v in _read(path, dict).items() if type(k) is bytes and type(v) is code_type)
    _STATE["path"] = path
    os.register_at_fork(after_in_child=_forked)
    for name, what in MODULE_BUILTINS.items():
        module = sys.modules.get(name)
        if module is not None and what not in vars(module):  # (else: not the builtin, left alone)
            setattr(module, what, _CACHED[what](_future_flags(module)))
    sys.meta_path.insert(0, _Finder())
    import atexit

    atexit.register(save)  # (a forked child of pipelines.parallel leaves by os._exit: it saves there)
    return True


def _forked() -> None:
    """In a forked child: what it compiles from now on is its own to save (its parent saves the rest)."""
    _NEW.clear()
    _USED.clear()


def save() -> None:
    """Where this process compiled text the table did not hold: the texts another process had compiled before
    (seen once) added to the table, which is written again (atomically, merged with the file as it is now),
    and the others noted as seen once (a small file of their keys beside it: in every run of ``analyze`` the
    recording's child notes its salted texts there). Never raises."""
    path = _STATE["path"]
    if path is None or not _NEW:
        return
    try:
        seen_path = path + ".seen"
        seen = _read(seen_path, list)
        again = _NEW.intersection(seen)
        if again:
            codes = _read(path, dict)
            codes.update({k: _CODES[k] for k in again})
            if len(codes) > MAX_ENTRIES:
                codes = {k: _CODES[k] for k in _USED if k in _CODES}
            _write(path, codes)
        known = set(seen)
        seen = [k for k in seen if k not in again] + sorted(k for k in _NEW - again if k not in known)
        _write(seen_path, seen[-MAX_SEEN:])
        _NEW.clear()
    except Exception:  # noqa: BLE001 - the next run compiles it again
        pass
