"""Registry: detection by content for every format, selector parsing, and bad input through the CLI
(``tapost inspect``): one line on stderr naming the file, exit 2, never a traceback."""
from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from logtools.errors import InputError
from parsers import registry
from parsers.base import Selector
from pipelines.cli import main

sys.path.insert(0, str(Path(__file__).parent))
from test_parsers_ulog import make_log  # noqa: E402

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
FORMATS = ("csv", "tlog", "dataflash", "rosbag1", "rosbag2", "mcap", "ulog", "csv-vendor")
VENDOR_HEADER = ("Time (s),Gyroscope X (deg/s),Gyroscope Y (deg/s),Gyroscope Z (deg/s),"
                 "Accelerometer X (g),Accelerometer Y (g),Accelerometer Z (g)")


def _module(name: str):
    try:
        return registry.format_by_name(name)
    except InputError:
        return None


def _vendor_text(n: int = 500) -> str:
    t = np.arange(n) * 0.02
    rows = np.c_[t, 10 * np.sin(t), 5 * np.cos(t), t, 0.01 * t, -0.02 * t, np.ones(n)]
    return VENDOR_HEADER + "\n" + "\n".join(",".join(f"{v:.9f}" for v in r) for r in rows) + "\n"


@pytest.fixture(scope="module")
def all_samples(tmp_path_factory) -> dict[str, Path | Exception]:
    """One small log per existing format, saved under a name whose extension says nothing ('.dat')."""
    d = tmp_path_factory.mktemp("formats")
    log = make_log(duration_s=3.0)
    out = {}
    for name in FORMATS:
        mod = _module(name)
        if mod is None:
            continue
        p = d / f"sample_{name.replace('-', '_')}.dat"
        if name == "csv-vendor":
            p.write_text(_vendor_text())
        elif hasattr(mod, "write"):
            try:
                registry.write(str(p), log, name)
            except Exception as exc:  # one broken writer must not take every format's tests down
                out[name] = exc
                continue
        else:
            continue
        out[name] = p
    return out


@pytest.fixture()
def samples(all_samples, request) -> dict[str, Path]:
    """The samples; a test parametrized by format name skips an absent format and fails on a broken writer."""
    name = request.node.callspec.params.get("name") if hasattr(request.node, "callspec") else None
    if name is not None:
        got = all_samples.get(name)
        if got is None:
            pytest.skip(f"format {name} not available")
        if isinstance(got, Exception):
            pytest.fail(f"writing a {name} sample failed: {type(got).__name__}: {got}")
    return all_samples


def _storage_file(p: Path) -> Path:
    """The data file of a log: the file itself, or a directory log's storage file."""
    if p.is_dir():
        return next(f for f in sorted(p.iterdir()) if not f.name.endswith((".yaml", ".json")))
    return p


def _variant(samples, name: str, tmp_path: Path, tag: str, data: bytes) -> Path:
    src = samples[name]
    if src.is_dir():
        dst = tmp_path / f"{tag}_{src.name}"
        shutil.copytree(src, dst)
        (dst / _storage_file(src).name).write_bytes(data)
        return dst
    dst = tmp_path / f"{tag}_{src.name}"
    dst.write_bytes(data)
    return dst


def _inspect(capsys, arg: str) -> tuple[int, str, str]:
    rc = main(["inspect", arg])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def _one_line_error(rc: int, err: str, path: Path) -> None:
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert str(path) in lines[0] or path.name in lines[0]
    assert "Traceback" not in err and "internal error" not in err


# ---- detection by content ------------------------------------------------------------------------
@pytest.mark.parametrize("name", FORMATS)
def test_detection_by_content_not_extension(samples, name, tmp_path):
    p = samples[name]
    assert registry.detect(str(p)).NAME == name
    # under another format's extension
    other = ".ulg" if name != "ulog" else ".bag"
    q = tmp_path / (p.stem + other)
    (shutil.copytree if p.is_dir() else shutil.copy)(p, q)
    assert registry.detect(str(q)).NAME == name
    log = registry.load(str(q))
    assert log.meta.format == name and (log.has_gyro or log.has_quat)


