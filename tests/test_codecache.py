"""pipelines.codecache: the code dataclasses, attrs and rosbags generate, served from a table kept on disk in
the CLI's processes: the same classes, the same analysis, a text kept once a second process compiles it,
a damaged table ignored."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_logs"

# a process that installs the cache on a table of its own, makes classes of every kind dataclasses and attrs
# generate, uses them, and prints what they did and how many texts it compiled itself
_CLASSES = r'''
import json, os, sys
from pipelines import codecache
codecache.table_path = lambda: sys.argv[1]
codecache.install()
import dataclasses
from dataclasses import dataclass, field

@dataclass(frozen=True)
class Config:
    rate_hz: float = 200.0
    names: tuple = ("x", "y")
    extra: list = field(default_factory=list, compare=False)

@dataclass(order=True)
class Sample:
    t_ns: int
    value: float = 0.0

compiled_for_dataclasses = len(codecache._NEW)
import attr

@attr.s(frozen=True, slots=True)
class Point:
    x = attr.ib(default=1.0)
    y = attr.ib(factory=list)

c = Config(100.0)
try:
    c.rate_hz = 1.0
    frozen = "assigned"
except dataclasses.FrozenInstanceError as exc:
    frozen = type(exc).__name__
out = {"repr": [repr(c), repr(Sample(3, 1.5)), repr(Point())], "eq": [c == Config(100.0), c == Config(50.0)],
       "hash": hash(c) == hash(Config(100.0)), "order": sorted([Sample(5), Sample(2, 1.0)]) == [Sample(2, 1.0), Sample(5)],
       "frozen": frozen, "fields": [f.name for f in dataclasses.fields(Config)], "attrs_eq": Point() == Point(),
       "compiled_here": len(codecache._NEW), "compiled_for_dataclasses": compiled_for_dataclasses}
codecache.save()
print(json.dumps(out))
'''


def _classes(table: Path, **env) -> dict:
    p = subprocess.run([sys.executable, "-c", _CLASSES, str(table)], capture_output=True, text=True, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT), **env}, timeout=120)
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)


def test_generated_methods_come_from_the_table_and_behave_as_compiled(tmp_path):
    """The first two processes compile the generated texts (the second's save keeps them: seen twice), the
    third compiles none; every class behaves the same in each, and as with the cache off."""
    table = tmp_path / "codecache.marshal"
    runs = [_classes(table) for _ in range(3)]
    plain = _classes(tmp_path / "unused.marshal", TAPOST_CODE_CACHE="0")
    assert runs[0]["compiled_for_dataclasses"] >= 8 and runs[1]["compiled_here"] == runs[0]["compiled_here"]
    assert runs[2]["compiled_for_dataclasses"] == 0
    # (attrs' __hash__ methods hold a hash of their class's name, which Python salts per process: those texts,
    # attrs' own classes' and Point's, are new in every process; the others come from the table)
    assert runs[2]["compiled_here"] < runs[0]["compiled_here"] // 2
    assert plain["compiled_here"] == 0 and not (tmp_path / "unused.marshal").exists()
    counts = ("compiled_here", "compiled_for_dataclasses")
    for r in runs:
        assert {k: v for k, v in r.items() if k not in counts} == {k: v for k, v in plain.items() if k not in counts}
    assert runs[0]["frozen"] == "FrozenInstanceError" and runs[0]["order"] and runs[0]["hash"]


def test_a_damaged_table_is_compiled_around_and_written_anew(tmp_path):
    table = tmp_path / "codecache.marshal"
    table.write_bytes(b"\x00garbage" * 100)
    first = _classes(table)
    assert first["compiled_for_dataclasses"] >= 8
    assert _classes(table)["compiled_here"] == first["compiled_here"]  # (the damaged file replaced: seen once)
    assert _classes(table)["compiled_for_dataclasses"] == 0


def _analyze(out: Path, table: Path, **env) -> dict:
    script = ("import sys; from pipelines import codecache, cli; path = sys.argv[1]; codecache.table_path = lambda: path; "
              "sys.argv = ['tapost', 'analyze'] + sys.argv[2:]; cli.script()")
    p = subprocess.run([sys.executable, "-c", script, str(table), str(SAMPLE / "master.mcap"),
                        str(SAMPLE / "slave.tlog"), "-o", str(out)], capture_output=True, text=True, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT), "TAPOST_WARMUP": "0", **env}, timeout=600)
    assert p.returncode == 0, p.stderr
    rep = json.loads((out / "report.json").read_text())
    for volatile in ("created_utc", "timings_s"):
        rep.pop(volatile)
    return rep


@pytest.mark.slow
def test_analyze_gives_the_same_report_with_the_table(tmp_path):
    """``tapost analyze`` of the sample pair: the table written by its processes (the analysing one and the
    forked children: the parse's, with rosbags' message classes, and the recording's, with rerun's attrs
    classes), then used; report.json the same as with the cache off."""
    table = tmp_path / "codecache.marshal"
    reps = [_analyze(tmp_path / f"out{i}", table) for i in range(3)]
    plain = _analyze(tmp_path / "plain", tmp_path / "unused.marshal", TAPOST_CODE_CACHE="0")
    assert all(r == plain for r in reps)
    import marshal

    codes = marshal.loads(table.read_bytes())
    assert len(codes) > 500  # (tapost's dataclasses, rosbags' and rerun's generated methods)
    assert (tmp_path / "out2" / "recording.rrd").stat().st_size > 0
