"""The path to rest after an input loss (:mod:`motcomp.core.tick`, the input-loss window), as a
property over random stop instants and speeds of a slalom-like motion, the tick run offline
with encoded frames (a 1 kHz sender stamping ``t``).

Axes: rails_y compensated (the example config as is), rails_x bypassed (``bypass = true``
added), hex_z predicted with its PID bypassed (the example's).  When the input is declared
stale, with the command at ``p`` moving at ``v`` (``s`` the sign of ``v``), for every later
tick of the episode::

    s (u - p) <= max(v^2 / (2 a_max), max over the references r since then of s (r - p)) + SLACK

(the braking distance, widened only by the ramp to neutral); every command within the axis'
limits from the start of the run
(:func:`tests.test_saturation.check_sequence`); the axis at neutral, at rest, at the end of the
ramp.  The hold then the ramp: until ``hold_s`` after
``stale``, once braked (its velocity no longer the way it went) the command only comes back
to the held reference (no ramp before ``hold_s``); its speed stays within the ramp's peak speed
(``ramp_speed_fraction x vel_max``), or within braking at ``a_max`` from its speed at the stale
instant while above it.  An axis back on the held reference when the hold ends follows the ramp
to neutral as it is (its acceleration within the ramp's, a quarter of ``a_max``): the window
takes in the ramp's reach where the command follows the ramp, so its edge never brakes it (it
did, at up to ``a_max`` for 10-45 ms, when it took in only the reference itself); a command
catching the ramp keeps the edge at the reference (with the reach it passed the ramp by 6.5 um:
the parking example below).

On the previous behaviour (no window) the travel bound fails for the compensated rails_y: on 14
stops (speeds 0.8-1.2, stops at 3.7-8.05 s) it ran 0.015-0.107 m beyond the bound, its speed
after the stop up to 1.21 m/s where the ramp's is 0.5 (the bypassed and predicted axes met the
bound on these stops); :func:`test_without_the_window_the_bound_fails` pins one of them.  Parking
requested mid-slalom (:func:`test_parking_mid_motion_is_bounded_alike`) failed it likewise
(rails_y 0.054 m beyond the bound, parking at 8.05 s).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable
from functools import cache

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from motcomp.config import ServiceConfig, new_tick, parse_config, read_toml
from motcomp.core import tick as tick_mod
from motcomp.core.axes import AXES
from motcomp.core.tick import TickParams, TickState, park, step
from motcomp.io.wire import encode_input
from tests.conftest import ran_in_plain_python
from tests.test_saturation import check_sequence
from tests.test_tick import EXAMPLE, MS, H

RY, RX, HZ = (AXES.index(a) for a in ("rails_y", "rails_x", "hex_z"))
SLACK = 1e-9
"""Travel beyond the bound allowed (m): rounding of the limiter's arithmetic."""
MOVE_SHARE = 1.0
"""Motion away from the held reference allowed during the hold, per tick, in ``a_max h^2``: the
limiter catches a target it approached with a step that it may overshoot by up to that much the
tick after (then passes it exactly)."""
RAMP_SPEED_TOL = 1e-6
"""Speed allowed beyond the ramp's peak speed once braked (fraction of it): rounding."""
SNAP_EVERY = 50
"""Live ticks between two snapshots of the tick state (each example starts from one)."""
FIRST_STOP_S, LAST_STOP_S = 3.0, 8.0
AFTER_S = 3.3
"""Ticks run after the stop: stale, hold and the longest ramp (0.6 m at 0.5 m/s, 2.25 s)."""


@cache
def config() -> ServiceConfig:
    """The example config, rails_x bypassed."""
    data = read_toml(EXAMPLE)
    data["axes"]["rails_x"]["bypass"] = True
    return parse_config(data)


def motion(k: int, speed: float) -> dict[str, float]:
    """The slalom-like sender at tick ``k``, amplitudes rising over 2 s; ``speed`` scales the
    rails' frequency (1: 0.31 Hz, 0.5 m: about 1 m/s at the centre line)."""
    t = k * H
    env = min(t / 2.0, 1.0)
    env = env * env * (3.0 - 2.0 * env)
    f = 0.31 * speed
    return {"rails_y": 0.5 * env * math.sin(2 * math.pi * f * t),
            "rails_x": 0.4 * env * math.sin(2 * math.pi * 0.8 * f * t + 1.0),
            "hex_z": 0.1 * env * math.sin(2 * math.pi * 0.5 * speed * t)}


Snapshot = tuple[int, TickState, list[list[float]]]