@pytest.mark.skipif(not REAL.exists(), reason="shared/realdata absent")
@pytest.mark.parametrize("fname,fmt", [("px4_sample.ulg", "ulog"), ("ngimu_session", "csv-vendor"),
                                       ("ngimu_session/blue/sensors.csv", "csv-vendor"),
                                       ("sitl_vtol.tlog", "tlog"), ("arduplane_elevator.BIN", "dataflash"),
                                       ("car_xsens_stereo_test1.bag", "rosbag1")])
def test_real_logs_detected(fname, fmt):
    if _module(fmt) is None:
        pytest.skip(f"format {fmt} not available")
    assert registry.detect(str(REAL / fname)).NAME == fmt


def test_registry_order_keeps_canonical_csv_for_csv_module():
    names = [m.NAME for m in registry.formats()]
    if "csv-vendor" in names and "csv" in names:
        assert names.index("csv-vendor") < names.index("csv")


# ---- selectors -----------------------------------------------------------------------------------
def test_selector_parsing():
    s = Selector.parse("imu=IMU2, NAV=NKF6,,clock=epoch")
    assert s.items == (("imu", "IMU2"), ("nav", "NKF6"), ("clock", "epoch"))
    assert s.get("nav") == "NKF6" and s.get("att") is None and str(s) == "imu=IMU2,nav=NKF6,clock=epoch"
    assert not Selector.parse("") and bool(s)
    path, sel = registry.parse_log_arg("/a/b.mcap::imu=/vn100/imu,vel=/vn100/velocity")
    assert path == "/a/b.mcap" and sel.get("imu") == "/vn100/imu" and sel.get("vel") == "/vn100/velocity"
    path, sel = registry.parse_log_arg("new.bin::imu=IMU[1]")
    assert sel.get("imu") == "IMU[1]"
    assert registry.parse_log_arg("plain.ulg") == ("plain.ulg", Selector())
    with pytest.raises(InputError, match="bad selector"):
        registry.parse_log_arg("x.ulg::imu")


def test_bad_selector_through_cli(samples, capsys):
    p = samples["ulog"]
    rc, _, err = _inspect(capsys, f"{p}::imu")
    _one_line_error(rc, err, p)
    assert "bad selector" in err


def test_duplicate_selector_key_is_one_line(samples, capsys):
    """``imu=/x,imu=/y`` (or ``IMU=``, keys are case-blind): one reader took the first, another the last,
    without a word; now a one-line error naming the key, exit 2."""
    with pytest.raises(InputError, match=r"bad selector: key 'imu' given twice \(imu=IMU and imu=IMU2\)"):
        registry.parse_log_arg("x.bin::imu=IMU,nav=NKF1,IMU=IMU2")
    with pytest.raises(InputError, match="key 'map' given twice"):
        registry.parse_log_arg("x.csv::map=a.json,map=a.json")
    p = samples["rosbag1"]
    rc, _, err = _inspect(capsys, f"{p}::imu=/imu,imu=/imu2")
    _one_line_error(rc, err, p)
    assert "given twice" in err
    assert registry.parse_log_arg("x.bin::imu=IMU,nav=NKF1")[1].get("nav") == "NKF1"


@pytest.mark.parametrize("name", [n for n in FORMATS if n != "csv"])
def test_missing_selector_target_is_one_line(samples, name, capsys):
    p = samples[name]
    key = "unit" if name == "csv-vendor" else "imu"
    rc, _, err = _inspect(capsys, f"{p}::{key}=NO_SUCH_STREAM")
    _one_line_error(rc, err, p)


