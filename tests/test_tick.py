"""The tick on its own: :func:`motcomp.core.tick.step` driven with given times and payloads.

Any payload: ``step`` never raises, a rejected frame is counted under one reason and changes
no output; the command stays finite and within every limit.  Any sequence of valid frames: the
reference stays finite and within the reach.  Catch-up after a stall equals ticking every
deadline.  The saturation verdict flags a limit that acts, and only then.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import struct
from functools import cache
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, event, example, given, settings
from hypothesis import strategies as st

from motcomp.config import ServiceConfig, load_config, new_tick, parse_config, read_toml
from motcomp.core import tick as tick_mod
from motcomp.core.axes import AXES
from motcomp.core.saturation import POS, VEL
from motcomp.core.tick import (
    MAX_CATCH_UP,
    MAX_ERROR_CHARS,
    REJECT_REASONS,
    TickOutput,
    TickParams,
    TickState,
    set_bypass,
    step,
)
from motcomp.io.wire import encode_input
from tests._frames import anything, frame_like, seqs
from tests.conftest import ran_in_plain_python
from tests.test_saturation import check_sequence

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "config" / "motcomp.toml"
MS = 1_000_000  # ns
H = 1e-3  # s, the period at the example's 1 kHz
Y = AXES.index("rails_y")
HEX = [a for a in AXES if a.startswith("hex")]
CONFIGS = ("example", "rails_only", "all_compensated", "hold")


@cache
def config(name: str = "example", **over: Any) -> ServiceConfig:
    """The example config (all eight axes driven, the hexapod in bypass), or a variant: only the
    rails driven, every axis compensated, ``hold`` reconstruction; ``over`` sets
    ``section__key`` values."""
    if name == "example" and not over:
        return load_config(EXAMPLE)
    data = read_toml(EXAMPLE)
    if name == "rails_only":
        data["axes"] = {a: v for a, v in data["axes"].items() if a not in HEX}
    elif name == "all_compensated":
        for axis in data["axes"].values():
            axis.pop("bypass", None)
    elif name == "hold":
        data["input"]["reconstruction"] = "hold"
    for key, value in over.items():
        section, name_ = key.split("__")
        data[section][name_] = value
    return parse_config(data)


def motion(k: int) -> dict[str, float]:
    """A feasible motion starting at rest (sin^3), at tick ``k``, on three axes."""
    t = k * H
    return {"rails_y": 0.25 * math.sin(2 * math.pi * 0.3 * t) ** 3,
            "rails_x": 0.1 * math.sin(2 * math.pi * 0.2 * t) ** 3,
            "hex_z": 0.05 * math.sin(2 * math.pi * 0.5 * t) ** 3}


def motion_frame(k: int) -> bytes:
    return encode_input(k, k * H, motion(k))


WARM_TICKS = 1200  # past the 1 s start-up blend


@cache
def _warm(name: str) -> tuple[TickParams, TickState, tuple[tuple[float, ...], ...]]:
    params, state = new_tick(config(name))
    head = tuple(tuple(step(state, params, k * MS, motion_frame(k)).u)
                 for k in range(WARM_TICKS))
    return params, state, head


def start(name: str, warm: bool) -> tuple[TickParams, TickState, list[list[float]]]:
    """A fresh tick, or (a copy of) one that has run the motion for :data:`WARM_TICKS`; with
    the outputs so far."""
    if not warm:
        params, state = new_tick(config(name))
        return params, state, []
    params, state, head = _warm(name)
    return params, copy.deepcopy(state), [list(u) for u in head]


def assert_within_limits(outputs: list[list[float]], state: TickState) -> None:
    """Every command finite and within the position, velocity and acceleration limits of its
    axis, from rest at neutral."""
    u = np.array(outputs)
    assert np.all(np.isfinite(u))
    for i in range(len(AXES)):
        check_sequence(u[:, i], 0.0, state.comp.limits, H, i)


def assert_same_state(a: TickState, b: TickState) -> None:
    sa, sb = a.comp.state(), b.comp.state()
    for f in dataclasses.fields(sa):
        assert np.array_equal(getattr(sa, f.name), getattr(sb, f.name)), f.name
    assert a.shaper.ref == b.shaper.ref


def same_output(a: TickOutput, b: TickOutput) -> bool:
    return (a.u, a.flags, a.limited, a.mode, a.src_seq) == (b.u, b.flags, b.limited, b.mode,
                                                            b.src_seq)


# --- any payload -----------------------------------------------------------------------------
well_formed = st.builds(
    encode_input, seqs, st.none() | st.floats(-10, 10) | st.floats(),
    st.dictionaries(st.sampled_from(AXES), st.floats(-0.5, 0.5) | st.floats(-5, 5), min_size=1))
typical = [  # one of each reason, for sure
    msgpack.packb({"seq": 1, "pos": [0.1]}),
    msgpack.packb({"seq": True, "pos": {"rails_y": 0.0}}),
    msgpack.packb({"seq": 10**9, "pos": {"rails_z": 0.0}}),
    msgpack.packb({"seq": 10**9, "pos": {"rails_y": float("nan")}}),
    msgpack.packb({"seq": 10**9, "pos": {"rails_y": 40.0}}),
    msgpack.packb({"seq": 10**9, "pos": {}}),
    b"\x91" * 1100 + b"\x00",  # nested beyond msgpack's stack
    b"\x80" * 5000,  # beyond max_frame_bytes
]
payloads = (st.binary(max_size=64) | st.builds(msgpack.packb, frame_like | anything)
            | well_formed | st.sampled_from(typical))
REPEATS = {"again": 1, "older": 5}
"""Markers for the motion's own frame of 1 or 5 ticks before (duplicate and old seq)."""

