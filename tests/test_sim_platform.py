"""The simulated platform's step (:class:`~motcomp.sim.platform.PlatformSimulator`): every axis
against its continuous closed-form step response, across the setpoint history's rewinds and a
drift of delay; its hard limits axis by axis; its accelerometer across the blocks in which the
disturbance is drawn; and ``motcomp hil``'s speed limit between setpoint frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

from motcomp.core.models import P1D, P2D, P2UZD, ProcessModel
from motcomp.sim.platform import HISTORY_REWIND, Accelerometer, PlatformSimulator

RATE = 1000.0


def p1d_step(t: float, m: P1D) -> float:
    """``K e^{-Td s} / (1 + Tp1 s)``: response to a unit step at t = 0."""
    s = t - m.Td
    return 0.0 if s <= 0 else m.K * (1.0 - math.exp(-s / m.Tp1))


def p2d_step(t: float, m: P2D) -> float:
    """``K e^{-Td s} / ((1 + T1 s)(1 + T2 s))``, T1 != T2: response to a unit step."""
    s, a, b = t - m.Td, m.Tp1, m.Tp2
    if s <= 0:
        return 0.0
    return m.K * (1.0 - (a * math.exp(-s / a) - b * math.exp(-s / b)) / (a - b))


def p2uzd_step(t: float, m: P2UZD) -> float:
    """``K e^{-Td s} (1 + Tz s) / (1 + 2 Zeta Tw s + Tw^2 s^2)``, Zeta < 1: g + Tz g' for the
    step response g of the poles alone."""
    s = t - m.Td
    if s <= 0:
        return 0.0
    assert m.Tw is not None and m.Zeta is not None
    wn = 1.0 / m.Tw
    sigma, wd = m.Zeta * wn, wn * math.sqrt(1.0 - m.Zeta**2)
    g = 1.0 - math.exp(-sigma * s) * (math.cos(wd * s) + sigma / wd * math.sin(wd * s))
    dg = wn**2 / wd * math.exp(-sigma * s) * math.sin(wd * s)
    return m.K * (g + m.Tz * dg)


AXES_TRUTH: list[tuple[ProcessModel, float]] = [  # each axis' truth and its closed form
    (P1D(K=1.0, Td=0.0175, Tp1=0.1857683128), 0),   # a fractional delay (17.5 samples)
    (P1D(K=1.0, Td=0.0, Tp1=0.05), 0),               # no delay
    (P1D(K=0.8, Td=0.2493, Tp1=0.02), 0),            # near the longest delay the history holds
    (P2D(K=1.0, Td=0.0123, Tp1=0.05, Tp2=0.02), 1),
    (P2D(K=1.2, Td=0.001, Tp1=0.3, Tp2=0.011), 1),
    (P2UZD(K=1.0, Td=0.0301, Tz=0.01, Tw=0.04, Zeta=0.3), 2),
    (P2UZD(K=1.0, Td=0.0035, Tz=-0.02, Tw=0.06, Zeta=0.7), 2),
    (P1D(K=1.0, Td=0.0005, Tp1=0.001), 0),           # faster than the period
]
CLOSED = (p1d_step, p2d_step, p2uzd_step)


def closed_form(i: int, t: float) -> float:
    model, kind = AXES_TRUTH[i]
    return float(CLOSED[kind](t, model))  # type: ignore[operator]


def simulator(accelerometer: Accelerometer | None = None, seed: int = 0) -> PlatformSimulator:
    n = len(AXES_TRUTH)
    return PlatformSimulator([m for m, _ in AXES_TRUTH], RATE, np.full(n, -10.0),
                             np.full(n, 10.0), accelerometer=accelerometer or Accelerometer(),
                             seed=seed)


def test_every_axis_follows_its_closed_form_step_response_across_the_history_rewinds() -> None:
    """Each axis steps at its own period, some just before the history buffer moves (every
    :data:`HISTORY_REWIND` periods), so that their delayed setpoints are read across the move;
    the position at the end of every period is the continuous response at that instant (ZOH:
    the discretisation is exact).  The acceleration is the positions' second difference."""
    n = len(AXES_TRUTH)
    sim = simulator()
    starts = [5, 40, HISTORY_REWIND - 120, HISTORY_REWIND - 3, HISTORY_REWIND + 1,
              2 * HISTORY_REWIND - 200, 777, HISTORY_REWIND - 1]
    amps = [0.5, -1.0, 2.0, 1.5, -0.7, 1.0, 0.3, 1.0]
    periods = 2 * HISTORY_REWIND + 400
    ys = np.empty((periods, n))
    accs = np.empty((periods, n))
    for k in range(periods):
        u = [a if k >= k0 else 0.0 for a, k0 in zip(amps, starts, strict=True)]
        y, acc, violated = sim.step(u)
        assert not violated.any()
        ys[k], accs[k] = y, acc
    for i in range(n):
        t = (np.arange(periods) + 1 - starts[i]) / RATE  # the end of period k, from the step
        expected = np.array([amps[i] * closed_form(i, float(ti)) for ti in t])
        assert np.abs(ys[:, i] - expected).max() <= 1e-9 * abs(amps[i]), i
    # the acceleration reported at step k is the second difference centred on its start
    second = (ys[2:] - 2 * ys[1:-1] + ys[:-2]) * RATE**2
    assert np.allclose(accs[2:], second, rtol=0, atol=1e-6)
    assert sim.violations.tolist() == [0] * n


