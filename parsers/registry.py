"""Format registry: detection by content (magic bytes), dispatch to the format's module."""
from __future__ import annotations

import importlib
import os
from dataclasses import replace
from types import ModuleType

from logtools.errors import InputError
from logtools.inslog import InsLog
from parsers.base import DAMAGED_HEAD_READ_BYTES, Inventory, Selector, check_readable, release_free_memory

#: format modules, most specific sniffers first, each with the name NAMED_BY_EXTENSION gives its extensions
#: (its NAME; CSV for the two CSV readers: test_registry). Each has NAME, sniff, load, inventory (and may
#: have write). A module that is not present (yet) is simply skipped.
_MODULES = (
    ("parsers.mcap_ros", "mcap"),
    ("parsers.rosbag1", "rosbag1"),
    ("parsers.rosbag2", "rosbag2"),
    ("parsers.ulog", "ulog"),
    ("parsers.dataflash", "dataflash"),
    ("parsers.mavlink_tlog", "tlog"),
    ("parsers.parquet_canonical", "parquet"),
    ("parsers.csv_vendor", "CSV"),
    ("parsers.csv_canonical", "CSV"),
)

HEAD_BYTES = 8192

#: what a file's extension says it is, for a file whose content is another format (said, not decided on:
#: detection is by content). Known without importing the format modules (a Parquet reader would import
#: pandas, a tlog reader a MAVLink dialect); each module's EXTENSIONS are here (test_registry)
NAMED_BY_EXTENSION = {".mcap": "mcap", ".bag": "rosbag1", ".db3": "rosbag2", ".yaml": "rosbag2", ".zstd": "rosbag2",
                      ".ulg": "ulog", ".bin": "dataflash", ".tlog": "tlog", ".parquet": "parquet",
                      ".pq": "parquet", ".csv": "CSV", ".txt": "CSV"}


def iter_formats(first: str | None = None):
    """The format modules in sniffing order, each imported when it is reached (detecting an MCAP file
    imports no MAVLink dialect: 0.13 s); ``first``: a file name, whose extension's modules
    (``NAMED_BY_EXTENSION``) come first, in that order (detecting a tlog then imports none of the four
    readers before it: about 20 ms)."""
    said = NAMED_BY_EXTENSION.get(os.path.splitext(first)[1].lower()) if first else None
    order = [name for name, tag in _MODULES if tag == said] + [name for name, tag in _MODULES if tag != said]
    for name in order:
        try:
            yield importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise


def formats() -> list[ModuleType]:
    return list(iter_formats())


def format_by_name(name: str) -> ModuleType:
    for mod in formats():
        if mod.NAME == name:
            return mod
    raise InputError(f"unknown format {name!r}; known: {', '.join(m.NAME for m in formats())}")


def _given(arg, limit: int = 60) -> str:
    """What a wrong argument was, for a message: its type and (short) repr."""
    if isinstance(arg, InsLog):
        return f"an InsLog (read from {arg.meta.source_path or 'memory'})"
    if arg is None:
        return "None"
    text = repr(arg)
    return f"{type(arg).__name__} {text if len(text) <= limit else text[:limit - 3] + '...'}"


def path_arg(arg, what: str = "a log", selector: bool = True, inslog: bool = False) -> str:
    """``arg`` as a str path: a str as it is, an ``os.PathLike`` (``pathlib.Path``) by ``os.fspath`` (its
    text read as a str's: ``PATH[::SELECTOR]`` where ``selector``); anything else (None, a number, bytes, a
    list, an InsLog) raises InputError naming ``what``, what was given and what is expected (``inslog``: the
    caller takes an InsLog too, and says so)."""
    if isinstance(arg, str):
        return arg
    if isinstance(arg, os.PathLike):
        try:
            return os.fsdecode(os.fspath(arg))
        except (TypeError, UnicodeDecodeError) as exc:
            raise InputError(f"{what} must be a path; {_given(arg)} gives none: {exc}") from None
    hint = ""
    if isinstance(arg, InsLog):
        hint = ": this takes a file, not a log already read (its path is log.meta.source_path)"
    elif isinstance(arg, (bytes, bytearray)):
        hint = ": decode it (os.fsdecode) or give a str or pathlib.Path"
    elif isinstance(arg, (list, tuple, set, frozenset, dict)):
        hint = ": give one path"
    form = ("a path: a str PATH[::SELECTOR] or an os.PathLike such as pathlib.Path" if selector
            else "a path: a str or an os.PathLike such as pathlib.Path")
    if inslog:
        form = "an InsLog (api.load) or " + form
    raise InputError(f"{what} must be {form}; got {_given(arg)}{hint}")


def parse_log_arg(arg) -> tuple[str, Selector]:
    """``PATH[::SELECTOR]`` (a str, or an ``os.PathLike`` whose text is read the same) -> (path, Selector)."""
    path, sep, sel = path_arg(arg).partition("::")
    try:
        selector = Selector.parse(sel) if sep else Selector()
    except ValueError as exc:
        raise InputError(f"bad selector: {exc}", path) from None
    seen: dict[str, str] = {}
    for k, v in selector.items:  # (a later one would be ignored or win, depending on the reader: neither is said)
        if k in seen:
            raise InputError(f"bad selector: key {k!r} given twice ({k}={seen[k]} and {k}={v}); give each key once",
                             path)
        seen[k] = v
    return path, selector


