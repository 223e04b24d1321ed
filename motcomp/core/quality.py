"""What the platform receives, measured: apparent delay and the smoothness of a command.

One implementation of each figure, used offline (demo, replay analysis, benchmarks) and live (the
service's status):

``estimate_delay``
    delay of a response behind a reference by cross-correlation, the integer peak refined by a
    parabola through it and its neighbours (sub-sample).
``sine_delay``
    delay of a response to a pure sine of known frequency behind that sine, from a least-squares
    fit of ``a sin(w tau) + b cos(w tau) + c + d tau`` (``-atan2(b, a) / w``): unbiased on any
    window, where the cross-correlation of two equal windows of a slow motion is pulled towards
    zero (a 0.31 Hz sine delayed 4.6 ms reads 0.1-0.3 ms over 16-19 s).
``command_quality``
    of a position command sampled at a uniform rate: the RMS of its acceleration above
    ``above_hz`` (what vibrates the cabin and wears the actuators: a motion-cueing command lives
    below 2-3 Hz), its jerk RMS and its peak acceleration.  Acceleration and jerk are the second
    and third backward differences scaled by the rate.  The high-pass is spectral: the acceleration
    is tapered by a Hann window (its sidelobes fall as ``1/k^3``, so a 0.2 Hz motion leaks nothing
    measurable above 5 Hz), the bins below ``above_hz`` are zeroed, and the RMS of what remains is
    divided by the window's RMS.  A sinusoid of acceleration amplitude ``A`` above the cut reads
    ``A/sqrt(2)`` within a few per cent; one below it reads ~0.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from motcomp.core.lti import FloatArray
from motcomp.errors import ConfigError

__all__ = [
    "AT_LIMIT_FRACTION",
    "CommandQuality",
    "SineFit",
    "at_acc_limit",
    "command_quality",
    "command_quality_over",
    "estimate_delay",
    "hf_rms",
    "hf_within",
    "sine_delay",
    "stretches",
]

HF_ABOVE_HZ = 5.0
"""Default lower edge of the "high-frequency" band of the command's acceleration."""
AT_LIMIT_FRACTION = 0.99
"""A tick is at the acceleration limit when its |acceleration| reaches this fraction of it."""
HF_RESOLUTION = 1e-4
"""What :func:`hf_within` allows beyond the ratio (m/s^2): over a stretch of several seconds an
ideal run's command, a pure sine, reads next to nothing above 5 Hz (1e-6 m/s^2 over 15 s), so
that a ratio alone would judge a live command against rounding; 0.1 mm/s^2 is a twentieth of
what a swinging playback instant put there (docs/TUNING.md, "Input reconstruction")."""


def estimate_delay(reference: ArrayLike, response: ArrayLike, rate_hz: float,
                   max_lag_s: float = 1.0, min_lag_s: float = -0.5) -> float:
    """Delay (s) of ``response`` behind ``reference`` by cross-correlation, sub-sample.

    The search covers lags in ``[min_lag_s, max_lag_s]``; the integer peak is refined by a
    parabola through it and its neighbours.  Two equal windows pull a slow motion's estimate
    towards zero by what each holds that the other lacks (1.7 ms for a 0.3-2.1 Hz multisine
    delayed by 37 ms over 20 s; nothing measurable for 2-8 Hz): a caller that has the reference
    beyond the response's window aligns them and iterates (:mod:`motcomp.runtime.monitor`).

    Raises
    ------
    ConfigError
        If the signals differ in length, are constant, or the peak sits on the edge of the range.
    """
    r = np.asarray(reference, dtype=float)
    y = np.asarray(response, dtype=float)
    if r.shape != y.shape or r.ndim != 1:
        raise ConfigError(f"reference and response must be 1-D of equal length, got {r.shape} "
                          f"and {y.shape}")
    r = r - r.mean()
    y = y - y.mean()
    if not (np.any(r) and np.any(y)):
        raise ConfigError("cannot estimate a delay: a signal is constant")
    n = r.size
    nfft = 1 << math.ceil(math.log2(2 * n))
    xc = np.fft.irfft(np.fft.rfft(y, nfft) * np.conj(np.fft.rfft(r, nfft)), nfft)
    lo = math.floor(min_lag_s * rate_hz)
    hi = math.ceil(max_lag_s * rate_hz)
    lags = np.arange(lo, hi + 1)
    vals = xc[lags % nfft]
    i = int(np.argmax(vals))
    if i == 0 or i == lags.size - 1:
        raise ConfigError(f"cross-correlation peak at the edge of the searched lags "
                          f"[{min_lag_s}, {max_lag_s}] s: widen the range")
    y0, y1, y2 = vals[i - 1], vals[i], vals[i + 1]
    denom = y0 - 2 * y1 + y2
    frac = 0.5 * (y0 - y2) / denom if denom != 0 else 0.0
    return float((lags[i] + frac) / rate_hz)


