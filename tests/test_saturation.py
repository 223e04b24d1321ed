"""The limiter: the emitted sequence never violates position, velocity or acceleration limits."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motcomp.core.minjerk import min_jerk
from motcomp.core.saturation import ACC, POS, RECOVER, VEL, AxisLimits, Saturator
from motcomp.errors import ConfigError
from motcomp.ident.excitation import AxisRange, excitation

H = 1e-3


def check_sequence(u: np.ndarray, u0: float, lim: AxisLimits, h: float, i: int = 0) -> None:
    """Assert the limits on a sequence that starts at rest at ``u0``."""
    full = np.concatenate([[u0, u0], u])
    v = np.diff(full) / h
    a = np.diff(v) / h
    scale = max(1.0, abs(lim.p_max[i]), abs(lim.p_min[i]))
    assert np.all(np.isfinite(u))
    assert np.all(u <= lim.p_max[i] + 1e-12 * scale) and np.all(u >= lim.p_min[i] - 1e-12 * scale)
    assert np.max(np.abs(v)) <= lim.v_max[i] * (1 + 1e-9) + 1e-9 * scale / h
    assert np.max(np.abs(a)) <= lim.a_max[i] * (1 + 1e-9) + 1e-9 * scale / h**2


limits_st = st.tuples(
    st.floats(0.01, 5.0), st.floats(0.01, 5.0),  # p_max, -p_min
    st.floats(0.01, 10.0), st.floats(0.1, 100.0),  # v_max, a_max
)


@settings(max_examples=150, deadline=None)
@given(lims=limits_st, targets=st.lists(st.floats(-20, 20), min_size=1, max_size=300),
       rate=st.sampled_from([100.0, 1000.0, 2000.0]), hold=st.integers(1, 50))
def test_never_violates_limits(lims: tuple, targets: list, rate: float, hold: int) -> None:
    p_max, neg_min, v_max, a_max = lims
    lim = AxisLimits([-neg_min], [p_max], [v_max], [a_max])
    sat = Saturator(lim, 1.0 / rate)
    seq = np.repeat(targets, hold)  # piecewise-constant targets with jumps
    out = np.array([sat.step([x])[0] for x in seq])
    check_sequence(out, 0.0, lim, 1.0 / rate)


def test_feasible_target_passes_through_bit_exactly() -> None:
    lim = AxisLimits([-2.6], [2.6], [2.0], [6.0])
    sat = Saturator(lim, H)
    t = np.arange(10000) * H
    target = 0.3 * np.sin(2 * np.pi * 0.3 * t) ** 3  # starts at rest, within all limits
    out = np.array([sat.step([x])[0] for x in target])
    np.testing.assert_array_equal(out, target)
    assert sat.flags == [0]


def test_step_is_met_without_overshoot_and_holds() -> None:
    lim = AxisLimits([-2.6], [2.6], [2.0], [6.0])
    sat = Saturator(lim, H)
    out, flags = [], []
    for _ in range(3000):
        out.append(sat.step([0.5])[0])
        flags.append(sat.flags[0])
    out_a = np.array(out)
    check_sequence(out_a, 0.0, lim, H)
    assert out_a.max() <= 0.5 + 1e-5  # no overshoot beyond 10 um on 0.5 m
    assert out_a[-1] == pytest.approx(0.5, abs=1e-12)
    assert np.all(np.abs(out_a[-500:] - 0.5) < 1e-12)  # settled, no oscillation
    assert flags[0] & ACC and any(f & RECOVER for f in flags)


def test_a_smooth_target_lost_for_a_moment_is_caught_again() -> None:
    """The identification multisine (content up to 4 Hz, 3 m/s^2 at most, half the limit) held
    for 0.3 s, then blended back over 0.5 s, as the service's reference does across a stale
    input: the limiter acts from the hold and catches the target again 0.59 s after it began,
    then passes it through bit-exactly.  With the tracker's velocity alone as the wall's it
    caught it 1.02 s after (the tracker lags such a target by up to 0.04 m/s)."""
    exc = excitation("multisine", "rails_y", AxisRange(-2.6, 2.6, 2.0, 6.0), duration_s=20.0,
                     seed=0, usage=0.5)
    ref = np.asarray(exc.cmd, dtype=float)
    k0, k1, blend = 10_000, 10_300, 500
    offset = ref[k0] - ref[k1]
    ref[k0:k1] = ref[k0]
    ref[k1:k1 + blend] += offset * (1.0 - min_jerk(np.arange(blend) / blend))
    lim = AxisLimits([-2.6], [2.6], [2.0], [6.0])
    sat = Saturator(lim, H, position=[ref[0]])
    out = np.empty(ref.size)
    flags = np.empty(ref.size, dtype=int)
    for k, x in enumerate(ref.tolist()):
        out[k] = sat.step([x])[0]
        flags[k] = sat.flags[0]
    check_sequence(out, ref[0], lim, H)
    acted = np.flatnonzero(flags)
    assert acted.size and acted[0] >= k0  # nothing to do before the hold
    caught = int(acted[-1]) + 1
    assert (caught - k0) * H <= 0.8
    assert np.array_equal(out[caught:], ref[caught:])


@pytest.mark.parametrize("rise_s", [0.05, 0.08, 0.1, 0.15])
def test_a_stepping_target_is_not_overshot_by_its_wall(rise_s: float) -> None:
    """A 20 mm minimum-jerk step on the hexapod's limits (7 m/s^2) rising in 50-150 ms needs
    1.1-10x the acceleration there is.  While catching up the limiter aims at the target moving
    at the wall's velocity; when the target stops, the wall stops with it (it slows down at
    once, it speeds up by the catch-up budget a sample): the output passes the target by what
    it cannot brake of its own speed, at most 11 % of the step here.  With the wall's slowing
    down bounded by the budget too, it went on moving for 0.3 s: 29-62 % beyond the step."""
    size = 0.02
    n = round(rise_s / H)
    ref = np.concatenate([np.zeros(100), size * min_jerk(np.arange(n) / n),
                          np.full(1500, size)])
    lim = AxisLimits([-0.25], [0.25], [0.6], [7.0])
    sat = Saturator(lim, H)
    out = np.array([sat.step([x])[0] for x in ref.tolist()])
    check_sequence(out, 0.0, lim, H)
    assert out.max() <= size * 1.11
    assert out[-1] == pytest.approx(size, abs=1e-9)


def test_braking_before_the_end_stop() -> None:
    # target far beyond the range: the axis must stop at p_max without exceeding it
    lim = AxisLimits([-1.0], [1.0], [3.0], [2.0])
    sat = Saturator(lim, H)
    out = np.array([sat.step([50.0])[0] for _ in range(5000)])
    check_sequence(out, 0.0, lim, H)
    assert out[-1] == pytest.approx(1.0, abs=1e-9)
    assert POS & sat.flags[0] or out[-1] == 1.0


def test_velocity_flag() -> None:
    lim = AxisLimits([-10.0], [10.0], [0.5], [1000.0])
    sat = Saturator(lim, H)
    for _ in range(100):
        sat.step([5.0])
    assert sat.flags[0] & VEL


def test_narrowed_limits_brake_at_amax_and_do_not_teleport() -> None:
    lim = AxisLimits([-2.0], [2.0], [2.0], [5.0])
    sat = Saturator(lim, H, position=[1.5])
    sat.set_limits(AxisLimits([-1.0], [1.0], [2.0], [5.0]))
    out = np.array([sat.step([1.5])[0] for _ in range(3000)])
    steps = np.diff(np.concatenate([[1.5], out]))
    assert np.max(np.abs(steps)) <= 2.0 * H * (1 + 1e-9)  # velocity limit held
    assert out[-1] == pytest.approx(1.0, abs=1e-9)  # moved back inside, smoothly


@pytest.mark.parametrize(("kwargs", "msg"), [
    (dict(p_min=[1.0], p_max=[-1.0], v_max=[1.0], a_max=[1.0]), "inverted or empty"),
    (dict(p_min=[0.0], p_max=[0.0], v_max=[1.0], a_max=[1.0]), "inverted or empty"),
    (dict(p_min=[-1.0], p_max=[1.0], v_max=[0.0], a_max=[1.0]), "v_max must be > 0"),
    (dict(p_min=[-1.0], p_max=[math.inf], v_max=[1.0], a_max=[1.0]), "must be finite"),
])
def test_invalid_limits_rejected(kwargs: dict, msg: str) -> None:
    with pytest.raises(ConfigError, match=msg):
        AxisLimits(**kwargs, names=("rails_x",))


def test_bad_rate_and_position_rejected() -> None:
    lim = AxisLimits.uniform(1, 1.0, 1.0, 1.0)
    for dt in (0.0, -1e-3, math.nan):
        with pytest.raises(ConfigError, match="sample period"):
            Saturator(lim, dt)
    with pytest.raises(ConfigError, match="outside"):
        Saturator(lim, H, position=[2.0])