def test_inspect_json_and_selection(samples, capsys):
    p = samples["ulog"]
    rc, out, _ = _inspect(capsys, f"{p}::imu=sensor_combined,clock=epoch")
    assert rc == 0 and "selected (imu=sensor_combined" in out and "clock epoch" in out
    rc = main(["inspect", "--json", str(p)])
    d = json.loads(capsys.readouterr().out)
    assert rc == 0 and d["schema"] == "tapost.inventory/1" and d["format"] == "ulog"
    assert {s["name"] for s in d["streams"]} >= {"sensor_combined", "vehicle_attitude"}
    assert all({"kind", "clock", "rate_hz", "count"} <= set(s) for s in d["streams"])


@pytest.mark.parametrize("name", FORMATS)
def test_inspect_lists_every_format(samples, name, capsys):
    rc = main(["inspect", "--json", str(samples[name])])
    d = json.loads(capsys.readouterr().out)
    assert rc == 0 and d["format"] == name and d["streams"]
    assert all(s["count"] > 0 and s["kind"] for s in d["streams"])
    rc, out, _ = _inspect(capsys, str(samples[name]))
    assert rc == 0 and out.splitlines()[0].endswith(name)


# ---- bad input ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", FORMATS)
def test_empty_and_random_bytes_are_one_line_exit_2(samples, name, tmp_path, capsys):
    rng = np.random.default_rng(7)
    for tag, data in (("empty", b""), ("random", rng.bytes(4096))):
        p = _variant(samples, name, tmp_path, tag, data)
        rc, _, err = _inspect(capsys, str(p))
        _one_line_error(rc, err, p if not p.is_dir() else _storage_file(p))


@pytest.mark.parametrize("name", FORMATS)
def test_truncated_file_is_reported(samples, name, tmp_path, capsys):
    data = _storage_file(samples[name]).read_bytes()
    # (a cut that lands exactly on a record boundary cannot be noticed: this one does not, for any format)
    p = _variant(samples, name, tmp_path, "trunc", data[: int(len(data) * 0.6) + 7])
    rc, out, err = _inspect(capsys, str(p))
    if rc == 2:  # nothing readable: one line
        _one_line_error(rc, err, p if not p.is_dir() else _storage_file(p))
    else:  # the readable part is used and the damage said
        assert rc == 0 and "Traceback" not in err
        assert "warning:" in out and any(w in out.lower() for w in ("truncat", "damag", "incomplete", "dropped"))


@pytest.mark.parametrize("name", FORMATS)
def test_flipped_byte_never_crashes(samples, name, tmp_path, capsys):
    """A flipped byte in a payload is undetectable in formats without checksums (ULog, DataFlash,
    ROS 1 bag): then the file reads; otherwise one line, exit 2. Never a traceback."""
    data = bytearray(_storage_file(samples[name]).read_bytes())
    for frac in (0.5, 0.3):
        flipped = bytearray(data)
        flipped[int(len(data) * frac)] ^= 0xFF
        p = _variant(samples, name, tmp_path, f"flip{int(frac * 10)}", bytes(flipped))
        rc, out, err = _inspect(capsys, str(p))
        if rc == 2:
            _one_line_error(rc, err, p if not p.is_dir() else _storage_file(p))
        else:
            assert rc == 0 and "Traceback" not in err and out.splitlines()[0].endswith(name)


def test_directory_without_metadata_and_missing_file(tmp_path, capsys):
    empty = tmp_path / "empty_dir"
    empty.mkdir()
    (empty / "notes.txt").write_text("hello")
    rc, _, err = _inspect(capsys, str(empty))
    _one_line_error(rc, err, empty)
    rc, _, err = _inspect(capsys, str(tmp_path / "nope.ulg"))
    _one_line_error(rc, err, tmp_path / "nope.ulg")
    assert "no such file" in err


