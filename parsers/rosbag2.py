"""ROS 2 bags: a directory with ``metadata.yaml`` and its storage files (sqlite3 ``.db3`` or ``.mcap``).

Accepted paths: the bag directory, its ``metadata.yaml``, or one ``.db3`` file (with or without the
metadata next to it). Detected by content: a directory by its ``metadata.yaml``
(``rosbag2_bagfile_information``), a file by the YAML key or the SQLite magic.

Reading: sqlite3 storage straight from the ``messages`` table (raw CDR + record timestamps, read in
batches: a damaged database gives the rows read before the damage, with a warning); message
definitions from the ``message_definitions`` table when present, else the built-in ROS 2 (humble)
definitions. mcap storage through :func:`parsers.mcap_ros.read_raw`. Compressed bags (metadata.yaml
``compression_mode: file`` -- ``*.db3.zstd`` / ``*.mcap.zstd`` storage files, decompressed into a temporary
folder -- or ``message`` -- each message zstd-compressed) are read too. Content decoded by
:mod:`parsers.ros_common`.

Writing (``write(path, log, storage="sqlite3"|"mcap", log_delay_ns=0, compression="none"|"file"|"message")``) with
``rosbags.rosbag2.Writer``: same topics as :mod:`parsers.mcap_ros`; written into a temporary
directory next to ``path`` and renamed into place.
"""
from __future__ import annotations

import os
import shutil
import sqlite3
import tempfile
from collections.abc import Callable, Iterator

import numpy as np

from logtools.errors import InputError
from logtools.inslog import InsLog
from parsers import ros_common as rc
from parsers.atomic import atomic_folder
from parsers.base import DAMAGED_HEAD_SEARCH_BYTES, Inventory, Selector, check_readable

NAME = "rosbag2"
EXTENSIONS = (".db3", ".yaml", ".zstd")
SQLITE_MAGIC = b"SQLite format 3\x00"
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
YAML_KEY = b"rosbag2_bagfile_information"
_BATCH = 2_000
_RETRY_QUERIES = 4_000  # a damaged batch is bisected down to single rows with at most this many queries


def message_rows(con, max_id: int, lost: list[tuple[int, int]], gaps: list[tuple[int, int]] | None = None
                 ) -> Iterator[list[tuple]]:
    """The readable message rows (topic_id, timestamp, data) in id order, a batch of ``_BATCH`` ids at a
    time (the caller keeps what it needs: a bag's other topics' payloads are not all held at once); the id
    ranges that could not be read go to ``lost``. A batch that hits a damaged page is split in halves until
    the damage is cornered (a zeroed 4 KiB page lost its whole batch of 2000 rows before). ``gaps``: the id
    ranges (inclusive) a batch read without error does not hold (rosbag2 numbers its rows 1, 2, ...: ids
    deleted, or rows the b-tree no longer leads to, see :func:`unreached`)."""
    budget = [_RETRY_QUERIES]
    query = "SELECT topic_id, timestamp, data FROM messages WHERE id >= ? AND id < ? ORDER BY id"

    def read(a: int, b: int) -> Iterator[list[tuple]]:
        try:
            rows = con.execute(query, (a, b)).fetchall()
        except sqlite3.DatabaseError:
            pass
        else:
            if gaps is not None and len(rows) < min(b, max_id + 1) - max(a, 1):
                _id_gaps(con, max(a, 1), min(b, max_id + 1), gaps)
            yield rows
            return
        if b - a <= 1 or budget[0] <= 0:
            if lost and lost[-1][1] == a - 1:
                lost[-1] = (lost[-1][0], b - 1)
            else:
                lost.append((a, b - 1))
            return
        budget[0] -= 2
        mid = (a + b) // 2
        yield from read(a, mid)
        yield from read(mid, b)

    for a in range(0, max_id + 1, _BATCH):
        yield from read(a, a + _BATCH)


#: the upper end of an id range open to the right (the ids past the largest SQLite finds)
OPEN_END = 1 << 62


