"""The playback policy (:mod:`motcomp.core.playback`) alone, and through the shaper: how far
behind the newest sample the input is played, and how fast that settles after a start, a
resume and a stall, with frames taken by late ticks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from motcomp.core.axes import AXIS_INDEX
from motcomp.core.interp import fade_transition, pole_transition
from motcomp.core.playback import (
    BIN_S,
    DELAY_POLE_FACTOR,
    DELAY_POLES,
    MAX_DRIFT,
    OFFSET_BINS,
    SETTLE_S,
    STALL_PERIODS,
    Playback,
    median_slope,
)
from motcomp.core.shaper import ReferenceShaper, ShaperParams

Y = AXIS_INDEX["rails_y"]
LAG = 0.0017


def _params(**kw: object) -> ShaperParams:
    return ShaperParams(driven=(True,) * 8, ramp_speed=(1.0,) * 8, reach_lo=(-10.0,) * 8,
                        reach_hi=(10.0,) * 8, playback_lag_s=LAG, **kw)  # type: ignore[arg-type]


def test_the_offset_is_the_smallest_transit_while_the_clocks_agree() -> None:
    """The smallest transit of the window, whatever came since: a prompt frame is held for the
    whole window (OFFSET_BINS bins), and only then is the next smallest the offset."""
    pb = Playback()
    transits = [0.004, 0.0021, 0.0035, 0.0020, 0.0050]
    for k, tr in enumerate(transits):
        pb.on_sample(k * 1e-3, k * 1e-3 + tr, 1e-3 if k else 0.0, 1e-3)
    assert pb.offset == 0.0020
    # 2 s of frames 0.1-0.2 ms slower (the ticks that take them): the prompt one still holds
    rng = np.random.default_rng(5)
    k = 5
    while k * 1e-3 < 2.0:
        pb.on_sample(k * 1e-3, k * 1e-3 + 0.0021 + rng.uniform(0.0, 1e-4), 1e-3, 1e-3)
        k += 1
        assert pb.drift < 5e-6 and 0.0020 <= pb.offset < 0.0020 + 1e-5
    # once it has left the window (the bins after it), the smallest of the rest
    while k * 1e-3 < (OFFSET_BINS + 3) * BIN_S:
        pb.on_sample(k * 1e-3, k * 1e-3 + 0.0021 + rng.uniform(0.0, 1e-4), 1e-3, 1e-3)
        k += 1
    assert 0.0021 < pb.offset < 0.0021 + 1e-5
    assert pb.drift < 5e-6


@pytest.mark.parametrize("drift", [0.0, 3e-4, 1e-3, 2e-3])
def test_a_drifting_clock_leaks_the_offset_at_its_drift(drift: float) -> None:
    """Transits rising at ``drift`` s per s (a sender clock that slow), each frame up to a
    period late to its tick: the offset follows the rise (the drift read within 5 %, up to
    MAX_DRIFT), within 0.15 ms of the smallest transit possible (the drift's error over the
    window), and never lies above the newest frame's transit."""
    rng = np.random.default_rng(9)
    pb = Playback()
    for k in range(20000):
        now = k * 1e-3
        true = 3e-4 + drift * now
        transit = true + rng.uniform(0.0, 1e-3)
        pb.on_sample(now - transit, now, 1e-3 if k else 0.0, 1e-3)
        assert pb.offset is not None and pb.offset <= transit + 1e-12
        if now <= 5.0:
            continue
        if drift > MAX_DRIFT:
            assert pb.drift == MAX_DRIFT
        elif drift == 0.0:
            assert pb.drift < 5e-6 and 0.0 <= pb.offset - true < 1e-5
        else:
            assert pb.drift == pytest.approx(drift, rel=0.05)
            assert -1.5e-4 < pb.offset - true < 2e-5


def test_the_median_slope_is_a_closed_form() -> None:
    x = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    y = [1.0, 9.0, 1.5, 2.5, -7.0, 3.0]  # medians 1.5 and 2.5 at 1 and 4
    assert median_slope(x, y) == pytest.approx(1.0 / 3.0)
    assert median_slope([0.0], [1.0]) == 0.0 and median_slope([1.0, 1.0], [0.0, 2.0]) == 0.0