def test_rosbag2_directory_without_metadata(samples, tmp_path, capsys):
    if not isinstance(samples.get("rosbag2"), Path) or not samples["rosbag2"].is_dir():
        pytest.skip("rosbag2 not available")
    d = tmp_path / "nometa"
    shutil.copytree(samples["rosbag2"], d)
    (d / "metadata.yaml").unlink()
    rc, out, err = _inspect(capsys, str(d))
    if rc == 0:  # a reader may rebuild the metadata from the storage: then it must say so
        assert "warning:" in out or "note:" in out
    else:
        _one_line_error(rc, err, d)


@pytest.mark.parametrize("fmt,ext", [("tlog", ".tlog"), ("dataflash", ".bin"), ("mcap", ".mcap"), ("rosbag1", ".bag")])
def test_a_damaged_file_start_is_read_past(tmp_path, fmt, ext):
    """The first 64 bytes zeroed: the strict sniffs fail, the formats that can read on past a damaged start
    recognise the file (tlog: records chain further on; DataFlash: an FMT record further on; MCAP: its footer;
    ROS 1 bag: a chunk or connection record further on)
    and read what follows, saying so; a file of no format is still one clear error."""
    from logtools import sim

    pair = sim.simulate(sim.scenario_config("vehicle", duration_s=30.0, seed=4))
    good = tmp_path / f"good{ext}"
    registry.write(str(good), pair.slave, fmt)
    raw = bytearray(good.read_bytes())
    raw[:64] = bytes(64)
    bad = tmp_path / f"bad{ext}"
    bad.write_bytes(bytes(raw))
    assert registry.detect(str(bad)).NAME == registry.detect(str(good)).NAME
    full, back = registry.load(str(good)), registry.load(str(bad))
    assert 0.5 * len(full.imu) < len(back.imu) <= len(full.imu)
    assert any("damaged" in w for w in back.meta.warnings), back.meta.warnings
    junk = tmp_path / f"junk{ext}"
    junk.write_bytes(bytes(64) + b"no log here" * 100)
    with pytest.raises(InputError, match="unrecognised format") as e:
        registry.detect(str(junk))
    assert f"named like {registry.detect(str(good)).NAME}" in str(e.value)  # (what the name suggests, said)


@pytest.mark.parametrize("fmt,ext", [("tlog", ".tlog"), ("dataflash", ".bin"), ("ulog", ".ulg"), ("mcap", ".mcap"),
                                     ("rosbag1", ".bag"), ("csv", ".csv")])
def test_bytes_put_before_a_file_are_skipped_within_the_search_window(tmp_path, fmt, ext):
    """Random bytes put before a log (a transfer's garbage in front of the file), 5 KiB and the whole search
    window (base.DAMAGED_HEAD_SEARCH_BYTES): every format finds its own start within the window, as its reader
    and its native export do (tlog and DataFlash detection looked at the first 4 KiB only, ROS 1 at the first
    8 KiB, and a ULog was read from its messages behind a header made anew, its start time lost): every
    sample read, the damage said. Beyond the window: one clear error naming what the file is named like."""
    from logtools import sim
    from parsers.base import DAMAGED_HEAD_SEARCH_BYTES
    from parsers.restamp import ClockShift
    from pipelines import export

    pair = sim.simulate(sim.scenario_config("vehicle", duration_s=20.0, seed=4))
    good = tmp_path / f"good{ext}"
    registry.write(str(good), pair.slave, fmt)
    full = registry.load(str(good))
    rng = np.random.default_rng(7)
    for n in (5000, DAMAGED_HEAD_SEARCH_BYTES):
        bad = tmp_path / f"bad{n}{ext}"
        bad.write_bytes(rng.integers(0, 256, n, dtype=np.uint8).tobytes() + good.read_bytes())
        assert registry.detect(str(bad)).NAME == registry.detect(str(good)).NAME
        back = registry.load(str(bad))
        assert len(back.imu) == len(full.imu) and len(back.nav) == len(full.nav)
        np.testing.assert_array_equal(back.t_imu_s() + (back.meta.t0_ns - full.meta.t0_ns) * 1e-9, full.t_imu_s())
        assert any("damaged" in w for w in back.meta.warnings), back.meta.warnings
        out = tmp_path / f"out{n}{ext}"
        st = export.write_native(str(bad), str(out), registry.detect(str(bad)).NAME,
                                 ClockShift(0.01, 0.0, full.meta.t0_ns), back.meta.selector)
        assert len(registry.load(str(out)).imu) == len(full.imu), st
    beyond = tmp_path / f"beyond{ext}"
    beyond.write_bytes(rng.integers(0, 256, DAMAGED_HEAD_SEARCH_BYTES + 4096, dtype=np.uint8).tobytes()
                       + good.read_bytes())
    with pytest.raises(InputError) as e:
        registry.load(str(beyond))
    assert "beyond" in str(e.value) and "\n" not in str(e.value)


