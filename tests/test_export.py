"""``motcomp export``: a recording as the lab's viewers and pandas read it.

The MCAP for viewers is read back with the ``mcap`` library (not motcomp's reader) and every
message is validated against its channel's JSON Schema with ``jsonschema``; its values must be
the recorded frames' own (decoded from the recording with msgpack), its times and sequence
numbers the recording's, and a bad frame kept as received.  The tables are read back with the
csv module and pyarrow and compared with :func:`motcomp.record.read_session`.
"""

from __future__ import annotations

import base64
import csv
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from motcomp.config import load_config
from motcomp.core.axes import AXES
from motcomp.io.wire import encode_output
from motcomp.record import read_session
from motcomp.record.recorder import SessionWriter
from motcomp.replay.synth import SynthOptions, synthesize
from motcomp.resources import config_file
from tests.conftest import motcomp_cmd, subprocess_env

CFG = load_config(config_file("motcomp.toml"))


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                          env=subprocess_env(), timeout=120)


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A session with every kind of frame: bad ones (not msgpack, NaN, an unknown axis),
    frames without t, partial frames, a stall, a gap; plus a key of no role."""
    path = tmp_path_factory.mktemp("export") / "s.mcap"
    synthesize(path, CFG, SynthOptions(duration_s=3.0, seed=4, stalls=[(1.0, 40)],
                                       gaps=[(2.0, 0.2)], partial_every=7, bad_every=50,
                                       no_t_every=13))
    # the same session with a key of no role (a wildcard subscription's) and its oddities
    extra = path.with_name("extra.mcap")
    from motcomp.record.mcapio import ScanResult, iter_records

    res = ScanResult(path)
    records = list(iter_records(path, result=res))
    (_, _, cfg_json), = res.attachments
    with SessionWriter(extra, [r for r in {rec.topic for rec in records}], None, cfg_json,
                       flush_s=0, fsync=False) as w:
        for rec in records:
            w.write_raw(rec.topic, rec.log_ns, rec.publish_ns, rec.sequence, rec.data)
        # output frames as the service sends them: rx (ns after t the tick took its inputs)
        last = max(r.log_ns for r in records if r.topic == "platform/setpoint")
        for j in range(3):
            w.write("platform/setpoint", last + 1 + j, encode_output(
                10**6 + j, 1.0 + j / 1e3, 7, [0.01 * j] * len(AXES), ["stale"], 35_000 + j))
        w.write("platform/status", records[-1].log_ns, msgpack.packb(
            {"t": 1.5, "setpoint_age_ms": float("nan"), "ticks": 3, "axes": ["rails_x"]}))
        w.write("platform/status", records[-1].log_ns + 1, msgpack.packb([1, 2, 3]))
        w.write("platform/status", records[-1].log_ns + 2, b"\xc1")
    return extra


def read_mcap(path: Path) -> tuple[dict[str, Any], list[tuple[str, Any, Any]]]:
    """``(metadata by name, [(topic, schema, message)])`` with the mcap library."""
    from mcap.reader import make_reader

    with path.open("rb") as f:
        reader = make_reader(f)
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        rows = [(c.topic, s, m) for s, c, m in reader.iter_messages(log_time_order=False)]
    return meta, rows


def test_every_message_validates_against_its_channel_schema_and_loses_nothing(
        session: Path, tmp_path: Path) -> None:
    import jsonschema
    from mcap.reader import make_reader

    out = tmp_path / "viewer.mcap"
    p = cli("export", str(session), "-o", str(out), "--json", "--quiet")
    assert p.returncode == 0, p.stderr
    summary = json.loads(p.stdout)
    meta, rows = read_mcap(out)
    with session.open("rb") as f:
        source = [(c.topic, m) for _, c, m in make_reader(f).iter_messages(log_time_order=False)]
    assert len(rows) == len(source) == sum(summary["counts"].values())
    validators: dict[int, Any] = {}
    invalid: dict[str, int] = {}
    for (topic, schema, m), (src_topic, src) in zip(rows, source, strict=True):
        # in the recording's order, with its times and sequence numbers
        assert (m.log_time, m.publish_time, m.sequence) == \
            (src.log_time, src.publish_time, src.sequence)
        assert schema is not None and schema.encoding == "jsonschema"
        if schema.id not in validators:
            body = json.loads(schema.data)
            assert body["type"] == "object"  # what Foxglove requires of a JSON schema
            jsonschema.Draft202012Validator.check_schema(body)
            validators[schema.id] = jsonschema.Draft202012Validator(body)
        obj = json.loads(m.data)
        validators[schema.id].validate(obj)
        if topic == src_topic + "/invalid":  # kept as received, with the reason
            assert base64.b64decode(obj["data_base64"]) == src.data and obj["reason"]
            invalid[src_topic] = invalid.get(src_topic, 0) + 1
            continue
        assert topic == src_topic
        frame = msgpack.unpackb(src.data, raw=False, strict_map_key=False)
        if topic == "platform/status" and not isinstance(frame, dict):
            assert obj == {"value": frame}
        elif topic == "platform/status":
            assert obj["setpoint_age_ms"] is None and obj["axes"] == ["rails_x"]
        else:
            assert obj == frame  # every number the very double recorded
    assert invalid == summary["invalid"]
    # the synthetic sender's bad frames: not msgpack, a NaN, an unknown axis (every 50th frame)
    assert invalid["sim/motion/setpoint"] >= 3000 // 50 - 10
    assert invalid["platform/status"] == 1
    assert "platform/setpoint" not in invalid and "platform/feedback" not in invalid
    assert sum("rx" in json.loads(m.data) for t, _, m in rows if t == "platform/setpoint") == 3
    channels = {topic for topic, _, _ in rows}
    assert {"sim/motion/setpoint", "platform/setpoint", "platform/feedback", "motcomp/status",
            "platform/status", "sim/motion/setpoint/invalid"} <= channels
    assert json.loads(meta["motcomp"]["keys"]) and meta["motcomp_export"]["source"] == \
        str(session)
    # frames without t and partial frames are valid input frames
    inputs = [json.loads(m.data) for t, _, m in rows if t == "sim/motion/setpoint"]
    assert any("t" not in f for f in inputs) and any(len(f["pos"]) == 2 for f in inputs)


def test_motcomp_reads_the_recording_and_refuses_the_export(session: Path, tmp_path: Path
                                                            ) -> None:
    out = tmp_path / "viewer.mcap"
    assert cli("export", str(session), "-o", str(out), "--quiet").returncode == 0
    p = cli("info", str(out))
    assert p.returncode == 2 and "an export for viewers (motcomp export)" in p.stderr
    assert str(session) in p.stderr
    p = cli("info", str(session))
    assert p.returncode == 0 and "platform/status" in p.stdout, p.stderr


def _float(cell: str) -> float:
    return math.nan if cell == "" else float(cell)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.array_equal(a, b, equal_nan=True))


def test_tables_read_back_as_the_recording(session: Path, tmp_path: Path) -> None:
    s = read_session(session, other_keys=False)
    assert s.inputs is not None and s.outputs is not None and s.feedback is not None
    p = cli("export", str(session), "-o", str(tmp_path / "csv"), "--format", "csv")
    assert p.returncode == 0, p.stderr
    with (tmp_path / "csv" / "output.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(s.outputs)
    for a, axis in enumerate(AXES):
        assert _same(np.array([_float(r[f"pos.{axis}"]) for r in rows]), s.outputs.pos[:, a])
    assert [int(r["log_time_ns"]) for r in rows] == s.outputs.log_ns.tolist()
    assert _same(np.array([float(r["t"]) for r in rows]), s.outputs.t)
    assert [int(r["rx"]) for r in rows] == s.outputs.rx.tolist()  # every field of the frame
    assert any("bypass:hex_z" in r["flags"].split() for r in rows)
    with (tmp_path / "csv" / "input.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(s.inputs)
    assert _same(np.array([_float(r["pos.rails_y"]) for r in rows]), s.inputs.pos[:, 1])
    assert _same(np.array([_float(r["t"]) for r in rows]), s.inputs.t)  # empty: no t
    with (tmp_path / "csv" / "status.csv").open() as fh:
        status = list(csv.DictReader(fh))
    assert len(status) == len(s.status) and "frames.received" in status[0]
    pq = pytest.importorskip("pyarrow.parquet")
    p = cli("export", str(session), "-o", str(tmp_path / "pq"), "--format", "parquet")
    assert p.returncode == 0, p.stderr
    fb = pq.read_table(tmp_path / "pq" / "feedback.parquet").to_pydict()
    for a, axis in enumerate(AXES):
        assert _same(np.array(fb[f"pos.{axis}"], float), s.feedback.pos[:, a])
        assert _same(np.array(fb[f"acc.{axis}"], float), s.feedback.acc[:, a])
    assert pq.read_table(tmp_path / "pq" / "status.parquet").num_rows == len(s.status)


def test_parquet_without_pyarrow_says_how_to_get_it(session: Path, tmp_path: Path) -> None:
    code = ("import sys; sys.modules['pyarrow'] = None; from motcomp.cli import main; "
            f"sys.exit(main(['export', {str(session)!r}, '-o', {str(tmp_path / 'pq')!r}, "
            "'--format', 'parquet']))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=subprocess_env(), timeout=60)
    assert p.returncode == 2 and "Parquet needs pyarrow: pip install 'motcomp[parquet]'" \
        in p.stderr, p.stderr
    p = cli("export", str(session), "-o", str(tmp_path / "no" / "such" / "x.mcap"))
    assert p.returncode == 2 and "does not exist" in p.stderr


def test_an_unfinished_recording_exports_what_it_holds(session: Path, tmp_path: Path) -> None:
    data = session.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:len(data) * 2 // 3])
    p = cli("export", str(cut), "-o", str(tmp_path / "cut-viewer.mcap"), "--quiet")
    assert p.returncode == 0, p.stderr
    assert "warning: " in p.stdout and "unfinished recording" in p.stdout
    meta, rows = read_mcap(tmp_path / "cut-viewer.mcap")
    assert rows and meta["motcomp_export"]["source"] == str(cut)
    cut.write_bytes(data[:300])  # before its first chunk: nothing to export, as nothing to read
    for fmt in ("mcap", "csv"):
        out = tmp_path / f"empty.{fmt}"
        p = cli("export", str(cut), "-o", str(out), "--format", fmt, "--quiet")
        assert p.returncode == 2 and "no complete chunk" in p.stderr, p.stderr
        assert not out.exists() or (fmt == "csv" and not any(out.iterdir()))


def test_an_input_frame_not_decoded_has_no_seq_in_the_tables(tmp_path: Path) -> None:
    """Input frames that are not msgpack, or a map without ``seq``: ``decoded`` 0 and the
    ``seq`` cell empty -- never a seq 0 that reads as the sender's first frame."""
    path = tmp_path / "bad.mcap"
    frames = [msgpack.packb({"seq": 7, "t": 1.0, "pos": {"rails_y": 0.1}}), b"\xc1 not msgpack",
              msgpack.packb({"t": 1.002, "pos": {"rails_y": 0.1}}),
              msgpack.packb({"seq": 9, "t": 1.003, "pos": {"rails_y": 0.1}})]
    with SessionWriter(path, ["sim/motion/setpoint"], None, None, flush_s=0, fsync=False) as w:
        for k, payload in enumerate(frames):
            w.write_raw("sim/motion/setpoint", 10**9 + k * 10**6, 10**9 + k * 10**6, k, payload)
    p = cli("export", str(path), "-o", str(tmp_path / "csv"), "--format", "csv")
    assert p.returncode == 0, p.stderr
    with (tmp_path / "csv" / "input.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["seq"], r["decoded"]) for r in rows] == [("7", "1"), ("", "0"), ("", "0"),
                                                        ("9", "1")]
