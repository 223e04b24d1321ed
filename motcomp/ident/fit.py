"""Output-error identification of a platform axis in the acceleration domain, with a free delay.

What is compared
----------------
The platform maps the commanded position ``u`` to the cabin position ``y = G u``; the
accelerometer reads ``y''``.  Because ``G`` is linear and time-invariant, ``y'' = G u''``: the
model's simulated response to the command's second derivative is compared with the measured
acceleration, with no integration of noisy measurements (which drifts with the bias) and no
differentiation of them.  In samples, with ``h = 1/rate``::

    v[k]     = (u[k+1] - 2 u[k] + u[k-1]) / h^2     (the command held at its end values)
    a_hat[k] = (G_d v)[k] + bias

where ``G_d`` is the exact zero-order-hold discretisation of ``G`` (the platform holds each
setpoint for one period) with its sub-sample delay (:func:`motcomp.core.lti.discretize_zoh`).
``a_hat[k]`` equals ``(y[k+1] - 2 y[k] + y[k-1]) / h^2`` of the exact positions: the true
acceleration averaged with a triangular window of +-h centred on ``t_k``, zero phase, which is what
an accelerometer band-limited to the sample rate reads at its time stamp.  The criterion is the
*simulation* (output) error ``sum (a[k] - a_hat[k])^2``: the model sees the command only, never
the measured outputs.

Prefilter
---------
The same zero-phase filter ``L`` is applied to ``v`` and to the measured ``a``: a 4th-order
Butterworth low-pass (forwards and backwards) above the command's band, and a notch on each
narrow line of the part of the measurement that the command does not explain (the controllers'
holding tremor, 10-20 Hz, found by coherence even inside the excitation band).  Since
``L a = G_d (L v) + L e`` exactly, the model is untouched: the filter only weights the error
towards the excited band.  That is why it can remove the tremor without
the "artificial phase lag" that filtering the measurement alone would add.  Samples within a few
filter time constants of either end are left out of every sum.

Estimation and validation
-------------------------
The usable samples are cut into 9 blocks; blocks 2, 5 and 8 (a third, spread over the record so
that a swept sine is validated across its band) are never used to fit.  The model is simulated
over the whole record and fit % and VAF are computed on the validation blocks only:
``fit = 100 (1 - ||a - a_hat|| / ||a - mean(a)||)`` (MATLAB's ``compare``) and
``VAF = 100 (1 - var(a - a_hat) / var(a))``, on the prefiltered signals (``fit_percent``) and on
the raw ones (``fit_percent_raw``, which the sensor noise caps).

The delay
---------
Never trusted to a gradient alone:

1. *Bracket*, non-parametric: a regularised FIR estimate of the impulse response from ``v`` to
   ``a`` (Toeplitz normal equations on the decimated data); a lag-type response cannot peak
   before its dead time, so the delay lies below the peak plus the estimate's blur.
2. *Coarse profile* at a decimated rate (the prefiltered signals downsampled to at least 4 times
   the filter's cut-off): for each starting ``theta`` of a grid and each half-sample phase, the
   regressors are simulated once and the least-squares error of *every* integer-sample shift is
   obtained from FFT correlations; the profile is the minimum over the grid.  If its minimum
   lies on the bracket's upper end the bracket is widened to the whole searched range; on the
   searched range's own ends, the data are rejected (the delay is outside the range).
3. *Fine profile* at the full rate with the exact model: ``P(Td) = min_theta SSE`` by
   separable least squares (``theta`` by Levenberg-Marquardt, warm-started; the linear
   parameters and the bias solved exactly), walked in steps of one sample until a minimum is
   enclosed, then in half and quarter samples around it and interpolated by a parabola.  The
   error is summed over every ``M``-th sample (``M`` the decimation factor): the prefiltered
   signals carry no more information than that, and the simulation stays at the full rate.
4. *Polish*: all nonlinear parameters and the delay together (bounded to one sample about the
   profile's minimum), kept only if it lowers the error.

Uncertainty and selection
-------------------------
Standard errors come from the Jacobian of the residual in the reported parameters (the bias
included) with a Newey-West (Bartlett) estimate of the residuals' long-run covariance, because
prefiltered residuals are strongly correlated from sample to sample:
``cov = (J'J)^-1 S (J'J)^-1``.  The standard error of the phase delay at 0.2 Hz follows by the
delta method.  AIC is ``N_eff ln(SSE/N) + 2 p`` with ``N_eff = N * 2 f_c / rate`` (the number of
independent samples in the prefilter's band).  The selected model is the simplest (P1D, P2D,
P2UZD, OE in that order) that is *adequate*: its validation fit is within ``select_tolerance``
points (default 1) of the best, and either its AIC is within 10 of the lowest or its pure delay
and phase delay at 0.2 Hz agree with those of the lowest-AIC model (:func:`select_model`).  A
more complex model must earn its parameters on data it has not seen *and* either explain the
data clearly better or change the numbers the compensator uses.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import linalg as sla
from scipy import signal

from motcomp.core.lti import FloatArray, discretize_zoh
from motcomp.core.models import ProcessModel
from motcomp.errors import ConfigError, DataError, ModelFitError
from motcomp.ident.data import Recording, spectrum_tops
from motcomp.ident.structures import STRUCTURES, Structure, make_structure

__all__ = [
    "DelayRangeError",
    "FitOptions",
    "Identification",
    "ModelFit",
    "Prepared",
    "fit_structure",
    "identify",
    "long_run_cov",
    "predict_acceleration",
    "prepare",
    "second_difference",
    "select_model",
]

BoolArray = NDArray[np.bool_]
ProgressFn = Callable[[str], None]


@dataclass(frozen=True)
class FitOptions:
    """Settings of :func:`identify` (all have defaults that suit the paper's excitations)."""

    models: tuple[str, ...] = STRUCTURES
    delay_min_s: float = 0.0
    delay_max_s: float = 0.25
    oe_order: int = 2
    oe_pade: int = 1
    cutoff_hz: float | None = None
    """Prefilter cut-off; default from the command's spectrum (see :func:`prepare`)."""
    notch: bool = True
    """Notch narrow lines of the measurement that the command does not have (tremor)."""
    select_tolerance: float = 1.0
    """Validation fit % points by which a simpler model may trail the best and still win."""

    def __post_init__(self) -> None:
        if not self.models:
            raise ConfigError("no model to fit")
        for kind in self.models:
            if kind not in STRUCTURES:
                raise ConfigError(f"unknown model kind {kind!r}; kinds: {', '.join(STRUCTURES)}")
        if len(set(self.models)) != len(self.models):
            raise ConfigError(f"model list {', '.join(self.models)} names a model twice")
        lo, hi = self.delay_min_s, self.delay_max_s
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi):
            raise ConfigError(f"delay range must satisfy 0 <= min < max, got [{lo}, {hi}] s")
        if self.cutoff_hz is not None and not (math.isfinite(self.cutoff_hz)
                                               and self.cutoff_hz > 0):
            raise ConfigError(f"prefilter cut-off must be > 0 Hz, got {self.cutoff_hz}")
        if not 1 <= self.oe_order <= 4:
            raise ConfigError(f"OE order must be 1..4, got {self.oe_order}")
        if not 0 <= self.oe_pade <= 4:
            raise ConfigError(f"OE Pade order must be 0..4, got {self.oe_pade}")
        if not (math.isfinite(self.select_tolerance) and self.select_tolerance >= 0):
            raise ConfigError(f"selection tolerance must be >= 0, got {self.select_tolerance}")


