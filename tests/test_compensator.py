"""The discrete pseudo open-loop compensator."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.signal import lfilter

from motcomp.core.axes import AXES
from motcomp.core.compensator import NONFINITE, Compensator, weight_duration
from motcomp.core.loop import pid_tf, stability
from motcomp.core.minjerk import PEAK_ACC_FACTOR, PEAK_DEPART_FACTOR, min_jerk
from motcomp.core.models import P1D, p1d_coefficients, simulate_axis
from motcomp.core.pid import PIDGains
from motcomp.core.saturation import AxisLimits
from motcomp.core.tuning import tune
from motcomp.design.frequency import loop_response
from motcomp.errors import ConfigError
from tests.conftest import RAILS
from tests.test_saturation import check_sequence

WIDE = AxisLimits.uniform(1, 1e6, 1e9, 1e12)


def test_hand_computed_first_samples() -> None:
    # h = 0.1 s, model K=1, Td=0, Tp1=1 -> phi = e^-0.1, g0 = 0, g1 = 1 - e^-0.1 (d = 0)
    # PI: kp = 2, ki = 10; step r = 1 from rest at 0
    m = P1D(K=1.0, Td=0.0, Tp1=1.0)
    c = Compensator([m], [PIDGains(kp=2.0, ki=10.0)], WIDE, rate_hz=10.0)
    phi, g1 = math.exp(-0.1), 1 - math.exp(-0.1)
    y, integ, expected = 0.0, 0.0, []
    for _ in range(4):
        v = 2.0 * (1.0 - y) + integ  # v = kp e + I
        expected.append(v)
        integ += 10.0 * 0.1 * (1.0 - y)  # I += ki h e
        y = phi * y + g1 * v  # model fed with v (d = 0: u[k-d] = v[k])
    got = [c.step([1.0])[0] for _ in range(4)]
    assert got == pytest.approx(expected, rel=1e-14)
    assert got[:2] == pytest.approx([2.0, 2.0 * (1 - 2 * g1) + 1.0])


def test_filtered_derivative_hand_computed() -> None:
    # PD with kd = 0.5, tf = 0.1 at h = 0.1: a_d = 0.5, b_d = 2.5; model output is 0 for the
    # first sample because Td = 0.25 s > 2 h
    m = P1D(K=1.0, Td=0.25, Tp1=1.0)
    c = Compensator([m], [PIDGains(kp=1.0, kd=0.5, tf=0.1)], WIDE, rate_hz=10.0)
    out = [c.step([1.0])[0] for _ in range(3)]
    # D[0] = 2.5 (1 - 0) = 2.5, D[1] = 0.5 D[0] = 1.25, D[2] = 0.625; model output still 0
    assert out == pytest.approx([1.0 + 2.5, 1.0 + 1.25, 1.0 + 0.625], rel=1e-14)


def test_p1d_coefficients_equal_the_generic_discretisation() -> None:
    for Td in (0.0, 0.0004, 0.001, 0.0175, 0.0203):
        m = P1D(K=1.7, Td=Td, Tp1=0.2)
        phi, g0, g1, d = p1d_coefficients(m, 1e-3)
        gen = m.discretize(1000.0)
        assert d == gen.delay_samples
        assert phi == pytest.approx(gen.phi[0, 0], rel=1e-13)
        # the generic realisation's state is y / C: compare the output-scaled input gains
        c = gen.c[0, 0]
        assert g0 == pytest.approx(c * gen.gamma0[0, 0], rel=1e-12, abs=1e-16)
        assert g1 == pytest.approx(c * gen.gamma1[0, 0], rel=1e-12, abs=1e-16)


@pytest.mark.parametrize("rule", ["zn", "cc", "amigo", "simc"])
def test_linear_response_equals_transfer_function(rule: str) -> None:
    """The kernel's recursion vs the polynomial algebra of F(z) = Cr/(1 + Cy M)."""
    g = tune(rule, RAILS).gains
    rate = 1000.0
    h = 1 / rate
    (nr, dr), (ny, _) = pid_tf(g, h)
    phi, g0, g1, d = p1d_coefficients(RAILS, h)
    nm = np.array([g0, g1])
    dm = np.concatenate([[1.0, -phi], np.zeros(d)])
    num = np.polymul(nr, dm)
    den = np.polyadd(np.polymul(dr, dm), np.polymul(ny, nm))
    rng = np.random.default_rng(1)
    r = np.cumsum(rng.normal(0, 1e-3, 3000))
    c = Compensator([RAILS], [g], WIDE, rate)
    got, _ = c.run(r[:, None])
    pad = len(den) - len(num)
    ref = lfilter(np.concatenate([np.zeros(pad), num]), den, r)
    np.testing.assert_allclose(got[:, 0], ref, atol=1e-9 * np.max(np.abs(ref)))