def test_a_drift_of_delay_keeps_the_setpoints_held_before_it() -> None:
    """The first axis' delay grows from 17.5 ms to 230 ms 100 ms after a step, across a rewind
    of the history: the output decays from where it was (the new delay reaches back before the
    step) and then rises as the step arrives through the new delay -- the closed form of a
    history that was kept."""
    sim = simulator()
    for _ in range(HISTORY_REWIND - 50):
        sim.step([0.0] * len(AXES_TRUTH))
    for _ in range(100):
        sim.step([1.0] + [0.0] * 7)
    first = P1D(K=1.0, Td=0.0175, Tp1=0.1857683128)
    later = P1D(K=1.0, Td=0.23, Tp1=0.1857683128)
    y_before = sim.position[0]
    assert y_before == pytest.approx(p1d_step(100 / RATE, first), abs=1e-9)
    sim.set_model(0, later)
    out = np.array([sim.step([1.0] + [0.0] * 7)[0][0] for _ in range(400)])
    j = np.arange(1, 401)
    expected = y_before * np.exp(-j / (RATE * later.Tp1)) + np.array(
        [p1d_step((100 + i) / RATE, later) for i in j])
    assert np.abs(out - expected).max() <= 1e-9
    assert out[128] < y_before - 0.15 and out[-1] > y_before + 0.3


def test_hard_limits_clamp_and_count_only_the_axes_that_break_them() -> None:
    """A setpoint beyond an axis' hard limit is clamped and counted on that axis alone; a
    non-finite one is held at the last setpoint and counted on its axis alone, in the same
    period as another axis' limit."""
    n = len(AXES_TRUTH)
    sim = PlatformSimulator([P1D(K=1.0, Td=0.0, Tp1=0.001)] * n, RATE, np.full(n, -1.0),
                            np.full(n, 1.0))
    sim.step([0.5] * n)
    _, _, v = sim.step([0.5, 3.0, 0.5, -2.0, 0.5, 0.5, 0.5, 0.5])
    assert v.tolist() == [False, True, False, True, False, False, False, False]
    _, _, v = sim.step([math.nan, 0.5, 0.5, 0.5, -1.5, math.inf, 0.5, 0.5])
    assert v.tolist() == [True, False, False, False, True, True, False, False]
    assert sim.violations.tolist() == [1, 1, 0, 1, 1, 1, 0, 0]
    for _ in range(50):  # the held and clamped setpoints are what the axes settle to
        y, _, _ = sim.step([math.nan, 3.0, 0.5, -2.0, -1.5, math.inf, 0.5, 0.5])
    assert y == pytest.approx([0.5, 1.0, 0.5, -1.0, -1.0, 0.5, 0.5, 0.5], abs=1e-12)