def _id_gaps(con, a: int, b: int, gaps: list[tuple[int, int]]) -> None:
    """The ids in [a, b) the messages table does not hold, as inclusive ranges appended to ``gaps``."""
    try:
        ids = np.array([r[0] for r in con.execute("SELECT id FROM messages WHERE id >= ? AND id < ? ORDER BY id",
                                                   (a, b))], np.int64)
    except sqlite3.DatabaseError:
        return
    have = np.zeros(b - a, bool)
    have[ids[(ids >= a) & (ids < b)] - a] = True
    edges = np.flatnonzero(np.diff(np.r_[1, have.astype(np.int8), 1]))  # (starts and ends of the runs of missing)
    gaps.extend((a + int(lo), a + int(hi) - 1) for lo, hi in zip(edges[::2], edges[1::2]))


def unreached(con, max_id: int, lost: list[tuple[int, int]], gaps: list[tuple[int, int]]
              ) -> tuple[list[tuple[int, int]], str]:
    """``lost`` with the id ``gaps`` of batches read without error, and every id past ``max_id``, added where the
    database fails SQLite's quick check (bytes cut from or put into the file move its later pages, and the
    b-tree's pointers then land on other pages: queries answer without error but without those rows, and the
    largest id is not the last row's; a 4 KiB cut early in a bag kept 549 of its 14000 messages), and why;
    ``lost`` alone where the check passes (ids deleted from an intact database)."""
    if not gaps:
        return lost, ""
    try:
        first = str(con.execute("PRAGMA quick_check(1)").fetchone()[0])
    except sqlite3.DatabaseError as exc:
        first = str(exc)
    if first == "ok":
        return lost, ""
    first = " ".join(first.replace("*** in database main ***", "").split())  # (SQLite's report: one line)
    return sorted(lost + gaps + [(max_id + 1, OPEN_END)]), f"rows its b-tree does not lead to: {first}"


def is_bag_folder(path: str) -> bool:
    """A ROS 2 bag's folder: one holding its metadata.yaml (what a bag written or exported may replace)."""
    return os.path.isfile(os.path.join(path, "metadata.yaml"))


def sniff(head: bytes, path: str) -> bool:
    if os.path.isdir(path):
        return is_bag_folder(path)
    if path.endswith((".db3.zstd", ".mcap.zstd")) and head.startswith(ZSTD_MAGIC):
        return True  # one file-compressed storage file
    return head.startswith(SQLITE_MAGIC) or YAML_KEY in head[:4096]


def _resolve(path: str) -> tuple[str, dict | None, list[str], str | None]:
    """(bag directory, metadata dict or None, storage files, what is wrong with metadata.yaml or None). A
    damaged metadata.yaml (unreadable, or no rosbag2 description) beside storage files leaves those files to
    be read alone: the sqlite3 and mcap storages name their topics and types themselves."""
    if os.path.isdir(path):
        bagdir, meta_path = path, os.path.join(path, "metadata.yaml")
        if not os.path.isfile(meta_path):
            raise InputError("directory has no metadata.yaml (not a ROS 2 bag)", path)
    elif path.endswith((".yaml", ".yml")):
        bagdir, meta_path = os.path.dirname(os.path.abspath(path)), path
    else:  # a storage file
        bagdir = os.path.dirname(os.path.abspath(path))
        meta_path = os.path.join(bagdir, "metadata.yaml")
        meta, damage = _read_meta_noted(meta_path) if os.path.isfile(meta_path) else (None, None)
        return bagdir, meta, [path], damage
    meta, damage = _read_meta_noted(meta_path)
    stored = sorted(os.path.join(bagdir, f) for f in os.listdir(bagdir)
                    if f.endswith((".db3", ".mcap", ".db3.zstd", ".mcap.zstd")))
    if meta is None:
        if not stored:
            raise InputError(damage, meta_path)
        return bagdir, None, stored, damage
    files = [os.path.join(bagdir, f) for f in meta.get("relative_file_paths") or []] or stored
    missing = [f for f in files if not os.path.isfile(f)]
    if missing:
        raise InputError(f"storage file(s) listed in metadata.yaml are missing: "
                         f"{', '.join(os.path.basename(m) for m in missing)}", bagdir)
    if not files:
        raise InputError("bag directory holds no storage file (.db3 or .mcap)", bagdir)
    return bagdir, meta, files, None