def test_a_csv_whose_header_line_is_damaged_is_said_to_be_one():
    """A CSV is read through its header: with the first line garbled the file is no format, and the line
    says the name is a CSV's and why it was not read as one."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = os.path.join(d, "slave.csv")
        with open(p, "wb") as fh:
            fh.write(b"\xb8\xf4v\xbc\t\xf7mQ (m/s),Latitude (deg)\n" + b"1.0,2.0,3.0\n" * 50)
        with pytest.raises(InputError, match="unrecognised format") as e:
            registry.detect(p)
        assert "named like a CSV" in str(e.value) and "header" in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("how", ["prepended", "prepended over the header", "cut"])
def test_an_mcap_whose_start_moved_is_read_with_its_summary_offsets_moved(tmp_path, how):
    """Bytes put before an MCAP's records (a transfer's garbage in front of the file), or lost from its start:
    every absolute offset the footer and summary give is off by the same amount, and the walk, which resumed
    at the summary's chunk offsets, read nothing ('no readable messages'). The records' start (its Header
    record, or the summary section chaining to the footer) gives the shift; the file is read with the
    offsets moved, saying so. The native export writes the records without the bytes put before them (the
    mcap library reads every message of it) and refuses a file whose start is cut, in one line."""
    from mcap.reader import make_reader

    from logtools import sim
    from parsers import restamp_ros
    from parsers.restamp import ClockShift

    pair = sim.simulate(sim.scenario_config("vehicle", duration_s=30.0, seed=4))
    good = tmp_path / "good.mcap"
    registry.write(str(good), pair.slave, "mcap")
    raw = good.read_bytes()
    if how == "prepended":
        data, moved = b"HTTP/1.1 200 OK\r\n\r\n" * 20 + raw, 380
    elif how == "prepended over the header":  # (the Header record's own bytes lost under the zeros)
        data, moved = bytes(199) + raw[20:], 179
    else:
        data, moved = bytes(8) + raw[38:], -30
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data)
    full, back = registry.load(str(good)), registry.load(str(bad))
    assert any(f"moved by {moved:+d} bytes" in w for w in back.meta.warnings), back.meta.warnings
    if how == "cut":  # (the first chunk began in the lost bytes)
        assert 0.3 * len(full.imu) < len(back.imu) < len(full.imu)
        with pytest.raises(InputError, match="start is cut"):
            restamp_ros.restamp_mcap(str(bad), str(tmp_path / "out.mcap"), ClockShift(0.01, 0.0, full.meta.t0_ns))
        return
    np.testing.assert_array_equal(back.imu.to_numpy(), full.imu.to_numpy())
    out = tmp_path / "out.mcap"
    restamp_ros.restamp_mcap(str(bad), str(out), ClockShift(0.01, 0.0, full.meta.t0_ns))
    with open(out, "rb") as a, open(good, "rb") as b:
        assert sum(1 for _ in make_reader(a).iter_messages()) == sum(1 for _ in make_reader(b).iter_messages())


@pytest.mark.parametrize("change", ["insert", "delete"])
def test_an_mcap_with_bytes_put_in_or_lost_inside_reads_the_chunks_after_them(tmp_path, change):
    """777 bytes put in or lost at 30 % of an MCAP: every offset past them, the summary's among them, is off;
    the summary was not found, the walk stopped at the damage and called the file truncated (60 % of the IMU
    samples gone). The summary is found by its chain to the footer, and the chunks after the damage are
    read at their offsets moved, saying so."""
    from logtools import sim

    pair = sim.simulate(sim.scenario_config("vehicle", duration_s=60.0, seed=4))
    good = tmp_path / "good.mcap"
    registry.write(str(good), pair.slave, "mcap")
    raw = good.read_bytes()
    k = int(0.3 * len(raw))
    data = raw[:k] + os.urandom(777) + raw[k:] if change == "insert" else raw[:k] + raw[k + 777:]
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data)
    full, back = registry.load(str(good)), registry.load(str(bad))
    moved = 777 if change == "insert" else -777
    assert any(f"the summary section is {moved:+d} bytes from where the footer says" in w
               for w in back.meta.warnings), back.meta.warnings
    assert len(back.imu) > 0.8 * len(full.imu)
    assert back.imu.index[-1] == full.imu.index[-1]  # (the last chunk read)


def test_inspect_selection_prints_a_note_as_a_note():
    from pipelines.inspect_cmd import format_selection
    lines = format_selection({"selector": "imu=/imu", "clock": "epoch", "duration_s": 1.0, "stamp_source": "header",
                              "channels": {}, "warnings": ["note: /imu: 5 of 40 orientations marked absent",
                                                           "gap of 2.0 s"]})
    assert lines[1:] == ["    note: /imu: 5 of 40 orientations marked absent", "    warning: gap of 2.0 s"]


def test_detecting_a_format_imports_only_the_readers_tried_before_it():
    """Detection walks the readers in order and imports each when it is reached: an MCAP master costs no
    MAVLink dialect import (0.13 s of every run)."""
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    code = ("import sys; from parsers import registry; "
            f"assert registry.detect({os.path.join(root, 'sample_logs', 'master.mcap')!r}).NAME == 'mcap'; "
            "print(sorted(m for m in sys.modules if m.startswith(('pymavlink', 'parsers.mavlink', 'parsers.csv'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_a_log_is_first_asked_of_the_reader_its_name_says():
    """Detection asks the reader the file's extension names first: a tlog slave imports none of the four
    readers sniffed before the tlog's (about 20 ms of every analysis of a tlog)."""
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    code = ("import sys; from parsers import registry; "
            f"assert registry.detect({os.path.join(root, 'sample_logs', 'slave.tlog')!r}).NAME == 'tlog'; "
            "print(sorted(m for m in sys.modules if m in ('parsers.rosbag1', 'parsers.rosbag2', 'parsers.ulog', "
            "'parsers.dataflash', 'parsers.mcap_ros')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("src,name,fmt", [("master.mcap", "m.tlog", "mcap"), ("master.mcap", "m.ulg", "mcap"),
                                          ("slave.tlog", "s.BIN", "tlog"), ("slave.tlog", "s.mcap", "tlog"),
                                          ("slave.tlog", "s.bag", "tlog"), ("slave.tlog", "s.csv", "tlog")])