@cache
def live_run(speed: float) -> tuple[TickParams, list[Snapshot]]:
    """The live motion up to LAST_STOP_S, a deep copy of the tick state (and the outputs so
    far) every SNAP_EVERY ticks from FIRST_STOP_S."""
    params, state = new_tick(config())
    outs: list[list[float]] = []
    snaps: list[Snapshot] = []
    first = round(FIRST_STOP_S / H)
    for k in range(round(LAST_STOP_S / H) + 1):
        if k >= first and (k - first) % SNAP_EVERY == 0:
            snaps.append((k, copy.deepcopy(state), list(outs)))
        outs.append(step(state, params, k * MS, encode_input(k, k * H, motion(k, speed))).u)
    return params, snaps


@dataclasses.dataclass
class Episode:
    u: np.ndarray
    """Every command of the run (ticks x axes)."""
    ref: np.ndarray
    """The shaper's reference after the stop."""
    k_stale: int
    """Index in :attr:`u` of the first stale tick; ``ref[0]`` is its reference."""
    state: TickState
    params: TickParams


def stop_at(speed: float, stop_s: float, parking: bool = False) -> Episode:
    """The sender stops at ``stop_s`` (or goes on, and parking is requested then); the tick
    runs on for AFTER_S."""
    params, snaps = live_run(speed)
    k_stop = round(stop_s / H)
    j = min((k_stop - snaps[0][0]) // SNAP_EVERY, len(snaps) - 1)
    k_snap, snap, head = snaps[j]
    state = copy.deepcopy(snap)
    outs = list(head)
    for k in range(k_snap, k_stop):
        outs.append(step(state, params, k * MS, encode_input(k, k * H, motion(k, speed))).u)
    k_stale = None
    refs = []
    lost = "stale"
    if parking:
        park(state, params, k_stop * MS)
        lost = "parking"
    for k in range(k_stop, k_stop + round(AFTER_S / H)):
        frame = encode_input(k, k * H, motion(k, speed)) if parking else None
        o = step(state, params, k * MS, frame)
        outs.append(o.u)
        if k_stale is None and o.mode == lost:
            k_stale = len(outs) - 1
        if k_stale is not None:
            refs.append(list(state.shaper.ref))
    assert k_stale is not None
    return Episode(np.array(outs), np.array(refs), k_stale, state, params)


def excess_travel(ep: Episode, i: int) -> tuple[float, float]:
    """``(worst travel beyond the bound, the braking distance)`` of axis ``i``: the bound is
    the braking distance from the command's state when the input was declared stale, widened by
    the references played since."""
    u = ep.u[:, i]
    k = ep.k_stale
    p, v = u[k - 1], (u[k - 1] - u[k - 2]) / H
    braking = v * v / (2.0 * ep.state.comp.limits.a_max[i])
    s = 1.0 if v >= 0.0 else -1.0
    reach = np.maximum(np.maximum.accumulate(s * (ep.ref[:, i] - p)), braking)
    return float(np.max(s * (u[k:] - p) - reach)), braking


def assert_path_to_rest(ep: Episode, i: int, hold: bool = True) -> float:
    """The property of the module docstring for axis ``i`` (without the hold: parking);
    returns the worst excess travel."""
    excess, _ = excess_travel(ep, i)
    assert excess <= SLACK, f"{AXES[i]}: {excess:.6f} m beyond the bound"
    u = ep.u[:, i]
    check_sequence(u, 0.0, ep.state.comp.limits, H, i)
    assert abs(u[-1]) < 1e-9 and abs(u[-1] - u[-2]) < 1e-12, \
        f"{AXES[i]}: not at rest at neutral after the ramp ({u[-1]})"
    sp = ep.params.shaper
    k = ep.k_stale
    k_hold = k + round(sp.hold_s / H) - 1  # the last tick of the hold
    vel = np.diff(u[k - 2:]) / H  # vel[j]: from u[k - 2 + j] to u[k - 1 + j]
    braked = k - 1 + int(np.argmax(vel[1:] * vel[0] <= 0.0))  # no speed left the way it went
    gap = np.abs(u[braked:k_hold + 1] - ep.ref[0, i])
    a_h = ep.state.comp.limits.a_max[i] * H
    assert not hold or np.all(np.diff(gap) <= MOVE_SHARE * a_h * H), \
        f"{AXES[i]}: moved away from the held reference during the hold"
    speed = np.abs(np.diff(u[k - 2:])) / H  # speed[0]: the command's at the stale instant
    cap = np.maximum(sp.ramp_speed[i], speed[0] - a_h * np.arange(speed.size))
    worst = int(np.argmax(speed[1:] - cap[1:] * (1.0 + RAMP_SPEED_TOL))) + 1
    assert speed[worst] <= cap[worst] * (1.0 + RAMP_SPEED_TOL), \
        f"{AXES[i]}: {speed[worst]:.4f} {worst} ms after stale, above the ramp's " \
        f"{sp.ramp_speed[i]} (or braking at a_max)"
    if hold and abs(u[k_hold] - ep.ref[0, i]) < 1e-9:
        # back on the held reference when the hold ends: the command follows the ramp to
        # neutral as it is, within its acceleration (the window never brakes it)
        acc = np.abs(np.diff(u[k_hold - 1:], 2)) / H**2
        assert acc.max() <= sp.blend_acc[i] * (1.0 + 1e-6), \
            f"{AXES[i]}: {acc.max():.3f} on the ramp to neutral, above its {sp.blend_acc[i]:g}"
    return excess


SPEEDS = (0.8, 1.0, 1.2)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(speed=st.sampled_from(SPEEDS), stop_s=st.floats(FIRST_STOP_S, LAST_STOP_S - 0.01))
@example(speed=1.0, stop_s=8.1 - 0.05)
@example(speed=1.0, stop_s=6.0)
@example(speed=0.8, stop_s=4.1)  # the window braked rails_x and hex_z at 0.99 and 0.91 a_max
def test_the_path_to_rest_after_an_input_loss_is_bounded(speed: float, stop_s: float) -> None:
    ep = stop_at(speed, stop_s)
    for i in (RY, RX, HZ):
        assert_path_to_rest(ep, i)


@settings(max_examples=5, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(speed=st.sampled_from(SPEEDS), stop_s=st.floats(FIRST_STOP_S, LAST_STOP_S - 0.01))
@example(speed=1.0, stop_s=8.05)
@example(speed=0.8, stop_s=5.593446496682622)  # the reach for a command catching the ramp: 6.5 um
def test_parking_mid_motion_is_bounded_alike(speed: float, stop_s: float) -> None:
    """Parking requested mid-slalom (the sender going on): the same bound, limits, speed and
    rest at neutral, without the hold."""
    ep = stop_at(speed, stop_s, parking=True)
    assert ep.state.shaper.parked
    for i in (RY, RX, HZ):
        assert_path_to_rest(ep, i, hold=False)


def test_without_the_window_the_bound_fails(monkeypatch: pytest.MonkeyPatch,
                                           request: pytest.FixtureRequest) -> None:
    """The scenario discriminates: with the window switched off (the tick exactly as before it)
    the compensated axis runs on past its braking distance by more than that distance again."""
    if ran_in_plain_python(request):
        return
    def no_window(state: TickState, sp: object, ref: object, mode: object) -> None:
        return None

    noop: Callable[..., None] = no_window
    monkeypatch.setattr(tick_mod, "_window", noop)
    live_run.cache_clear()
    try:
        ep = stop_at(1.0, 8.05)
    finally:
        live_run.cache_clear()
    excess, braking = excess_travel(ep, RY)
    assert excess > braking > 0.05


@pytest.mark.parametrize("gap_s", [0.3, 1.0])
def test_the_input_back_mid_hold_or_mid_ramp_is_taken_up_within_the_limits(gap_s: float) -> None:
    """Frames come back during the hold (0.3 s) or the ramp (1.0 s): the window is closed, the
    command stays within every axis' limits through the rejoin (compensation switching back on
    from the command being sent) and ends up where the uninterrupted run is, to within 2 mm
    (hex_z stays 1.3-1.6 mm off it after the 1 s gap, rails_x 0.4 mm: the same as without the
    window, measured; the compensated rails_y is back within 0.5 mm 2 s after the rejoin)."""
    params, snaps = live_run(1.0)
    k0, snap, head = snaps[0]
    state, ref_state = copy.deepcopy(snap), copy.deepcopy(snap)
    outs, ref_outs = list(head), list(head)
    k_stop, k_back = k0 + 500, k0 + 500 + round(gap_s / H)
    modes = set()
    for k in range(k0, k_back + 3000):
        frame = encode_input(k, k * H, motion(k, 1.0))
        o = step(state, params, k * MS, None if k_stop <= k < k_back else frame)
        outs.append(o.u)
        modes.add(o.mode)
        ref_outs.append(step(ref_state, params, k * MS, frame).u)
    assert {"stale", "rejoin"} <= modes and o.mode == ""
    assert state.comp.window == [None] * len(AXES)
    u = np.array(outs)
    for i in (RY, RX, HZ):
        check_sequence(u[:, i], 0.0, state.comp.limits, H, i)
    assert np.max(np.abs(u[-500:] - np.array(ref_outs[-500:]))) < 2e-3


PAUSE_PHASES = np.arange(6.0, 9.3, 0.25)
"""Instants (s) of a sender's pause in mid-slalom: 14 phases of the 0.3 Hz slalom."""


def sender_pause(start: float, pause_s: float) -> tuple[list[float], list[str]]:
    """The example config's tick fed a 0.4 m, 0.3 Hz rails_y slalom at 1 kHz (amplitude rising
    over 2 s) whose sender pauses ``pause_s`` from ``start``, for 3 s after it: rails_y's
    command and the tick's mode, per tick."""
    params, state = new_tick(parse_config(read_toml(EXAMPLE)))
    y = AXES.index("rails_y")
    u, modes = [], []
    for k in range(round((start + 3.0) * 1000)):
        t = k / 1000.0
        frame = None
        if not start <= t < start + pause_s:
            value = 0.4 * math.sin(2 * math.pi * 0.3 * t) * min(t / 2.0, 1.0)
            frame = encode_input(k, t, {"rails_y": value})
        out = step(state, params, 10**9 + k * MS, frame)
        u.append(out.u[y])
        modes.append(out.mode)
    return u, modes


def test_a_short_loss_never_carries_the_command_beyond_the_compensated_motion() -> None:
    """A sender stalling 62 ms in mid-slalom (the input stale for 12 ms), at 14 phases, the
    example config: the command's difference to its target when the window closes is blended
    out within half the acceleration limit, so it stays within 20 mm of the compensated
    slalom's own range (0.425 m here; 0.424-0.440 m measured, the most near a trough where the
    rejoin's blend is lengthened for its jerk; carried over a quarter of the limit it reached
    0.66 m).  The PID and the prediction start over at the loss (the PID at rest on the held
    reference, the prediction held off), so that compensation comes back on the compensated
    path of the reference since the loss, and the shaper's blend keeps its jerk within what the
    compensated command can carry: at none of the 14 phases does the command meet its
    acceleration limit after the rejoin (before, 110-401 ticks at every phase: the PID's
    response to the hold leaked through the weight; with the PID restarted but the blend sized
    for its acceleration alone, 136 and 242 ticks at two phases near a crest or a trough)."""
    at_limit = []
    for start in PAUSE_PHASES:
        u, modes = sender_pause(start, 0.062)
        assert max(abs(x) for x in u[round(start * 1000):]) < 0.425 + 0.02, start
        stale = [k for k, m in enumerate(modes) if m == "stale"]
        assert stale, start
        back = stale[0] + next(j for j, m in enumerate(modes[stale[0]:]) if m != "stale")
        acc = np.abs(np.diff(u[back - 2:], 2)) * 1e6
        at_limit.append(int(np.sum(acc >= 0.9999 * 6.0)))
    assert at_limit == [0] * len(at_limit), at_limit


def test_a_loss_of_one_deadline_keeps_the_command_on_the_compensated_motion() -> None:
    """The sender pauses 50.5 ms in mid-slalom, at 14 phases, the example config: the input is
    stale at one deadline (at two for the first few phases), and the window opens and closes
    at the next tick.  At the loss the reference changes path at once (the prediction held
    off), so the target's last value is restated on the plain reference's path: taken from the
    predicted path, the jump between the two (1.5 mm in a tick) read as the target's velocity
    at the rejoin (1.5 m/s), and the difference blended out from it carried the rails to their
    end stop, 2.6 m, from a 0.4 m slalom.  The command stays within 20 mm of the compensated
    slalom's range (0.425 m; 0.425-0.440 measured)."""
    one = 0
    for start in PAUSE_PHASES:
        u, modes = sender_pause(start, 0.0505)
        stale = modes.count("stale")
        assert 1 <= stale <= 2, (start, stale)
        one += stale == 1
        assert max(abs(x) for x in u[round(start * 1000):]) < 0.425 + 0.02, start
    assert one >= 7, one


def test_a_jump_of_the_reference_does_not_open_the_window() -> None:
    """The reach the window takes in is the ramp's motion, at most its peak speed: the jump a
    held reference beyond the range makes when the ramp starts from within it (input is taken
    up to a quarter of the range beyond the limits) is no speed.  Taken as one, it opened the
    window to the far end of the range (-2.6 m) and the window stopped nothing."""
    params, state = new_tick(config())
    comp = state.comp
    p_max = float(comp.limits.p_max[RY])
    at = [0.0] * len(AXES)
    at[RY] = p_max
    comp.reset(at)
    held = list(at)
    held[RY] = p_max + 0.1  # the held reference, beyond the range
    speed = params.shaper.ramp_speed
    comp.open_window([i == RY for i in range(len(AXES))], held, speed)
    assert comp.window[RY] == (p_max, p_max)
    comp.widen_window(at)  # the ramp starts from the reference brought within the range
    lo, hi = comp.window[RY]  # type: ignore[misc]
    step = speed[RY] * H  # one step at the ramp's peak speed and its braking at half a_max
    reach = step + step * step / (H * H * comp.limits.a_max[RY])
    assert hi == p_max and p_max - lo <= reach + 1e-12, (lo, reach)
