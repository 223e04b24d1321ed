"""A simulated motion platform: true per-axis dynamics and a realistic accelerometer.

Used three ways: by the offline evaluation (batch), by the identification tests to make data with
known truth, and by ``motcomp hil`` (one sample per setpoint, in real time).

Dynamics
    Each axis follows its own :class:`~motcomp.core.models.ProcessModel` (P1D, P2D, underdamped
    P2UZD, OE...) driven by the setpoints held constant over each period (exact ZOH, sub-sample
    delays kept), so a sampled simulation is exact, not an approximation.

Hard limits
    The platform's own position limits (wider than the compensator's soft limits).  A setpoint
    outside them is clamped and counted as a violation; so is a setpoint step that implies a
    velocity beyond the platform's hard velocity limit (if one is given).

Accelerometer
    The true acceleration at each sample is the second difference of the true position,
    ``(y[k] - 2 y[k-1] + y[k-2]) / h^2`` (what an accelerometer averaged over the period reads;
    exact in discrete time: for an LTI model, the acceleration response to the command is the
    model's response to the command's second difference).  On top of it: a constant bias, white
    noise, a *tremor* line (the position controllers' holding vibration, 10-20 Hz) with slowly
    wandering amplitude and phase, and quantisation to the sensor's LSB.

Sample-time jitter
    :func:`measure_irregular` samples a recorded run at jittered instants (what a logger with an
    imperfect clock delivers), for the identification's resampling.

Identification data sets
    :func:`true_acceleration` is the cabin acceleration at the sample instants: the central
    second difference ``(y[k+1] - 2 y[k] + y[k-1]) / h^2`` of the exact position, i.e. the true
    acceleration averaged with a triangular window of +-h centred on ``t_k`` (zero phase; what
    an accelerometer band-limited to the sample rate reads at its time stamp).  The positions
    come from a simulation on a finer grid, independent of the identification's own
    discretisation.
    :func:`record_identification` adds the accelerometer's imperfections and the time-stamp
    jitter: a ``t, cmd, acc`` recording with known truth.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from motcomp.core.lti import DiscreteLTI, FloatArray
from motcomp.core.models import ProcessModel
from motcomp.errors import ConfigError

__all__ = [
    "Accelerometer",
    "PlatformSimulator",
    "measure_irregular",
    "record_identification",
    "simulate_axis",
    "true_acceleration",
]


@dataclass(frozen=True)
class Accelerometer:
    """Imperfections of the cabin accelerometer (per axis, axis units/s^2).

    Attributes
    ----------
    noise_std
        Standard deviation of white noise.
    bias
        Constant offset.
    tremor_hz
        Frequency of the holding-vibration line (0 for none).
    tremor_amp
        Amplitude of the tremor line.
    lsb
        Quantisation step (0 for none).
    """

    noise_std: float = 0.0
    bias: float = 0.0
    tremor_hz: float = 0.0
    tremor_amp: float = 0.0
    lsb: float = 0.0

    def __post_init__(self) -> None:
        for name in ("noise_std", "bias", "tremor_hz", "tremor_amp", "lsb"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise ConfigError(f"accelerometer {name} must be finite, got {value!r}")
        for name in ("noise_std", "tremor_hz", "tremor_amp", "lsb"):
            if getattr(self, name) < 0:
                raise ConfigError(f"accelerometer {name} must be >= 0, got {getattr(self, name)!r}")

    @classmethod
    def realistic(cls, signal_rms: float, snr_db: float = 10.0, tremor_hz: float = 14.0,
                  bias: float = 0.02) -> Accelerometer:
        """Noise and tremor sized for a given SNR on a signal of RMS ``signal_rms``.

        The disturbance power (noise + tremor, split 1:1) is ``signal_rms^2 / 10^(snr/10)``; the
        LSB is 1/2000 of the signal RMS.
        """
        power = signal_rms**2 / 10.0 ** (snr_db / 10.0)
        noise_std = math.sqrt(power / 2.0)
        tremor_amp = math.sqrt(power)  # a sine's power is amp^2 / 2
        return cls(noise_std=noise_std, bias=bias, tremor_hz=tremor_hz, tremor_amp=tremor_amp,
                   lsb=signal_rms / 2000.0)

    def apply(self, acc_true: ArrayLike, rate_hz: float, rng: np.random.Generator,
              t0_s: float = 0.0) -> FloatArray:
        """Measured acceleration for a block of true samples at ``rate_hz``."""
        a = np.asarray(acc_true, dtype=float)
        out = a + self.bias
        if self.noise_std > 0:
            out = out + rng.normal(0.0, self.noise_std, a.shape)
        if self.tremor_amp > 0 and self.tremor_hz > 0:
            t = t0_s + np.arange(a.shape[0]) / rate_hz
            # slow random-walk modulation of amplitude (+-20 %) and phase
            walk = np.cumsum(rng.normal(0.0, 1.0, (a.shape[0], 2)), axis=0) / math.sqrt(rate_hz)
            amp = self.tremor_amp * (1.0 + 0.2 * np.tanh(0.3 * walk[:, 0]))
            ph = 0.5 * walk[:, 1] + rng.uniform(0, 2 * math.pi)
            line = amp * np.sin(2 * math.pi * self.tremor_hz * t + ph)
            out = out + (line if a.ndim == 1 else line[:, None])
        if self.lsb > 0:
            out = np.round(out / self.lsb) * self.lsb
        return np.asarray(out)


def simulate_axis(model: ProcessModel, commands: ArrayLike, rate_hz: float,
                  initial: float | None = None) -> FloatArray:
    """Position response of one axis to a ZOH command sequence, from rest at ``initial``
    (default: the first command).  Exact; uses scipy's ``lfilter`` when available (offline)."""
    u = np.asarray(commands, dtype=float)
    u0 = float(u[0]) if initial is None else float(initial)
    disc = model.discretize(rate_hz)
    try:
        from scipy.signal import lfilter, lfilter_zi
    except ImportError:  # pragma: no cover - scipy is a dependency, this is for slim installs
        return disc.simulate(u, u_before=u0)
    num, den = disc.tf()
    b = np.concatenate([np.zeros(den.size - num.size), num])
    zi = lfilter_zi(b, den) * u0 if abs(np.sum(den)) > 1e-12 else np.zeros(den.size - 1)
    y, _ = lfilter(b, den, u, zi=zi)
    return np.asarray(y)


