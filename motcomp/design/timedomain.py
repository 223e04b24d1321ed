"""Time-domain evaluation: test signals, closed simulation, and delay by cross-correlation.

Test signals
------------
Swept sine (the paper's Fig. 3)
    A logarithmic chirp from 0.1 to 3 Hz with a raised-cosine fade in and out.
Slalom (the paper's Fig. 4)
    The lateral setpoint of a car driving a slalom.  Default: cones every 18 m driven at
    40 km/h -- a "moderate speed" slalom like the paper's reference task; the car weaves at
    ``f = v / (2 spacing) = 0.31 Hz``, inside the 0.2-0.5 Hz band where steering inputs
    concentrate.  The car's lateral offset swings +-1 m between the cones; the rails receive a
    0.5 scale of it (+-0.5 m, peak lateral acceleration 1.9 m/s^2, well inside the rails'
    limits), entering and leaving the slalom over one cone pitch with a minimum-jerk envelope
    and driving straight before and after.

Delay measurement
-----------------
The delay of ``y`` behind ``r`` is the lag maximising their cross-correlation (computed by FFT,
means removed), refined to a fraction of a sample by fitting a parabola through the peak and its
two neighbours.  This is what an engineer does with recorded traces, and it is what the demo and
replay report as the "apparent delay".
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from motcomp.core.compensator import Compensator
from motcomp.core.lti import FloatArray
from motcomp.core.minjerk import min_jerk
from motcomp.core.models import P1D, ProcessModel, simulate_axis
from motcomp.core.pid import PIDGains
from motcomp.core.quality import estimate_delay
from motcomp.core.saturation import AxisLimits
from motcomp.errors import ConfigError

__all__ = [
    "SimulationResult",
    "fade_envelope",
    "limits_for",
    "minimum_jerk",
    "simulate_compensated",
    "slalom",
    "swept_sine",
]


def minimum_jerk(p: ArrayLike) -> FloatArray:
    """0 -> 1 over ``p`` in [0, 1] with zero velocity and acceleration at both ends:
    ``10 p^3 - 15 p^4 + 6 p^5`` (a raised cosine has acceleration steps at its ends, which a
    high-gain compensator turns into command spikes)."""
    return np.asarray(min_jerk(np.clip(np.asarray(p, dtype=float), 0.0, 1.0)))


def fade_envelope(n: int, n_fade: int) -> FloatArray:
    """1 with minimum-jerk fades over the first and last ``n_fade`` samples."""
    env = np.ones(n)
    n_fade = min(n_fade, n // 2)
    if n_fade > 0:
        ramp = minimum_jerk(np.arange(n_fade) / n_fade)
        env[:n_fade] = ramp
        env[n - n_fade:] = ramp[::-1]
    return env


def swept_sine(rate_hz: float, f0_hz: float = 0.1, f1_hz: float = 3.0, duration_s: float = 60.0,
               amplitude: float = 0.2, fade_s: float = 2.0) -> tuple[FloatArray, FloatArray]:
    """Logarithmic swept sine ``(t, r)``: phase ``2 pi f0 T (k^(t/T) - 1)/ln k``, ``k = f1/f0``.

    Starts and ends at 0 with minimum-jerk fades of ``fade_s``.
    """
    if not (0 < f0_hz < f1_hz and duration_s > 0 and rate_hz > 0):
        raise ConfigError(f"swept sine needs 0 < f0 < f1 and positive duration/rate, got "
                          f"f0={f0_hz}, f1={f1_hz}, duration={duration_s}, rate={rate_hz}")
    n = round(duration_s * rate_hz)
    t = np.arange(n) / rate_hz
    k = f1_hz / f0_hz
    phase = 2 * math.pi * f0_hz * duration_s * (k ** (t / duration_s) - 1.0) / math.log(k)
    r = amplitude * np.sin(phase) * fade_envelope(n, int(fade_s * rate_hz))
    return t, r


def swept_sine_frequency(t: ArrayLike, f0_hz: float = 0.1, f1_hz: float = 3.0,
                         duration_s: float = 60.0) -> FloatArray:
    """Instantaneous frequency (Hz) of :func:`swept_sine` at times ``t``."""
    return np.asarray(f0_hz * (f1_hz / f0_hz) ** (np.asarray(t) / duration_s))


def slalom(rate_hz: float, speed_kmh: float = 40.0, cone_spacing_m: float = 18.0,
           n_cones: int = 10, lateral_m: float = 1.0, scale: float = 0.5,
           straight_s: float = 3.0) -> tuple[FloatArray, FloatArray]:
    """Rails lateral setpoint ``(t, r)`` of a car driving a slalom (see module docstring)."""
    if speed_kmh <= 0 or cone_spacing_m <= 0 or n_cones < 2 or straight_s < 0:
        raise ConfigError("slalom needs positive speed and spacing, >= 2 cones, straight_s >= 0")
    v = speed_kmh / 3.6
    f = v / (2.0 * cone_spacing_m)
    pitch_s = cone_spacing_m / v
    weave_s = n_cones * pitch_s
    total = 2 * straight_s + weave_s
    n = round(total * rate_hz)
    t = np.arange(n) / rate_hz
    tw = t - straight_s
    inside = (tw >= 0) & (tw <= weave_s)
    env = np.zeros(n)
    env[inside] = 1.0
    ramp_in = inside & (tw < pitch_s)
    env[ramp_in] = minimum_jerk(tw[ramp_in] / pitch_s)
    ramp_out = inside & (tw > weave_s - pitch_s)
    env[ramp_out] = minimum_jerk((weave_s - tw[ramp_out]) / pitch_s)
    r = scale * lateral_m * env * np.sin(2 * math.pi * f * np.clip(tw, 0, None))
    return t, r


@dataclass
class SimulationResult:
    """Traces of one axis, uncompensated vs compensated, and the measured delays."""

    t: FloatArray
    reference: FloatArray
    command_off: FloatArray
    command_on: FloatArray
    response_off: FloatArray
    response_on: FloatArray
    delay_off_s: float
    delay_on_s: float
    saturated_samples_on: int
    saturated_samples_off: int

    @property
    def reduction_s(self) -> float:
        return self.delay_off_s - self.delay_on_s


def simulate_compensated(reference: ArrayLike, gains: PIDGains, model: P1D,
                         plant: ProcessModel | None, limits: AxisLimits, rate_hz: float,
                         max_lag_s: float = 1.0) -> SimulationResult:
    """Run one axis through the discrete compensator (saturation on) and the platform.

    The uncompensated run sends the reference through the same saturator (bypass), so both runs
    face the same limits.
    """
    plant = plant or model
    r = np.asarray(reference, dtype=float)
    if limits.size != 1:
        raise ConfigError("simulate_compensated runs one axis: give limits of size 1")
    t = np.arange(r.size) / rate_hz
    runs = {}
    for bypass in (True, False):
        comp = Compensator([model], [gains], limits, rate_hz, position=[r[0]])
        comp.set_bypass([bypass])
        cmd, flags = comp.run(r[:, None])
        runs[bypass] = (cmd[:, 0], int(np.count_nonzero(flags[:, 0] & 7)))
    y_off = simulate_axis(plant, runs[True][0], rate_hz)
    y_on = simulate_axis(plant, runs[False][0], rate_hz)
    return SimulationResult(
        t=t, reference=r, command_off=runs[True][0], command_on=runs[False][0],
        response_off=y_off, response_on=y_on,
        delay_off_s=estimate_delay(r, y_off, rate_hz, max_lag_s=max_lag_s),
        delay_on_s=estimate_delay(r, y_on, rate_hz, max_lag_s=max_lag_s),
        saturated_samples_on=runs[False][1], saturated_samples_off=runs[True][1],
    )


def limits_for(p: float, v: float, a: float, names: Sequence[str] = ("axis",)) -> AxisLimits:
    """Symmetric limits for ``len(names)`` axes."""
    n = len(names)
    return AxisLimits(np.full(n, -p), np.full(n, p), np.full(n, v), np.full(n, a), tuple(names))
