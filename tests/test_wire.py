"""Wire contract: codecs round-trip, and validation never lets a bad frame through."""

from __future__ import annotations

import math

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motcomp.core.axes import AXES
from motcomp.errors import FrameError
from motcomp.io import wire
from motcomp.io.wire import (
    REJECT_REASONS,
    InputValidator,
    decode_feedback,
    decode_input,
    decode_output,
    encode_feedback,
    encode_input,
    encode_output,
)

LIM = [-2.6] * 2 + [-0.25] * 6, [2.6] * 2 + [0.25] * 6

positions = st.dictionaries(st.sampled_from(AXES), st.floats(-0.2, 0.2), min_size=1)


@given(seq=st.integers(0, 2**62), t=st.floats(0, 1e10), pos=positions)
def test_input_round_trip(seq: int, t: float, pos: dict[str, float]) -> None:
    assert decode_input(encode_input(seq, t, pos)) == (seq, t, pos)


@given(seq=st.integers(0, 2**40), t=st.floats(0, 1e10),
       pos=st.lists(st.floats(allow_nan=False), min_size=8, max_size=8),
       flags=st.lists(st.text(max_size=12), max_size=5))
def test_output_and_feedback_round_trip(seq: int, t: float, pos: list[float],
                                        flags: list[str]) -> None:
    out = decode_output(encode_output(seq, t, seq - 1, pos, flags))
    assert out["pos"] == dict(zip(AXES, pos, strict=True)) and out["flags"] == flags
    fb = decode_feedback(encode_feedback(t, {"rails_x": 1.0}, {"rails_x": 2.0}))
    assert fb["pos"]["rails_x"] == 1.0


ints = st.integers(-(2**63), 2**64 - 1)  # what msgpack can carry
anything = st.recursive(
    st.none() | st.booleans() | ints | st.floats() | st.text(max_size=8)
    | st.binary(max_size=8),
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c, max_size=4),
    max_leaves=12)
frame_like = st.fixed_dictionaries(
    {}, optional={"seq": anything | ints, "t": anything | st.floats(),
                  "pos": anything | st.dictionaries(st.sampled_from([*AXES, "rails_z"]),
                                                    anything | st.floats(), max_size=4),
                  "other": anything})


@settings(max_examples=400)
@given(obj=frame_like | anything)
def test_validation_accepts_only_well_formed_frames(obj: object) -> None:
    payload = msgpack.packb(obj)
    v = InputValidator(*LIM)
    res = v.accept(payload)
    if res is None:
        assert v.rejected == 1 and sum(v.counts.values()) == 1
        assert set(v.counts) == set(REJECT_REASONS)
        return
    # accepted: then it is exactly a valid frame
    seq, t, pos = res
    assert isinstance(obj, dict) and set(obj) <= {"seq", "t", "pos"}
    assert isinstance(seq, int) and not isinstance(seq, bool)
    assert t is None or math.isfinite(t)
    for axis, value in pos.items():
        i = AXES.index(axis)
        span = LIM[1][i] - LIM[0][i]
        assert math.isfinite(value)
        assert LIM[0][i] - 0.25 * span <= value <= LIM[1][i] + 0.25 * span


@given(data=st.binary(max_size=64))
def test_garbage_bytes_never_raise(data: bytes) -> None:
    v = InputValidator(*LIM)
    v.accept(data)  # must not raise, whatever the bytes
    try:
        decode_input(data)
    except FrameError as exc:
        assert exc.reason in REJECT_REASONS


def test_sequence_rules() -> None:
    v = InputValidator(*LIM)
    frames = [encode_input(s, None, {"rails_x": 0.0}) for s in (3, 4, 4, 2, 9)]  # type: ignore[arg-type]
    got = [v.accept(f) is not None for f in frames]
    assert got == [True, True, False, False, True]
    assert v.counts["duplicate"] == 1 and v.counts["old"] == 1
    assert v.accept(encode_input(1, None, {"rails_x": 0.0}), after_stale=True) is not None  # type: ignore[arg-type]


def test_nonfinite_sender_time_is_rejected() -> None:
    v = InputValidator(*LIM)
    for k, t in enumerate((math.nan, math.inf, -math.inf)):
        assert v.accept(encode_input(k, t, {"rails_x": 0.0})) is None
    assert v.counts["nonfinite"] == 3 and v.last_error == "nonfinite: t is -inf"


# --- the compiled codec (motcomp/io/_cwire.c) against msgpack-python and the Python path ---

needs_cwire = pytest.mark.skipif(wire._cwire is None, reason="the compiled codec is not built")