def _read_meta_noted(meta_path: str) -> tuple[dict | None, str | None]:
    """(the rosbag2 description, None), or (None, what is wrong with the file)."""
    try:
        meta = _read_meta(meta_path)
    except InputError as exc:
        return None, exc.problem
    return (meta, None) if meta is not None else (None, "metadata.yaml is not a rosbag2 description")


def _read_meta(meta_path: str) -> dict | None:
    import yaml

    try:
        with open(meta_path, encoding="utf-8") as fh:
            doc = yaml.safe_load(fh)
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise InputError(f"metadata.yaml unreadable: {str(exc).splitlines()[0]}", meta_path) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("rosbag2_bagfile_information"), dict):
        return None
    return doc["rosbag2_bagfile_information"]


def _read_sqlite(path: str, keep: Callable[[str, str], bool], typestore, warnings: list[str],
                 topics: dict[str, rc.RawTopic]) -> None:
    check_readable(path)
    k = sqlite_start(path)
    if k != 0:
        if k < 0:
            raise InputError("storage file is not an SQLite database", path)
        # bytes put before the database (a transfer's garbage in front of it): SQLite reads a file from its
        # start, so a copy from the database's own header is read (damaged files only)
        with tempfile.TemporaryDirectory(prefix="tapost-rosbag2-") as tmp:
            moved = database_copy(path, k, tmp)
            warnings.append(prefix_damage(path, k))
            try:
                _read_sqlite(moved, keep, typestore, warnings, topics)
            except InputError as exc:
                raise InputError(exc.problem, path) from None
        return
    try:
        con = connect_ro(path)
    except sqlite3.Error as exc:
        raise InputError(f"cannot open sqlite3 storage: {exc}", path) from None
    try:
        try:
            trows = con.execute("SELECT id, name, type, serialization_format FROM topics ORDER BY id").fetchall()
        except sqlite3.DatabaseError as exc:
            raise InputError(f"sqlite3 storage damaged (topics table unreadable: {exc})", path) from None
        try:
            for ttype, enc, text in con.execute(
                    "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions"):
                mt = rc.normalize_msgtype(ttype)
                if text and mt not in typestore.fielddefs and mt in rc.SUPPORTED:
                    try:
                        rc.register_msgdef(typestore, mt, text, "idl" if "idl" in enc else "msg")
                    except Exception as exc:
                        warnings.append(f"message definition of {mt} unusable ({type(exc).__name__})")
        except sqlite3.DatabaseError:
            pass  # older bags: no message_definitions table
        by_id: dict[int, rc.RawTopic] = {}
        for tid, name, ttype, fmt in trows:
            mt = rc.normalize_msgtype(ttype)
            raw = topics.get(name) or rc.RawTopic(name, mt, "cdr" if fmt == "cdr" else str(fmt))
            topics[name] = raw
            by_id[tid] = raw
            if fmt != "cdr" and mt in rc.SUPPORTED:
                warnings.append(f"{name}: serialization format {fmt!r} not supported; topic ignored")
        keep_ids = {tid for tid, r in by_id.items() if r.encoding == "cdr" and keep(r.name, r.msgtype)}
        _read_messages(con, path, by_id, keep_ids, warnings)
    finally:
        con.close()


def sqlite_start(path: str) -> int:
    """Where the SQLite database of the storage file ``path`` starts: 0 at its first byte; k > 0 where k bytes
    were put before it (its header found within DAMAGED_HEAD_SEARCH_BYTES); -1 where no header is found."""
    with open(path, "rb") as fh:
        head = fh.read(DAMAGED_HEAD_SEARCH_BYTES)
    if head.startswith(SQLITE_MAGIC):
        return 0
    k = head.find(SQLITE_MAGIC)
    return k if k > 0 else -1


def database_copy(path: str, start: int, folder: str, name: str | None = None) -> str:
    """A copy of ``path`` from byte ``start`` on (its database: :func:`sqlite_start`) in ``folder``, under
    ``name`` (default the file's own); its path."""
    moved = os.path.join(folder, name or os.path.basename(path))
    with open(path, "rb") as src, open(moved, "wb") as dst:
        src.seek(start)
        shutil.copyfileobj(src, dst, 1 << 22)
    return moved