def test_sine_response_equals_frequency_response() -> None:
    """Gain and phase of the command for sines, measured on the kernel, vs F(e^{jwh})."""
    g = tune("zn", RAILS).gains
    rate = 1000.0
    for f in (0.5, 2.0, 15.0):
        n = 20000
        k = np.arange(n)
        r = np.sin(2 * np.pi * f * k / rate)
        c = Compensator([RAILS], [g], WIDE, rate)
        u, _ = c.run(r[:, None])
        tail = slice(n // 2, None)
        ph = 2 * np.pi * f * k / rate
        basis = np.column_stack([np.sin(ph), np.cos(ph)])
        a, b = np.linalg.lstsq(basis[tail], u[tail, 0], rcond=None)[0]
        resp = loop_response(g, RAILS, RAILS, [1e-3, f], rate).command[1]
        assert math.hypot(a, b) == pytest.approx(abs(resp), rel=1e-6)
        assert math.atan2(b, a) == pytest.approx(np.angle(resp), abs=1e-6)


def test_residual_low_frequency_lag_is_one_over_k_ki() -> None:
    g = PIDGains(kp=5.0, ki=100.0)
    c = Compensator([RAILS], [g], WIDE, 1000.0)
    t = np.arange(60000) / 1000.0
    r = 0.1 * t  # ramp: the delivered output trails by 1/(K ki) = 10 ms in steady state
    u, _ = c.run(r[:, None])
    y = simulate_axis(RAILS, u[:, 0], 1000.0)
    lag = (r[-1] - y[-1]) / 0.1
    assert lag == pytest.approx(1.0 / 100.0, rel=1e-3)


def test_start_without_kick() -> None:
    lim = AxisLimits.uniform(8, 2.0, 1.0, 5.0)
    p0 = np.linspace(-0.5, 0.5, 8)
    c = Compensator([RAILS] * 8, [tune("zn", RAILS).gains] * 8, lim, 1000.0, position=p0)
    for _ in range(200):
        out = c.step(p0)
    np.testing.assert_allclose(out, p0, atol=1e-12)
    assert c.flags == [0] * 8


def test_nonfinite_reference_is_held_and_never_propagates() -> None:
    lim = AxisLimits.uniform(2, 2.0, 1.0, 5.0)
    c = Compensator([RAILS] * 2, [tune("zn", RAILS).gains] * 2, lim, 1000.0)
    for k in range(500):
        c.step([0.1 * math.sin(k / 100), 0.0])
    before = c.state()
    out = c.step([math.nan, math.inf])
    assert all(math.isfinite(x) for x in out)
    assert c.flags[0] & NONFINITE and c.flags[1] & NONFINITE
    st_ = c.state()
    for field in ("r", "xc", "xm", "integral", "deriv", "u"):
        assert np.all(np.isfinite(getattr(st_, field)))
    assert st_.r[0] == before.r[0]  # the last finite reference is held


def test_unstable_gains_rejected_and_nothing_changes() -> None:
    lim = AxisLimits.uniform(1, 1.0, 1.0, 1.0)
    with pytest.raises(ConfigError, match="unstable at 1000 Hz"):
        Compensator([RAILS], [PIDGains(kp=0.0, kd=1.0)], lim, 1000.0)  # kd/h = 1000
    c = Compensator([RAILS], [tune("zn", RAILS).gains], lim, 1000.0)
    before = c.gains
    with pytest.raises(ConfigError, match="largest pole modulus"):
        c.set_gains([PIDGains(kp=200.0, ki=10.0)])
    assert c.gains == before
    # and the verdict agrees with a simulation: the rejected loop diverges, the kept one not
    h = 1e-3
    for g, diverges in ((PIDGains(kp=200.0, ki=10.0), True), (before[0], False)):
        (nr, dr), (ny, _) = pid_tf(g, h)
        from motcomp.core.loop import model_tf
        nm, dm = model_tf(RAILS, h)
        den = np.polyadd(np.polymul(dr, dm), np.polymul(ny, nm))
        num = np.polymul(nr, dm)
        with np.errstate(all="ignore"):
            u = lfilter(np.concatenate([np.zeros(len(den) - len(num)), num]), den, np.ones(2000))
        tail = np.abs(u[-100:])
        assert bool(np.any(~np.isfinite(tail)) or np.max(tail) > 1e6) == diverges


def test_bad_construction_rejected() -> None:
    lim = AxisLimits.uniform(1, 1.0, 1.0, 1.0)
    g = PIDGains(kp=1.0)
    for rate in (0.0, -1000.0, math.nan, math.inf):
        with pytest.raises(ConfigError, match="rate"):
            Compensator([RAILS], [g], lim, rate)
    with pytest.raises(ConfigError, match="2 gain sets for 1 axes"):
        Compensator([RAILS], [g, g], lim, 1000.0)
    with pytest.raises(ConfigError, match="must be P1D"):
        from motcomp.core.models import P2D
        Compensator([P2D(K=1, Td=0.01, Tp1=0.1, Tp2=0.01)], [g], lim, 1000.0)  # type: ignore[list-item]


def _rails_limits(n: int = 1) -> AxisLimits:
    return AxisLimits(np.full(n, -2.6), np.full(n, 2.6), np.full(n, 2.0), np.full(n, 6.0))


def test_saturated_step_settles_without_limit_cycle() -> None:
    """ZN asks ~90x a step at onset; with model-recovery anti-windup the loop stays linear and
    the output settles on the reference (back-calculation limit-cycles here)."""
    c = Compensator([RAILS], [tune("zn", RAILS).gains], _rails_limits(), 1000.0)
    out = np.array([c.step([0.5])[0] for _ in range(4000)])
    check_sequence(out, 0.0, _rails_limits(), 1e-3)
    assert out.max() < 0.52  # no overshoot worth the name (the raw command asks 45 m)
    assert np.all(np.abs(out[-1000:] - 0.5) < 1e-6)
    y = simulate_axis(RAILS, out, 1000.0)
    assert abs(y[-1] - 0.5) < 1e-3


def test_model_output_mirrors_what_the_platform_receives() -> None:
    c = Compensator([RAILS], [tune("zn", RAILS).gains], _rails_limits(), 1000.0)
    rng = np.random.default_rng(3)
    r = np.repeat(rng.uniform(-1, 1, 40), 100)  # saturating steps
    mirror, cmds = [], []
    for x in r:
        cmds.append(c.step([x])[0])
        mirror.append(c.model_output[0])
    # the mirror after step k is the model's output at k+1 for the commands sent
    y = simulate_axis(RAILS, np.array([*cmds, cmds[-1]]), 1000.0, initial=0.0)
    np.testing.assert_allclose(mirror, y[1:], atol=1e-9)


@settings(max_examples=80, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1), rule=st.sampled_from(["zn", "cc", "amigo", "simc"]),
    fkp=st.floats(0.1, 1.5), fki=st.floats(0.0, 1.5), fkd=st.floats(0.0, 1.5),
    td=st.floats(0.001, 0.05), tp1=st.floats(0.01, 1.0),
    p=st.floats(0.05, 3.0), v=st.floats(0.05, 5.0), a=st.floats(0.5, 50.0),
    scale=st.floats(0.01, 10.0), bypass_at=st.integers(0, 600),
)
def test_output_always_within_limits_and_finite(seed: int, rule: str, fkp: float, fki: float,
                                                fkd: float, td: float, tp1: float, p: float,
                                                v: float, a: float, scale: float,
                                                bypass_at: int) -> None:
    """Gains are a rule's gains scaled at random (most loops stable, some not)."""
    base = tune(rule, P1D(K=1.0, Td=td, Tp1=tp1)).gains
    kp, ki, kd, tf = base.kp * fkp, base.ki * fki, base.kd * fkd, base.tf
    rng = np.random.default_rng(seed)
    n = 3
    lim = AxisLimits(np.full(n, -p), np.full(n, p), np.full(n, v), np.full(n, a))
    m = P1D(K=1.0, Td=td, Tp1=tp1)
    g = PIDGains(kp=kp, ki=ki, kd=kd, tf=tf)
    g2 = PIDGains(kp=kp / 2, ki=ki, kd=kd, tf=tf)
    if not (stability(g, m, 1000.0)[0] and stability(g2, m, 1000.0)[0]):
        with pytest.raises(ConfigError, match="unstable"):
            Compensator([m] * n, [g] * n, lim, 1000.0)
            Compensator([m] * n, [g2] * n, lim, 1000.0)
        return
    c = Compensator([m] * n, [g] * n, lim, 1000.0)
    kind = rng.integers(0, 3)
    if kind == 0:
        r = rng.normal(0, scale, (800, n))
    elif kind == 1:
        r = np.repeat(rng.uniform(-scale, scale, (8, n)), 100, axis=0)
    else:
        r = scale * np.sin(np.arange(800)[:, None] * rng.uniform(0.001, 0.5, n))
    r[rng.integers(0, 800, 5), rng.integers(0, n, 5)] = np.nan
    out = np.empty_like(r)
    for k in range(r.shape[0]):
        if k == bypass_at:
            c.set_bypass([True, False, True])
        if k == bypass_at + 150:
            c.set_gains([g2] * n)
            c.set_bypass([False] * n)
        out[k] = c.step(r[k])
    for i in range(n):
        check_sequence(out[:, i], 0.0, lim, 1e-3, i)