def test_a_binary_log_under_another_formats_name_is_still_read_by_its_content(tmp_path, src, name, fmt):
    """The name only decides which reader is asked first: the one it names refuses, the others are asked in
    their order, and the log is read by its content (and said to be named otherwise)."""
    p = tmp_path / name
    shutil.copyfile(Path(__file__).resolve().parents[1] / "sample_logs" / src, p)
    assert registry.detect(str(p)).NAME == fmt
    assert any("by its content" in w for w in registry.inspect_log(str(p)).warnings)


def test_the_sniffing_order_names_each_reader_as_its_extensions_are_named():
    """registry._MODULES tags each reader with the name NAMED_BY_EXTENSION gives its extensions."""
    import importlib

    for name, tag in registry._MODULES:
        mod = importlib.import_module(name)
        assert tag == ("CSV" if mod.NAME.startswith("csv") else mod.NAME)
        assert all(registry.NAMED_BY_EXTENSION[e.lower()] == tag for e in mod.EXTENSIONS)


def test_a_selector_key_without_a_value_is_refused_naming_it(tmp_path):
    """FILE::imu= chose nothing and the reader then said it found no INS messages; now 'bad selector'."""
    from parsers.base import Selector

    with pytest.raises(ValueError, match="gives imu no value"):
        Selector.parse("imu=,att=ATT")
    assert Selector.parse("imu=IMU, ,att=ATT").get("att") == "ATT"