@needs_cwire
@settings(max_examples=300)
@given(seq=ints, src=ints, t=st.floats(),
       pos=st.lists(st.floats() | st.integers(-(2**53), 2**53), min_size=8, max_size=8),
       flags=st.lists(st.text(max_size=300), max_size=20))
def test_compiled_output_is_msgpacks_bytes(seq: int, src: int, t: float, pos: list[float],
                                           flags: list[str]) -> None:
    got = wire._cwire.pack_output(seq, t, src, AXES, pos, flags)
    expect = msgpack.packb({"seq": seq, "t": t, "src_seq": src,
                            "pos": dict(zip(AXES, map(float, pos), strict=True)),
                            "flags": flags}, use_bin_type=True)
    assert got == expect


@needs_cwire
def test_compiled_output_rejects_wrong_arguments() -> None:
    with pytest.raises(ValueError, match="7 positions for 8 axes"):
        wire._cwire.pack_output(0, 0.0, 0, AXES, [0.0] * 7, [])
    with pytest.raises(TypeError, match="flags must be str"):
        wire._cwire.pack_output(0, 0.0, 0, AXES, [0.0] * 8, [3])
    with pytest.raises(OverflowError):
        wire._cwire.pack_output(2**64, 0.0, 0, AXES, [0.0] * 8, [])


def _verdicts(payloads: list[bytes], compiled: bool) -> tuple[list[object], dict[str, int], str]:
    saved = wire._cwire
    wire._cwire = saved if compiled else None
    try:
        v = InputValidator(*LIM)
        out = [v.accept(p, after_stale=True) for p in payloads]
        return out, dict(v.counts), v.last_error
    finally:
        wire._cwire = saved


float32_frame = st.builds(
    lambda seq, pos: b"\x82\xa3seq" + msgpack.packb(seq) + b"\xa3pos"
    + bytes([0x80 | len(pos)]) + b"".join(msgpack.packb(a) + msgpack.packb(x, use_single_float=True)
                                         for a, x in pos.items()),
    st.integers(0, 2**64 - 1), positions)


@needs_cwire
@settings(max_examples=400)
@given(frames=st.lists(st.builds(msgpack.packb, frame_like | anything)
                       | st.builds(encode_input, st.integers(0, 2**62),
                                   st.floats(), positions)
                       | float32_frame | st.binary(max_size=40), min_size=1, max_size=6))
def test_compiled_parsing_gives_the_python_verdicts(frames: list[bytes]) -> None:
    """Every frame gets the same verdict, values and counted reason with the compiled fast
    path as without it (the compiled path only ever accepts, or hands over)."""
    assert _verdicts(frames, True) == _verdicts(frames, False)


@needs_cwire
def test_compiled_parsing_hands_over_anything_unusual() -> None:
    lo, hi = InputValidator(*LIM)._lo, InputValidator(*LIM)._hi
    parse = wire._cwire.parse_input
    good = encode_input(7, 1.5, {"rails_x": 0.5, "hex_yaw": -0.1})
    assert parse(good, wire.AXIS_INDEX, lo, hi) == (7, 1.5, {"rails_x": 0.5, "hex_yaw": -0.1})
    assert parse(msgpack.packb({"pos": {"rails_y": 0.25}, "seq": 2**64 - 1}), wire.AXIS_INDEX,
                 lo, hi) == (2**64 - 1, None, {"rails_y": 0.25})
    for bad in (good + b"\x00",  # trailing bytes
                good[:-3],  # truncated
                msgpack.packb({"seq": 1, "pos": {"rails_x": 1}}),  # an int position
                msgpack.packb({"seq": True, "pos": {"rails_x": 0.0}}),
                msgpack.packb({"seq": 1, "pos": {"rails_x": 9.0}}),  # out of range
                msgpack.packb({"seq": 1, "pos": {"rails_x": math.nan}}),
                msgpack.packb({"seq": 1, "t": math.inf, "pos": {"rails_x": 0.0}}),
                msgpack.packb({"seq": 1, "pos": {}}),
                msgpack.packb({"seq": 1, "pos": {"rails_z": 0.0}}),
                msgpack.packb({"seq": 1, "t": 1.0, "pos": {"rails_x": 0.0}, "x": 1}),
                msgpack.packb({"seq": 1, "seq ": 2}),
                msgpack.packb([1, 2])):
        assert parse(bad, wire.AXIS_INDEX, lo, hi) is None, bad
    with pytest.raises(TypeError):
        parse("not bytes", wire.AXIS_INDEX, lo, hi)