def test_frames_taken_by_a_late_tick_never_lower_the_offset() -> None:
    """A frame's arrival is the instant its tick took it (never before it landed): a tick late
    by 14 ms makes its frames' transits look longer, not shorter."""
    rng = np.random.default_rng(3)
    pb = Playback()
    true_min = 3e-4
    for k in range(3000):
        landed = k * 1e-3 + true_min + rng.uniform(0.0, 2e-4)
        late = 0.014 if 500 <= k < 520 else rng.uniform(0.0, 1e-3)  # the tick that took it
        pb.on_sample(k * 1e-3, landed + late, 1e-3 if k else 0.0, 1e-3)
        assert pb.offset is not None and pb.offset >= true_min - 1e-12


def test_the_need_is_the_spacings_quantile_and_stalls_are_left_out() -> None:
    pb = Playback()
    rng = np.random.default_rng(1)
    steps = rng.uniform(0.5e-3, 2.0e-3, 64)
    for s in steps:
        pb.on_sample(0.0, 0.0, float(s), 1.25e-3)
    assert pb.need == pytest.approx(np.sort(steps)[int(0.9 * 64)], abs=1e-15)
    before = pb.need
    pb.on_sample(0.0, 0.0, STALL_PERIODS * 1.25e-3 * 1.01, 1.25e-3)  # a stall: not spacing
    assert pb.need == before


def test_the_delay_follows_its_target_through_the_pole() -> None:
    """A step of the target: the delay meets it as ``1 - e^(-wt) sum_{k<5} (wt)^k / k!``
    (the critically damped pole of order 5), w = 9 / SETTLE_S, to rounding (the exact
    transition per tick): within 6 % after SETTLE_S, and its fourth difference -- the
    reference's jerk rate at a constant speed -- never steps at the target's step."""
    assert (DELAY_POLES, DELAY_POLE_FACTOR) == (5, 9.0)
    pb = Playback()
    pb.on_sample(0.0, 0.001, 1e-3, 1e-3)
    now = 0.001
    assert pb.step(now, 0.002) == pytest.approx(0.003, abs=1e-15)
    w = 9.0 / SETTLE_S
    ds = []
    for k in range(1, 2001):
        d = pb.step(now + k * 1e-3, 0.005)  # the target moves 3 ms
        wt = w * k * 1e-3
        expected = 0.006 - 0.003 * math.exp(-wt) * sum(wt ** i / math.factorial(i)
                                                       for i in range(5))
        assert d == pytest.approx(expected, abs=1e-12)
        ds.append(d)
        if k == round(SETTLE_S * 1e3):
            assert 0.006 - d <= 0.06 * 0.003
    assert abs(pb.step(now + 2.001, 0.005) - 0.006) < 0.003 * 0.001
    # the first ticks after the step: the delay moves as (wt)^5 / 5!, no lower power
    d5 = np.array(ds[:5]) - 0.003
    k = np.arange(1, 6)
    np.testing.assert_allclose(d5, 0.003 * (w * k * 1e-3) ** 5 / 120, rtol=0.05)


def test_the_transition_is_the_exponential_of_the_triple_pole() -> None:
    """fade_transition(dt) x its state equals the closed form of the critically damped triple
    pole at the same dt (value, rate, acceleration) from each unit initial condition."""
    from scipy.linalg import expm

    blend, dt = 0.2, 0.0137
    w = 6.0 / blend
    a = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-w**3, -3 * w * w, -3 * w]])
    np.testing.assert_allclose(np.array(fade_transition(dt, blend)).reshape(3, 3),
                               expm(a * dt), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5, 6])
def test_the_pole_transition_is_the_exponential_of_its_companion(order: int) -> None:
    """pole_transition(dt, w, n) equals expm of the companion matrix of (s + w)^n."""
    from scipy.linalg import expm

    w, dt = 9.0, 0.0137
    a = np.zeros((order, order))
    a[np.arange(order - 1), np.arange(1, order)] = 1.0
    a[-1, :] = [-math.comb(order, c) * w ** (order - c) for c in range(order)]
    np.testing.assert_allclose(np.array(pole_transition(dt, w, order)).reshape(order, order),
                               expm(a * dt), rtol=1e-11, atol=1e-11)