def test_a_unit_folder_given_a_unit_says_it_is_one_units_folder():
    """ngimu_session/blue::unit=blue said the folder held no sensors.csv (it does)."""
    from pathlib import Path

    from logtools.errors import InputError
    from parsers import load

    blue = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "ngimu_session" / "blue"
    if not blue.exists():
        pytest.skip("../shared/realdata absent")
    with pytest.raises(InputError, match="this folder is one unit's"):
        load(f"{blue}::unit=blue")


def test_the_rate_of_a_bursty_stream_is_its_mean_rate_not_the_rate_in_a_burst():
    """Telemetry received a few messages at a time (a tlog's AHRS2 on receive stamps: 4.3 Hz in groups 3-9 ms
    apart) was reported at 111 Hz; its rate is now the samples per second over its bursts. A regular stream,
    with jitter or with a long gap, keeps 1 / its median step."""
    import numpy as np

    from parsers.base import rate_of

    rng = np.random.default_rng(1)
    bursts = np.arange(200) * 1.0  # a burst a second, 4 messages 5 ms apart
    t = (bursts[:, None] + np.arange(4)[None, :] * 0.005).ravel()
    assert rate_of(t) == pytest.approx(4.0, rel=0.02)
    regular = np.arange(2000) * 0.01 + rng.normal(0, 1e-4, 2000)
    assert rate_of(regular) == pytest.approx(100.0, rel=0.01)
    gap = np.concatenate([np.arange(1000) * 0.01, 600 + np.arange(200) * 0.01])  # most of the span a gap
    assert rate_of(gap) == pytest.approx(100.0, rel=1e-6)


@pytest.mark.parametrize("name", ["unit.mcap", "unit.tlog", "unit.bag", "unit.ulg", "unit.BIN"])
def test_a_log_named_like_another_format_is_read_by_its_content_and_said(tmp_path, name):
    """A vendor CSV saved under another format's extension (renamed by hand, or another file than the one
    meant): read by its content, and its log says so (report.json's warnings), as does ``tapost inspect``; a
    CSV named .csv says nothing."""
    for fname in (name, "unit.csv"):
        p = tmp_path / fname
        p.write_text(_vendor_text())
        want = ([] if fname == "unit.csv" else
                [f"read as csv-vendor by its content, though its name ({fname}) says "
                 f"{registry.NAMED_BY_EXTENSION[p.suffix.lower()]}: another file than the one meant?"])
        assert [w for w in registry.load(str(p)).meta.warnings if "by its content" in w] == want
        assert [w for w in registry.inspect_log(str(p)).warnings if "by its content" in w] == want


def test_every_formats_extensions_are_named():
    """NAMED_BY_EXTENSION (what a name says, known without importing the readers) holds every reader's
    extensions, each under that reader's name (CSV for the two CSV readers)."""
    for mod in registry.formats():
        for ext in mod.EXTENSIONS:
            assert registry.NAMED_BY_EXTENSION[ext.lower()] == ("CSV" if mod.NAME.startswith("csv") else mod.NAME)