def detect(path) -> ModuleType:
    """The format module for ``path`` (a str or ``os.PathLike``), decided by content (a directory by its
    metadata)."""
    path = path_arg(path, "the log file", selector=False)
    check_readable(path)
    head = b""
    if not os.path.isdir(path):
        with open(path, "rb") as fh:
            head = fh.read(HEAD_BYTES)
    for mod in iter_formats(first=path):  # (by content: the name only decides which reader asks first)
        try:
            if mod.sniff(head, path):
                return mod
        except OSError:
            continue
    if not os.path.isdir(path):
        # a file whose first bytes are damaged, or that has bytes put before it: the formats that can read on
        # past them, each looking for its own start over the same window (base.DAMAGED_HEAD_READ_BYTES); the
        # formats the file is named like first
        with open(path, "rb") as fh:
            head = fh.read(DAMAGED_HEAD_READ_BYTES)
        named = _named_formats(path)
        for mod in sorted(formats(), key=lambda m: m not in named):
            sniff_damaged = getattr(mod, "sniff_damaged", None)
            try:
                if sniff_damaged is not None and sniff_damaged(head, path):
                    return mod
            except OSError:
                continue
    if os.path.isdir(path):
        raise InputError("directory holds no recognised log (no metadata.yaml, no sensors.csv)", path)
    raise InputError("unrecognised format (not MCAP, ROS bag, ULog, DataFlash, tlog, CSV or tapost's Parquet)" + _named_like(path), path)


def _named_formats(path: str) -> list[ModuleType]:
    """The format modules whose file extensions the name of ``path`` has."""
    ext = os.path.splitext(path)[1]
    return [m for m in formats() if ext and ext.lower() in (e.lower() for e in m.EXTENSIONS)]


#: the words of :func:`_named_otherwise`'s warning that mark it (analyze repeats it in a failure's line)
NAMED_OTHERWISE = "by its content, though its name"


def _named_otherwise(path: str, mod: ModuleType) -> str | None:
    """What to say where a file read as ``mod`` (by its content) is named like another format
    (``NAMED_BY_EXTENSION``): a log renamed by hand, or another file than the one meant. Not for a ROS 2 bag's
    storage file (named .mcap or .db3 as its storage plugin writes it)."""
    ext = os.path.splitext(path)[1].lower()
    said = NAMED_BY_EXTENSION.get(ext)
    if (said is None or os.path.isdir(path) or mod.NAME == "rosbag2"
            or ext in (e.lower() for e in getattr(mod, "EXTENSIONS", ()))):
        return None
    return (f"read as {mod.NAME} {NAMED_OTHERWISE} ({os.path.basename(path)}) says {said}: another file than the "
            "one meant?")


def _named_like(path: str) -> str:
    """What the file's name suggests, where its content is not that format (a damaged start, mostly)."""
    named = _named_formats(path)
    if not named:
        return ""
    if all(m.NAME.startswith("csv") for m in named):
        with open(path, "rb") as fh:
            bom = fh.read(2)
        if bom in (b"\xff\xfe", b"\xfe\xff"):  # (Excel's "Unicode text", some Windows loggers)
            return "; a CSV in UTF-16 text: save it as UTF-8 (or ASCII) and read that"
        return ("; named like a CSV, but its first line is no header of named columns (damaged?): a CSV is "
                "read through its header (time_s,... or names with units)")
    return f"; named like {named[0].NAME}, but its first bytes are not (damaged, or another format?)"


def load(arg) -> InsLog:
    """Read ``PATH[::SELECTOR]`` (a str, or an ``os.PathLike`` such as ``pathlib.Path``) into an InsLog.
    Raises InputError with a one-line reason (a wrong type of ``arg`` too)."""
    path, selector = parse_log_arg(arg)
    mod = detect(path)
    try:
        log = mod.load(path, selector)
    except InputError:
        raise
    except (MemoryError, KeyboardInterrupt):
        raise
    except Exception as exc:  # a library choking on damaged input: one line, not a traceback
        raise InputError(f"cannot read as {mod.NAME}: {type(exc).__name__}: {exc}", path) from exc
    finally:
        release_free_memory()  # the parse's temporaries: not held into the next stage
    other = _named_otherwise(path, mod)
    return log.with_streams(meta=log.meta.with_warning(other)) if other else log


def inspect_log(path) -> Inventory:
    """What a log holds (its selectable units); ``path``: a str or ``os.PathLike``."""
    path = path_arg(path, "the log file", selector=False)
    mod = detect(path)
    try:
        inv = mod.inventory(path)
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"cannot read as {mod.NAME}: {type(exc).__name__}: {exc}", path) from exc
    other = _named_otherwise(path, mod)
    return replace(inv, warnings=inv.warnings + (other,)) if other else inv


def write(path, log: InsLog, fmt: str, **options) -> None:
    """Write ``log`` to ``path`` (a str or ``os.PathLike``) in format ``fmt`` (atomically: temp file + rename)."""
    path = path_arg(path, "the output", selector=False)
    if not isinstance(log, InsLog):
        raise InputError(f"the log to write must be an InsLog, not {_given(log)}", path)
    mod = format_by_name(fmt)
    if not hasattr(mod, "write"):
        raise InputError(f"format {fmt} cannot be written", path)
    mod.write(path, log, **options)