class PlatformSimulator:
    """Sample-by-sample platform for ``motcomp hil`` and tests.

    Parameters
    ----------
    models
        True dynamics of each axis (any :class:`ProcessModel`).
    rate_hz
        Setpoint rate: one :meth:`step` per received setpoint period.
    p_min, p_max
        Hard position limits of each axis.
    v_max
        Hard velocity limits (optional): a setpoint step implying a faster move is a violation.
    accelerometer
        Imperfections of the acceleration measurement (one for all axes, or one per axis).
    position
        Initial position (default 0), at rest.
    seed
        Seed of the noise generator.
    """

    def __init__(self, models: Sequence[ProcessModel], rate_hz: float, p_min: ArrayLike,
                 p_max: ArrayLike, v_max: ArrayLike | None = None,
                 accelerometer: Accelerometer | Sequence[Accelerometer] = Accelerometer(),
                 position: ArrayLike | None = None, seed: int = 0) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ConfigError(f"platform rate must be a positive finite number, got {rate_hz!r}")
        self.n = len(models)
        self.rate_hz = float(rate_hz)
        self.dt_s = 1.0 / rate_hz
        self.models = tuple(models)
        self.p_min = np.array(p_min, dtype=float).reshape(self.n)
        self.p_max = np.array(p_max, dtype=float).reshape(self.n)
        if np.any(self.p_min >= self.p_max):
            raise ConfigError("platform hard limits: p_min must be < p_max on every axis")
        self.v_max = None if v_max is None else np.array(v_max, dtype=float).reshape(self.n)
        if isinstance(accelerometer, Accelerometer):
            self.accelerometers: tuple[Accelerometer, ...] = (accelerometer,) * self.n
        else:
            self.accelerometers = tuple(accelerometer)
        self._disc: list[DiscreteLTI] = [m.discretize(rate_hz) for m in models]
        self._rng = np.random.default_rng(seed)
        self.violations = np.zeros(self.n, dtype=np.int64)
        self.reset(np.zeros(self.n) if position is None else position)

    def reset(self, position: ArrayLike) -> None:
        """At rest at ``position`` (the command and the output, for unit-gain axes)."""
        p = np.array(position, dtype=float).reshape(self.n)
        self._k = 0
        self._x = [d.steady_state(float(pi)) for d, pi in zip(self._disc, p, strict=True)]
        # per axis [u[k-d], ..., u[k]] once u[k] is applied
        self._hist = [[float(pi)] * (d.delay_samples + 1) for d, pi in zip(self._disc, p,
                                                                          strict=True)]
        y = np.array([self._output(i) for i in range(self.n)])
        self._y1 = y.copy()
        self._y2 = y.copy()
        self._u_last = p.copy()
        self.position = y

    def _output(self, i: int) -> float:
        """Position at the end of the current period, ``C x[k+1] + D u[k+1-d]`` (``u[k]`` for
        ``d = 0``: the held value just before the next setpoint)."""
        d = self._disc[i]
        hist = self._hist[i]
        out = d.d_feed * hist[1 if len(hist) > 1 else 0]
        if d.order:
            out += float(d.c[0] @ self._x[i])
        return out

    def step(self, setpoint: ArrayLike) -> tuple[FloatArray, FloatArray, np.ndarray]:
        """Apply one setpoint for one period.

        Returns ``(position, measured_acceleration, violated)`` at the end of the period, where
        ``violated`` flags the axes whose setpoint broke a hard limit (and was clamped).
        """
        u = np.array(setpoint, dtype=float).reshape(self.n)
        violated = (u < self.p_min) | (u > self.p_max) | ~np.isfinite(u)
        u = np.where(np.isfinite(u), u, self._u_last)
        u = np.clip(u, self.p_min, self.p_max)
        if self.v_max is not None:
            too_fast = np.abs(u - self._u_last) > self.v_max * self.dt_s * (1 + 1e-9)
            violated |= too_fast
        self.violations += violated
        self._u_last = u
        y = np.empty(self.n)
        for i, d in enumerate(self._disc):
            hist = self._hist[i]
            hist.append(float(u[i]))
            hist.pop(0)
            # x[k+1] = phi x[k] + g0 u[k-d+1] + g1 u[k-d]   (g0 = 0 when d = 0)
            if d.order:
                u_next = hist[1] if len(hist) > 1 else 0.0
                self._x[i] = (d.phi @ self._x[i] + d.gamma0[:, 0] * u_next
                              + d.gamma1[:, 0] * hist[0])
            y[i] = self._output(i)
        acc_true = (y - 2.0 * self._y1 + self._y2) * self.rate_hz**2
        self._y2 = self._y1
        self._y1 = y
        acc = np.array([a.apply(np.array([acc_true[i]]), self.rate_hz, self._rng,
                                self._k * self.dt_s)[0]
                        for i, a in enumerate(self.accelerometers)])
        self._k += 1
        self.position = y
        return y, acc, violated