def second_difference(cmd: FloatArray, rate_hz: float) -> FloatArray:
    """``(u[k+1] - 2 u[k] + u[k-1]) * rate^2`` with ``u`` held at its end values outside."""
    u = np.concatenate([cmd[:1], cmd, cmd[-1:]])
    return np.asarray((u[2:] - 2.0 * u[1:-1] + u[:-2]) * rate_hz**2)


# --- data preparation ---------------------------------------------------------------------------

@dataclass
class Prepared:
    """Prefiltered, split and decimated data, ready for fitting."""

    recording: Recording
    rate_hz: float
    v: FloatArray
    y: FloatArray
    v_raw: FloatArray
    y_raw: FloatArray
    acc_mean: float
    est: BoolArray
    val: BoolArray
    cutoff_hz: float
    band_hz: float
    notches_hz: list[float]
    edge_samples: int
    coarse_factor: int
    v_c: FloatArray
    y_c: FloatArray
    est_c: BoolArray

    @property
    def h(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def rate_c(self) -> float:
        return self.rate_hz / self.coarse_factor

    @property
    def coarse_extra_s(self) -> float:
        """Delay to add to a model on the coarse data (see :func:`prepare`)."""
        return 0.5 / self.rate_hz + 0.5 / self.rate_c

    def summary(self) -> dict[str, Any]:
        return {
            "rate_hz": self.rate_hz,
            "samples": int(self.v.size),
            "duration_s": self.v.size / self.rate_hz,
            "resampled": self.recording.resampled,
            "period_jitter_ms": self.recording.period_jitter_s * 1e3,
            "excitation_band_hz": self.band_hz,
            "prefilter_cutoff_hz": self.cutoff_hz,
            "notches_hz": self.notches_hz,
            "estimation_samples": int(self.est.sum()),
            "validation_samples": int(self.val.sum()),
            "edge_s": self.edge_samples / self.rate_hz,
            "coarse_rate_hz": self.rate_c,
            "acc_mean": self.acc_mean,
        }


def _lines(y: FloatArray, v: FloatArray, rate_hz: float, f_hi: float) -> list[float]:
    """Frequencies of narrow lines in the part of ``y`` that ``v`` does not explain (up to 3,
    strongest first).

    That part's spectrum is estimated without any model as ``P_yy (1 - coherence(v, y))``
    (Welch, 4 s segments); a line stands 15 dB above its running median (+-2 Hz).  Inside the
    excitation band the response hides a tremor line from a plain spectrum; the coherence does
    not, and the lines of a multisine, explained by the command, are not taken for tremor.
    """
    nper = min(y.size, max(256, int(4.0 * rate_hz)))
    f, py = signal.welch(y, fs=rate_hz, nperseg=nper)
    _, coh = signal.coherence(v, y, fs=rate_hz, nperseg=nper)
    pn = py * np.clip(1.0 - coh, 0.0, 1.0)
    df = f[1] - f[0]
    width = max(5, round(4.0 / df) | 1)
    from scipy.ndimage import median_filter

    base = median_filter(pn, size=width, mode="nearest")
    score = pn / np.maximum(base, 1e-300)
    ok = (f >= 1.0) & (f <= f_hi) & (score > 10 ** 1.5)
    peaks = [i for i in np.nonzero(ok)[0]
             if score[i] >= score[max(i - 1, 0)] and score[i] >= score[min(i + 1, f.size - 1)]]
    peaks.sort(key=lambda i: -score[i])
    out: list[float] = []
    for i in peaks:
        # centroid over the bin and its neighbours for a sub-bin frequency
        sl = slice(max(i - 1, 0), min(i + 2, f.size))
        fc = float(np.sum(f[sl] * pn[sl]) / np.sum(pn[sl]))
        if all(abs(fc - o) > 1.0 for o in out):
            out.append(fc)
        if len(out) == 3:
            break
    return out


REFERENCE_CUTOFF_FACTOR = 2.0
"""With the reference the platform was asked to follow in the recording (the excitation), the
prefilter's cut-off is this many times its band's top (:attr:`Recording.band_hz`): the command
the platform received also carries the limiter's and the stack's work above that band, which
the fit must not try to explain (docs/IDENTIFICATION.md)."""


def prepare(rec: Recording, options: FitOptions = FitOptions()) -> Prepared:
    """Second difference of the command, prefilter, split and decimation (module notes).

    The prefilter cut-off is :data:`REFERENCE_CUTOFF_FACTOR` times the excitation's band when
    the recording holds the reference (:attr:`Recording.band_hz`), else 1.25 times the
    frequency above which the spectrum of ``v`` stays 30 dB below its peak (at least 1 Hz, at
    most a fifth of the rate).  The decimated data used
    by the coarse profile keep every ``M``-th sample, ``M = floor(rate / (4 f_c))``, with the
    command advanced by one coarse sample; a zero-order hold at the coarse period lags a smooth
    signal by half that period and the full-rate hold by half a full period, so a model of
    delay ``Td`` is simulated there with ``Td + h/2 + h_c/2``.

    Raises
    ------
    DataError
        If the record is too short for the filters' edges and the split.
    """
    rate = rec.rate_hz
    v_raw = second_difference(rec.cmd, rate)
    acc_mean = float(np.mean(rec.acc))
    y_raw = rec.acc - acc_mean
    f30, band = spectrum_tops(v_raw, rate)
    if not f30 > 0:
        raise DataError(f"{rec.source}: column cmd: the command has no acceleration content")
    if rec.band_hz is not None:  # the excitation's own band, from the reference input
        band = rec.band_hz
        auto = min(max(REFERENCE_CUTOFF_FACTOR * band, 1.0), rate / 5.0)
    else:
        auto = min(max(1.25 * f30, 1.0), rate / 5.0)
    cutoff = options.cutoff_hz or auto
    if cutoff >= rate / 2.0:
        raise ConfigError(f"prefilter cut-off {cutoff:g} Hz is above the Nyquist frequency "
                          f"{rate / 2:g} Hz")
    notches = _lines(y_raw, v_raw, rate, min(2.0 * cutoff, 0.45 * rate)) if options.notch else []
    sos = signal.butter(4, cutoff, btype="low", fs=rate, output="sos")
    v = signal.sosfiltfilt(sos, v_raw)
    y = signal.sosfiltfilt(sos, y_raw)
    for f0 in notches:
        b, a = signal.iirnotch(f0, f0 / 0.5, fs=rate)
        v = signal.filtfilt(b, a, v)
        y = signal.filtfilt(b, a, y)
    n = v.size
    edge_s = max(0.25, 4.0 / cutoff, 1.5 if notches else 0.0)
    edge = math.ceil(edge_s * rate)
    usable = n - 2 * edge
    if usable < 9 * max(50, math.ceil(2.0 * rate / cutoff)):
        raise DataError(f"{rec.source}: {rec.duration_s:.3g} s of data is too short: after "
                        f"{edge_s:.3g} s filter edges at both ends, {usable / rate:.3g} s are left")
    est = np.zeros(n, dtype=bool)
    val = np.zeros(n, dtype=bool)
    bounds = edge + np.round(np.linspace(0, usable, 10)).astype(int)
    for i in range(9):
        (val if i % 3 == 1 else est)[bounds[i]:bounds[i + 1]] = True
    m = max(1, math.floor(rate / (4.0 * cutoff)))
    v_c = v[m::m]
    y_c = y[: v_c.size * m: m]
    est_c = est[: v_c.size * m: m]
    return Prepared(recording=rec, rate_hz=rate, v=np.asarray(v), y=np.asarray(y), v_raw=v_raw,
                    y_raw=np.asarray(y_raw), acc_mean=acc_mean, est=est, val=val,
                    cutoff_hz=float(cutoff), band_hz=band, notches_hz=notches, edge_samples=edge,
                    coarse_factor=m, v_c=np.asarray(v_c), y_c=np.asarray(y_c), est_c=est_c)


# --- simulation and separable least squares -----------------------------------------------------

def _response(num: FloatArray, den: FloatArray, delay_s: float, h: float, v: FloatArray
              ) -> FloatArray:
    """Exact ZOH response of ``num/den e^{-delay s}`` to ``v`` from rest (integer part shifted)."""
    m = math.floor(delay_s / h + 1e-9)
    frac = delay_s - m * h
    if frac < 1e-9 * h:
        frac = 0.0
    b, a = discretize_zoh(num, den, frac, h).tf()
    if b.size < a.size:
        b = np.concatenate([np.zeros(a.size - b.size), b])
    y = signal.lfilter(b, a, v)
    if m > 0:
        y = np.concatenate([np.zeros(min(m, v.size)), y[: max(v.size - m, 0)]])
    return np.asarray(y)


def predict_acceleration(model: ProcessModel, v: FloatArray, rate_hz: float) -> FloatArray:
    """``G_d v``: the model's acceleration for the command's second difference ``v``."""
    num, den = model.rational()
    return _response(num, den, model.dead_time_s, 1.0 / rate_hz, v)


class _Data:
    """One data set (full-rate or coarse) on which structures are evaluated.

    The model is simulated on every sample of ``v``; the error is summed over the samples
    ``idx`` (which may skip samples: the prefiltered signals are band-limited far below the
    rate, so every ``M``-th sample carries the same information as all of them).
    """

    def __init__(self, v: FloatArray, y: FloatArray, mask: BoolArray, h: float,
                 extra_delay_s: float, every: int = 1) -> None:
        self.v = v
        self.y = y
        self.mask = mask
        keep = mask.copy()
        if every > 1:
            keep &= (np.arange(mask.size) % every) == 0
        self.idx = np.nonzero(keep)[0]
        self.yi = y[self.idx]
        self.h = h
        self.extra = extra_delay_s
        self.evals = 0

    def regressors(self, s: Structure, theta: FloatArray, delay_s: float) -> FloatArray:
        regs, dead = s.regressors(theta, delay_s)
        self.evals += 1
        return np.array([_response(n, d, dead + self.extra, self.h, self.v) for n, d in regs])

    def solve(self, R: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Coefficients ``[c..., bias]`` minimising the masked error, and the full residual."""
        coef = self._coef(R[:, self.idx])
        return coef, self.y - np.einsum("i,ik->k", coef[:-1], R) - coef[-1]

    def _coef(self, Ri: FloatArray) -> FloatArray:
        # einsum rather than BLAS: three or four long vectors, where a threaded BLAS only adds
        # contention on a busy machine
        X = np.vstack([Ri, np.ones(Ri.shape[1])])
        G = np.einsum("ik,jk->ij", X, X)
        g = np.einsum("ik,k->i", X, self.yi)
        scale = np.sqrt(np.maximum(np.diag(G), 1e-300))
        coef_s, *_ = np.linalg.lstsq(G / np.outer(scale, scale), g / scale, rcond=1e-13)
        return np.asarray(coef_s / scale)

    def residual(self, s: Structure, theta: FloatArray, delay_s: float) -> FloatArray:
        """The residual on the criterion's samples ``idx``."""
        Ri = self.regressors(s, theta, delay_s)[:, self.idx]
        coef = self._coef(Ri)
        return np.asarray(self.yi - np.einsum("i,ik->k", coef[:-1], Ri) - coef[-1])

    def sse(self, s: Structure, theta: FloatArray, delay_s: float) -> float:
        r = self.residual(s, theta, delay_s)
        return float(r @ r)

    def shift_profile(self, R: FloatArray, m_lo: int, m_hi: int) -> FloatArray:
        """Least-squares error for the regressors shifted by ``m = m_lo..m_hi`` samples.

        ``R_m[k] = R[k - m]`` (zero before the record: the axis was at rest).  The normal
        equations of every shift come from FFT correlations:
        ``sum_k w_k R_i[k-m] R_j[k-m] = corr(w, R_i R_j)[m]`` and
        ``sum_k w_k y_k R_i[k-m] = corr(w y, R_i)[m]``.
        """
        n = R.shape[1]
        p = R.shape[0]
        L = _fast_len(n + m_hi + 1)
        w = self.mask.astype(float)
        scale = np.sqrt(np.maximum(np.einsum("ij,ij->i", R, R), 1e-300))
        Rs = R / scale[:, None]
        fw = np.fft.rfft(w, L)
        fwy = np.fft.rfft(w * self.y, L)

        def corr(fx: NDArray[Any], z: FloatArray) -> FloatArray:
            c = np.fft.irfft(fx * np.conj(np.fft.rfft(z, L)), L)
            return np.asarray(c[m_lo:m_hi + 1])

        M = m_hi - m_lo + 1
        A = np.empty((M, p + 1, p + 1))
        g = np.empty((M, p + 1))
        for i in range(p):
            for j in range(i, p):
                A[:, i, j] = A[:, j, i] = corr(fw, Rs[i] * Rs[j])
            A[:, i, p] = A[:, p, i] = corr(fw, Rs[i])
            g[:, i] = corr(fwy, Rs[i])
        A[:, p, p] = w.sum()
        g[:, p] = float(np.sum(w * self.y))
        yy = float(np.sum(w * self.y**2))
        ridge = 1e-12 * np.trace(A, axis1=1, axis2=2)[:, None, None] * np.eye(p + 1)
        sol = np.linalg.solve(A + ridge, g[..., None])[..., 0]
        return np.asarray(yy - np.einsum("mi,mi->m", g, sol))


def _fast_len(n: int) -> int:
    from scipy.fft import next_fast_len

    return int(next_fast_len(n, real=True))


def _lm(fun: Callable[[FloatArray], FloatArray], x0: FloatArray, lo: FloatArray,
        hi: FloatArray, steps: FloatArray, tol: float, max_iter: int
        ) -> tuple[FloatArray, float]:
    """Projected Levenberg-Marquardt for a handful of parameters and a long residual.

    Forward-difference Jacobian with the given ``steps`` (taken inwards at a bound), damping
    ``lambda diag(J'J)``, steps clipped to the bounds; stops when the cost or the step falls
    below ``tol`` (relative).  Small and BLAS-free on purpose: ``J'J`` is a 4x4 at most, and
    the residual is tens of thousands long.  Returns ``(x, cost)`` with ``cost = sum r^2``.
    """
    x = np.clip(np.asarray(x0, dtype=float), lo, hi)
    r = fun(x)
    cost = float(np.einsum("k,k->", r, r))
    lam = 1e-3
    n = x.size
    J = np.empty((n, r.size))
    for _ in range(max_iter):
        for i in range(n):
            xi = x.copy()
            step = steps[i] if x[i] + steps[i] <= hi[i] else -steps[i]
            xi[i] += step
            J[i] = (fun(xi) - r) / step
        A = np.einsum("ik,jk->ij", J, J)
        g = np.einsum("ik,k->i", J, r)
        d = np.maximum(np.diag(A), 1e-300)
        improved = False
        for _ in range(12):
            try:
                dx = -np.linalg.solve(A + lam * np.diag(d), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            xn = np.clip(x + dx, lo, hi)
            rn = fun(xn)
            cn = float(np.einsum("k,k->", rn, rn))
            if cn < cost:
                improved = True
                small_step = bool(np.all(np.abs(xn - x) <= tol * (np.abs(x) + tol)))
                small_gain = cost - cn <= tol * cost
                x, r, cost = xn, rn, cn
                lam = max(lam / 4.0, 1e-9)
                break
            lam *= 4.0
        if not improved or small_step or small_gain:
            break
    return x, cost


def _inner(data: _Data, s: Structure, theta0: FloatArray, delay_s: float,
           bounds: tuple[FloatArray, FloatArray], tol: float = 1e-9) -> tuple[FloatArray, float]:
    """``min_theta SSE(theta, delay)`` by Levenberg-Marquardt from ``theta0``."""
    lo, hi = bounds
    try:
        return _lm(lambda th: data.residual(s, th, delay_s), theta0, lo, hi,
                   np.full(theta0.size, 1e-6), tol, max_iter=25)
    except (np.linalg.LinAlgError, ValueError, ModelFitError):
        x0 = np.clip(theta0, lo, hi)
        return x0, data.sse(s, x0, delay_s)


# --- the delay: bracket, profiles, polish -------------------------------------------------------

@dataclass
class Bracket:
    """The non-parametric bracket of the delay."""

    lo_s: float
    hi_s: float
    ir_peak_s: float
    ir_t_s: FloatArray = field(repr=False)
    ir: FloatArray = field(repr=False)


def delay_bracket(prep: Prepared, lo_s: float, hi_s: float) -> Bracket:
    """Regularised FIR estimate of the impulse response ``v -> a`` on the coarse data; the
    delay lies in ``[lo, min(hi, peak + blur)]`` for a response that cannot peak before its
    dead time; the blur allowance is ``max(4 h_c, 2 / f_c)``.
    """
    h_c = 1.0 / prep.rate_c
    e = prep.coarse_extra_s
    taps = max(8, math.ceil((hi_s + e + 1.0) / h_c))
    v, y = prep.v_c, prep.y_c
    n = v.size
    taps = min(taps, n // 4)
    L = _fast_len(2 * n)
    fv = np.fft.rfft(v, L)
    r_vv = np.fft.irfft(fv * np.conj(fv), L)[:taps]
    r_vy = np.fft.irfft(np.fft.rfft(y, L) * np.conj(fv), L)[:taps]
    col = r_vv.copy()
    col[0] *= 1.0 + 1e-2
    g = sla.solve_toeplitz(col, r_vy)
    t = np.arange(taps) * h_c - e
    sel = (t >= lo_s - 2 * h_c) & (t <= hi_s + 1.0)
    idx = np.nonzero(sel)[0]
    k = int(idx[np.argmax(np.abs(g[idx]))]) if idx.size else 0
    peak = float(t[k])
    blur = max(4.0 * h_c, 2.0 / prep.cutoff_hz)
    b_hi = min(hi_s, max(peak, lo_s) + blur)
    return Bracket(lo_s=lo_s, hi_s=max(b_hi, min(hi_s, lo_s + blur)), ir_peak_s=peak,
                   ir_t_s=t, ir=np.asarray(g))


class DelayRangeError(DataError):
    """The best pure delay of a structure lies on ``side`` (``"lower"``, ``"upper"``) of the
    searched range, at ``value_s``."""

    def __init__(self, message: str, side: str, value_s: float) -> None:
        super().__init__(message)
        self.side, self.value_s = side, value_s


def _outside(side: str, value_s: float, lo_s: float, hi_s: float) -> DelayRangeError:
    if side == "upper":
        hint = "widen the delay range (--delay-range)"
    elif lo_s > 0:
        hint = ("lower the delay range's minimum, or the measurement may lead the command "
                "(clocks or columns misaligned?)")
    else:
        hint = ("a delay of zero or less: the measurement may lead the command (clocks or "
                "columns misaligned?)")
    return DelayRangeError(f"pure delay outside the searched range: the best delay is at the "
                           f"{side} end ({value_s * 1e3:.1f} ms) of [{lo_s * 1e3:.1f}, "
                           f"{hi_s * 1e3:.1f}] ms; {hint}", side, value_s)


def _coarse_profile(prep: Prepared, s: Structure, lo_s: float, hi_s: float, grid: FloatArray
                    ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Profile on the coarse data over ``[lo, hi]``: ``(tau, sse, best theta per tau)``."""
    h_c = 1.0 / prep.rate_c
    data = _Data(prep.v_c, prep.y_c, prep.est_c, h_c, prep.coarse_extra_s)
    if s.shift_delay:
        m_lo = math.floor(lo_s / h_c)
        m_hi = math.ceil(hi_s / h_c)
        taus, sses, thetas = [], [], []
        for phase in (0.0, 0.5):
            best = np.full(m_hi - m_lo + 1, np.inf)
            best_th = np.zeros((m_hi - m_lo + 1, grid.shape[1]))
            for theta in grid:
                try:
                    R = data.regressors(s, theta, phase * h_c)
                    prof = data.shift_profile(R, m_lo, m_hi)
                except (np.linalg.LinAlgError, ValueError):
                    continue
                better = prof < best
                best[better] = prof[better]
                best_th[better] = theta
            taus.append((np.arange(m_lo, m_hi + 1) + phase) * h_c)
            sses.append(best)
            thetas.append(best_th)
        tau = np.concatenate(taus)
        sse = np.concatenate(sses)
        th = np.concatenate(thetas)
        keep = (tau >= lo_s - 1e-12) & (tau <= hi_s + 1e-12)
        order = np.argsort(tau[keep])
        return tau[keep][order], sse[keep][order], th[keep][order]
    # delay inside the rational (Pade): a sparser delay grid, every theta at every delay
    n_tau = max(9, min(17, math.ceil((hi_s - lo_s) / (h_c / 2)) + 1))
    tau = np.linspace(lo_s, hi_s, n_tau)
    sse = np.full(n_tau, np.inf)
    th = np.zeros((n_tau, grid.shape[1]))
    for i, d in enumerate(tau):
        for theta in grid:
            try:
                val = data.sse(s, theta, float(d))
            except (np.linalg.LinAlgError, ValueError, ModelFitError):
                continue
            if val < sse[i]:
                sse[i], th[i] = val, theta
    return tau, sse, th


def _parabola_min(x: FloatArray, y: FloatArray) -> float:
    """Vertex of the parabola through three points (the middle one lowest)."""
    x0, x1, x2 = x
    y0, y1, y2 = y
    den = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den
    b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / den
    if not a > 0:
        return float(x1)
    return float(np.clip(-b / (2 * a), x0, x2))


@dataclass
class ModelFit:
    """One fitted structure and how well it does."""

    kind: str
    model: ProcessModel
    params: dict[str, Any]
    stderr: dict[str, float | None]
    fit_percent: float
    vaf_percent: float
    fit_percent_raw: float
    vaf_percent_raw: float
    aic: float
    n_params: int
    rmse: float
    bias: float
    seconds: float
    table1: dict[str, Any]
    at_bounds: list[str]
    profile_coarse: tuple[FloatArray, FloatArray] = field(repr=False)
    profile_fine: tuple[FloatArray, FloatArray] = field(repr=False)
    prediction: FloatArray = field(repr=False)
    prediction_raw: FloatArray = field(repr=False)
    evaluations: int = 0
    stage_evals: dict[str, int] = field(default_factory=dict)
    tradeoffs: list[dict[str, Any]] = field(default_factory=list)
    """Parameters the data do not tell apart, and what they fix instead (:func:`_tradeoffs`)."""

    def to_json(self) -> dict[str, Any]:
        return {
            "spec": self.model.spec(),
            "params": self.params,
            "stderr": self.stderr,
            "fit_percent": self.fit_percent,
            "vaf_percent": self.vaf_percent,
            "fit_percent_raw": self.fit_percent_raw,
            "vaf_percent_raw": self.vaf_percent_raw,
            "aic": self.aic,
            "n_params": self.n_params,
            "rmse": self.rmse,
            "bias": self.bias,
            "at_bounds": self.at_bounds,
            "not_identified_separately": self.tradeoffs,
            "seconds": self.seconds,
            **self.table1,
        }


def _fit_metrics(y: FloatArray, yhat: FloatArray, mask: BoolArray) -> tuple[float, float]:
    e = y[mask] - yhat[mask]
    ym = y[mask]
    fit = 100.0 * (1.0 - float(np.linalg.norm(e)) / float(np.linalg.norm(ym - ym.mean())))
    vaf = 100.0 * (1.0 - float(np.var(e)) / float(np.var(ym)))
    return fit, vaf


def long_run_cov(scores: FloatArray, lags: int) -> FloatArray:
    """Newey-West ``sum_{|l|<=L} (1 - |l|/(L+1)) sum_k s_k s_{k+l}'`` of score rows ``(q, N)``."""
    q, n = scores.shape
    L = _fast_len(n + lags + 1)
    F = np.fft.rfft(scores, L, axis=1)
    S = np.empty((q, q))
    w = 1.0 - np.arange(lags + 1) / (lags + 1.0)
    for i in range(q):
        for j in range(i, q):
            c = np.fft.irfft(F[i] * np.conj(F[j]), L)
            # c[l] = sum_k s_i[k+l] s_j[k]; negative lags at the end
            pos = c[: lags + 1]
            neg = c[L - lags:][::-1]
            val = w[0] * pos[0] + float(np.sum(w[1:] * (pos[1:] + neg)))
            S[i, j] = S[j, i] = val
    return S


def _derived(model: ProcessModel) -> dict[str, float]:
    """Pure delay and phase delay at 0.2 Hz (ms); for a negative gain (an accelerometer
    mounted the other way round), the phase delay of ``-G``."""
    flip = 0.5 / 0.2 if model.gain < 0 else 0.0  # pi / w at 0.2 Hz
    return {
        "pure_delay_ms": model.pure_delay_s * 1e3,
        "phase_delay_0p2hz_ms": (float(model.phase_delay(0.2)[0]) + flip) * 1e3,
    }


def _table1(model: ProcessModel, cov_derived: dict[str, float | None]) -> dict[str, Any]:
    d = _derived(model)
    bw3, bw6 = model.bandwidth(-3.0), model.bandwidth(-6.0)
    return {
        "pure_delay_ms": d["pure_delay_ms"],
        "pure_delay_ms_stderr": cov_derived.get("pure_delay_ms"),
        "phase_delay_0p2hz_ms": d["phase_delay_0p2hz_ms"],
        "phase_delay_0p2hz_ms_stderr": cov_derived.get("phase_delay_0p2hz_ms"),
        "bandwidth_hz": {"-3dB": bw3 if math.isfinite(bw3) else None,
                         "-6dB": bw6 if math.isfinite(bw6) else None},
    }


TRADEOFF_CORRELATION = 0.98
"""Two parameters whose estimates correlate beyond this (in absolute value) are not identified
separately: the data fix one combination of them (:func:`_tradeoffs`)."""


def _tradeoffs(names: list[str], values: FloatArray, cov: FloatArray) -> list[dict[str, Any]]:
    """The groups of natural parameters the data do not tell apart: linked by estimates that
    correlate beyond :data:`TRADEOFF_CORRELATION` (in absolute value; a covariance so
    degenerate that it reads beyond 1 counts too).  For a pair of time constants, the
    combination the data do fix: their difference when they move together (a delay and a
    zero's lead: only ``Td - Tz``), their sum when they move against each other (two equal
    poles).  A larger group is named only: the data fix fewer combinations than it has
    parameters."""
    n = len(names)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    group = list(range(n))

    def root(k: int) -> int:
        while group[k] != k:
            k = group[k]
        return k

    corr: dict[tuple[int, int], float] = {}
    for i in range(n):
        for j in range(i + 1, n):
            if sd[i] > 0 and sd[j] > 0:
                r = float(cov[i, j] / (sd[i] * sd[j]))
                if abs(r) > TRADEOFF_CORRELATION:
                    corr[(i, j)] = r
                    group[root(j)] = root(i)
    members: dict[int, list[int]] = {}
    for k in range(n):
        members.setdefault(root(k), []).append(k)
    out: list[dict[str, Any]] = []
    for ks in members.values():
        if len(ks) < 2:
            continue
        item: dict[str, Any] = {"params": [names[k] for k in ks]}
        if len(ks) == 2:
            i, j = ks
            r = max(-1.0, min(1.0, corr[(i, j)]))
            item["correlation"] = r
            if names[i].startswith("T") and names[j].startswith("T"):  # two times (s)
                sign = -1.0 if r > 0 else 1.0
                var = float(cov[i, i] + cov[j, j] + 2 * sign * cov[i, j])
                item.update(identified=f"{names[i]} {'-' if sign < 0 else '+'} {names[j]}",
                            value_ms=float(values[i] + sign * values[j]) * 1e3,
                            stderr_ms=math.sqrt(var) * 1e3 if var >= 0 else None)
        out.append(item)
    return out


def _uncertainty(prep: Prepared, s: Structure, model: ProcessModel, bias: float,
                 residual: FloatArray) -> tuple[dict[str, float | None], dict[str, float | None],
                                                list[dict[str, Any]]]:
    """Standard errors of the natural parameters and of the Table 1 delays (delta method), and
    the parameters the data do not tell apart (:func:`_tradeoffs`)."""
    nat = s.natural(model)
    names = list(nat)
    x0 = np.array([nat[k] for k in names] + [bias])
    mask = prep.est
    rate = prep.rate_hz

    def resid(x: FloatArray) -> FloatArray:
        m = s.from_natural(dict(zip(names, x[:-1], strict=True)))
        return np.asarray((prep.y - predict_acceleration(m, prep.v, rate) - x[-1])[mask])

    q = x0.size
    J = np.empty((int(mask.sum()), q))
    steps = np.maximum(np.abs(x0) * 1e-5, 1e-9)
    steps[-1] = max(float(np.std(prep.y)) * 1e-5, 1e-12)
    nan: dict[str, float | None] = dict.fromkeys(names)
    for i in range(q):
        xp, xm = x0.copy(), x0.copy()
        xp[i] += steps[i]
        xm[i] -= steps[i]
        try:
            J[:, i] = -(resid(xp) - resid(xm)) / (2 * steps[i])
        except (ConfigError, ModelFitError, ValueError):
            return nan, {}, []
    e = residual[mask]
    lags = math.ceil(2.0 * rate / prep.cutoff_hz)
    try:
        JtJ_inv = np.linalg.inv(J.T @ J)
        S = long_run_cov(J.T * e[None, :], lags)
        cov = JtJ_inv @ S @ JtJ_inv
    except np.linalg.LinAlgError:
        return nan, {}, []
    diag = np.diag(cov)
    tradeoffs = _tradeoffs(names, x0[:-1], cov[:-1, :-1])
    se: dict[str, float | None] = {
        k: (math.sqrt(float(d)) if d >= 0 and math.isfinite(d) else None)
        for k, d in zip(names, diag[:-1], strict=True)}
    # delta method for the Table 1 delays
    base = _derived(model)
    grads = {k: np.zeros(q) for k in base}
    for i in range(q - 1):
        xp = x0.copy()
        xp[i] += steps[i]
        try:
            dv = _derived(s.from_natural(dict(zip(names, xp[:-1], strict=True))))
        except (ConfigError, ModelFitError, ValueError):
            return se, {}, tradeoffs
        for k in base:
            grads[k][i] = (dv[k] - base[k]) / steps[i]
    derived: dict[str, float | None] = {}
    for k, gk in grads.items():
        var = float(gk @ cov @ gk)
        derived[k] = math.sqrt(var) if var >= 0 and math.isfinite(var) else None
    return se, derived, tradeoffs


def _coarse_stage(prep: Prepared, s: Structure, bracket: Bracket, options: FitOptions,
                  grid: FloatArray, bounds: tuple[FloatArray, FloatArray]
                  ) -> tuple[float, FloatArray, float, tuple[FloatArray, FloatArray], int]:
    """Coarse profile within the bracket (widened to the whole range if its minimum sits on the
    bracket's end), then a local profile with continuous ``theta`` on the coarse data.

    Returns ``(delay, theta, coarse step, (delays, errors), evaluations)``.
    """
    lo_s, hi_s = options.delay_min_s, options.delay_max_s
    tau_c, sse_c, th_c = _coarse_profile(prep, s, bracket.lo_s, bracket.hi_s, grid)
    if not np.any(np.isfinite(sse_c)):
        raise ModelFitError(f"{s.kind}: no starting point gave a finite error")
    i = int(np.nanargmin(sse_c))
    if i == tau_c.size - 1 and bracket.hi_s < hi_s:
        tau_c, sse_c, th_c = _coarse_profile(prep, s, lo_s, hi_s, grid)
        i = int(np.nanargmin(sse_c))
    if i == tau_c.size - 1 and tau_c.size > 1:
        raise _outside("upper", float(tau_c[i]), lo_s, hi_s)
    # (a minimum on the lower end is decided at the full rate: it may lie within a sample)
    step_c = float(np.median(np.diff(tau_c))) if tau_c.size > 1 else 1.0 / prep.rate_c
    data_c = _Data(prep.v_c, prep.y_c, prep.est_c, 1.0 / prep.rate_c, prep.coarse_extra_s)
    taus = np.unique(np.clip(tau_c[i] + np.linspace(-1.0, 1.0, 5) * step_c, lo_s, hi_s))
    vals = np.empty(taus.size)
    thetas: list[FloatArray] = [th_c[i]] * taus.size
    centre = int(np.argmin(np.abs(taus - tau_c[i])))
    for order in (range(centre, taus.size), range(centre - 1, -1, -1)):
        th = thetas[centre] if order.start < centre else th_c[i]
        for j in order:  # outwards from the grid's best, each start from its neighbour
            th, vals[j] = _inner(data_c, s, th, float(taus[j]), bounds, tol=1e-4)
            thetas[j] = th
    j = int(np.argmin(vals))
    tau1 = (_parabola_min(taus[j - 1:j + 2], vals[j - 1:j + 2]) if 0 < j < taus.size - 1
            else float(taus[j]))
    return tau1, thetas[j], step_c, (tau_c, sse_c), data_c.evals


class _FineProfile:
    """``P(Td) = min_theta SSE(theta, Td)`` on the full-rate data, cached per 1/64 sample."""

    def __init__(self, data: _Data, s: Structure, bounds: tuple[FloatArray, FloatArray],
                 theta0: FloatArray, lo_s: float, hi_s: float) -> None:
        self.data, self.s, self.bounds = data, s, bounds
        self.theta0 = theta0
        self.lo, self.hi = lo_s, hi_s
        self.h = data.h
        self.cache: dict[float, tuple[float, FloatArray]] = {}

    def _key(self, d: float) -> float:
        return round(d / self.h * 64.0) / 64.0

    def theta_near(self, d: float) -> FloatArray:
        """The optimal ``theta`` of the nearest delay already profiled (a warm start)."""
        if not self.cache:
            return self.theta0
        k = min(self.cache, key=lambda c: abs(c * self.h - d))
        return self.cache[k][1]

    def __call__(self, d: float) -> float:
        key = self._key(d)
        if key not in self.cache:
            th, val = _inner(self.data, self.s, self.theta_near(d), key * self.h, self.bounds,
                             tol=1e-6)
            self.cache[key] = (val, th)
        return self.cache[key][0]

    def theta(self, d: float) -> FloatArray:
        self(d)
        return self.cache[self._key(d)][1]

    def inside(self, d: float) -> bool:
        return self.lo - 1e-12 <= d <= self.hi + 1e-12

    def walk(self, d: float, limit: int) -> float:
        """Whole-sample steps downhill from ``d`` until a minimum is enclosed (or the range's
        end is reached, which is an error unless the minimum lies within its first sample)."""
        h = self.h
        for _ in range(limit):
            left, right = max(d - h, self.lo), min(d + h, self.hi)
            pl = self(left) if left < d else math.inf
            pr = self(right) if right > d else math.inf
            if self(d) <= pl and self(d) <= pr:
                break
            d = left if pl < pr else right
        if d >= self.hi - 1e-12 and self(d) <= self(max(d - h, self.lo)):
            raise _outside("upper", d, self.lo, self.hi)
        if d <= self.lo + 1e-12 and self.lo + h <= self.hi and self(d) <= self(self.lo + h):
            quarter = [self(self.lo + q * h / 4) for q in range(5)]
            if int(np.argmin(quarter)) == 0:
                raise _outside("lower", self.lo, self.lo, self.hi)
        return d

    def refine(self, d: float) -> float:
        """Halve the step twice about the best point, then the vertex of the parabola through
        the best quarter-sample point and its two neighbours."""
        h = self.h
        best = d
        for step in (h / 2, h / 4):
            for x in (best - step, best + step):
                if self.inside(x):
                    self(x)
            near = [c * h for c in self.cache if abs(c * h - best) <= step + 1e-12 * h]
            best = min(near, key=self)
        trio = [x for x in (best - h / 4, best, best + h / 4) if self.inside(x)]
        vals = [self(x) for x in trio]
        if len(trio) == 3 and vals[1] <= min(vals[0], vals[2]):
            return _parabola_min(np.array(trio), np.array(vals))
        return best

    def curve(self) -> tuple[FloatArray, FloatArray]:
        keys = sorted(self.cache)
        return (np.array([k * self.h for k in keys]),
                np.array([self.cache[k][0] for k in keys]))


def fit_structure(prep: Prepared, s: Structure, bracket: Bracket, options: FitOptions,
                  progress: ProgressFn | None = None, start: ProcessModel | None = None
                  ) -> ModelFit:
    """Fit one structure: coarse profile, fine profile, polish, uncertainty (module notes).

    ``start`` (a model already fitted, e.g. P2UZD for OE) adds its ``theta`` to the grid.

    Raises
    ------
    DataError
        If the best delay lies on an end of the searched range.
    ModelFitError
        If no valid model comes out.
    """
    t0 = time.perf_counter()
    note = progress or (lambda _msg: None)
    h = prep.h
    lo_s, hi_s = options.delay_min_s, options.delay_max_s
    t_lo = max(0.5 * h, 1e-3)
    t_hi = max(min(5.0, prep.recording.duration_s / 8.0), 4.0 * t_lo)
    bounds = s.bounds(t_lo, t_hi)
    grid = s.theta_grid(t_lo, t_hi)
    if start is not None:
        with contextlib.suppress(NotImplementedError):
            grid = np.vstack([grid, s.theta_of(start)[None, :]])

    # 1-2. bracket (given) and coarse profile
    note(f"{s.kind}: coarse delay profile")
    tau1, theta1, step_c, coarse_profile, evals_c = _coarse_stage(prep, s, bracket, options,
                                                                  grid, bounds)

    # 3. fine profile at the full rate
    note(f"{s.kind}: fine delay profile")
    data = _Data(prep.v, prep.y, prep.est, h, 0.0, every=prep.coarse_factor)
    prof = _FineProfile(data, s, bounds, theta1, lo_s, hi_s)
    walk_limit = math.ceil((2.0 * step_c + 3.0 / prep.rate_c) / h) + 4
    d = prof.walk(min(max(round(tau1 / h) * h, lo_s), hi_s), walk_limit)
    tau_f = prof.refine(d)
    theta_f = prof.theta(tau_f)
    sse_f = prof(tau_f)
    evals_fine = data.evals

    # 4. polish jointly, the delay bounded to one sample about the profile's minimum
    note(f"{s.kind}: joint polish")
    lo_b = np.concatenate([bounds[0], [max(tau_f - h, lo_s)]])
    hi_b = np.concatenate([bounds[1], [min(tau_f + h, hi_s)]])
    steps = np.concatenate([np.full(theta_f.size, 1e-7), [1e-4 * h]])
    try:
        x_pol, cost = _lm(lambda xv: data.residual(s, xv[:-1], float(xv[-1])),
                          np.concatenate([theta_f, [tau_f]]), lo_b, hi_b, steps, 1e-12,
                          max_iter=30)
        if cost <= sse_f:
            theta_f, tau_f = np.asarray(x_pol[:-1]), float(x_pol[-1])
    except (np.linalg.LinAlgError, ValueError, ModelFitError):
        pass
    stage_evals = {"coarse": evals_c, "fine": evals_fine, "polish": data.evals - evals_fine}

    note(f"{s.kind}: uncertainty")
    fit = _finish(prep, s, data, theta_f, tau_f, bounds)
    fit.profile_coarse, fit.profile_fine = coarse_profile, prof.curve()
    fit.evaluations = evals_c + data.evals
    fit.stage_evals = stage_evals
    fit.seconds = time.perf_counter() - t0
    return fit


def _finish(prep: Prepared, s: Structure, data: _Data, theta: FloatArray, tau: float,
            bounds: tuple[FloatArray, FloatArray]) -> ModelFit:
    """The model at ``(theta, tau)`` with its scores and uncertainties."""
    R = data.regressors(s, theta, tau)
    coef, resid = data.solve(R)
    model = s.build(theta, tau, coef)
    bias = float(coef[-1])
    yhat = prep.y - resid
    fit, vaf = _fit_metrics(prep.y, yhat, prep.val)
    yhat_raw = predict_acceleration(model, prep.v_raw, prep.rate_hz) + bias
    fit_raw, vaf_raw = _fit_metrics(prep.y_raw, yhat_raw, prep.val)
    e = resid[prep.est]
    n_est = e.size
    sse = float(e @ e)
    n_eff = n_est * min(1.0, 2.0 * prep.cutoff_hz / prep.rate_hz)
    aic = n_eff * math.log(max(sse, 1e-300) / n_est) + 2 * s.n_params
    se, se_derived, tradeoffs = _uncertainty(prep, s, model, bias, resid)
    lo_th, hi_th = bounds
    at_bounds = []
    if np.any(np.abs(theta - lo_th) < 1e-6) or np.any(np.abs(theta - hi_th) < 1e-6):
        at_bounds.append("time constant or damping at its search bound")
    empty = (np.zeros(0), np.zeros(0))
    return ModelFit(
        kind=s.kind, model=model, params=model.params(), stderr=se, fit_percent=fit,
        vaf_percent=vaf, fit_percent_raw=fit_raw, vaf_percent_raw=vaf_raw, aic=aic,
        n_params=s.n_params, rmse=math.sqrt(sse / n_est), bias=bias + prep.acc_mean,
        seconds=0.0, table1=_table1(model, se_derived), at_bounds=at_bounds,
        profile_coarse=empty, profile_fine=empty, prediction=yhat, prediction_raw=yhat_raw,
        tradeoffs=tradeoffs)


# --- the whole identification -------------------------------------------------------------------

@dataclass
class Identification:
    """All fits of one axis, the selection and what was done to the data."""

    prep: Prepared
    options: FitOptions
    bracket: Bracket
    fits: dict[str, ModelFit]
    errors: dict[str, str]
    selected: str
    reason: str
    seconds: float
    warnings: list[str] = field(default_factory=list)

    @property
    def axis(self) -> str | None:
        return self.prep.recording.axis

    @property
    def best(self) -> ModelFit:
        return self.fits[self.selected]


AIC_SUPPORT = 10.0
"""AIC points beyond which a model has essentially no support against the best (Burnham and
Anderson, *Model Selection and Multimodel Inference*, 2002, sec. 2.6)."""


def _equivalent(a: ModelFit, ref: ModelFit) -> bool:
    """Same Table 1 numbers as ``ref`` for practical purposes: phase delay at 0.2 Hz within
    max(2 ms, 2 standard errors), pure delay within max(1 ms, 2 standard errors)."""
    ta, tr = a.table1, ref.table1

    def close(key: str, floor_ms: float) -> bool:
        se = max(ta.get(f"{key}_stderr") or 0.0, tr.get(f"{key}_stderr") or 0.0)
        return bool(abs(ta[key] - tr[key]) <= max(floor_ms, 2.0 * se))
    return close("phase_delay_0p2hz_ms", 2.0) and close("pure_delay_ms", 1.0)


def _same_numbers(f: ModelFit, kind: str, ref: ModelFit) -> str:
    """Why ``f`` (of kind ``kind``) gives what ``ref`` gives (:func:`_equivalent` holds): the
    same Table 1 numbers, or numbers ``ref``'s standard errors cannot tell from ``f``'s."""
    pairs = [(f.table1[key], ref.table1[key],
              max(f.table1.get(f"{key}_stderr") or 0.0, ref.table1.get(f"{key}_stderr") or 0.0),
              floor)
             for key, floor in (("pure_delay_ms", 1.0), ("phase_delay_0p2hz_ms", 2.0))]
    nums = ", ".join(f"{a:.1f} vs {b:.1f}" + (f" +- {se:.1f}" if se else "") + " ms"
                     for a, b, se, _ in pairs)
    if all(abs(a - b) <= floor for a, b, _, floor in pairs):
        return f"but gives the same pure delay and phase delay at 0.2 Hz ({nums})"
    return (f"but its pure delay and phase delay at 0.2 Hz are too uncertain to differ from "
            f"{kind}'s ({nums}: within two standard errors)")


def select_model(fits: dict[str, ModelFit], tolerance: float) -> tuple[str, str]:
    """The simplest adequate model, and why.

    The reference is the model with the lowest AIC.  A model is *adequate* when its validation
    fit is within ``tolerance`` points of the best validation fit, and either its AIC is within
    :data:`AIC_SUPPORT` of the reference's or its Table 1 numbers (pure delay, phase delay at
    0.2 Hz) agree with the reference's (:func:`_equivalent`): a more complex model must
    either explain the data clearly better or change what the compensator will use.  Models are
    tried from the simplest (P1D, P2D, P2UZD, OE).

    Returns ``(kind, reason)``.
    """
    order = sorted(fits, key=lambda k: (STRUCTURES.index(k), fits[k].n_params))
    ref = min(fits, key=lambda k: fits[k].aic)
    best_val = max(fits[k].fit_percent for k in fits)
    r = fits[ref]
    rejected: list[str] = []
    for k in order:
        f = fits[k]
        d_aic = f.aic - r.aic
        ok_val = f.fit_percent >= best_val - tolerance
        ok_stat = d_aic <= AIC_SUPPORT
        ok_prac = _equivalent(f, r)
        if ok_val and (ok_stat or ok_prac):
            parts = [f"{k} is the simplest adequate model: validation fit {f.fit_percent:.2f} % "
                     f"(best {best_val:.2f} %)"]
            if k == ref:
                parts.append(f"lowest AIC ({f.aic:.1f})")
            elif ok_stat:
                parts.append(f"AIC within {d_aic:.1f} of the lowest ({ref})")
            else:
                parts.append(f"{ref} lowers the AIC by {d_aic:.1f}, " + _same_numbers(f, k, r))
            if rejected:
                parts.append("simpler models rejected: " + "; ".join(rejected))
            return k, "; ".join(parts)
        why = []
        if not ok_val:
            why.append(f"validation fit {f.fit_percent:.2f} % trails the best by more than "
                       f"{tolerance:g} points")
        else:
            why.append(f"AIC {d_aic:.1f} above {ref}'s and phase delay at 0.2 Hz "
                       f"{f.table1['phase_delay_0p2hz_ms']:.1f} ms vs "
                       f"{r.table1['phase_delay_0p2hz_ms']:.1f} ms")
        rejected.append(f"{k} ({', '.join(why)})")
    best = max(fits, key=lambda k: fits[k].fit_percent)
    return best, f"{best} has the best validation fit; " + "; ".join(rejected)


def identify(rec: Recording, options: FitOptions = FitOptions(),
             progress: ProgressFn | None = None) -> Identification:
    """Prepare the data, bracket the delay and fit every requested structure.

    ``progress(message)`` is called at each stage (for a progress bar).

    A structure whose best delay lies on an end of the searched range is left out, with the
    reason in ``errors`` (a richer structure may trade its delay for a lag: P2UZD's
    ``Td + Tp2`` is what the data fix when the platform is first order).

    Raises
    ------
    DataError
        For unusable data, or when every structure's best delay lies on an end of the searched
        range (the simplest structure's error: the data or the range are wrong).
    ModelFitError
        If no structure could be fitted.
    """
    t0 = time.perf_counter()
    note = progress or (lambda _msg: None)
    note("prefilter")
    prep = prepare(rec, options)
    bracket = delay_bracket(prep, options.delay_min_s, options.delay_max_s)
    fits: dict[str, ModelFit] = {}
    errors: dict[str, str] = {}
    outside: dict[str, DelayRangeError] = {}
    for kind in sorted(options.models, key=STRUCTURES.index):
        s = make_structure(kind, options.oe_order, options.oe_pade)
        seed = fits.get("p2uzd") or fits.get("p2d") if kind == "oe" else None
        try:
            fits[kind] = fit_structure(prep, s, bracket, options, note,
                                       start=seed.model if seed else None)
        except ModelFitError as exc:
            errors[kind] = str(exc)
        except DelayRangeError as exc:
            outside[kind] = exc
    if not fits and outside:
        raise next(iter(outside.values()))
    for kind, out in outside.items():  # others fitted: the data are fine, this structure is not
        errors[kind] = (f"its best delay is at the {out.side} end of the searched range "
                        f"({out.value_s * 1e3:.1f} ms): " +
                        ("on these data it trades its delay for its lags" if out.side == "lower"
                         else "widen the delay range (--delay-range) to fit it"))
    if not fits:
        raise ModelFitError("no model could be fitted: " + "; ".join(
            f"{k}: {v}" for k, v in errors.items()))
    selected, reason = select_model(fits, options.select_tolerance)
    return Identification(prep=prep, options=options, bracket=bracket, fits=fits, errors=errors,
                          selected=selected, reason=reason, seconds=time.perf_counter() - t0,
                          warnings=_warnings(prep, fits[selected]))


PHASE_DELAY_SE_WARN_MS = 5.0
"""Standard error of the phase delay at 0.2 Hz above which the report warns."""
LOW_MOTION_HZ = 0.25
"""A command whose motion starts at or below this frequency has motion near 0.2 Hz."""


def lowest_motion_hz(cmd: FloatArray, rate: float) -> float | None:
    """The lowest frequency at which the command's position spectrum (Welch, 60 s segments,
    mean removed) reaches 10 % of its peak: where the excitation's motion starts; None for a
    constant command."""
    x = np.asarray(cmd, dtype=float)
    nper = min(x.size, int(60.0 * rate))
    if nper < 16:
        return None
    f, p = signal.welch(x - x.mean(), fs=rate, nperseg=nper)
    peak = float(p[1:].max()) if p.size > 1 else 0.0
    if not peak > 0:
        return None
    return float(f[1:][np.nonzero(p[1:] >= 0.1 * peak)[0][0]])


def _warnings(prep: Prepared, fit: ModelFit) -> list[str]:
    """What a user should know before trusting the selected model."""
    out = []
    if fit.model.gain < 0:
        out.append(f"the measured acceleration has the opposite sign of the command (gain "
                   f"{fit.model.gain:.3g}): the accelerometer's axis looks reversed; the delays "
                   "are those of the sign-corrected response")
    se = fit.table1.get("phase_delay_0p2hz_ms_stderr")
    if se is None or se > PHASE_DELAY_SE_WARN_MS:
        shown = "undetermined" if se is None else f"+-{se:.1f} ms"
        low = lowest_motion_hz(prep.recording.cmd, prep.rate_hz)
        if low is not None and low <= LOW_MOTION_HZ:
            out.append(f"the phase delay at 0.2 Hz is uncertain ({shown}) although the command "
                       f"moves from {low:.2g} Hz up: the response there is noisy, or the "
                       f"{fit.kind} does not describe the platform at low frequency")
        else:
            where = "" if low is None else f" (its motion starts at {low:.2g} Hz)"
            out.append(f"the phase delay at 0.2 Hz is uncertain ({shown}): the command holds "
                       f"little motion near 0.2 Hz{where}; excite down to 0.1 Hz "
                       "(motcomp excite --f-min 0.1)")
    if fit.at_bounds:
        out.append(f"{fit.kind}: {', '.join(fit.at_bounds)}")
    jitter = prep.recording.period_jitter_s * prep.rate_hz
    if jitter > 0.2:
        out.append(f"the time stamps jitter by {jitter * 100:.0f} % of the period; the "
                   "resampled data lose accuracy at high frequency")
    return out