def test_the_accelerometer_s_disturbance_runs_on_across_its_blocks() -> None:
    """At rest, with a tremor line alone, the measurement is the line: its amplitude within
    its +-20 % modulation and no jump between samples anywhere -- including where a new block
    of the disturbance is drawn -- larger than the line's own slope allows."""
    amp, hz = 0.03, 14.0
    sim = simulator(Accelerometer(tremor_hz=hz, tremor_amp=amp), seed=7)
    acc = np.array([sim.step([0.0] * len(AXES_TRUTH))[1] for _ in range(3500)])
    assert np.abs(acc).max() <= 1.2 * amp + 1e-12
    assert np.abs(acc).max(axis=0).min() >= 0.8 * amp
    jump = np.abs(np.diff(acc, axis=0)).max()
    # the line's slope at most 1.2 amp w per s; its phase walks by 0.5 N(0, 1/sqrt(rate))
    assert jump <= 1.2 * amp * (2 * math.pi * hz / RATE + 0.5 * 4 / math.sqrt(RATE)), jump


def test_the_accelerometer_s_noise_bias_and_quantum() -> None:
    """A still platform's measurement: mean the bias, spread the noise, every value a multiple
    of the quantum."""
    sensor = Accelerometer(noise_std=0.05, bias=0.02, lsb=0.001)
    sim = simulator(sensor, seed=3)
    acc = np.array([sim.step([0.0] * len(AXES_TRUTH))[1] for _ in range(4000)])
    assert np.abs(acc.mean(axis=0) - 0.02).max() < 4 * 0.05 / math.sqrt(4000)
    assert np.allclose(acc.std(axis=0), 0.05, rtol=0.06)
    q = acc / 0.001
    assert np.abs(q - np.round(q)).max() < 1e-6


def test_a_block_measured_at_once_has_the_same_imperfections() -> None:
    """``Accelerometer.apply`` (recordings made offline) measures a block as the platform's
    stream does sample by sample: the bias as mean, the noise as spread, the quantum, and the
    tremor line within its +-20 % modulation; a 2-D block's columns are separate axes."""
    rng = np.random.default_rng(5)
    acc = Accelerometer(noise_std=0.05, bias=0.02, lsb=0.001).apply(np.zeros((4000, 3)),
                                                                     RATE, rng)
    assert acc.shape == (4000, 3)
    assert np.abs(acc.mean(axis=0) - 0.02).max() < 4 * 0.05 / math.sqrt(4000)
    assert np.allclose(acc.std(axis=0), 0.05, rtol=0.06)
    assert np.abs(acc / 0.001 - np.round(acc / 0.001)).max() < 1e-6
    assert abs(np.corrcoef(acc[:, 0], acc[:, 1])[0, 1]) < 0.1  # independent axes
    amp = 0.03
    line = Accelerometer(tremor_hz=14.0, tremor_amp=amp).apply(np.zeros(3500), RATE, rng)
    assert line.shape == (3500,)
    assert 0.8 * amp <= np.abs(line).max() <= 1.2 * amp + 1e-12
    assert Accelerometer().apply(np.zeros(0), RATE, rng).shape == (0,)


def test_the_platform_judges_its_speed_limit_between_frames_at_their_own_times() -> None:
    """``motcomp hil``'s hard velocity limit (1 m/s here) between consecutive setpoint frames,
    over the frames' own ``t``: 0.9 mm in 1 ms passes, 1.1 mm in 1 ms is a violation of that
    axis alone, 1.9 mm over 2 ms passes, and a frame whose ``t`` does not advance is not
    judged."""
    from motcomp.core.axes import AXES
    from motcomp.io.wire import encode_output
    from motcomp.sim.hil import HilConfig, HilPlatform

    n = len(AXES)
    plat = HilPlatform(HilConfig(models=[P1D(K=1.0, Td=0.0, Tp1=0.01)] * n,
                                 p_min=np.full(n, -1.0), p_max=np.full(n, 1.0),
                                 v_max=np.full(n, 1.0)))
    frames = [  # (t, rails_x, rails_y)
        (0.000, 0.0, 0.0),
        (0.001, 0.0009, 0.0),     # 0.9 m/s
        (0.002, 0.0009, 0.0011),  # rails_y 1.1 m/s
        (0.004, 0.0028, 0.0011),  # rails_x 0.95 m/s over 2 ms
        (0.004, 0.5, 0.0011),     # t did not advance: not judged
    ]
    for seq, (t, x, y) in enumerate(frames):
        plat.take_frame(encode_output(seq, t, seq, [x, y] + [0.0] * (n - 2), []))
        plat.step(t)
    assert plat.sim.violations.tolist() == [0, 1] + [0] * (n - 2)
    assert plat.setpoint[:2] == [0.5, 0.0011] and plat.bad == 0