TICKS = 250


@settings(max_examples=120, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(name=st.sampled_from(CONFIGS), warm=st.booleans(),
       inserted=st.dictionaries(st.integers(0, TICKS - 1),
                                payloads | st.sampled_from(sorted(REPEATS)), max_size=12),
       silence=st.tuples(st.integers(0, TICKS), st.integers(0, 150)))
def test_any_payload_never_raises_and_a_rejected_one_changes_nothing(
        name: str, warm: bool, inserted: dict[int, bytes | str], silence: tuple[int, int]
) -> None:
    """Arbitrary payloads in place of the motion's frames (and a silence): the state fed them
    and a twin fed nothing wherever the first one rejected give bit-identical outputs at every
    tick; each rejection counts once under one reason (never ``internal``) with a bounded
    text; every command is finite and within the limits."""
    params, a, outputs = start(name, warm)
    b = copy.deepcopy(a)
    k0 = len(outputs)
    for j in range(TICKS):
        k = k0 + j
        if j in inserted:
            p = inserted[j]
            payload: bytes | None = motion_frame(k - REPEATS[p]) if isinstance(p, str) else p
        elif silence[0] <= j < silence[0] + silence[1]:
            payload = None
        else:
            payload = motion_frame(k)
        counts, accepted = dict(a.rejected_by_reason), a.accepted
        out_a = step(a, params, k * MS, payload)
        rejected = [r for r in REJECT_REASONS if a.rejected_by_reason[r] != counts[r]]
        out_b = step(b, params, k * MS, None if rejected else payload)
        assert same_output(out_a, out_b), j
        if rejected:
            (reason,) = rejected
            event(f"rejected: {reason}")
            assert a.rejected_by_reason[reason] == counts[reason] + 1
            assert reason != "internal", a.last_reject
            assert a.last_reject.startswith(f"{reason}: ")
            assert len(a.last_reject) <= MAX_ERROR_CHARS
            assert a.accepted == accepted
        elif payload is not None:
            if j in inserted:
                event("an arbitrary payload accepted")
            assert a.accepted == accepted + 1
        outputs.append(out_a.u)
    assert a.received - b.received == a.rejected - b.rejected
    assert_same_state(a, b)
    assert_within_limits(outputs, a)


# --- named regressions -------------------------------------------------------------------------
def take(state: TickState, params: TickParams, k: int, payload: bytes) -> str | None:
    """Step with ``payload``; the reason it was rejected for (None: accepted), after checking
    that exactly one counter moved and the output is finite."""
    counts, accepted = dict(state.rejected_by_reason), state.accepted
    out = step(state, params, k * MS, payload)
    assert all(math.isfinite(x) for x in out.u)
    moved = [r for r in REJECT_REASONS if state.rejected_by_reason[r] != counts[r]]
    if not moved:
        assert state.accepted == accepted + 1
        return None
    (reason,) = moved
    assert state.rejected_by_reason[reason] == counts[reason] + 1
    assert len(state.last_reject) <= MAX_ERROR_CHARS
    return reason


@pytest.mark.parametrize(("depth", "expect"), [
    (1000, ("schema", "type", "axis")),  # within msgpack's 1024-level stack: the checks reject
    (5000, ("decode", "decode", "decode")),  # beyond it: msgpack refuses
])
def test_deeply_nested_frame_is_rejected_not_raised(depth: int, expect: tuple[str, ...]) -> None:
    params, state = new_tick(config(input__max_frame_bytes=65536))
    frames = (b"\x81\xa3pos" + b"\x91" * depth + b"\x00",  # {"pos": [[[...[0]...]]]}
              b"\x82\xa3seq\x00\xa3pos" + b"\x91" * depth + b"\x00",  # with a seq
              b"\x82\xa3seq\x00\xa3pos" + b"\x81\xa1a" * depth + b"\x00")  # {"a": {"a": ...}}
    got = tuple(take(state, params, k, f) for k, f in enumerate(frames))
    assert got == expect, state.last_reject
    assert take(state, params, 3, motion_frame(3)) is None  # and the next valid frame goes in


def duplicate_key_frame(entries: int) -> bytes:
    """``{"seq": 1, "pos": {"rails_y": 0.1}, "pos": ... x entries}``: a map32 that repeats
    its ``pos`` key; decoded, it is the valid frame ``{"seq": 1, "pos": {"rails_y": 0.1}}``."""
    entry = b"\xa3pos\x81\xa7rails_y\xcb" + struct.pack(">d", 0.1)
    return b"\xdf" + (entries + 1).to_bytes(4, "big") + b"\xa3seq\x01" + entry * entries


def test_oversize_frame_is_rejected_unread(monkeypatch: pytest.MonkeyPatch) -> None:
    unpacked: list[int] = []

    def spy(payload: bytes, **kw: Any) -> Any:
        unpacked.append(len(payload))
        return msgpack.unpackb(payload, **kw)

    monkeypatch.setattr(tick_mod, "_unpackb", spy)
    big = duplicate_key_frame(48_000)  # 1 MB and more
    cap = 1_048_576  # the largest input.max_frame_bytes allowed
    assert len(big) > cap
    params, state = new_tick(config(input__max_frame_bytes=cap))
    assert params.max_frame_bytes == cap
    assert take(state, params, 0, big) == "oversize" and not unpacked
    assert state.last_reject == f"oversize: frame of {len(big)} bytes exceeds the cap of {cap}"
    # the cap is input.max_frame_bytes: a 5 kB frame is too big for the default 4096 bytes ...
    small = duplicate_key_frame(230)
    assert 4096 < len(small) < 8192
    params, state = new_tick(config())
    assert params.max_frame_bytes == config().input.max_frame_bytes == 4096
    assert take(state, params, 0, small) == "oversize" and not unpacked
    # ... and a valid frame, read and accepted, under a cap of its size
    for cap in (len(small), 8192):
        params, state = new_tick(config(input__max_frame_bytes=cap))
        assert take(state, params, 0, small) is None and unpacked[-1] == len(small)
    params, state = new_tick(config(input__max_frame_bytes=len(small) - 1))
    assert take(state, params, 0, small) == "oversize"


@pytest.mark.parametrize(("t_prev", "t_next"), [
    (1.0, math.nextafter(1.0, math.inf)),  # one ulp (2.2e-16 s)
    (1.7e9, math.nextafter(1.7e9, math.inf)),  # one ulp of an epoch time (2.4e-7 s)
    (0.0, 5e-324),  # a subnormal step
    (1.0, 1.0),  # the same t
    (1.0, math.nextafter(1.0, -math.inf)),  # one ulp back
    (1.0, 0.999),  # 1 ms back
], ids=["ulp", "ulp-epoch", "subnormal", "same", "ulp-back", "back"])
@pytest.mark.parametrize("reconstruction", ["linear", "smooth"])
def test_one_ulp_time_step_never_divides_by_zero(t_prev: float, t_next: float,
                                                 reconstruction: str) -> None:
    """Frames at -3.8 m on rails_y, then one ``t_next - t_prev`` later at +3.8 m (both within
    the reach, +-3.9 m).  The slope through the last two samples would be 7.6 m over that step:
    3.4e16 m/s for an ulp, inf for the subnormal -- before the fix the reference went to +-inf
    (or ~1e13 m after a millisecond of extrapolation), and a t going back gave the same slope
    with its sign flipped.  Now a step below ``min_dt_s`` replaces the sample and a step back
    restarts the line: with ``linear`` the reference is the new value, exactly, until the next
    frame; ``smooth`` plays the jump back, then (no frame follows) extrapolates it, within the
    reach (a ``t`` more than ``min_dt_s`` back is no sample of a live sender: rejected,
    ``jump``); the command stays within the limits."""
    params, state = new_tick(config(loop__startup_s=0.0, input__reconstruction=reconstruction))
    sp = params.shaper
    v0, v1 = -3.8, 3.8
    assert sp.reach_lo[Y] < v0 and v1 < sp.reach_hi[Y]
    frames = [(t_prev - 2e-3, v0), (t_prev - 1e-3, v0), (t_prev, v0), (t_next, v1)]
    outputs, refs = [], []
    for k in range(40):
        payload = (encode_input(k, frames[k][0], {"rails_y": frames[k][1]}) if k < len(frames)
                   else None)
        outputs.append(step(state, params, k * MS, payload).u)
        refs.append(state.shaper.ref[Y])
    assert all(math.isfinite(r) and sp.reach_lo[Y] <= r <= sp.reach_hi[Y] for r in refs)
    if reconstruction == "smooth" and t_next < t_prev - sp.min_dt_s:
        assert state.accepted == 3 and state.rejected_by_reason["jump"] == 1
        assert "beyond" in state.last_reject
        return
    assert state.accepted == 4
    if reconstruction == "linear":
        assert refs[2] == v0 and refs[3:] == [v1] * 37
    else:  # the new value through the band limit (its 1.1 % overshoot), within the reach
        assert refs[2] == v0
        assert all(v1 - 1e-3 * (v1 - v0) <= r <= sp.reach_hi[Y] for r in refs[-10:])
    assert_within_limits(outputs, state)


tiny_and_huge_steps = st.sampled_from([
    0.0, 5e-324, -5e-324, 1e-300, 2.2e-16, -2.2e-16, 1e-6, -1e-6, 1e-5, 1e-3, 1e-3, 1e-3,
    2e-3, -1e-3, 0.04, 0.1, 1e6, -1e6, 1e300, -1e300]) | st.floats(-1e3, 1e3)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@example(name="example", t0=0.0,  # a period of 1e-98 s, then a stamp 1e300 s on
         frames=[(0.0, {"rails_x": 0.0}, 1), (8.7e-99, {"rails_x": 0.0}, 1),
                 (1e300, {"rails_x": 0.0}, 1)])
@given(name=st.sampled_from(CONFIGS), t0=st.sampled_from([0.0, 1.0, 1.7e9, -5.0]),
       frames=st.lists(st.tuples(tiny_and_huge_steps,
                                 st.dictionaries(st.sampled_from(AXES), st.floats(0.0, 1.0),
                                                 min_size=1),
                                 st.sampled_from([1, 1, 1, 2, 3, 60])),
                       min_size=1, max_size=60))
def test_any_valid_frames_keep_the_reference_finite_and_within_reach(
        name: str, t0: float, frames: list[tuple[float, dict[str, float], int]]) -> None:
    """Valid frames (values anywhere in the reach, as fractions of it) whose sender times step
    by zero, a subnormal, an ulp, backwards or by 1e300, with silences: every frame is
    accepted but those whose ``t`` no live sender's next sample can have (``jump``), the
    reference stays finite and within the reach and the command within the limits."""
    params, state = new_tick(config(name))
    lo, hi = params.shaper.reach_lo, params.shaper.reach_hi
    t = t0
    k = 0
    outputs = []
    for seq, (dt, fractions, gap) in enumerate(frames):
        t += dt
        pos = {}
        for axis, f in fractions.items():
            i = AXES.index(axis)
            pos[axis] = lo[i] + f * (hi[i] - lo[i])
        for j in range(gap):
            out = step(state, params, k * MS, encode_input(seq, t, pos) if j == 0 else None)
            outputs.append(out.u)
            ref = state.shaper.ref
            assert all(math.isfinite(r) and lo[i] <= r <= hi[i] for i, r in enumerate(ref)), ref
            k += 1
    assert state.accepted + state.rejected_by_reason["jump"] == len(frames)
    assert state.rejected == state.rejected_by_reason["jump"]
    assert_within_limits(outputs, state)


def test_error_text_is_bounded_whatever_the_frame() -> None:
    """Half-megabyte keys, strings and binaries, long lists and out-of-range numbers: each
    rejected for its own reason, with a text of at most MAX_ERROR_CHARS that still names the
    key."""
    params, state = new_tick(config(input__max_frame_bytes=1_048_576))
    big = 500_000
    ok = {"rails_y": 0.0}
    cases: list[tuple[Any, str, str]] = [
        ({"x" * big: 1, "seq": 1, "pos": ok}, "schema", "unknown key 'xxx"),
        ({"seq": "s" * big, "pos": ok}, "type", "seq must be an int"),
        ({"seq": 1, "t": "t" * big, "pos": ok}, "type", "t must be a number"),
        ({"seq": 1, "pos": {"z" * big: 0.0}}, "axis", "unknown axis 'zzz"),
        ({"seq": 1, "pos": {"rails_y": "v" * big}}, "type", "pos.rails_y must be a number"),
        ({"seq": 1, "pos": {"rails_y": b"\x00" * big}}, "type", "pos.rails_y must be a number"),
        ({"seq": 1, "pos": {"rails_y": [0.0] * 50_000}}, "type", "a list of 50000 items"),
        ({"seq": 1, "pos": {"rails_y": 2**64 - 1}}, "range", "pos.rails_y = 1.8446744"),
        ({"seq": 1, "pos": {"rails_y": -1e308}}, "range", "pos.rails_y = -1e+308"),
        ({"seq": 2**64 - 1, "pos": "p" * big}, "type", "pos must be a map"),
    ]
    for k, (obj, reason, text) in enumerate(cases):
        assert take(state, params, k, msgpack.packb(obj)) == reason, state.last_reject
        assert text in state.last_reject, state.last_reject
    # not UTF-8, and an unhashable key: msgpack's own errors, cut short
    for k, payload in enumerate((b"\x81\xda\x00\x04\xff\xfe\xfd\xfc\x00",
                                 b"\x81\x91\xa1x\x00"), start=len(cases)):
        assert take(state, params, k, payload) == "decode", state.last_reject


def test_an_unexpected_exception_is_counted_and_the_tick_goes_on(
        monkeypatch: pytest.MonkeyPatch, request: pytest.FixtureRequest) -> None:
    """The decoder running out of memory or stack is a ``decode`` rejection; an exception of
    any other kind in the checks (a bug) is ``internal``; either way nothing changes and the
    next frame is taken."""
    if ran_in_plain_python(request):
        return
    params, state = new_tick(config())
    for k in range(10):
        assert take(state, params, k, motion_frame(k)) is None
    twin = copy.deepcopy(state)

    def raising(exc: BaseException) -> Any:
        def f(*args: Any, **kw: Any) -> Any:
            raise exc
        return f

    cases = [("_unpackb", MemoryError(), "decode"),
             ("_unpackb", RecursionError("maximum recursion depth exceeded"), "decode"),
             ("parse_input", ZeroDivisionError("a bug in the checks"), "internal")]
    for k, (where, exc, reason) in enumerate(cases, start=10):
        before = state.rejected_by_reason[reason]
        with monkeypatch.context() as m:
            m.setattr(tick_mod, where, raising(exc))
            out = step(state, params, k * MS, motion_frame(k))
        assert state.rejected_by_reason[reason] == before + 1 and state.rejected == k - 9
        assert same_output(out, step(twin, params, k * MS))  # as if no frame had come
    assert state.last_reject == "internal: ZeroDivisionError: a bug in the checks"
    k = 10 + len(cases)
    assert same_output(step(state, params, k * MS, motion_frame(k)),
                       step(twin, params, k * MS, motion_frame(k)))
    assert state.accepted == twin.accepted == 11
    assert_same_state(state, twin)


def test_sequence_rules() -> None:
    """``seq`` must increase (duplicate, old); a jump counts the frames in between as
    superseded; after a stale spell any ``seq`` is taken (a restarted sender) and its regress
    is not counted."""
    params, state = new_tick(config())
    got = [take(state, params, k, encode_input(s, k * H, {"rails_x": 0.0}))
           for k, s in enumerate((3, 4, 4, 2, 9))]
    assert got == [None, None, "duplicate", "old", None]
    assert state.last_seq == state.src_seq == 9 and state.superseded == 4
    assert state.last_reject == "old: seq 2 after 4"
    step(state, params, 100 * MS)  # 95 ms of silence: stale
    assert take(state, params, 101, encode_input(1, 0.101, {"rails_x": 0.0})) is None
    assert state.src_seq == 1 and state.superseded == 4


def test_bypass_ignores_undriven_axes() -> None:
    """Bypass asked for all eight axes acts on the driven ones; the undriven stay bypassed and
    are never flagged (the rails' configured prediction is switched off with them)."""
    params, state = new_tick(config("rails_only"))
    assert set_bypass(state, [True] * len(AXES)) == list(AXES)  # undriven: bypassed anyway
    assert step(state, params, 0).flags == ["bypass:rails_x", "bypass:rails_y",
                                            "nopredict:rails_x", "nopredict:rails_y"]
    assert set_bypass(state, [False] * len(AXES)) == HEX
    assert step(state, params, MS).flags == []


# --- catch-up ----------------------------------------------------------------------------------
def stalls(every: int, first: int, k: int, until: int) -> dict[int, int]:
    """``{deadline after a stall: deadlines skipped}``: a stall of ``k`` every ``every``."""
    return {m + k: k for m in range(first, until - k, every)}


@pytest.mark.parametrize("name", ["example", "all_compensated"])
@pytest.mark.parametrize("k", [1, 2, 7, 150])
def test_catch_up_equals_ticking_every_deadline(name: str, k: int) -> None:
    """A tick after ``k`` skipped deadlines, given the frames that landed meanwhile (one per
    deadline), leaves the compensator exactly where ticking every deadline as they landed would
    have, and gives the same command; through start-up, live input and a silence (stale, hold,
    ramp)."""
    params, a = new_tick(config(name))
    _, b = new_tick(config(name))
    resume = stalls(37 + k, 5, k, 2600)
    silent = range(1500, 2100)
    m = 0
    checked = 0
    while m < 2600:
        frame = None if m in silent else motion_frame(m)
        if m + k in resume:  # b stalls over m .. m+k-1; a ticks them, taking each frame
            landed = []
            for j in range(m, m + k):
                f = None if j in silent else motion_frame(j)
                step(a, params, j * MS, f)
                if f is not None:
                    landed.append(f)
            m += k
            frame = None if m in silent else motion_frame(m)
            out_b = step(b, params, m * MS, landed + ([frame] if frame else []), skipped=k)
            out_a = step(a, params, m * MS, frame)
            assert out_a.u == out_b.u, m
            assert_same_state(a, b)
            checked += 1
        else:
            assert step(a, params, m * MS, frame).u == step(b, params, m * MS, frame).u, m
        m += 1
    assert checked >= 10 and a.comp.state().k == b.comp.state().k
    assert b.ticks < a.ticks and b.accepted == a.accepted


def test_a_longer_stall_is_caught_up_over_its_last_max_catch_up_deadlines() -> None:
    """MAX_CATCH_UP + 30 deadlines skipped, no frame meanwhile: the compensator is stepped at
    the last MAX_CATCH_UP of them only, as a loop that had been dead before those and then
    ticked them without input."""
    params, a = new_tick(config())
    _, b = new_tick(config())
    for m in range(1200):
        step(a, params, m * MS, motion_frame(m))
        step(b, params, m * MS, motion_frame(m))
    skipped = MAX_CATCH_UP + 30
    now = 1200 + skipped
    for j in range(now - MAX_CATCH_UP, now):
        step(a, params, j * MS)
    out_a = step(a, params, now * MS)
    out_b = step(b, params, now * MS, None, skipped=skipped)
    assert out_a.u == out_b.u
    assert_same_state(a, b)


# --- the saturation verdict --------------------------------------------------------------------
def run_rails_y(reference: Any, ticks: int) -> tuple[TickState, list[TickOutput], list[int]]:
    """The example's tick fed ``reference(t)`` on rails_y; the outputs and the limiter's bits
    of each tick."""
    params, state = new_tick(config())
    outs, bits = [], []
    for k in range(ticks):
        outs.append(step(state, params, k * MS,
                         encode_input(k, k * H, {"rails_y": reference(k * H)})))
        bits.append(state.comp.flags[Y])
    return state, outs, bits


def assert_verdicts_flagged(state: TickState, outs: list[TickOutput]) -> list[bool]:
    limited = [o.limited[Y] for o in outs]
    for o in outs:
        assert o.limited[Y] == ("sat:rails_y" in o.flags)
        assert not any(o.limited[i] for i in range(len(AXES)) if i != Y)
        # in this order: mode, sat:<axis>, bypass:<axis>, then the band monitor's fallback
        fallback = ["fallback:rails_y"] if "fallback:rails_y" in o.flags else []
        assert o.flags == ([o.mode] if o.mode else []) + (["sat:rails_y"] if o.limited[Y]
                                                           else []) + [f"bypass:{a}" for a in HEX] \
            + fallback
    assert state.sat[Y] == sum(limited)
    assert state.sat[:Y] + state.sat[Y + 1:] == [0] * (len(AXES) - 1)
    return limited


def test_the_velocity_limit_acting_is_flagged() -> None:
    """After 1.2 s at rest, a minimum-jerk move of 2 m in 1 s: its peak speed, 3.75 m/s, is
    beyond the rails' 2 m/s.  The command moves at exactly 2 m/s for a while, and every tick
    where the velocity (or position) bound acted is flagged."""
    def move(t: float) -> float:
        x = min(max(t - 1.2, 0.0), 1.0)
        return 2.0 * x**3 * (10.0 - 15.0 * x + 6.0 * x * x)

    state, outs, bits = run_rails_y(move, 3000)
    limited = assert_verdicts_flagged(state, outs)
    u = np.array([o.u[Y] for o in outs])
    assert np.max(np.abs(np.diff(u))) / H == pytest.approx(state.comp.limits.v_max[Y], rel=1e-9)
    assert any(b & VEL for b in bits)
    assert all(lim for lim, b in zip(limited, bits, strict=True) if b & (POS | VEL))
    assert not any(limited[:1200])  # at rest before the move


def test_holding_the_end_of_the_range_is_flagged() -> None:
    """A slow ramp to 3.5 m, within the reach (3.9 m) but beyond the rails (2.6 m): the command
    stops at 2.6 m and stays there, flagged saturated for as long as the target lies beyond --
    though the limiter, holding the clamped target, raises no bit."""
    state, outs, bits = run_rails_y(lambda t: 0.5 * min(max(t - 1.2, 0.0), 7.0), 9000)
    limited = assert_verdicts_flagged(state, outs)
    u = np.array([o.u[Y] for o in outs])
    beyond = int(np.argmax(u >= 2.6))
    assert u.max() == 2.6 and np.all(u[beyond:] == 2.6)
    assert all(limited[beyond:]) and bits[-1] == 0


def test_a_feasible_smooth_reference_is_never_flagged() -> None:
    state, outs, _ = run_rails_y(lambda t: 0.25 * math.sin(2 * math.pi * 0.3 * t) ** 3, 6000)
    assert not any(any(o.limited) for o in outs)
    assert not any(f.startswith("sat:") for o in outs for f in o.flags)
    assert state.sat == [0] * len(AXES)


def test_the_wait_for_a_first_frame_is_no_stale_episode() -> None:
    """300 ms without a frame after the start (stale after 50 ms: the mode says so), then a
    live sender: no stale episode and no stale time counted; a 100 ms gap later is one
    episode, its stale time from 50 ms after the last frame to the next."""
    params, state = new_tick(config())
    for k in range(300):
        out = step(state, params, k * MS)
    assert out.mode == "stale" and state.shaper.stale_episodes == 0
    for k in range(300, 1300):
        step(state, params, k * MS, encode_input(k, k * 1e-3, {"rails_y": 0.1}))
    assert state.shaper.stale_episodes == 0 and state.shaper.stale_total_s == 0.0
    for k in range(1300, 1400):
        step(state, params, k * MS)
    for k in range(1400, 1500):
        step(state, params, k * MS, encode_input(k, k * 1e-3, {"rails_y": 0.1}))
    assert state.shaper.stale_episodes == 1
    assert state.shaper.stale_total_s == pytest.approx(0.1 - params.shaper.stale_after_s,
                                                       abs=2e-3)
