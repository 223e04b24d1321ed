"""The reference shaper's compiled loops (motcomp/runtime/_cshaper.c) against its Python ones.

Two shapers, one with each, get the same frames and ticks -- jittery frames with and without
sender time, partial frames, integer positions, undriven axes, silences long enough to go
stale and rejoin, parking -- and must return *equal* references and modes at every tick and
end in equal states.  (Frame gaps of 0-3 ms around a 3 ms `max_extrapolation_s`: either bound
of the extrapolation can be the longer.)
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motcomp.core.axes import AXES
from motcomp.runtime import shaper as shaper_mod
from motcomp.runtime.shaper import ReferenceShaper

pytestmark = pytest.mark.skipif(shaper_mod._cshaper is None,
                                reason="the compiled shaper loops are not built")

DRIVEN = [True, True, True, True, True, True, False, True]
SPEEDS = [0.8, 0.8, 0.2, 0.2, 0.2, 0.3, 0.3, 0.3]

event = st.one_of(
    # (kind, gap to this event in ms, payload)
    st.tuples(st.just("frame"), st.floats(0.0, 3.0),
              st.dictionaries(st.sampled_from(AXES), st.floats(-1.0, 1.0) | st.integers(-1, 1),
                              min_size=1),
              st.none() | st.floats(-0.5, 0.5)),
    st.tuples(st.just("tick"), st.floats(0.0, 3.0), st.none(), st.none()),
    st.tuples(st.just("silence"), st.floats(50.0, 400.0), st.none(), st.none()),
)


def _run(events: list[tuple], compiled: bool, linear: bool) -> tuple[list, dict]:
    saved = shaper_mod._cshaper
    shaper_mod._cshaper = saved if compiled else None
    try:
        sh = ReferenceShaper(DRIVEN, SPEEDS, stale_after_s=0.05, hold_s=0.1, rejoin_s=0.2,
                             startup_s=0.3, linear=linear, max_extrapolation_s=0.003)
        now = 1.0
        out = []
        for k, (kind, gap_ms, pos, t_off) in enumerate(events):
            now += gap_ms / 1000.0
            if kind == "frame":
                sh.on_input(pos, now, None if t_off is None else now + t_off * 1e-3)
            else:
                if kind == "silence" and k == len(events) - 1:
                    sh.park(now)
                out.append(sh.reference(now))
        state = {name: getattr(sh, name) for name in (
            "live", "_t_frame", "_slope", "_period", "_excess", "ref", "_offset",
            "stale_total_s", "stale_episodes")}
        return out, state
    finally:
        shaper_mod._cshaper = saved


@settings(max_examples=300, deadline=None)
@given(events=st.lists(event, min_size=1, max_size=80), linear=st.booleans())
def test_compiled_loops_are_bit_identical(events: list[tuple], linear: bool) -> None:
    assert _run(events, True, linear) == _run(events, False, linear)


def test_a_jittery_slalom_is_bit_identical_and_extrapolated() -> None:
    """The service's common case, long enough for periods and caps to settle."""
    events: list[tuple] = []
    for k in range(3000):
        t = k / 1000.0
        jitter = 0.15 * math.sin(7.3 * k)  # ms
        events.append(("frame", 1.0 + jitter, {"rails_y": 0.25 * math.sin(2 * math.pi * 0.3 * t)
                                               ** 3, "hex_z": 0.01 * math.cos(t)},
                       -0.2 + 0.05 * math.sin(k)))
        if k % 3:
            events.append(("tick", 0.0, None, None))
    fast, slow = _run(events, True, True), _run(events, False, True)
    assert fast == slow
    refs = [r for r, _ in fast[0]]
    assert len({r[1] for r in refs}) > 1000  # it moved
    assert 0.0 < fast[1]["_period"][1] <= 0.01 and fast[1]["_slope"][1] != 0.0


def test_compiled_loops_reject_wrong_state() -> None:
    c = shaper_mod._cshaper
    five = [0.0] * 5
    with pytest.raises(TypeError, match="lists of 8 floats"):
        c.update_axes({"rails_x": 0.1}, {"rails_x": 0}, [True] * 8, 1.0, True, 0.05,
                      five, five, five, five)
    with pytest.raises(KeyError):
        eight = [0.0] * 8
        c.update_axes({"rails_z": 0.1}, {"rails_x": 0}, [True] * 8, 1.0, True, 0.05,
                      eight, eight[:], eight[:], eight[:])
    with pytest.raises(TypeError, match="live must be a list"):
        c.live_now(1.0, 0.0, 0.0, 0.02, (0.0,) * 8, [0.0] * 8, [0.0] * 8, [0.0] * 8)
    with pytest.raises(TypeError, match="lists of 8 floats"):
        c.live_now(1.0, 0.0, 0.0, 0.02, [0.0] * 8, [0.0] * 8, [0.0] * 8, [0.0] * 5)
    with pytest.raises(TypeError, match="must be real number"):
        c.live_now(1.0, "0", 0.0, 0.02, [0.0] * 8, [0.0] * 8, [0.0] * 8, [0.0] * 8)
    with pytest.raises(TypeError, match=r"live_now\(t_now, age, late"):
        c.live_now(1.0, [0.0] * 8, [0.0] * 8, [0.0] * 8, [0.0] * 8)
