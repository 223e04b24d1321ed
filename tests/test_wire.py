"""Wire contract: codecs round-trip, and input validation never lets a bad frame through.

The validation of input frames is :func:`motcomp.core.tick.parse_input` (the sequence rules and
the counting live in :func:`motcomp.core.tick.step`: tests/test_tick.py).
"""

from __future__ import annotations

import math
import re

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motcomp.core.axes import AXES, AXIS_INDEX
from motcomp.core.tick import REJECT_REASONS, parse_input
from motcomp.errors import FrameError
from motcomp.io.wire import (
    decode_feedback,
    decode_output,
    encode_feedback,
    encode_input,
    encode_output,
)
from tests._frames import anything, frame_like, ints

LIMITS = [-2.6] * 2 + [-0.25] * 6, [2.6] * 2 + [0.25] * 6
REACH = tuple(lo - 0.25 * (hi - lo) for lo, hi in zip(*LIMITS, strict=True)), \
    tuple(hi + 0.25 * (hi - lo) for lo, hi in zip(*LIMITS, strict=True))
"""Accepted values: the limits widened by a quarter of the range (reject_beyond_fraction)."""

positions = st.dictionaries(st.sampled_from(AXES), st.floats(-0.2, 0.2), min_size=1)


def parse(payload: bytes, max_bytes: int = 4096) -> tuple[int, float | None, dict[int, float]]:
    return parse_input(payload, *REACH, max_bytes=max_bytes)


@given(seq=st.integers(0, 2**62), t=st.floats(0, 1e10), pos=positions)
def test_input_round_trip(seq: int, t: float, pos: dict[str, float]) -> None:
    assert parse(encode_input(seq, t, pos)) == (seq, t, {AXIS_INDEX[a]: v for a, v in pos.items()})


@given(seq=st.integers(0, 2**40), t=st.floats(0, 1e10),
       pos=st.lists(st.floats(allow_nan=False), min_size=8, max_size=8),
       flags=st.lists(st.text(max_size=12), max_size=5))
def test_output_and_feedback_round_trip(seq: int, t: float, pos: list[float],
                                        flags: list[str]) -> None:
    out = decode_output(encode_output(seq, t, seq - 1, pos, flags))
    assert out["pos"] == dict(zip(AXES, pos, strict=True)) and out["flags"] == flags
    fb = decode_feedback(encode_feedback(t, {"rails_x": 1.0}, {"rails_x": 2.0}))
    assert fb["pos"]["rails_x"] == 1.0




@settings(max_examples=200)
@given(seq=ints, src=ints, t=st.floats(),
       pos=st.lists(st.floats() | st.integers(-(2**53), 2**53), min_size=8, max_size=8),
       flags=st.lists(st.text(max_size=300), max_size=20))
def test_output_is_plain_msgpack(seq: int, src: int, t: float, pos: list[float],
                                 flags: list[str]) -> None:
    """An output frame is exactly msgpack's encoding of the documented map, positions as
    floats: any msgpack client reads it."""
    got = encode_output(seq, t, src, pos, flags)
    expect = msgpack.packb({"seq": seq, "t": t, "src_seq": src,
                            "pos": dict(zip(AXES, map(float, pos), strict=True)),
                            "flags": flags}, use_bin_type=True)
    assert got == expect


def test_output_rejects_wrong_arguments() -> None:
    with pytest.raises(ValueError):
        encode_output(0, 0.0, 0, [0.0] * 7, [])  # 7 positions for 8 axes
    with pytest.raises(OverflowError):
        encode_output(2**64, 0.0, 0, [0.0] * 8, [])


float32_frame = st.builds(
    lambda seq, pos: b"\x82\xa3seq" + msgpack.packb(seq) + b"\xa3pos"
    + bytes([0x80 | len(pos)]) + b"".join(msgpack.packb(a) + msgpack.packb(x, use_single_float=True)
                                         for a, x in pos.items()),
    st.integers(0, 2**64 - 1), positions)


@settings(max_examples=400)
@given(payload=st.builds(msgpack.packb, frame_like | anything) | float32_frame)
def test_validation_accepts_only_well_formed_frames(payload: bytes) -> None:
    try:
        seq, t, pos = parse(payload)
    except FrameError as exc:
        assert exc.reason in REJECT_REASONS and exc.reason != "internal"
        return
    # accepted: then it is exactly a valid frame
    obj = msgpack.unpackb(payload, strict_map_key=False)
    assert isinstance(obj, dict) and set(obj) <= {"seq", "t", "pos"}
    assert isinstance(seq, int) and not isinstance(seq, bool) and seq == obj["seq"]
    assert t is None or math.isfinite(t)
    assert pos and set(pos) == {AXIS_INDEX[a] for a in obj["pos"]}
    for i, value in pos.items():
        assert type(value) is float and math.isfinite(value)
        assert REACH[0][i] <= value <= REACH[1][i]
        assert value == obj["pos"][AXES[i]]


@given(data=st.binary(max_size=64))
def test_garbage_bytes_never_raise_anything_but_a_frame_error(data: bytes) -> None:
    try:
        parse(data)
    except FrameError as exc:
        assert exc.reason in REJECT_REASONS


def test_rejections_name_the_key_and_the_value() -> None:
    cases = {
        "nonfinite": ({"seq": 1, "t": -math.inf, "pos": {"rails_x": 0.0}}, "t is -inf"),
        "range": ({"seq": 1, "pos": {"hex_z": 0.5}}, "pos.hex_z = 0.5 is outside [-0.375, 0.375]"),
        "axis": ({"seq": 1, "pos": {"rails_z": 0.0}}, "unknown axis 'rails_z' in pos"),
        "type": ({"seq": 1.0, "pos": {"rails_x": 0.0}}, "seq must be an int, got 1.0"),
        "schema": ({"seq": 1, "pos": {"rails_x": 0.0}, "tt": 0}, "unknown key 'tt'"),
    }
    for reason, (obj, text) in cases.items():
        with pytest.raises(FrameError, match=re.escape(text)) as info:
            parse(msgpack.packb(obj))
        assert info.value.reason == reason


def test_nonfinite_sender_time_is_rejected() -> None:
    for t in (math.nan, math.inf, -math.inf):
        with pytest.raises(FrameError) as info:
            parse(encode_input(1, t, {"rails_x": 0.0}))
        assert info.value.reason == "nonfinite" and str(info.value) == f"t is {t!r}"


def test_a_frame_over_the_cap_is_rejected_before_decoding() -> None:
    frame = encode_input(1, 0.0, {"rails_x": 0.0})
    assert parse(frame, max_bytes=len(frame))[0] == 1
    with pytest.raises(FrameError) as info:
        parse(frame, max_bytes=len(frame) - 1)
    assert info.value.reason == "oversize"