def _mid_motion(rule: str = "zn") -> tuple[Compensator, np.ndarray]:
    lim = _rails_limits()
    c = Compensator([RAILS], [tune(rule, RAILS).gains], lim, 1000.0)
    t = np.arange(8000) / 1000.0
    r = 0.4 * np.sin(2 * np.pi * 0.3 * t) ** 3
    return c, r


@pytest.mark.parametrize(("rule_from", "rule_to"), [("amigo", "zn"), ("zn", "amigo"),
                                                    ("amigo", "simc")])
@pytest.mark.parametrize("switch_s", [3.0, 3.5, 4.1, 4.6, 5.2])
def test_a_gain_change_blends_the_command_onto_the_new_gains_path(
        rule_from: str, rule_to: str, switch_s: float) -> None:
    """New gains in mid-slalom, the rails at full speed: the command leaves the old gains' path
    with its position and velocity and joins the path the new gains would have made all along,
    without meeting its acceleration limit and with its acceleration changing by less than
    0.1 m/s^2 a tick.  (Matching the raw output's level alone, the switch to ZN's gains rode
    the 6 m/s^2 limit for 200-230 ticks, 12 m/s^2 a tick from one sign to the other: the new
    loop's transient from a state the old gains had made.)"""
    t = np.arange(9000) / 1000.0
    r = 0.4 * np.sin(2 * np.pi * 0.31 * t) * min_jerk(np.minimum(t / 2.0, 1.0))
    old, new = [tune(rule_from, RAILS).gains], [tune(rule_to, RAILS).gains]
    c = Compensator([RAILS], old, _rails_limits(), 1000.0)
    before = Compensator([RAILS], old, _rails_limits(), 1000.0)
    after = Compensator([RAILS], new, _rails_limits(), 1000.0)
    at = round(switch_s * 1000)
    out, u_old, u_new, raw_gap = [], [], [], []
    for k, x in enumerate(r):
        if k == at:
            c.set_gains(new)
            assert c.gains == tuple(new)
        out.append(c.step([x])[0])
        u_old.append(before.step([x])[0])
        u_new.append(after.step([x])[0])
        raw_gap.append(abs(c.raw_output[0] - after.raw_output[0]))
    u, u0, u1 = np.array(out), np.array(u_old), np.array(u_new)
    # from the first step after the change the PID's output is that of the gains that ran all
    # along, but for what is left of the re-run's start on a curved reference (0.1 mm at most
    # here), which dies out
    assert max(raw_gap[at:]) < 2e-4 and max(raw_gap[at + 2000:]) < 1e-10
    np.testing.assert_array_equal(u[:at], u0[:at])
    acc = np.diff(u[at - 5:], 2) * 1e6
    assert np.abs(acc).max() < 0.9 * 6.0
    assert np.abs(np.diff(acc)).max() < 0.1
    # on the new gains' path once the blend is over (what is left of the re-run's start)
    assert np.abs(u[at + 2000:] - u1[at + 2000:]).max() < 1e-9
    assert np.abs(u0[at:] - u1[at:]).max() > 1e-3  # two paths apart: the blend did something


