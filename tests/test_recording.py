"""recording.rrd: written column-wise, read back with rerun's own reader (rerun.chunk.RrdReader):
entity paths, lengths, timelines, blueprint, downsampling of long series."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from pipelines.recording import block_mean, read_entities, write_recording

sys.path.insert(0, str(Path(__file__).parent))
from test_report import fake_report, make_fake_analysis  # noqa: E402


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    an = make_fake_analysis(duration_s=60, rate_hz=100)  # 6000 IMU rows
    path = tmp_path_factory.mktemp("rrd") / "recording.rrd"
    info = write_recording(str(path), an, fake_report(an), max_rows=2500)
    return path, info, an


def test_entities_and_lengths(rec):
    path, info, an = rec
    ents = read_entities(str(path))
    k = 3  # ceil(6000 / 2500)
    for ax in "xyz":
        for who in ("master", "slave_raw", "slave_comp"):
            e = ents[f"/rates/{ax}/{who}"]
            # the fake master is on UNIX time: a timestamp timeline "utc" beside "time" (DESIGN.md)
            assert e["rows"] == 6000 // k and e["timelines"] == ["time", "utc"] and e["static"]
            assert info["factors"][f"/rates/{ax}/{who}"] == k
    assert ents["/world/master"]["rows"] == 600  # poses at 10 Hz over 60 s
    assert ents["/world/track"]["static"]
    assert ents["/latency/cost/tapost"]["rows"] == len(an.latency.cost_lag_s)
    assert ents["/latency/cost/tapost"]["timelines"] == ["lag"]
    assert ents["/latency/window"]["rows"] == len(an.latency.window_latency_s)
    res = an.alignment["compensated"]
    for name in res.history_names:
        for part in ("value", "upper", "lower"):
            assert ents[f"/alignment/compensated/{name}/{part}"]["rows"] == len(res.history_t_s)
    n, m = len(res.residual_t_s), info["max_rows_states"]
    kr = -(-n // m)
    assert kr > 1  # residuals are block-averaged with the smaller state budget
    assert ents["/alignment/uncompensated/residuals/dv_n_m_s"]["rows"] == n // kr
    assert ents["/latency/cost_chart"]["static"]


def test_blueprint_and_values(rec):
    path, _, an = rec
    from rerun.chunk import RrdReader

    r = RrdReader(str(path))
    assert len(r.recordings()) == 1 and len(r.blueprints()) == 1
    # the downsampled master x rate equals the block mean of the input (deg/s)
    vals = []
    for ch in r.stream().to_chunks():
        if ch.entity_path == "/rates/x/master" and not ch.is_static:
            rb = ch.to_record_batch()
            col = [n for n in rb.schema.names if "scalars" in n.lower()][0]
            vals.append(np.concatenate([np.asarray(v, float) for v in rb.column(col).to_pylist()]))
    got = np.concatenate(vals)
    want = np.degrees(an.master.gyro_rad_s()[:, 0]).reshape(-1, 3).mean(axis=1)
    assert np.allclose(np.sort(got), np.sort(want), atol=1e-9)


def test_block_mean_rule():
    t = np.arange(10.0)
    y = np.arange(20.0).reshape(10, 2)
    tb, yb, k = block_mean(t, y, max_rows=4)
    assert k == 3 and np.allclose(tb, [1, 4, 7]) and np.allclose(yb[:, 0], [2, 8, 14])
    assert block_mean(t, y[:, 0], max_rows=100)[2] == 1


def test_view_command_rejects_missing(tmp_path, capsys):
    from pipelines.cli import main

    assert main(["view", str(tmp_path)]) == 2
    assert "no recording found" in capsys.readouterr().err


def test_view_command_rejects_a_file_that_is_no_recording(tmp_path, capsys):
    """A report or a log given to `tapost view` is said to be no recording (it went on to the display check,
    or to the viewer, which failed on it)."""
    from pipelines.cli import main

    for name, data in (("report.json", b'{"schema": "tapost.report/1"}'), ("empty.rrd", b"")):
        (tmp_path / name).write_bytes(data)
        assert main(["view", "--web", str(tmp_path / name)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "not a rerun recording" in err[0] and name in err[0], err


def test_a_recording_that_fails_while_streamed_to_its_file_leaves_no_file(tmp_path, monkeypatch):
    """The recording is streamed to its temporary file as it is built (rerun's encoder beside the builder);
    an error while building stops the stream and leaves neither the recording nor a temporary file."""
    import pipelines.recording as recording

    an = make_fake_analysis()
    real = recording._fill

    def fail(rec, *args):
        real(rec, *args)  # (everything logged, then the failure)
        raise RuntimeError("a failure while building")

    monkeypatch.setattr(recording, "_fill", fail)
    out = tmp_path / "recording.rrd"
    with pytest.raises(RuntimeError, match="while building"):
        write_recording(str(out), an, fake_report(an))
    assert list(tmp_path.iterdir()) == []


def test_a_recording_written_with_pandas_refused_is_the_same_recording(tmp_path):
    """``without_pandas`` (the recording's prepared child): the recording is written without pandas ever
    loading (pyarrow and rerun's bar chart skip their pandas checks), and it is the same recording as one
    written where pandas is there (``rerun rrd compare``); a second call changes nothing."""
    import subprocess

    code = "\n".join([
        "import sys",
        f"sys.path.insert(0, {str(Path(__file__).parent)!r})",
        "from pipelines.recording import without_pandas, write_recording",
        "without_pandas(); without_pandas()",
        "from test_report import fake_report, make_fake_analysis",
        "an = make_fake_analysis(duration_s=20, rate_hz=50)",
        f"write_recording({str(tmp_path / 'refused.rrd')!r}, an, fake_report(an), max_rows=400)",
        "print('pandas' in sys.modules, sum(type(f).__name__ == '_PandasRefused' for f in sys.meta_path))",
    ])
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split() == ["False", "1"]
    import pandas  # noqa: F401 - the reference: written where pandas is loaded

    an = make_fake_analysis(duration_s=20, rate_hz=50)
    write_recording(str(tmp_path / "here.rrd"), an, fake_report(an), max_rows=400)
    cmp = subprocess.run([sys.executable, "-m", "rerun", "rrd", "compare", str(tmp_path / "refused.rrd"),
                          str(tmp_path / "here.rrd")], capture_output=True, text=True, timeout=120)
    assert cmp.returncode == 0, cmp.stdout + cmp.stderr


def test_a_recording_started_before_the_uncompensated_run_ends_is_the_same_recording(tmp_path):
    """The CLI starts the recording once the compensated run is done (pipelines.analyze.compute): it gets the
    uncompensated run with the report (``later`` -> Rest). The same entities, rows, properties and
    downsampling factors, in the same order, as a recording of the whole analysis."""
    import copy

    from pipelines.recording import Rest, read_properties

    an = make_fake_analysis(duration_s=30, rate_hz=50)
    assert set(an.alignment) == {"uncompensated", "compensated"}
    rep = fake_report(an)
    whole = write_recording(str(tmp_path / "whole.rrd"), an, rep, max_rows=500)
    early_an = copy.copy(an)
    early_an.alignment = {"compensated": an.alignment["compensated"]}
    early = write_recording(str(tmp_path / "early.rrd"), early_an, max_rows=500,
                            later=lambda: Rest(rep, dict(an.alignment)))
    assert early == whole and list(early["factors"]) == list(whole["factors"])
    assert any(k.startswith("/alignment/uncompensated/") for k in early["factors"])
    assert read_entities(str(tmp_path / "early.rrd")) == read_entities(str(tmp_path / "whole.rrd"))
    assert read_properties(str(tmp_path / "early.rrd")) == read_properties(str(tmp_path / "whole.rrd"))



def test_a_recording_skipped_by_a_stray_file_named_like_a_library_names_that_file(tmp_path):
    """A file named like a library in the working directory (``python -m`` puts it first on the path) is run
    when rerun imports that library; the recording is skipped (the analysis still ends, exit 0) and the reason
    names the file and line that raised, not only the exception (a stray ``attr.py`` reading its argv said
    "No such file or directory: 'analyze'" and nothing more)."""
    import json
    import os
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    stray = tmp_path / "attr.py"
    stray.write_text("raise RuntimeError('not the attrs package')\n")
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "pipelines.cli", "analyze", os.path.join(root, "sample_logs", "master.mcap"),
                        os.path.join(root, "sample_logs", "slave.tlog"), "-o", str(out)],
                       cwd=str(tmp_path), capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    why = json.loads((out / "report.json").read_text())["skipped"]["recording"]
    assert why.startswith("RuntimeError: not the attrs package") and f"raised in {stray}, line 1" in why
    assert f"raised in {stray}" in p.stdout + p.stderr