@dataclass(frozen=True)
class SineFit:
    """A response fitted as a sine of the reference's frequency (:func:`sine_delay`)."""

    amplitude: float
    delay_s: float
    """Behind the reference, within half a period either way."""
    r2: float
    """Share of the response's variance the fit explains."""


def sine_delay(t_s: ArrayLike, y: ArrayLike, t0_s: float, frequency_hz: float) -> SineFit:
    """``y`` sampled at ``t_s`` as a delayed ``sin(2 pi f (t - t0_s))``: least squares of
    ``a sin(w tau) + b cos(w tau) + c + d tau`` (tau = t - t0_s), delay ``-atan2(b, a) / w``.

    Raises
    ------
    ConfigError
        If the samples are too few, of unequal length, or ``y`` is constant.
    """
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(y, dtype=float)
    if t.shape != v.shape or t.ndim != 1 or t.size < 5:
        raise ConfigError(f"a sine fit needs equal 1-D arrays of 5 samples or more, got "
                          f"{t.shape} and {v.shape}")
    if not (math.isfinite(frequency_hz) and frequency_hz > 0):
        raise ConfigError(f"sine frequency must be a positive number of Hz, got {frequency_hz}")
    var = float(v.var())
    if var == 0.0:
        raise ConfigError("cannot fit a sine: the response is constant")
    tau = t - t0_s
    w = 2.0 * math.pi * frequency_hz
    basis = np.column_stack([np.sin(w * tau), np.cos(w * tau), np.ones_like(tau),
                             tau - tau.mean()])
    coef, *_ = np.linalg.lstsq(basis, v, rcond=None)
    resid = v - basis @ coef
    return SineFit(float(math.hypot(coef[0], coef[1])), -math.atan2(coef[1], coef[0]) / w,
                   1.0 - float(resid.var()) / var)


def hf_within(live: float, ideal: float, ratio: float) -> bool:
    """Whether a command's HF acceleration RMS ``live`` is within ``ratio`` times the ideal
    run's over the same ticks, ``ideal``, plus :data:`HF_RESOLUTION`."""
    return live <= ratio * ideal + HF_RESOLUTION


def above(x: np.ndarray, rate_hz: float, above_hz: float = HF_ABOVE_HZ) -> FloatArray:
    """The part of the series ``x`` (sampled at ``rate_hz``) above ``above_hz``: its spectrum
    with the lower lines zeroed, as is (the caller tapers the series)."""
    spec = np.fft.rfft(x)
    spec[np.fft.rfftfreq(x.size, 1.0 / rate_hz) < above_hz] = 0.0
    return np.fft.irfft(spec, x.size)


def hf_rms(x: ArrayLike, rate_hz: float, above_hz: float = HF_ABOVE_HZ) -> float:
    """RMS of the part of ``x`` above ``above_hz`` (Hann-tapered spectrum, module docstring);
    0 for fewer than 8 samples."""
    a = np.asarray(x, dtype=float)
    n = a.size
    if n < 8:
        return 0.0
    w = np.hanning(n)
    hp = above((a - a.mean()) * w, rate_hz, above_hz)
    return float(math.sqrt(np.mean(hp * hp) / np.mean(w * w)))


@dataclass(frozen=True)
class CommandQuality:
    """Smoothness of a position command (units/s^2, units/s^3)."""

    hf_acc_rms: float
    """RMS of the acceleration above ``above_hz``."""
    jerk_rms: float
    acc_peak: float

    def as_dict(self) -> dict[str, float]:
        return {"hf_acc_rms": self.hf_acc_rms, "jerk_rms": self.jerk_rms,
                "acc_peak": self.acc_peak}


def command_quality(u: ArrayLike, rate_hz: float, above_hz: float = HF_ABOVE_HZ
                    ) -> CommandQuality:
    """:class:`CommandQuality` of the command ``u`` sampled at ``rate_hz`` (module docstring).

    Raises
    ------
    ConfigError
        If ``u`` is not 1-D or the rate is not positive.
    """
    x = np.asarray(u, dtype=float)
    if x.ndim != 1:
        raise ConfigError(f"command must be 1-D, got shape {x.shape}")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ConfigError(f"rate must be a positive number of Hz, got {rate_hz!r}")
    if x.size < 4:
        return CommandQuality(0.0, 0.0, 0.0)
    acc = np.diff(x, 2) * rate_hz ** 2
    jerk = np.diff(acc) * rate_hz
    return CommandQuality(hf_acc_rms=hf_rms(acc, rate_hz, above_hz),
                          jerk_rms=float(math.sqrt(np.mean(jerk * jerk))),
                          acc_peak=float(np.max(np.abs(acc))))