def prefix_damage(path: str, start: int) -> str:
    """The damage of a storage file whose database starts at byte ``start`` (:func:`sqlite_start`)."""
    return (f"damaged: {os.path.basename(path)}: its first {start} bytes are not SQLite's; the database read "
            f"from byte {start}")


def connect_ro(path: str) -> sqlite3.Connection:
    """A read-only connection to a .db3 that never writes (``immutable``) and opens a truncated file too:
    ``writable_schema`` lets SQLite read a file shorter than its header's page count (without it, every
    query of a copy cut short fails, "database disk image is malformed", even where its pages are whole)."""
    con = sqlite3.connect(f"file:{path}?mode=ro&immutable=1", uri=True)
    con.execute("PRAGMA writable_schema=ON")
    return con


def max_message_id(con) -> tuple[int | None, str]:
    """The largest message id, or (None, why) when the table's b-tree cannot be followed to its end."""
    try:
        (max_id,) = con.execute("SELECT max(id) FROM messages").fetchone()
    except sqlite3.DatabaseError as exc:
        return None, str(exc)
    return int(max_id or 0), ""


def recovered_rows(path: str, lost: list[tuple[int, int]] | None, why: str) -> tuple[list[tuple], str]:
    """The rows (topic_id, timestamp, data) of the id ranges ``lost`` (inclusive; None: every row) that a
    page scan of the file finds (``restamp_sqlite.recover``: the leaf pages, whatever the b-tree's interior
    pages say), and one sentence on what was read and what is still missing."""
    from parsers import restamp_sqlite

    name = os.path.basename(path)
    rec = restamp_sqlite.recover(path)
    if rec is None or not len(rec.rowid):
        where = ", ".join(f"{a}-{b}" for a, b in lost) if lost else "all"
        return [], f"{name}: sqlite3 storage damaged ({why}): message rows {where} unreadable, none found by a page scan"
    take = np.ones(len(rec.rowid), bool)
    if lost is not None:
        lo = np.array([a for a, _ in lost], np.int64)
        hi = np.array([b for _, b in lost], np.int64)
        j = np.searchsorted(lo, rec.rowid, side="right") - 1
        take = (j >= 0) & (rec.rowid <= hi[np.clip(j, 0, None)])
    idx = np.flatnonzero(take).tolist()
    rows = [(int(rec.topic[i]), int(rec.timestamp[i]), rec.data[i]) for i in idx]
    ids = rec.rowid[take]
    want = int(sum(b - a + 1 for a, b in lost if b < OPEN_END)) if lost is not None else None
    note = f"{name}: sqlite3 storage damaged ({why}); {len(rows)} message row{'' if len(rows) == 1 else 's'}"
    note += f" of the {want} unreadable ones" if want is not None else ""
    note += " and the rows past the last id SQLite finds" if lost is not None and any(b >= OPEN_END for _, b in lost) else ""
    note += " read from its intact pages by a page scan"
    if rec.truncated:
        note += (f"; the file ends at page {rec.pages_present} of the {rec.pages_declared} its header declares "
                 f"(truncated: the rows after id {int(ids.max()) if len(ids) else 0} are lost)")
    if rec.moved:
        note += "; " + "; ".join(rec.moved)
    if rec.cells_passed_over:
        note += f"; {rec.cells_passed_over} damaged cells passed over"
    return rows, note


def _read_messages(con, path: str, by_id: dict, keep_ids: set, warnings: list[str]) -> None:
    """Messages in rowid batches, so that a damaged page loses only its batch; what SQLite cannot reach
    (a b-tree page lost: a truncated copy) is looked for page by page (``recovered_rows``); reported."""
    max_id, why = max_message_id(con)
    lost: list[tuple[int, int]] | None = None if max_id is None else []
    touched = set()

    def take(rows: list[tuple]) -> None:
        for tid, ts, data in rows:
            raw = by_id.get(tid)
            if raw is None:
                continue
            touched.add(tid)
            raw.log_ns.append(ts)
            if tid in keep_ids:
                raw.data.append(data)

    gaps: list[tuple[int, int]] = []
    if max_id is not None:
        for rows in message_rows(con, max_id, lost, gaps):
            take(rows)
        lost, why_gaps = unreached(con, max_id, lost, gaps)
        why = why or why_gaps
    if lost is None or lost:
        rows, note = recovered_rows(path, lost, why or "pages unreadable")
        take(rows)
        warnings.append(note + ("; readable part used" if rows or max_id else ""))
    for tid in touched:  # rowid order is insertion order; make it log-time order
        raw = by_id[tid]
        t = np.asarray(raw.log_ns, np.int64)
        if len(t) > 1 and np.any(np.diff(t) < 0):
            order = np.argsort(t, kind="stable")
            raw.log_ns = t[order].tolist()
            if raw.data:
                raw.data = [raw.data[i] for i in order.tolist()]


