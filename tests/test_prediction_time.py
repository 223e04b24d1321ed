"""The example config's hexapod prediction, as the platform receives it: the shipped prefilters
against the issue's frequency bounds (exact discrete responses), and in time through the tick
(:func:`motcomp.sim.ideal.ideal_run`, what the service runs) and the axis' true model: braking
steps and a lane change overshoot the reference by the platform's own amount plus at most
:data:`MAX_ADDED_OVERSHOOT` of the step, sines come out with the lead the design states."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import freqz

from motcomp.config import ServiceConfig, load_config, new_tick, resolve_axes
from motcomp.core.axes import AXIS_INDEX
from motcomp.core.minjerk import min_jerk
from motcomp.core.quality import estimate_delay
from motcomp.resources import config_file
from motcomp.sim.ideal import ideal_run
from tests._laguerre import laguerre_filter

RATE = 1000.0
HEX = ("hex_x", "hex_y", "hex_z", "hex_roll", "hex_pitch", "hex_yaw")
MAX_ADDED_OVERSHOOT = 0.05
"""Largest overshoot beyond the reference that prediction adds to the platform's own, as a share
of the step (the issue's aim; measured at most 0.3 points: docs/PREDICTION.md)."""
STACK_LAG_S = 0.0028
"""What the example config's prefilters are designed for beyond the platform's truth model and
the band limit (config/motcomp.toml, `--input-lag-ms 2.8`): a 1 kHz sender's playback and the
platform's setpoint age on the live stack."""


@pytest.fixture(scope="module")
def cfg() -> ServiceConfig:
    return load_config(config_file("motcomp.toml"))


def _plain(cfg: ServiceConfig) -> ServiceConfig:
    axes = {a: ax.model_copy(update={"predict": False}) for a, ax in cfg.axes.items()}
    return cfg.model_copy(update={"axes": axes})


IMPULSE_SAMPLES = 1 << 16
"""The prefilter's impulse response is taken this long: its slowest factor, ``a^n n^40/40!``
with ``a = exp(-2 pi 1 Hz / 1 kHz)``, has fallen to 1e-34 by then (and never reaches the
subnormal range, which some CPUs compute a hundred times slower)."""
FFT_POINTS = 1 << 20
"""Its frequency response: the FFT zero-padded to this, bins 0.95 mHz apart."""


def test_shipped_prefilters_meet_the_bounds(cfg: ServiceConfig) -> None:
    """What the prefilters were designed for (config/motcomp.toml): the platform behind a 1 kHz
    sender's playback and the platform's setpoint age (STACK_LAG_S) and the config's band limit;
    worst phase delay over 0.1-2 Hz <= 2 ms (from 75.5), in-band gain error <= 1 dB, peak of
    the delivered response <= +6 dB, command gain above 10 Hz <= 7, on the FFT's uniform grid:
    plant by freqz of its discretisation, prefilter by the FFT of its impulse response (the
    recursion through lfilter), the band limit by scipy's Bessel through the bilinear transform,
    phase unwrapped bin by bin from DC."""
    from scipy.signal import bessel, bilinear

    axes = resolve_axes(cfg)
    f = np.fft.rfftfreq(FFT_POINTS, 1.0 / RATE)[1:-1]  # (0, Nyquist), ends excluded
    impulse = np.zeros(IMPULSE_SAMPLES)
    impulse[0] = 1.0
    for name in HEX:
        i = AXIS_INDEX[name]
        p = axes.prediction[i]
        assert p is not None and axes.predict[i] and axes.bypass[i], name
        h = laguerre_filter(p, impulse)
        assert np.max(np.abs(h[-100:])) < 1e-12 * np.max(np.abs(h)), name  # decayed
        assert np.min(np.abs(h[h != 0.0])) > 1e-300, name  # no subnormal on the way
        pre = np.fft.rfft(h, FFT_POINTS)[1:-1]
        num, den = axes.plants[i].discretize(RATE).tf()
        b = np.concatenate([np.zeros(len(den) - len(num)), num])
        _, plant = freqz(b, den, worN=f, fs=RATE)
        band_hz = cfg.input.bands_hz()[i]
        band_delay = 2.113917674904216 / (2 * np.pi * band_hz)  # the Bessel's -3 dB
        bz, az = bilinear(*bessel(4, 1.0 / band_delay, norm="delay", analog=True), fs=RATE)
        _, lim = freqz(bz, az, worN=f, fs=RATE)
        t = plant * pre * lim * np.exp(-2j * np.pi * f * STACK_LAG_S)
        band = (f >= 0.1) & (f <= 2.0)
        tau = -np.unwrap(np.angle(t))[band] / (2 * np.pi * f[band])
        mag_db = 20 * np.log10(np.abs(t))
        assert np.max(np.abs(tau)) <= 0.002, (name, np.max(np.abs(tau)))
        assert np.max(np.abs(mag_db[band])) <= 1.0 + 0.01, name
        assert mag_db.max() <= 6.0 + 0.01, name
        assert np.abs(pre[f >= 10.0]).max() <= 7.0 * 1.001, name


def _step(size: float, rise_s: float) -> np.ndarray:
    n = max(round(rise_s * RATE), 1)
    return np.concatenate([np.zeros(1000), size * min_jerk(np.arange(n) / n),
                           np.full(2500, size)])


def _lane_change(width: float) -> np.ndarray:
    n = 2000
    move = width * min_jerk(np.arange(n) / n)
    return np.concatenate([np.zeros(1000), move, np.full(2000, width), move[::-1],
                           np.zeros(1500)])


def _delivered(cfg: ServiceConfig, axis: str, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from motcomp.core.models import simulate_axis

    res = ideal_run(cfg, {axis: r}, RATE)
    u = res.u[axis]
    return u, simulate_axis(resolve_axes(cfg).plants[AXIS_INDEX[axis]], u, RATE)


def _overshoot(r: np.ndarray, y: np.ndarray) -> float:
    n = min(r.size, y.size)
    return max(float(y[:n].max() - r.max()), float(r.min() - y[:n].min()), 0.0) / float(
        np.ptp(r))


@pytest.mark.parametrize(("size", "rise_s"), [(0.1, 0.0), (0.02, 0.0), (0.02, 0.15),
                                              (0.02, 0.3), (0.002, 0.3), (0.05, 0.6)])
def test_braking_step_overshoot_added_by_prediction_is_bounded(cfg: ServiceConfig, size: float,
                                                               rise_s: float) -> None:
    r = _step(size, rise_s)
    u_on, y_on = _delivered(cfg, "hex_x", r)
    _, y_off = _delivered(_plain(cfg), "hex_x", r)
    added = _overshoot(r, y_on) - _overshoot(r, y_off)
    assert added <= MAX_ADDED_OVERSHOOT, (size, rise_s, _overshoot(r, y_on), _overshoot(r, y_off))
    lim = resolve_axes(cfg).limits
    i = AXIS_INDEX["hex_x"]
    assert lim.p_min[i] <= u_on.min() and u_on.max() <= lim.p_max[i]


@pytest.mark.parametrize("speed", [0.02, 0.1, 0.3])
def test_sudden_reversal_overshoot_added_by_prediction_is_bounded(cfg: ServiceConfig,
                                                                   speed: float) -> None:
    """hex_x moving at ``speed`` for 0.5 s turns back at once (a velocity step).  Nothing
    before the turn tells it, so a predictor that cancels a delay ``D`` runs past the turning
    point by ``speed x D``: prediction adds at most that to the platform's own overshoot, ``D``
    the delay its design cancels: the platform's low-frequency phase delay (35.5 ms at 0.2 Hz)
    and what the service adds before it (the band limit's 5.3 ms and STACK_LAG_S,
    config/motcomp.toml).  Measured before the band limit: 0.55-0.94 of the platform's
    (0.4, 3.0 and 10 mm; 3.9-6.7 % of these 10-150 mm travels: a reversal after a short travel
    costs more than 5 % of it)."""
    up = speed * np.arange(500) / RATE
    r = np.concatenate([np.zeros(1000), up, up[-1] - speed * np.arange(1, 501) / RATE,
                        np.zeros(2000)])
    _, y_on = _delivered(cfg, "hex_x", r)
    _, y_off = _delivered(_plain(cfg), "hex_x", r)
    travel = float(np.ptp(r))
    added_m = (_overshoot(r, y_on) - _overshoot(r, y_off)) * travel
    band = new_tick(cfg)[0].shaper.band[AXIS_INDEX["hex_x"]]
    assert band is not None
    delay_s = (float(resolve_axes(cfg).plants[AXIS_INDEX["hex_x"]].phase_delay(0.2)[0])
               + band.delay_s + STACK_LAG_S)
    assert added_m <= speed * delay_s, (speed, added_m, speed * delay_s)


def test_lane_change_overshoot_and_lead(cfg: ServiceConfig) -> None:
    """A 10 cm sway in 2 s and back on hex_y: prediction adds at most the bound to the
    platform's own overshoot and takes most of its lag off (velocities' cross-correlation)."""
    r = _lane_change(0.1)
    _, y_on = _delivered(cfg, "hex_y", r)
    _, y_off = _delivered(_plain(cfg), "hex_y", r)
    assert _overshoot(r, y_on) - _overshoot(r, y_off) <= MAX_ADDED_OVERSHOOT
    n = min(r.size, y_on.size, y_off.size)
    d_on = estimate_delay(np.diff(r[:n]), np.diff(y_on[:n]), RATE, 0.2, -0.1)
    d_off = estimate_delay(np.diff(r[:n]), np.diff(y_off[:n]), RATE, 0.2, -0.1)
    assert d_off > 0.030 and d_on < 0.012, (d_off, d_on)