def command_quality_masked(u: ArrayLike, ok: ArrayLike, rate_hz: float,
                           above_hz: float = HF_ABOVE_HZ) -> CommandQuality:
    """:class:`CommandQuality` of ``u`` where ``ok`` marks the samples that are the command's
    (False: a missed tick on the grid), in a few vectorised passes (the service's status
    computes it beside its loop).  The jerk and the peak come from the differences whose
    samples all are, nothing bridged; the high-frequency figure from the whole acceleration
    series, a difference that is not interpolated in acceleration from its neighbours (a
    straight line in position over a missing sample would read the command's acceleration as
    a jerk of ``a / h``).  NaN without a whole third difference."""
    x = np.asarray(u, dtype=float)
    have = np.asarray(ok, dtype=bool)
    nan = math.nan
    if x.size < 4:
        return CommandQuality(nan, nan, nan)
    acc = np.diff(x, 2) * rate_hz ** 2
    acc_ok = have[:-2] & have[1:-1] & have[2:]
    jerk_ok = acc_ok[:-1] & acc_ok[1:]
    if not jerk_ok.any():
        return CommandQuality(nan, nan, nan)
    jerk = np.diff(acc)[jerk_ok] * rate_hz
    if not acc_ok.all():
        k = np.arange(acc.size)
        acc_f = acc.copy()
        acc_f[~acc_ok] = np.interp(k[~acc_ok], k[acc_ok], acc[acc_ok])
    else:
        acc_f = acc
    return CommandQuality(hf_acc_rms=hf_rms(acc_f, rate_hz, above_hz),
                          jerk_rms=float(math.sqrt(np.mean(jerk * jerk))),
                          acc_peak=float(np.max(np.abs(acc[acc_ok]))))


def stretches(have: ArrayLike) -> list[slice]:
    """The runs of consecutive True in ``have`` (e.g. the ticks a frame was recorded for)."""
    h = np.concatenate([[False], np.asarray(have, dtype=bool), [False]])
    edges = np.flatnonzero(np.diff(h.astype(np.int8)))
    return [slice(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def command_quality_over(u: ArrayLike, parts: Sequence[slice], rate_hz: float,
                         above_hz: float = HF_ABOVE_HZ) -> CommandQuality:
    """:func:`command_quality` over the stretches ``parts`` of ``u``, nothing bridged between
    them: the RMS values weighted by the differences each stretch holds (a stretch shorter than
    8 samples adds nothing to the HF figure, shorter than 4 nothing at all), the peak the
    largest.  A missing sample bridged linearly instead is an acceleration error of the
    command's own acceleration at that tick; and over a stretch of a second or so the spectrum
    leaks some of the motion's acceleration above ``above_hz``: compare two commands over the
    same stretches."""
    x = np.asarray(u, dtype=float)
    hf2 = jerk2 = 0.0
    n_hf = n_jerk = 0
    peak = 0.0
    for part in parts:
        seg = x[part]
        if seg.size < 4:
            continue
        q = command_quality(seg, rate_hz, above_hz)
        if seg.size >= 8:
            hf2 += q.hf_acc_rms ** 2 * (seg.size - 2)
            n_hf += seg.size - 2
        jerk2 += q.jerk_rms ** 2 * (seg.size - 3)
        n_jerk += seg.size - 3
        peak = max(peak, q.acc_peak)
    nan = math.nan
    return CommandQuality(hf_acc_rms=math.sqrt(hf2 / n_hf) if n_hf else nan,
                          jerk_rms=math.sqrt(jerk2 / n_jerk) if n_jerk else nan,
                          acc_peak=peak if n_jerk else nan)


def at_acc_limit(u: ArrayLike, rate_hz: float, a_max: float) -> np.ndarray:
    """Per second difference of the command ``u`` (element ``k`` belongs to tick ``k + 2``):
    its |acceleration| is within 1 % of ``a_max`` (:data:`AT_LIMIT_FRACTION`), the limiter
    holding the command at its acceleration bound."""
    acc = np.diff(np.asarray(u, dtype=float), 2) * rate_hz ** 2
    return np.asarray(np.abs(acc) >= AT_LIMIT_FRACTION * a_max)