@pytest.mark.parametrize(("rule_from", "rule_to"), [("amigo", "zn"), ("zn", "simc")])
def test_a_gain_change_on_a_ramp_takes_the_new_gains_steady_state_exactly(
        rule_from: str, rule_to: str) -> None:
    """On a ramp the re-run starts from the new loop's steady state, in closed form, and
    steps the tick's own recurrence: the PID's output after the change is, to rounding, that of
    a compensator that ran the new gains all along (a wrong closed form or a recurrence that
    departs from the step's would leave a transient of the loop's own)."""
    wide = AxisLimits.uniform(1, 1e6, 1e9, 1e12)
    old, new = [tune(rule_from, RAILS).gains], [tune(rule_to, RAILS).gains]
    c = Compensator([RAILS], old, wide, 1000.0, history_s=0.5)
    ref = Compensator([RAILS], new, wide, 1000.0, history_s=0.5)
    ramp = 0.01 + 0.3e-3 * np.arange(6000)  # 0.3 m/s
    for k, x in enumerate(ramp):
        if k == 5000:
            c.set_gains(new)
        c.step([x])
        ref.step([x])
        if k >= 5000:
            assert c.raw_output[0] == pytest.approx(ref.raw_output[0], abs=1e-12), k


def test_a_model_change_in_an_input_loss_window_keeps_the_held_raw_output() -> None:
    """In a window the target is the reference and the PID started over at rest there: a new
    model or new gains keep its raw output (the integrator re-seeded), so the path the command
    returns to at the rejoin starts where the PID stood."""
    c, r = _mid_motion("amigo")
    for x in r[:3000]:
        c.step([x])
    held = float(r[2999])
    c.open_window([True], [held], [0.5])
    for _ in range(50):
        c.step([held])
    raw = c.raw_output[0]
    model = P1D(K=1.0, Td=0.02, Tp1=0.15)
    c.reconfigure([model], [tune("zn", model).gains])
    assert c._virtual_raw()[0] == pytest.approx(raw, abs=1e-12)
    c.step([held])
    assert c.raw_output[0] == pytest.approx(held, abs=1e-6)