def measure_irregular(t: ArrayLike, signal: ArrayLike, jitter_s: float,
                      rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """Sample ``signal`` (given on the regular grid ``t``) at jittered instants.

    Instants are ``t[k] + N(0, jitter_s)`` kept strictly increasing; values are interpolated
    linearly.  Returns ``(t_jittered, values)``.
    """
    t_a = np.asarray(t, dtype=float)
    s = np.asarray(signal, dtype=float)
    if jitter_s == 0:
        _jittered_instants(t_a, jitter_s, rng)  # validates
        return t_a.copy(), s.copy()
    tj = _jittered_instants(t_a, jitter_s, rng)
    return tj, np.interp(tj, t_a, s)


def _jittered_instants(t_a: FloatArray, jitter_s: float, rng: np.random.Generator) -> FloatArray:
    if jitter_s < 0 or not math.isfinite(jitter_s):
        raise ConfigError(f"jitter must be finite and >= 0 s, got {jitter_s!r}")
    if jitter_s == 0:
        return t_a.copy()
    dt = float(np.median(np.diff(t_a)))
    tj = t_a + np.clip(rng.normal(0.0, jitter_s, t_a.shape), -0.45 * dt, 0.45 * dt)
    tj = np.clip(tj, t_a[0], t_a[-1])
    tj = np.maximum.accumulate(tj)
    keep = np.concatenate([[True], np.diff(tj) > 0])
    return np.asarray(tj[keep])


def true_acceleration(model: ProcessModel, commands: ArrayLike, rate_hz: float,
                      oversample: int = 8) -> FloatArray:
    """Acceleration of the axis at the command's sample instants ``t_k = k / rate_hz``.

    The command is held over each period (as the platform does); the positions ``y(t_k)`` come
    from the model's exact ZOH response computed on a grid ``oversample`` times finer; the
    acceleration at ``t_k`` is ``(y(t_k + h) - 2 y(t_k) + y(t_k - h)) / h^2``, the true
    acceleration averaged with the triangular window ``(1 - |s|/h) / h`` over ``+-h``.  That window
    sums to one over any set of instants ``h`` apart, so the velocity steps that a first-order
    response makes at every command step (acceleration impulses) are all counted once, wherever
    the delay puts them.  The axis is at rest at ``commands[0]`` before the first sample.
    """
    u = np.asarray(commands, dtype=float)
    if u.ndim != 1 or u.size < 2:
        raise ConfigError("true_acceleration needs a 1-D command sequence of 2 samples or more")
    if not (isinstance(oversample, int) and oversample >= 1):
        raise ConfigError(f"oversample must be an integer >= 1, got {oversample!r}")
    m = oversample
    fine = np.repeat(np.concatenate([u, u[-1:]]), m)
    y = simulate_axis(model, fine, rate_hz * m, initial=float(u[0]))[::m]  # y(t_0..t_N)
    y = np.concatenate([[y[0]], y])  # y(t_-1): at rest
    return np.asarray((y[2:] - 2.0 * y[1:-1] + y[:-2]) * rate_hz**2)


def record_identification(model: ProcessModel, commands: ArrayLike, rate_hz: float,
                          accelerometer: Accelerometer = Accelerometer(), jitter_s: float = 0.0,
                          seed: int = 0, oversample: int = 8
                          ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A recording ``(t, cmd, acc)`` of one axis driven by ``commands`` at ``rate_hz``.

    ``acc`` is :func:`true_acceleration` plus the accelerometer's bias, noise, tremor and
    quantisation; with ``jitter_s > 0`` both columns are sampled at jittered instants (the logger
    of :func:`measure_irregular`), so the time column is irregular.
    """
    u = np.asarray(commands, dtype=float)
    rng = np.random.default_rng(seed)
    acc = accelerometer.apply(true_acceleration(model, u, rate_hz, oversample), rate_hz, rng)
    t = np.arange(u.size) / rate_hz
    if jitter_s == 0:
        _jittered_instants(t, jitter_s, rng)
        return t, u.copy(), acc
    tj = _jittered_instants(t, jitter_s, rng)
    return tj, np.interp(tj, t, u), np.interp(tj, t, acc)
