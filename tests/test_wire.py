"""Wire contract: codecs round-trip, and validation never lets a bad frame through."""

from __future__ import annotations

import math

import msgpack
from hypothesis import given, settings
from hypothesis import strategies as st

from motcomp.core.axes import AXES
from motcomp.errors import FrameError
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
    assert t is None or math.isfinite(t) or t == obj.get("t")
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