def test_bumpless_bypass_on_and_off() -> None:
    c, r = _mid_motion()
    out, moving = [], []
    for k, x in enumerate(r):
        if k == 3000:
            c.set_bypass([True])
        if k == 6000:
            c.set_bypass([False])
        out.append(c.step([x])[0])
        moving.append(c.moving)
    out_a = np.array(out)
    # ``moving`` says the blends: one stretch from each switch's step on, as long as the fade
    # at least (longer for a larger gap), and nothing else
    on = np.flatnonzero(moving)
    first, second = on[on < 6000], on[on >= 6000]
    assert first[0] == 3000 and second[0] == 6000
    assert np.all(np.diff(first) == 1) and np.all(np.diff(second) == 1)
    assert first.size >= round(c.fade_s * 1000) and second.size >= round(c.fade_s * 1000)
    d = np.abs(np.diff(out_a))
    normal = np.max(d[2000:2990])
    assert d[2999] <= 2 * normal and d[5999] <= 2 * normal
    check_sequence(out_a, 0.0, _rails_limits(), 1e-3)
    # once the switch's blend is over, bypass sends the reference itself
    np.testing.assert_array_equal(out_a[5200:5990], r[5200:5990])


@pytest.mark.parametrize("rule", ["zn", "amigo"])
@pytest.mark.parametrize("switch_s", [3.0, 3.5, 4.1, 4.6, 5.2])
def test_switching_compensation_blends_the_command_alone(rule: str, switch_s: float) -> None:
    """Bypass on at ``switch_s`` into a slalom (once the compensated start is over), off again
    2.5 s later, the rails at full speed:
    the PID runs on all along, so once the blend back has ended the command is the never
    bypassed compensator's, bit for bit, and in bypass the reference, bit for bit; meanwhile
    the command never meets its acceleration limit and its acceleration changes by less than
    0.2 m/s^2 a tick (each switch used to hold it at the limit, 2-67 ticks switching off and
    680-900 switching on, with steps of 7-12 m/s^2 a tick)."""
    t = np.arange(11000) / 1000.0
    r = 0.4 * np.sin(2 * np.pi * 0.31 * t) * min_jerk(np.minimum(t / 2.0, 1.0))
    gains = [tune(rule, RAILS).gains]
    ref_c = Compensator([RAILS], gains, _rails_limits(), 1000.0)
    c = Compensator([RAILS], gains, _rails_limits(), 1000.0)
    on, off = round(switch_s * 1000), round((switch_s + 2.5) * 1000)
    never, out = [], []
    for k, x in enumerate(r):
        if k == on:
            c.set_bypass([True])
        if k == off:
            c.set_bypass([False])
        never.append(ref_c.step([x])[0])
        out.append(c.step([x])[0])
    u, u0 = np.array(out), np.array(never)
    np.testing.assert_array_equal(u[:on], u0[:on])
    acc = np.diff(u[on - 5:], 2) * 1e6
    assert np.abs(acc).max() < 0.9 * 6.0
    assert np.abs(np.diff(acc)).max() < 0.2
    np.testing.assert_array_equal(u[off + 2000:], u0[off + 2000:])
    np.testing.assert_array_equal(u[on + 2000:off], r[on + 2000:off])
    assert np.abs(np.diff(u0[on:], 2) * 1e6).max() < 0.9 * 6.0  # the compensated path's