def _jittery_run(p: ShaperParams, seconds: float, seed: int, pauses: list[tuple[float, float]],
                 stalls: bool) -> tuple[np.ndarray, np.ndarray]:
    """A 1 kHz sender whose sample instants are its (late) wake-ups: 0.4-0.5 ms after each
    deadline, a stall of 20-30 ms every 2-4 s (no samples meanwhile), input pauses; transit
    0.1-0.4 ms; a tick every 1 ms on another clock, taking the frames that landed, late by
    0-0.3 ms and by 5-15 ms now and then.  Returns (tick instants, the shaper's lag)."""
    rng = np.random.default_rng(seed)
    sh = ReferenceShaper(8)
    base = 1.7e9
    off = 123.456  # loop clock - sender clock
    frames: list[tuple[float, float, float]] = []  # (landed on the loop clock, t, value)
    t, next_stall = 0.0, rng.uniform(2.0, 4.0)
    while t < seconds:
        if stalls and t >= next_stall:
            t += rng.uniform(0.02, 0.03)
            next_stall = t + rng.uniform(2.0, 4.0)
        if not any(a <= t < b for a, b in pauses):
            ts = t + rng.uniform(4e-4, 5e-4)
            frames.append((ts + off + rng.uniform(1e-4, 4e-4), ts, 0.3 * math.sin(1.9 * ts)))
        t = math.floor(t * 1e3 + 1.0 + 1e-9) / 1e3
    ticks, lags = [], []
    j = 0
    now = off
    for _ in range(int(seconds * 1000)):
        now += 1e-3
        late = rng.uniform(0.0, 3e-4) if rng.random() > 0.002 else rng.uniform(5e-3, 15e-3)
        taken = now + late
        while j < len(frames) and frames[j][0] <= taken:
            _, ts, v = frames[j]
            sh.on_input(p, {Y: v}, now, base + ts, 1, taken)
            j += 1
        sh.reference(p, now)
        ticks.append(now - off)
        lags.append(sh.lag_s)
    return np.array(ticks), np.array(lags)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_lag_settles_within_a_second_of_a_start_and_a_resume(seed: int) -> None:
    """Issue 36's sender: after the start and after a 4 s pause, the lag is within 0.5 ms of
    its settled value 1 s on, and a stall never moves it by more."""
    p = _params()
    ticks, lags = _jittery_run(p, 16.0, seed, [(7.0, 11.0)], stalls=True)
    settled = float(np.median(lags[(ticks > 5.0) & (ticks < 7.0)]))
    assert settled == pytest.approx(LAG, abs=1e-4)  # the sender's spacing fits in the lag
    for start in (0.0, 11.0):
        live = (ticks > start + 1.0) & (ticks < start + 5.0) & ((ticks < 7.0) | (ticks > 11.05))
        assert np.max(np.abs(lags[live] - settled)) <= 5e-4, start


def test_a_slow_sender_is_played_behind_its_spacing() -> None:
    """A 100 Hz sender's samples are 10 ms apart: the playback lags by them (and its moving
    average by 4.5 ticks), more than the configured lag."""
    p = _params()
    sh = ReferenceShaper(8)
    for k in range(3000):
        now = 1e-3 * k + 0.002
        if k % 10 == 0:
            sh.on_input(p, {Y: 0.1 * math.sin(k * 1e-3)}, now, 1e-3 * k)
        sh.reference(p, now)
    assert sh.lag_s == pytest.approx(0.010 + 0.0045, abs=1e-9)


def test_estimated_instants_leak_the_offset_at_the_most_drift_followed() -> None:
    """Frames without ``t``: the instants are the timeline's estimate, moved by each correction
    of its fit, so a low transit is not held for the window: the offset rises from it at
    MAX_DRIFT, as far as the transits since allow."""
    pb = Playback()
    pb.on_sample(0.0, 0.0005, 0.0, 1e-3, stamped=False)  # one frame 1.5 ms "early"
    for k in range(1, 3001):
        now = k * 1e-3
        pb.on_sample(now - 0.002, now, 1e-3, 1e-3, stamped=False)
        assert pb.drift == MAX_DRIFT
        assert pb.offset == pytest.approx(min(0.0005 + MAX_DRIFT * (now - 0.0005), 0.002),
                                          abs=1e-12)
