"""The reference band limit (motcomp.core.bandlimit) against independent computations: scipy's
Bessel design and bilinear transform, the Bessel polynomial's closed forms, and the filter run
sample by sample."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from motcomp.core.bandlimit import (
    BESSEL_W3DB,
    BandLimit,
    band_limit_freqresp,
    band_limit_params,
)
from motcomp.errors import ConfigError

RATE = 1000.0


def _run(p, x: np.ndarray) -> np.ndarray:
    bl = BandLimit(1)
    return np.array([bl.step((p,), [float(v)])[0] for v in x])


def test_the_prototype_is_the_bessel_polynomial_with_its_3db_point() -> None:
    """|105 / B4(j w)| = 1/sqrt(2) at w = BESSEL_W3DB, and the group delay at DC is 1."""
    b4 = np.array([1.0, 10.0, 45.0, 105.0, 105.0])
    h = 105.0 / np.polyval(b4, 1j * BESSEL_W3DB)
    assert abs(h) == pytest.approx(1.0 / math.sqrt(2.0), rel=1e-9)
    # group delay at DC of 1/B(s) is B'(0)/B(0) = 105/105
    assert np.polyval(np.polyder(b4), 0.0) / np.polyval(b4, 0.0) == pytest.approx(1.0)


@pytest.mark.parametrize("band_hz", [20.0, 48.0, 100.0, 250.0])
def test_the_sections_are_scipys_bessel_through_the_bilinear_transform(band_hz: float) -> None:
    p = band_limit_params(band_hz, RATE)
    assert p is not None
    delay = BESSEL_W3DB / (2.0 * math.pi * band_hz)
    assert p.delay_s == pytest.approx(delay)
    b, a = signal.bessel(4, 1.0 / delay, norm="delay", analog=True)
    bz, az = signal.bilinear(b, a, fs=RATE)
    f = np.linspace(0.01, 499.0, 3000)
    _, ref = signal.freqz(bz, az, worN=f, fs=RATE)
    assert np.max(np.abs(band_limit_freqresp(p, f) - ref)) < 1e-9
    # the realisation (two sections, run sample by sample) is that response: its impulse
    # response's DFT
    imp = _run(p, np.r_[0.0, 1.0, np.zeros(8191)])[1:]  # seeded at rest on 0
    spec = np.fft.rfft(imp)
    fk = np.fft.rfftfreq(imp.size, 1.0 / RATE)
    assert np.max(np.abs(spec - band_limit_freqresp(p, fk))) < 1e-9


def test_in_the_driver_band_it_is_a_pure_delay() -> None:
    """48 Hz: the phase over 0-3 Hz is -2 pi f D to within 1e-4 of D, the gain within 0.02 dB."""
    p = band_limit_params(48.0, RATE)
    assert p is not None
    assert p.delay_s == pytest.approx(7.009e-3, abs=1e-6)
    f = np.linspace(0.01, 3.0, 300)
    h = band_limit_freqresp(p, f)
    tau = -np.unwrap(np.angle(h)) / (2 * np.pi * f)
    assert np.max(np.abs(tau - p.delay_s)) < 1e-4 * p.delay_s
    assert np.max(np.abs(20 * np.log10(np.abs(h)))) < 0.02


def test_a_step_overshoots_by_the_bessels_own_fraction_and_settles_on_it() -> None:
    p = band_limit_params(48.0, RATE)
    y = _run(p, np.r_[np.zeros(5), np.ones(2000)])
    b, a = signal.bilinear(*signal.bessel(4, 1.0 / p.delay_s, norm="delay", analog=True),
                           fs=RATE)
    ref = signal.lfilter(b, a, np.r_[np.zeros(5), np.ones(2000)])
    assert np.max(np.abs(y - ref)) < 1e-12
    assert 0.008 < y.max() - 1.0 < 0.012  # the Bessel's 0.8 %, 1.1 % after the bilinear transform
    assert y[-1] == pytest.approx(1.0, abs=1e-12)


def test_it_starts_at_rest_on_its_first_value_and_restarts_after_reset() -> None:
    p = band_limit_params(48.0, RATE)
    bl = BandLimit(2)
    out = [bl.step((p, None), [0.7, 3.0]) for _ in range(50)]
    assert all(o == pytest.approx([0.7, 3.0], abs=1e-13) for o in out)
    bl.reset()
    assert bl.step((p, None), [-0.2, 1.0]) == pytest.approx([-0.2, 1.0], abs=1e-13)


def test_a_non_finite_value_is_not_kept() -> None:
    p = band_limit_params(48.0, RATE)
    bl = BandLimit(1)
    for _ in range(10):
        bl.step((p,), [0.5])
    assert bl.step((p,), [math.inf]) == [math.inf]  # passed as it is (the shaper holds it)
    assert bl.step((p,), [0.5]) == pytest.approx([0.5], abs=1e-13)  # and the state is clean


def test_white_noise_comes_out_with_the_responses_rms_gain() -> None:
    """The RMS of filtered white noise is the response's RMS over (0, pi): the figure
    motcomp.design.frequency.noise_figures reports."""
    p = band_limit_params(48.0, RATE)
    x = np.random.default_rng(3).normal(0.0, 1.0, 400_000)
    y = _run(p, x)
    f = (np.arange(1, 20000) + 0.5) * (RATE / 2 / 20000)
    gain = np.sqrt(np.mean(np.abs(band_limit_freqresp(p, f)) ** 2))
    assert np.std(y[1000:]) == pytest.approx(gain, rel=0.02)


@pytest.mark.parametrize(("band_hz", "match"), [
    (-1.0, "input.band_hz must be a finite number >= 0, got -1.0"),
    (math.nan, "input.band_hz must be a finite number >= 0"),
    (300.0, r"input.band_hz = 300 Hz must be at most a quarter of the loop rate \(250 Hz\)"),
])
def test_bad_bands_are_refused_naming_the_key(band_hz: float, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        band_limit_params(band_hz, RATE)


def test_zero_is_off() -> None:
    assert band_limit_params(0.0, RATE) is None
    assert np.all(band_limit_freqresp(None, [1.0, 100.0]) == 1.0)
