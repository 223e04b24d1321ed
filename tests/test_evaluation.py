"""Frequency- and time-domain evaluation, against closed forms and the paper's claims."""

from __future__ import annotations

import math

import numpy as np
import pytest

from motcomp.core.loop import stability
from motcomp.core.models import P1D
from motcomp.core.pid import PIDGains
from motcomp.core.tuning import tune
from motcomp.design.frequency import evaluate, loop_response, pid_continuous
from motcomp.design.timedomain import (
    estimate_delay,
    limits_for,
    simulate_compensated,
    slalom,
    swept_sine,
    swept_sine_frequency,
)
from motcomp.presets import load_preset
from tests.conftest import RAILS


def test_rails_uncorrected_and_zn_nulling() -> None:
    g = tune("zn", RAILS).gains
    ev_c = evaluate(g, RAILS, rate_hz=None)
    assert ev_c.uncorrected_phase_delay_ms["0.2"] == pytest.approx(200.0, abs=0.5)
    ev = evaluate(g, RAILS, rate_hz=1000.0)
    assert ev.phase_delay_ms["0.2"] < 10.0  # the paper's "nulling"
    assert ev.peak_gain_db > 6.0  # and its over-amplification
    assert 10.0 < ev.peak_gain_hz < 30.0
    assert ev.stable


def test_reference_figures_for_zn_at_2khz() -> None:
    # REFERENCE.md section 2, computed independently: ZN at 2 kHz, 4.1 ms, +10.9 dB near 20 Hz,
    # Ms 4.5; AMIGO ~30 ms, +1.4 dB, Ms 1.45
    ev = evaluate(tune("zn", RAILS).gains, RAILS, rate_hz=2000.0)
    assert ev.max_residual_delay_ms == pytest.approx(4.1, abs=0.1)
    assert ev.peak_gain_db == pytest.approx(10.9, abs=0.2)
    assert ev.peak_gain_hz == pytest.approx(20.0, abs=1.0)
    assert ev.ms == pytest.approx(4.5, abs=0.1)
    am = evaluate(tune("amigo", RAILS).gains, RAILS, rate_hz=2000.0)
    assert am.max_residual_delay_ms == pytest.approx(30.0, abs=1.0)
    assert am.peak_gain_db == pytest.approx(1.4, abs=0.2)
    assert am.ms == pytest.approx(1.45, abs=0.05)


@pytest.mark.parametrize("rule", ["zn", "cc", "amigo", "simc"])
def test_continuous_and_discrete_agree_below_2hz(rule: str) -> None:
    g = tune(rule, RAILS).gains
    ev_c = evaluate(g, RAILS, rate_hz=None)
    ev_d = evaluate(g, RAILS, rate_hz=1000.0)
    for f in ("0.2", "0.5", "1", "2"):
        assert ev_d.phase_delay_ms[f] == pytest.approx(ev_c.phase_delay_ms[f], abs=1.0)


def test_exact_model_closed_loop_formula() -> None:
    """T = P C/(1 + C M) in continuous time, computed by hand at one frequency."""
    g = PIDGains(kp=3.0, ki=40.0, kd=0.02, tf=0.002)
    f = 1.3
    s = 2j * math.pi * f
    c = 3.0 + 40.0 / s + 0.02 * s / (1 + 0.002 * s)
    m = 1.0 * np.exp(-0.0175 * s) / (1 + 0.1857683128 * s)
    resp = loop_response(g, RAILS, RAILS, [1e-3, 0.01, 0.1, f], None)
    assert resp.delivered[-1] == pytest.approx(m * c / (1 + c * m), rel=1e-12)
    (nr, dr), _ = pid_continuous(g)
    assert np.polyval(nr, s) / np.polyval(dr, s) == pytest.approx(c, rel=1e-12)


def test_model_mismatch_floor() -> None:
    """With P != M the low-frequency response tends to P/M: a 20 % Tp1 error shifts the 0.2 Hz
    phase delay by roughly 35 ms (REFERENCE), whatever the gains."""
    g = tune("zn", RAILS).gains
    plant = P1D(K=1.0, Td=0.0175, Tp1=0.1857683128 * 1.2)
    ev = evaluate(g, RAILS, plant, rate_hz=1000.0)
    floor = (plant.phase_delay(0.2)[0] - RAILS.phase_delay(0.2)[0]) * 1e3
    assert floor == pytest.approx(35.0, abs=3.0)
    assert ev.phase_delay_ms["0.2"] == pytest.approx(floor + 2.8, abs=1.5)


