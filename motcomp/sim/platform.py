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
from motcomp.core.models import ProcessModel, simulate_axis
from motcomp.errors import ConfigError

__all__ = [
    "Accelerometer",
    "PlatformSimulator",
    "measure_irregular",
    "record_identification",
    "simulate_axis",  # (motcomp.core.models), kept here for the simulator's users
    "true_acceleration",
]


MAX_DELAY_S = 0.25
"""Longest delay a drift may give an axis (the delay range ``motcomp identify`` searches)."""
HISTORY_REWIND = 4096
"""Steps between two moves of the setpoints' history to the start of its buffer."""


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
        """Measured acceleration for a block of true samples at ``rate_hz`` (the first at
        ``t0_s``; a 2-D block's columns are measured as separate axes): the imperfections of
        :class:`_SensorStream` over one block."""
        a = np.asarray(acc_true, dtype=float)
        cols = a.reshape(a.shape[0], math.prod(a.shape[1:]))
        stream = _SensorStream([self] * cols.shape[1], rate_hz, rng, block=max(cols.shape[0], 1))
        return stream.measure(cols, t0_s * rate_hz).reshape(a.shape)


class _SensorStream:
    """Per-sample accelerometer imperfections of all axes at once (noise, bias, tremor line with
    a slow random-walk modulation of amplitude and phase, quantisation; :meth:`measure` gives a
    block at once, as :meth:`Accelerometer.apply` does).  Sample ``k`` is measured at ``k / rate``;
    the disturbance of a block of samples (random numbers, walk, tremor line) is computed at
    once, so a sample costs an addition and the quantisation."""

    def __init__(self, accs: Sequence[Accelerometer], rate_hz: float, rng: np.random.Generator,
                 block: int = 1024) -> None:
        self.n = len(accs)
        self.rate_hz = rate_hz
        self.rng = rng
        self.block = block
        self.bias = np.array([a.bias for a in accs])
        self.noise_std = np.array([a.noise_std for a in accs])
        self.tremor_amp = np.array([a.tremor_amp for a in accs])
        self.tremor_w = np.array([2 * math.pi * a.tremor_hz for a in accs])
        self.lsb = np.array([a.lsb for a in accs])
        self.quantise = bool(np.any(self.lsb > 0))
        self.quantise_all = bool(np.all(self.lsb > 0))
        self.lsb_safe = np.where(self.lsb > 0, self.lsb, 1.0)
        self.ideal = not (np.any(self.bias) or np.any(self.noise_std)
                          or np.any(self.tremor_amp) or self.quantise)
        self.phase0 = rng.uniform(0, 2 * math.pi, self.n)
        self.walk = np.zeros((2, self.n))
        self._k0: float = 0
        self._i = block
        self._dist = np.zeros((block, self.n))

    def _fill(self, k0: float) -> None:
        """The disturbance of samples ``k0 .. k0 + block - 1``."""
        noise = self.rng.normal(0.0, 1.0, (self.block, self.n)) * self.noise_std
        steps = self.rng.normal(0.0, 1.0, (self.block, 2, self.n)) / math.sqrt(self.rate_hz)
        walk = self.walk + np.cumsum(steps, axis=0)
        self.walk = walk[-1].copy()
        amp = self.tremor_amp * (1.0 + 0.2 * np.tanh(0.3 * walk[:, 0]))
        t = (k0 + np.arange(self.block))[:, None] / self.rate_hz
        self._dist = self.bias + noise + amp * np.sin(self.tremor_w * t + self.phase0
                                                      + 0.5 * walk[:, 1])
        self._k0 = k0
        self._i = 0

    def sample(self, acc_true: np.ndarray, k: int) -> np.ndarray:
        """The measurement of sample ``k`` (true acceleration ``acc_true``); consecutive
        samples reuse the block's disturbance, any other ``k`` starts a new block."""
        if self.ideal:
            return acc_true
        if self._i == self.block or k != self._k0 + self._i:
            self._fill(k)
        out = acc_true + self._dist[self._i]
        self._i += 1
        return self._quantised(out)

    def measure(self, acc_true: np.ndarray, k0: float) -> np.ndarray:
        """The measurement of the samples ``k0, k0 + 1, ...`` of ``acc_true`` (rows; at most
        a block of them) at once."""
        if self.ideal or acc_true.shape[0] == 0:
            return np.array(acc_true, dtype=float)
        self._fill(k0)
        self._i = self.block
        return self._quantised(acc_true + self._dist[:acc_true.shape[0]])

    def _quantised(self, out: np.ndarray) -> np.ndarray:
        if self.quantise_all:
            return np.round(out / self.lsb) * self.lsb
        if self.quantise:
            return np.where(self.lsb > 0, np.round(out / self.lsb_safe) * self.lsb_safe, out)
        return out


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

    Notes
    -----
    All axes are advanced together: their exact ZOH discretisations are stacked into one
    block-diagonal system advanced by one matrix product a step (the output's row included),
    and each axis reads its own delayed inputs from the setpoints' history (a buffer whose
    newest part moves to its start every :data:`HISTORY_REWIND` steps).
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
        self._rate2 = self.rate_hz**2
        self._rng = np.random.default_rng(seed)
        self._sensor = _SensorStream(self.accelerometers, self.rate_hz, self._rng)
        self._build()
        self.violations = np.zeros(self.n, dtype=np.int64)
        self._lo, self._hi = self.p_min.tolist(), self.p_max.tolist()
        self._step_max = (None if self.v_max is None
                          else (self.v_max * self.dt_s * (1 + 1e-9)).tolist())
        self._none = np.zeros(self.n, dtype=bool)
        self._none.setflags(write=False)
        self.reset(np.zeros(self.n) if position is None else position)

    def _build(self) -> None:
        """Stack the axes into ``x' = Phi x + G0 u[k-d+1] + G1 u[k-d]``, ``y = C x + D u``."""
        orders = [d.order for d in self._disc]
        total = sum(orders)
        self._phi = np.zeros((total, total))
        self._g0 = np.zeros((total, self.n))
        self._g1 = np.zeros((total, self.n))
        self._c = np.zeros((self.n, total))
        self._dfeed = np.array([d.d_feed for d in self._disc])
        o = 0
        for i, (d, k) in enumerate(zip(self._disc, orders, strict=True)):
            self._phi[o:o + k, o:o + k] = d.phi
            self._g0[o:o + k, i] = d.gamma0[:, 0]
            self._g1[o:o + k, i] = d.gamma1[:, 0]
            self._c[i, o:o + k] = d.c[0]
            o += k
        self._order = total
        # the setpoints' history: a linear buffer whose last ``room`` columns move to its start
        # when it is full (room for any delay a drift may set without losing history)
        self._room = max(max(d.delay_samples for d in self._disc),
                         math.ceil(MAX_DELAY_S * self.rate_hz)) + 3
        self._cols = self._room + HISTORY_REWIND
        self._hist = np.zeros((self.n, self._cols))
        self._flat = self._hist.reshape(-1)
        self._base = np.arange(self.n) * self._cols
        self._d = np.array([d.delay_samples for d in self._disc])
        self._restack()

    def _restack(self) -> None:
        """The step's matrix from the axes' systems: ``[x'; y] = M [x; u[k-d+1]; u[k-d]]``
        with ``y = C x' + D u[k-d+1]``, and the history's offsets of each axis' delays."""
        c = self._c
        top = np.hstack((self._phi, self._g0, self._g1))
        bottom = np.hstack((c @ self._phi, c @ self._g0 + np.diag(self._dfeed), c @ self._g1))
        self._big = np.vstack((top, bottom))
        self._off_d = self._base - self._d
        # u[k-d+1] is the value held at the end of the period: this period's own for d = 0
        self._off_d1 = self._base - np.maximum(self._d - 1, 0)

    def set_model(self, axis: int, model: ProcessModel) -> None:
        """Change the true dynamics of ``axis`` (an index) now, keeping its motion: the output
        carries over (a first-order model may change any parameter; a higher-order one only its
        delay, up to :data:`MAX_DELAY_S`), and the setpoints it held are kept.

        Raises
        ------
        ConfigError
            For another order, a higher-order model whose dynamics change, or a longer delay.
        """
        new = model.discretize(self.rate_hz)
        old = self._disc[axis]
        if new.delay_samples + 3 > self._room:
            raise ConfigError(f"drift of axis {axis}: delay {model.dead_time_s:g} s beyond "
                              f"{MAX_DELAY_S:g} s")
        if new.order != old.order or (new.order > 1 and not (
                np.allclose(new.phi, old.phi) and np.allclose(new.c, old.c))):
            raise ConfigError(f"drift of axis {axis}: {model} is not {self.models[axis]} with "
                              "other parameters of the same first-order form, or the same "
                              "higher-order dynamics with another delay")
        o = sum(d.order for d in self._disc[:axis])
        k = new.order
        if k:
            x = self._x[o:o + k]
            y = float(old.c[0] @ x)
            if k == 1 and new.c[0, 0] != 0:
                self._x[o] = y / new.c[0, 0]
        models = list(self.models)
        models[axis] = model
        self.models = tuple(models)
        self._disc[axis] = new
        self._phi[o:o + k, o:o + k] = new.phi
        self._g0[o:o + k, axis] = new.gamma0[:, 0]
        self._g1[o:o + k, axis] = new.gamma1[:, 0]
        self._c[axis, o:o + k] = new.c[0]
        self._dfeed[axis] = new.d_feed
        self._d[axis] = new.delay_samples
        self._restack()

    def reset(self, position: ArrayLike) -> None:
        """At rest at ``position`` (the command and the output, for unit-gain axes)."""
        p = np.array(position, dtype=float).reshape(self.n)
        self._k = 0
        self._p = self._room
        self._hist[:] = p[:, None]
        self._x = np.concatenate([d.steady_state(float(pi)) for d, pi in
                                  zip(self._disc, p, strict=True)]) if self._phi.size else \
            np.zeros(0)
        y = self._c @ self._x + self._dfeed * p
        self._y1 = y.copy()
        self._y2 = y.copy()
        self.position_at_start = y.copy()
        self._u_last = p.tolist()
        self.position = y

    def step(self, setpoint: ArrayLike) -> tuple[FloatArray, FloatArray, np.ndarray]:
        """Apply one setpoint for one period.

        Returns ``(position, measured_acceleration, violated)``: the position at the *end* of
        the period, the acceleration measured at its *start* (the centre of the second
        difference; :attr:`position_at_start` is the position at that instant), and the axes
        whose setpoint broke a hard limit (and was clamped) or was not finite (and was held).
        """
        # per axis in plain floats: eight of them cost less than numpy's calls on arrays
        u = np.asarray(setpoint, dtype=float).reshape(self.n).tolist()
        last = self._u_last
        lo, hi, step_max = self._lo, self._hi, self._step_max
        violated = self._none
        for i, x in enumerate(u):
            bad = False
            if not lo[i] <= x <= hi[i]:  # out of range, or not finite
                bad = True
                # held: the last setpoint (inside the limits); else clamped
                u[i] = x = last[i] if not math.isfinite(x) else (lo[i] if x < lo[i] else hi[i])
            if step_max is not None and abs(x - last[i]) > step_max[i]:
                bad = True
            if bad:
                if violated is self._none:
                    violated = np.zeros(self.n, dtype=bool)
                violated[i] = True
                self.violations[i] += 1
        self._u_last = u
        p = self._p
        self._hist[:, p] = u
        flat = self._flat
        xy = self._big @ np.concatenate((self._x, flat[self._off_d1 + p], flat[self._off_d + p]))
        self._x = xy[:self._order]
        y = xy[self._order:]
        acc_true = (y - 2.0 * self._y1 + self._y2) * self._rate2
        # the stencil is centred on the start of this period: that is the instant at which
        # the acceleration is measured, and the position reported with it
        self.position_at_start = self._y1
        self._y2 = self._y1
        self._y1 = y
        self._k += 1
        if p + 1 == self._cols:  # full: the history the delays reach moves to the start
            self._hist[:, :self._room] = self._hist[:, -self._room:]
            p = self._room - 1
        self._p = p + 1
        acc = self._sensor.sample(acc_true, self._k)
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