def test_eight_axes_are_independent() -> None:
    gains = [tune("zn", RAILS).gains] * 8
    lim = AxisLimits.uniform(8, 2.6, 2.0, 6.0)
    multi = Compensator([RAILS] * 8, gains, lim, 1000.0)
    t = np.arange(2000) / 1000.0
    refs = np.stack([0.1 * (i + 1) * np.sin(2 * np.pi * 0.4 * t) ** 3 for i in range(8)], axis=1)
    out, _ = multi.run(refs)
    for i in (0, 5):
        single = Compensator([RAILS], gains[:1], AxisLimits.uniform(1, 2.6, 2.0, 6.0), 1000.0)
        np.testing.assert_array_equal(single.run(refs[:, i:i + 1])[0][:, 0], out[:, i])
    assert len(AXES) == 8


@pytest.mark.parametrize("stop_s", [3.0, 3.4, 3.8, 4.2])
def test_an_input_loss_starts_the_pid_over_at_rest_at_the_held_reference(stop_s: float) -> None:
    """The input lost mid-slalom (the window opened on the held reference, which then stays):
    the PID's output is the held reference from the first tick on, so that the compensated
    path the command returns to is the one of the reference since the loss, not the PID's
    response to the step the hold made of the motion (that swung by 40-130 mm, at tens of
    m/s^2, and leaked through the weight when the input came back)."""
    t = np.arange(round(stop_s * 1000)) / 1000.0
    r = 0.4 * np.sin(2 * np.pi * 0.31 * t) * min_jerk(np.minimum(t / 2.0, 1.0))
    c = Compensator([RAILS], [tune("zn", RAILS).gains], _rails_limits(), 1000.0)
    for x in r:
        c.step([x])
    held = float(r[-1])
    c.open_window([True], [held], [0.5])
    raw = []
    for _ in range(300):
        c.step([held])
        raw.append(float(c.raw_output[0]))
    assert np.abs(np.array(raw) - held).max() <= 1e-12


@pytest.mark.parametrize(("gap", "rate", "acc"), [(0.01, 0.0, 1.5), (0.0, 0.2, 1.5),
                                                  (-0.05, 0.3, 1.5), (0.002, -0.7, 3.0)])
def test_weight_duration_bounds_the_acceleration_the_weight_adds(gap: float, rate: float,
                                                                 acc: float) -> None:
    """A minimum-jerk weight over :func:`weight_duration` moving a target from a path to one
    ``gap`` away and departing at ``rate``: the acceleration it adds, ``(w (gap + rate t))''``
    on a fine grid, stays within ``acc``, and reaches it for either alone (the bound sums
    the two peaks); the duration solves its closed form; paths that meet at rest: 0."""
    T = weight_duration(gap, rate, acc)
    assert PEAK_ACC_FACTOR * abs(gap) / T**2 + PEAK_DEPART_FACTOR * abs(rate) / T \
        == pytest.approx(acc, rel=1e-12)
    s = np.linspace(0.0, 1.0, 20001)
    w = np.polynomial.Polynomial([0, 0, 0, 10, -15, 6])  # minimum-jerk weight in s
    d = np.polynomial.Polynomial([gap, rate * T])  # the paths' difference, in s
    added = (w * d).deriv(2)(s) / T**2
    assert np.abs(added).max() <= acc
    assert np.abs(added).max() > (0.999 if gap == 0.0 or rate == 0.0 else 0.5) * acc
    assert weight_duration(0.0, 0.0, acc) == 0.0