def read_raw(path: str, keep: Callable[[str, str], bool] = rc.keep_supported) -> rc.RawLog:
    from rosbags.typesys import Stores, get_typestore

    check_readable(path)
    bagdir, meta, files, meta_damage = _resolve(path)
    storage = (meta or {}).get("storage_identifier") or ""
    warnings: list[str] = []
    if meta_damage is not None:
        warnings.append(f"damaged: {meta_damage}; the storage file(s) read without it "
                        f"({', '.join(os.path.basename(f) for f in files)})")
    topics: dict[str, rc.RawTopic] = {}
    typestore = get_typestore(Stores.EMPTY)
    mode, cfmt = _compression(meta)
    if mode in ("file", "message") and cfmt != "zstd":
        raise InputError(f"compression format {cfmt!r} not supported (zstd is)", bagdir)
    with tempfile.TemporaryDirectory(prefix="tapost-rosbag2-") as tmp:
        for f in files:
            if not (mode == "file" or f.endswith(".zstd")):
                _read_storage(f, storage, keep, typestore, warnings, topics)
                continue
            try:  # errors name the user's (compressed) file, not the temporary copy
                _read_storage(_unzstd_file(f, tmp), storage, keep, typestore, warnings, topics)
            except InputError as exc:
                raise InputError(exc.problem, f) from None
    if meta is None and mode == "none" and any(t.data and bytes(t.data[0][:4]) == ZSTD_MAGIC for t in topics.values()):
        mode = "message"  # (no metadata to say so: per-message zstd frames seen in the data)
    if mode == "message":
        _unzstd_messages(topics, warnings)
    from parsers.mcap_ros import register_builtin

    register_builtin(typestore, {t.msgtype for t in topics.values() if t.msgtype in rc.SUPPORTED and t.data}, "cdr")
    if meta is not None:
        declared = int(meta.get("message_count") or 0)
        have = sum(t.count for t in topics.values())
        total = (f"read {have} of the {declared} messages metadata.yaml declares"
                 if declared and have < declared else "")
        short = []  # (each topic read against its count in metadata.yaml: a topic's messages lost alone)
        for entry in meta.get("topics_with_message_count") or ():
            try:
                name, count = entry["topic_metadata"]["name"], int(entry["message_count"])
            except (KeyError, TypeError, ValueError):
                continue
            t = topics.get(name)
            if t is not None and t.count < count:
                short.append(f"{name} {t.count} of {count}")
        per_topic = (f"fewer messages than metadata.yaml declares per topic: {', '.join(short[:5])}"
                     + (f" (and {len(short) - 5} more topics)" if len(short) > 5 else "")) if short else ""
        if total or per_topic:  # (one damage, one warning: the total and the topics it fell short in)
            warnings.append("damaged or cut short: " + "; ".join(x for x in (total, per_topic) if x))
    return rc.RawLog(path=path, fmt=NAME, topics=topics, typestore=typestore, warnings=warnings)


