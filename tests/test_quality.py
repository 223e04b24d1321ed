"""motcomp.core.quality against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from motcomp.core.quality import (
    HF_RESOLUTION,
    at_acc_limit,
    command_quality,
    command_quality_masked,
    command_quality_over,
    estimate_delay,
    hf_rms,
    hf_within,
    sine_delay,
    stretches,
)
from motcomp.errors import ConfigError

RATE = 1000.0
T = np.arange(10_000) / RATE  # 10 s: a whole number of periods of every sine below


@pytest.mark.parametrize("f_hz", [6.0, 20.0, 100.0])
def test_hf_acceleration_of_a_sine_above_the_cut_is_its_rms(f_hz: float) -> None:
    """x = A sin(2 pi f t): the second difference is a sine of amplitude
    A (2 sin(pi f h)/h)^2 exactly; its RMS is that over sqrt(2)."""
    a = 0.01
    q = command_quality(a * np.sin(2 * math.pi * f_hz * T), RATE)
    amp = a * (2 * math.sin(math.pi * f_hz / RATE) * RATE) ** 2
    assert q.hf_acc_rms == pytest.approx(amp / math.sqrt(2), rel=1e-3)
    # the samples miss the crest by at most half a sample
    assert amp * math.cos(math.pi * f_hz / RATE) <= q.acc_peak <= amp * (1 + 1e-9)


@pytest.mark.parametrize("f_hz", [0.2, 1.0, 3.0])
def test_a_driving_motion_below_the_cut_reads_nothing(f_hz: float) -> None:
    q = command_quality(0.5 * np.sin(2 * math.pi * f_hz * T), RATE)
    assert q.hf_acc_rms < 1e-4 * q.acc_peak


def test_jerk_rms_of_a_sine() -> None:
    """Third difference of A sin(w t): amplitude A (2 sin(w h/2)/h)^3."""
    a, f = 0.2, 2.0
    q = command_quality(a * np.sin(2 * math.pi * f * T), RATE)
    amp = a * (2 * math.sin(math.pi * f / RATE) * RATE) ** 3
    assert q.jerk_rms == pytest.approx(amp / math.sqrt(2), rel=1e-3)


def test_stretches_are_the_runs_of_recorded_ticks() -> None:
    have = np.array([True, True, False, True, False, False, True, True, True])
    assert stretches(have) == [slice(0, 2), slice(3, 4), slice(6, 9)]
    assert stretches(np.zeros(3, dtype=bool)) == []


def test_quality_over_stretches_weights_them_and_bridges_nothing() -> None:
    """A 20 Hz sine in stretches of 2 s: each stretch holds whole periods, so each reads the
    closed-form RMS and so does the weighted whole; a 1 Hz motion of 1 m/s^2 with a tick missing
    every second reads little above 5 Hz over the stretches (their edges leak a little of the
    motion), while bridging the holes linearly reads the motion's own acceleration at each."""
    a, f = 0.01, 20.0
    u = a * np.sin(2 * math.pi * f * T)
    parts = [slice(0, 2000), slice(2500, 4500), slice(5000, 7000), slice(7002, 7003)]
    q = command_quality_over(u, parts, RATE)
    amp = a * (2 * math.sin(math.pi * f / RATE) * RATE) ** 2
    assert q.hf_acc_rms == pytest.approx(amp / math.sqrt(2), rel=2e-3)
    w = 2 * math.pi
    slow = np.sin(w * T) / w**2
    have = np.ones(T.size, dtype=bool)
    have[250::1000] = False  # at the crests: |acceleration| 1 m/s^2
    over = command_quality_over(slow, stretches(have), RATE)
    idx = np.flatnonzero(have)
    bridged = np.interp(np.arange(T.size), idx, slow[idx])
    assert over.hf_acc_rms < 0.01  # what stretches of 1 s leak of a 1 Hz motion
    assert command_quality(bridged, RATE).hf_acc_rms > 4 * over.hf_acc_rms


def test_at_acceleration_limit_on_parabolas() -> None:
    """x = a t^2 / 2 has the second difference a exactly: at the limit from 0.99 a_max."""
    t = np.arange(100) / RATE
    assert at_acc_limit(0.5 * 5.95 * t * t, RATE, 6.0).all()
    assert not at_acc_limit(0.5 * 5.93 * t * t, RATE, 6.0).any()
    assert at_acc_limit(-0.5 * 6.5 * t * t, RATE, 6.0).all()  # either sign
    assert at_acc_limit(t, RATE, 6.0).size == t.size - 2


def test_estimate_delay_of_a_shifted_band_limited_signal() -> None:
    """A 2-8 Hz multisine delayed by 37.4 ms over 20 s, whose peak is sharp: within 0.1 ms (0.07
    short measured).  A 0.3-2.1 Hz one: 1.7 ms short (the documented pull of two equal windows),
    within 2 ms."""
    t = np.arange(20_000) / RATE
    freqs = (0.3, 0.7, 1.3, 2.1)
    ref = sum(np.sin(2 * math.pi * f * t + k) for k, f in enumerate(freqs))
    resp = sum(np.sin(2 * math.pi * f * (t - 0.0374) + k) for k, f in enumerate(freqs))
    slow = estimate_delay(ref, resp, RATE, max_lag_s=0.2, min_lag_s=-0.1)
    assert 0.0374 - 2e-3 < slow < 0.0374
    fast = (2.0, 3.5, 5.0, 8.0)
    ref = sum(np.sin(2 * math.pi * f * t + k) for k, f in enumerate(fast))
    resp = sum(np.sin(2 * math.pi * f * (t - 0.0374) + k) for k, f in enumerate(fast))
    assert estimate_delay(ref, resp, RATE, max_lag_s=0.2, min_lag_s=-0.1) == pytest.approx(
        0.0374, abs=1e-4)


