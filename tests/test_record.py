"""Recordings: the MCAP layout of docs/RECORDING.md, the fast reader against msgpack and the
``mcap`` package's own readers, rotation, and files cut short."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motcomp.core.axes import AXES
from motcomp.io.wire import encode_feedback, encode_input, encode_output
from motcomp.record import read_session
from motcomp.record.frames import FLAG_BITS, InputColumns, OutputColumns, decode_rows
from motcomp.record.recorder import SessionWriter

KEYS = ["sim/motion/setpoint", "platform/setpoint", "platform/feedback", "motcomp/status"]
T0 = 1_750_000_000.0


def mcap_messages(path: Path) -> list[tuple[str, int, int, int, bytes]]:
    """What the ``mcap`` package reads, with its stream reader (tolerates a cut file)."""
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    topics: dict[int, str] = {}
    out = []
    with path.open("rb") as f:
        try:
            for rec in StreamReader(f).records:
                if isinstance(rec, Channel):
                    topics[rec.id] = rec.topic
                elif isinstance(rec, Message):
                    out.append((topics[rec.channel_id], rec.log_time, rec.publish_time,
                                rec.sequence, rec.data))
        except Exception:  # the cut: everything before it was yielded
            pass
    return out


def write_mixed(path: Path, n: int = 3000, **kw: Any) -> list[tuple[str, int, bytes]]:
    """Frames of every shape the reader must handle, interleaved as on the wire."""
    rng = np.random.default_rng(0)
    msgs: list[tuple[str, int, bytes]] = []
    for k in range(n):
        t = T0 + k * 1e-3
        log = round(t * 1e9) + 100_000
        pos = {a: float(v) for a, v in zip(AXES, rng.normal(0, 0.1, 8), strict=True)}
        if k % 11 == 0:
            frame = encode_input(k, t, {"rails_x": pos["rails_x"]})  # partial
        elif k % 13 == 0:
            frame = msgpack.packb({"seq": k, "pos": {"rails_y": 1}})  # int value, no t
        elif k % 97 == 0:
            frame = [b"\xc1bad", msgpack.packb({"seq": k, "pos": {"rails_y": math.nan}}),
                     msgpack.packb({"seq": k, "pos": {"rails_q": 0.0}}),
                     msgpack.packb({"seq": "k", "pos": {"rails_y": 0.0}}),
                     msgpack.packb({"seq": k, "pos": {}})][k // 97 % 5]
        else:
            frame = encode_input(k * 1000, t, pos)  # seq grows past 2^16: int widths change
        msgs.append((KEYS[0], log, frame))
        flags = [f"sat:{AXES[k % 8]}"] if k % 5 == 0 else []
        flags += ["bypass:hex_x", "bypass:hex_y"] + (["stale"] if k % 17 == 0 else [])
        msgs.append((KEYS[1], log + 1000, encode_output(k, t, k - 1, list(pos.values()), flags)))
        msgs.append((KEYS[2], log + 2000, encode_feedback(t, pos, {a: 0.5 * v for a, v in
                                                                   pos.items()})))
        if k % 1000 == 0:
            msgs.append((KEYS[3], log + 3000, msgpack.packb({"t": t, "ticks": k})))
    with SessionWriter(path, KEYS, {"config_hash": "abc"}, b'{"loop": {}}', **kw) as w:
        for key, log, payload in msgs:
            w.write(key, log, payload)
    return msgs


def test_layout_and_fast_reader_equal_msgpack_and_mcap(tmp_path: Path) -> None:
    path = tmp_path / "mixed.mcap"
    msgs = write_mixed(path, chunk_bytes=64 << 10)
    # the mcap package reads it: channels per key, publish time = frame t, sequence = seq
    got = mcap_messages(path)
    assert len(got) == len(msgs)
    ins = [m for m in got if m[0] == KEYS[0]]
    _, log, pub, seq, data = ins[1]
    frame = msgpack.unpackb(data)
    assert pub == round(frame["t"] * 1e9) and seq == frame["seq"] % 2**32 and log != pub
    from mcap.reader import make_reader

    with path.open("rb") as f:
        r = make_reader(f)
        summary = r.get_summary()
        assert summary is not None
        chans = {c.topic: c for c in summary.channels.values()}
        assert set(chans) == set(KEYS)
        assert all(c.message_encoding == "msgpack" and c.schema_id == 0 and
                   c.metadata == {"zenoh_key": t} for t, c in chans.items())
        meta = next(r.iter_metadata())
        assert meta.name == "motcomp" and json.loads(meta.metadata["keys"]) == KEYS
        assert meta.metadata["config_hash"] == "abc" and "started" in meta.metadata
        att = next(r.iter_attachments())
        assert att.name == "config.json" and att.media_type == "application/json"
    # the fast reader: the same values as msgpack, frame by frame
    s = read_session(path)
    assert s.messages == len(msgs) and not s.warnings and s.config_json == {"loop": {}}
    assert s.inputs is not None and s.outputs is not None and s.feedback is not None
    expect = InputColumns(len(ins))
    for i, (*_, payload) in enumerate(ins):
        try:
            obj = msgpack.unpackb(payload)
        except Exception:
            expect.undecodable(i, "not msgpack")
        else:
            expect.from_object(obj, i)
    assert np.array_equal(s.inputs.seq, expect.seq)
    assert np.array_equal(s.inputs.pos, expect.pos, equal_nan=True)
    assert np.array_equal(s.inputs.t, expect.t, equal_nan=True)
    assert np.array_equal(s.inputs.decoded, expect.decoded)
    # not decoded for analysis: the msgpack garbage and the string seq; the NaN, the unknown
    # axis and the empty pos are decoded (the tick, not the reader, rejects them)
    assert (~s.inputs.decoded).sum() == sum(1 for k in range(len(ins)) if k % 97 == 0 and
                                            k % 11 and k % 13 and k // 97 % 5 in (0, 3))
    # the raw payloads, byte for byte, in one buffer
    assert [s.inputs.payload(i) for i in range(len(ins))] == [m[4] for m in ins]
    assert s.inputs.bounds[-1] == len(s.inputs.data) == sum(len(m[4]) for m in ins)
    outs = [m for m in got if m[0] == KEYS[1]]
    flags = np.array([sum(FLAG_BITS[f] for f in msgpack.unpackb(m[4])["flags"]) for m in outs])
    assert np.array_equal(s.outputs.flags, flags)
    assert np.array_equal(s.outputs.src_seq, np.arange(len(outs)) - 1)
    fb = [msgpack.unpackb(m[4]) for m in got if m[0] == KEYS[2]]
    assert np.array_equal(s.feedback.acc[:, 3], [f["acc"]["hex_y"] for f in fb])
    assert [st_["ticks"] for _, st_ in s.status] == [0, 1000, 2000]
    # identification: (feedback time, command in force, acceleration)
    t, cmd, _ = s.identification_data("rails_y")
    assert t.size == len(fb) and np.array_equal(cmd, s.outputs.pos[:, 1])


@settings(max_examples=40, deadline=None)
@given(st.lists(st.fixed_dictionaries(
    {"seq": st.integers(-2**40, 2**62), "pos": st.dictionaries(
        st.sampled_from(AXES), st.one_of(st.floats(allow_nan=True), st.integers(-2**31, 2**31)),
        max_size=3)},
    optional={"t": st.one_of(st.floats(), st.none(), st.booleans())}), min_size=1, max_size=40))
def test_template_decoding_equals_msgpack(frames: list[dict[str, object]]) -> None:
    payloads = [msgpack.packb(f) for f in frames] * 3  # groups of equal length
    buf = np.frombuffer(b"".join(payloads) + bytes(4096), np.uint8)
    lens = np.array([len(p) for p in payloads])
    offs = np.concatenate([[0], np.cumsum(lens)[:-1]])
    fast = InputColumns(len(payloads))
    decode_rows(buf, offs, lens, fast)
    slow = InputColumns(len(payloads))
    for i, p in enumerate(payloads):
        slow.from_object(msgpack.unpackb(p, strict_map_key=False), i)
    assert np.array_equal(fast.decoded, slow.decoded)
    assert np.array_equal(fast.seq, slow.seq)
    assert np.array_equal(fast.pos, slow.pos, equal_nan=True)
    assert np.array_equal(fast.t, slow.t, equal_nan=True)


def test_outputs_of_odd_layouts_fall_back_exactly() -> None:
    frames = [encode_output(k, T0 + k, k, [0.1 * k] * 8, ["sat:rails_x"] if k % 2 else [])
              for k in range(50)]
    frames += [msgpack.packb({"seq": 1, "t": 2.0, "src_seq": 3, "pos": {"rails_y": 4},
                              "flags": ["rejoin", "nonsense"]}), b"\x93\x01\x02\x03"]
    buf = np.frombuffer(b"".join(frames) + bytes(4096), np.uint8)
    lens = np.array([len(p) for p in frames])
    offs = np.concatenate([[0], np.cumsum(lens)[:-1]])
    ex = OutputColumns(len(frames))
    decode_rows(buf, offs, lens, ex)
    assert ex.valid[:-1].all() and not ex.valid[-1]
    assert ex.flags[1] == FLAG_BITS["sat:rails_x"] and ex.flags[50] == FLAG_BITS["rejoin"]
    assert ex.pos[50, 1] == 4.0 and np.isnan(ex.pos[50, 0])


def test_rotation_parts_read_as_one_session(tmp_path: Path) -> None:
    path = tmp_path / "rot.mcap"
    msgs = write_mixed(path, n=2000, rotate_bytes=100_000, chunk_bytes=32 << 10)
    parts = sorted(tmp_path.glob("rot-*.mcap"))
    assert not path.exists() and len(parts) >= 3
    assert parts[0].name == "rot-0001.mcap"
    s = read_session(path)
    assert s.messages == len(msgs) and len(s.paths) == len(parts)
    assert s.inputs is not None and np.all(np.diff(s.inputs.log_ns) > 0)
    for p in parts:  # every part stands alone
        assert len(mcap_messages(p)) > 0


@pytest.mark.parametrize("where", [0.37, 0.71])
def test_cut_file_is_read_up_to_the_cut(tmp_path: Path, where: float,
                                        caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "full.mcap"
    write_mixed(path, chunk_bytes=48 << 10)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:int(len(data) * where)])
    s = read_session(cut)
    expect = mcap_messages(cut)  # the mcap stream reader up to the cut
    assert s.truncated and s.messages == len(expect) > 0
    assert len(s.warnings) == 1 and str(cut) in s.warnings[0]
    assert f"recovered {len(expect)} messages" in s.warnings[0]
    assert any("unfinished recording" in r.message for r in caplog.records)
    assert s.inputs is not None and len(s.inputs) == sum(1 for m in expect if m[0] == KEYS[0])


def test_file_cut_in_its_summary_loses_nothing(tmp_path: Path) -> None:
    path = tmp_path / "full.mcap"
    msgs = write_mixed(path, n=500)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:-40])  # footer and part of the summary gone
    s = read_session(cut)
    assert s.messages == len(msgs) and not s.warnings


def test_the_summary_says_which_keys_got_nothing() -> None:
    """A key the recorder subscribed to that no message came on is said, the commands' with
    why that happens (a service whose output goes over CAN alone); a wildcard is not."""
    from motcomp.record.recorder import RecordSummary
    from motcomp.record.session import DEFAULT_KEYS

    out, fb = DEFAULT_KEYS["output"], DEFAULT_KEYS["feedback"]
    text = RecordSummary([Path("s.mcap")], {fb: 10}, 0, 1.0, None, None,
                         (out, fb, "other/**")).text()
    assert f"  {fb}: 10" in text
    assert f"  {out}: nothing came (a service whose output goes over CAN alone" in text
    assert "other/**" not in text


def test_a_topic_s_span_from_the_indexes_is_its_first_and_last_message(tmp_path: Path) -> None:
    from motcomp.record.mcapio import topic_span

    path = tmp_path / "s.mcap"
    msgs = [(k, log, p) for k, log, p in write_mixed(tmp_path / "all.mcap", n=3000)
            if k != KEYS[0] or log < round((T0 + 1.2) * 1e9)]  # the input stops at 1.2 s
    with SessionWriter(path, KEYS, {}, b"{}", chunk_bytes=16 << 10) as w:
        for key, log, payload in msgs:
            w.write(key, log, payload)
    read = mcap_messages(path)  # the mcap package's own reader
    assert sum(1 for m in read if m[0] == KEYS[0]) > 100
    for key in KEYS:
        logs = [m[1] for m in read if m[0] == key]
        assert topic_span(path, key) == (min(logs), max(logs)), key
    assert topic_span(path, "no/such/key") is None
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-40])  # no summary: no index to read
    assert topic_span(cut, KEYS[0]) is None


def test_a_corrupt_chunk_is_said_and_nothing_after_it_is_read(tmp_path: Path) -> None:
    """A chunk whose bytes changed on disk (its size intact, so that it decompresses or, stored
    plain, reads as records) fails its CRC: the session holds the chunks before it and says
    where it stopped, rather than frames no recorder wrote."""
    from mcap.reader import make_reader

    path = tmp_path / "full.mcap"
    write_mixed(path, chunk_bytes=48 << 10, compression="none")
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    bad = chunks[len(chunks) // 2]
    data = bytearray(path.read_bytes())
    at = bad.chunk_start_offset + bad.chunk_length - 100  # in its last records' data
    data[at:at + 8] = bytes(255 - b for b in data[at:at + 8])
    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes(bytes(data))
    s = read_session(corrupt)
    before = mcap_messages(_write(tmp_path / "before.mcap", bytes(data[:bad.chunk_start_offset])))
    assert s.truncated and s.messages == len(before) > 0
    want = f"damaged recording (chunk at byte {bad.chunk_start_offset} is corrupt"
    assert len(s.warnings) == 1 and want in s.warnings[0], s.warnings
    assert s.damaged and not read_session(path).damaged


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path