def _read_storage(f: str, storage: str, keep: Callable[[str, str], bool], typestore, warnings: list[str],
                  topics: dict[str, rc.RawTopic]) -> None:
    """One (uncompressed) storage file into ``topics``."""
    from parsers import mcap_ros

    if f.endswith(".mcap") or storage == "mcap":
        part = mcap_ros.read_raw(f, keep, fmt=NAME)
        warnings += [f"{os.path.basename(f)}: {w}" for w in part.warnings]
        for name, t in part.topics.items():
            if t.msgtype in part.typestore.fielddefs and t.msgtype not in typestore.fielddefs:
                need = mcap_ros._closure(part.typestore, {t.msgtype})
                typestore.register({k: part.typestore.fielddefs[k] for k in need
                                    if k not in typestore.fielddefs})
            if name in topics:
                topics[name].log_ns.extend(t.log_ns)
                topics[name].data.extend(t.data)
            else:
                topics[name] = t
    else:
        _read_sqlite(f, keep, typestore, warnings, topics)


# ---- compressed bags (``ros2 bag record --compression-mode file|message --compression-format zstd``) --
def _compression(meta: dict | None) -> tuple[str, str]:
    """(mode: "none" | "file" | "message" | "storage", format) from metadata.yaml."""
    meta = meta or {}
    mode = str(meta.get("compression_mode") or "none").strip().lower() or "none"
    return mode, str(meta.get("compression_format") or "").strip().lower()


def _unzstd_file(f: str, tmpdir: str) -> str:
    """A zstd-compressed storage file decompressed into ``tmpdir`` (the input is left as it is)."""
    import zstandard

    name = os.path.basename(f)
    out = os.path.join(tmpdir, name[:-5] if name.endswith(".zstd") else name + ".raw")
    check_readable(f)
    dobj = zstandard.ZstdDecompressor().decompressobj()
    try:
        with open(f, "rb") as src, open(out, "wb") as dst:
            while chunk := src.read(1 << 22):
                dst.write(dobj.decompress(chunk))
    except zstandard.ZstdError as exc:
        raise InputError(f"compressed storage file cannot be decompressed (zstd: {exc})", f) from None
    if not dobj.eof:
        raise InputError("compressed storage file cannot be decompressed: the zstd stream is cut "
                         "(file truncated)", f)
    return out


def _unzstd_messages(topics: dict[str, rc.RawTopic], warnings: list[str]) -> None:
    """Per-message zstd compression undone; a message that does not decompress is dropped (reported)."""
    import zstandard

    dctx = zstandard.ZstdDecompressor()
    for name, raw in topics.items():
        if not raw.data:
            continue
        out, keep = [], []
        for i, d in enumerate(raw.data):
            try:
                out.append(dctx.decompressobj().decompress(d))
                keep.append(i)
            except zstandard.ZstdError:
                pass
        if len(keep) < len(raw.data):
            warnings.append(f"{name}: {len(raw.data) - len(keep)} of {len(raw.data)} compressed messages "
                            "do not decompress (damaged); dropped")
            raw.log_ns = [raw.log_ns[i] for i in keep]
        raw.data = out


def load(path: str, selector: Selector) -> InsLog:
    return rc.to_inslog(read_raw(path), selector)


def inventory(path: str) -> Inventory:
    return rc.to_inventory(read_raw(path))


def write(path: str, log: InsLog, *, storage: str = "sqlite3", log_delay_ns: int = 0,
          compression: str = "none") -> None:
    """Write ``log`` as a ROS 2 bag directory (``storage`` "sqlite3" or "mcap"; ``compression`` "none",
    "file" or "message", zstd), atomically."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

    plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}.get(storage)
    if plugin is None:
        raise InputError(f"rosbag2 storage must be sqlite3 or mcap, not {storage!r}", path)
    cmode = {"none": None, "file": CompressionMode.FILE, "message": CompressionMode.MESSAGE}.get(compression, 0)
    if cmode == 0:
        raise InputError(f"rosbag2 compression must be none, file or message, not {compression!r}", path)
    typestore = rc.default_typestore("cdr")
    topics = rc.ros_topics_from_inslog(log, typestore, "cdr")
    with atomic_folder(path, same_kind=is_bag_folder, what="ROS 2 bag") as tmp:
        w = Writer(tmp, version=9, storage_plugin=plugin)
        if cmode is not None:
            w.set_compression(cmode, CompressionFormat.ZSTD)
        with w:
            conns = [w.add_connection(tp.name, tp.msgtype, typestore=typestore) for tp in topics]
            for t, k, i in rc.merged_order(topics, log_delay_ns):
                w.write(conns[k], t, topics[k].data[i])