def test_unwrapped_phase_matches_dense_numpy_unwrap() -> None:
    g = tune("cc", RAILS).gains
    f = np.geomspace(1e-3, 499.0, 60000)
    resp = loop_response(g, RAILS, RAILS, f, 1000.0)
    ref = np.unwrap(np.angle(resp.delivered))
    ref += 2 * np.pi * round((0.0 - ref[0]) / (2 * np.pi))
    np.testing.assert_allclose(resp.delivered_phase, ref, atol=1e-6)


def test_stability_by_poles_for_a_wild_gain() -> None:
    stable, rho = stability(PIDGains(kp=60.0, ki=500.0, kd=0.2, tf=0.0005), RAILS, 1000.0)
    assert not stable and rho > 1.0
    ev = evaluate(PIDGains(kp=60.0, ki=500.0, kd=0.2, tf=0.0005), RAILS, rate_hz=1000.0)
    assert not ev.stable and "UNSTABLE" in ev.notes[0]


def test_delay_estimate_with_fractional_delay() -> None:
    rng = np.random.default_rng(0)
    rate = 1000.0
    n = 2**15
    x = rng.normal(size=n)
    spec = np.fft.rfft(x)
    f = np.fft.rfftfreq(n, 1 / rate)
    spec[f > 5.0] = 0  # band-limited so a fractional shift is exact
    for delay in (0.0173, 0.1234567, -0.0051):
        y = np.fft.irfft(spec * np.exp(-2j * np.pi * f * delay), n)
        xr = np.fft.irfft(spec, n)
        est = estimate_delay(xr, y, rate)
        assert est == pytest.approx(delay, abs=0.05 / rate)


def test_delay_estimate_errors() -> None:
    with pytest.raises(ValueError, match="constant"):
        estimate_delay(np.ones(100), np.arange(100.0), 1000.0)
    with pytest.raises(ValueError, match="equal length"):
        estimate_delay(np.ones(100), np.ones(99), 1000.0)


def test_signals() -> None:
    _, r = swept_sine(1000.0, 0.1, 3.0, 60.0, 0.5, fade_s=2.0)
    assert r[0] == 0 and abs(r[-1]) < 1e-3 and np.max(np.abs(r)) <= 0.5
    assert swept_sine_frequency(np.array([0.0, 60.0])) == pytest.approx([0.1, 3.0])
    _, r = slalom(1000.0)
    # 18 m cones at 40 km/h: 0.309 Hz weave, +-0.5 m on the rails
    spec = np.abs(np.fft.rfft(r, 2**18))
    f = np.fft.rfftfreq(2**18, 1e-3)
    assert f[np.argmax(spec)] == pytest.approx(40 / 3.6 / 36, abs=0.01)
    assert np.max(np.abs(r)) == pytest.approx(0.5, abs=0.01)


def test_slalom_delay_drops_by_more_than_150ms() -> None:
    lim = load_preset("rails").axis_limits("rails_y")
    _, r = slalom(1000.0)
    res = simulate_compensated(r, tune("zn", RAILS).gains, RAILS, None, lim, 1000.0)
    assert res.delay_off_s == pytest.approx(0.195, abs=0.005)  # tau_phi at 0.31 Hz: 195.9 ms
    assert res.reduction_s > 0.150
    assert res.saturated_samples_on == 0


def test_swept_sine_time_domain_matches_frequency_domain_at_low_frequency() -> None:
    lim = limits_for(2.6, 2.0, 6.0)
    _, r = swept_sine(1000.0, 0.1, 0.5, 60.0, 0.2)
    res = simulate_compensated(r, tune("zn", RAILS).gains, RAILS, None, lim, 1000.0)
    ev = evaluate(tune("zn", RAILS).gains, RAILS, rate_hz=1000.0)
    assert res.delay_on_s * 1e3 == pytest.approx(ev.phase_delay_ms["0.2"], abs=1.0)