@pytest.mark.parametrize("window_s", [16.0, 17.0, 18.0, 19.0])
def test_sine_delay_on_any_window_where_cross_correlation_is_biased(window_s: float) -> None:
    """A 0.31 Hz sine 4.6 ms late, with an offset, a drift and irregular instants: the fit reads
    the delay and the amplitude on every window, where equal windows' cross-correlation reads
    a fraction of it (a window that is not a whole number of periods)."""
    rng = np.random.default_rng(3)
    t = 2.0 + np.sort(rng.uniform(0.0, window_s, round(window_s * 1000)))
    y = 0.02 + 0.001 * t + 0.4 * np.sin(2 * math.pi * 0.31 * (t - 0.0046))
    fit = sine_delay(t, y, 0.0, 0.31)
    assert fit.delay_s == pytest.approx(0.0046, abs=1e-9)
    assert fit.amplitude == pytest.approx(0.4, rel=1e-9) and fit.r2 == pytest.approx(1.0)
    grid = np.arange(2.0, 2.0 + window_s, 1e-3)
    xc = estimate_delay(0.4 * np.sin(2 * math.pi * 0.31 * grid),
                        0.4 * np.sin(2 * math.pi * 0.31 * (grid - 0.0046)), RATE)
    assert xc < 0.0035  # the bias the fit avoids


def test_sine_delay_ahead_and_noisy() -> None:
    """Ahead is negative; white noise lowers R^2 to 1 - its share of the variance."""
    rng = np.random.default_rng(4)
    t = np.arange(0.0, 20.0, 1e-3)
    clean = 0.05 * np.sin(2 * math.pi * 0.5 * (t + 0.002))
    noise = rng.normal(0.0, 0.001, t.size)
    fit = sine_delay(t, clean + noise, 0.0, 0.5)
    # the phase's standard error: sigma / (A sqrt(N / 2)) rad = 0.064 ms; 5 of them
    assert fit.delay_s == pytest.approx(-0.002, abs=3.2e-4)
    assert fit.r2 == pytest.approx(1.0 - 0.001**2 / (0.05**2 / 2 + 0.001**2), abs=1e-4)
    with pytest.raises(ConfigError, match="constant"):
        sine_delay(t, np.zeros_like(t), 0.0, 0.5)
    with pytest.raises(ConfigError, match="equal 1-D"):
        sine_delay(t, clean[:-1], 0.0, 0.5)


def test_bad_input_is_a_clear_error() -> None:
    with pytest.raises(ConfigError, match="1-D"):
        command_quality(np.zeros((3, 3)), RATE)
    with pytest.raises(ConfigError, match="rate"):
        command_quality(np.zeros(10), 0.0)
    with pytest.raises(ConfigError, match="constant"):
        estimate_delay(np.zeros(100), np.ones(100), RATE)
    assert hf_rms(np.zeros(4), RATE) == 0.0


def test_hf_within_is_the_ratio_plus_the_resolution() -> None:
    """The one rule the outside-sender test and tools/bench_senders.py judge the command's HF
    acceleration by: within ``ratio`` times the ideal run's, plus 0.1 mm/s^2."""
    assert HF_RESOLUTION == 1e-4
    assert hf_within(0.0, 0.0, 2.0) and hf_within(1e-4, 0.0, 2.0)
    assert not hf_within(1.01e-4, 0.0, 2.0)
    assert hf_within(2.1e-3, 1e-3, 2.0) and not hf_within(2.11e-3, 1e-3, 2.0)


def test_masked_command_quality_leaves_a_missing_sample_out() -> None:
    """Every sample there: :func:`command_quality` exactly.  A sine with every 50th sample
    missing: the jerk and peak of the whole stencils are the sine's own (closed form), the
    high frequencies stay near zero; a straight line over the gaps reads a jerk of a/h."""
    rate, w, amp = 1000.0, 2 * math.pi * 0.4, 0.2
    t = np.arange(2002) / rate
    u = amp * np.sin(w * t)
    assert command_quality_masked(u, np.ones(u.size, bool), rate) == command_quality(u, rate)
    ok = np.arange(u.size) % 50 != 49
    q = command_quality_masked(np.where(ok, u, 0.0), ok, rate)  # the missing values unused
    jerk = -amp * w ** 3 * np.cos(w * t)
    assert q.jerk_rms == pytest.approx(math.sqrt(np.mean(jerk ** 2)), rel=0.02)
    assert q.acc_peak == pytest.approx(amp * w ** 2 * np.abs(np.sin(w * t)).max(), rel=0.01)
    assert q.hf_acc_rms < 1e-3 * amp * w ** 2
    bridged = np.interp(np.arange(u.size), np.flatnonzero(ok), u[ok])
    assert command_quality(bridged, rate).jerk_rms > 50 * q.jerk_rms
    assert math.isnan(command_quality_masked(u, np.zeros(u.size, bool), rate).jerk_rms)
