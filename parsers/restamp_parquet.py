"""The slave on the master's clock, natively: a Parquet file of canonical columns (tapost's own export).

Rewritten through pyarrow: every row and column kept in order with its type, the file's key/value metadata
kept (the shift applied added as ``tapost.restamp.*``), only the time columns changed: ``time_ns`` to the
master's clock exactly, and ``time_s`` (float64 seconds) from it where present; a file with ``time_s``
only gets it rewritten from its nanoseconds rounded. Rows without a time keep their empty cell.
"""
from __future__ import annotations

from logtools.errors import InputError
from parsers.atomic import atomic_path
from parsers.restamp import ClockShift, RestampStats

HOW = "rewritten through pyarrow (every row and column kept; only the time columns changed)"


def restamp_parquet(src: str, dst: str, shift: ClockShift, *, selector=None) -> RestampStats:
    import pyarrow as pa
    import pyarrow.parquet as pq

    from parsers.csv_canonical import TIME
    from parsers.parquet_canonical import TIME_NS, read_parquet, seconds_of_ns, stamps_ns

    table = read_parquet(src)
    names = table.column_names
    t_ns, valid, _ = stamps_ns(table, src)
    new = t_ns.copy()
    new[valid] = shift.to_master_ns(t_ns[valid])
    if (new[valid] < 0).any():
        raise InputError("native export: shifted stamps would be negative (the master's clock starts later than "
                         "the slave's; export csv instead)", src)
    changed = []
    for name in (TIME_NS, TIME):
        if name not in names:
            continue
        i = names.index(name)
        if name == TIME_NS:
            arr = pa.array(new.astype(table.schema.field(i).type.to_pandas_dtype(), copy=False),
                           table.schema.field(i).type, mask=~valid)
        else:
            arr = pa.array(seconds_of_ns(new), table.schema.field(i).type, mask=~valid)
        table = table.set_column(i, table.schema.field(i), arr)
        changed.append(name)
    meta = dict(table.schema.metadata or {})
    meta.update({f"tapost.restamp.{k}".encode(): str(v).encode() for k, v in
                 (("latency_s", shift.latency_s), ("drift_ppm", shift.drift_ppm), ("t_ref_ns", shift.t_ref_ns))})
    table = table.replace_schema_metadata(meta)
    with atomic_path(dst) as tmp:
        pq.write_table(table, tmp)
    damage = (f"{int((~valid).sum())} row(s) without a time copied unchanged",) if not valid.all() else ()
    return RestampStats(path=dst, format="parquet", how=HOW, records=len(new), records_by_type={"rows": len(new)},
                        time_fields=tuple(changed), damage=damage)
