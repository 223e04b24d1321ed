"""The platform's model estimated from ordinary driving: :func:`estimate_axis`, and the sliding
window a supervising process keeps of the service's outputs and feedback: :class:`LiveWindow`.

The command-to-feedback path is the platform itself, open loop, whatever the compensator does:
its P1D model (``K e^{-Td s} / (1 + Tp1 s)``) is identified from the service's outputs and the
platform's measured acceleration over the last ``window_s``, with the pairing rule of
``motcomp identify`` on a recording (the output in force at each instant, on the frames' own
clocks: :func:`motcomp.record.session.output_in_force`), on a uniform grid whose stalls are cut
out: a gap of the feedback or of the outputs during which the command moved (the platform held
a stale setpoint the pairing does not know of) costs its samples and ``settle_s`` after, not
the window.

The fit (why and how: docs/SUPERVISION.md) is an output-error fit: the command's second
difference and the measured acceleration, low-passed by one causal filter and decimated, the
command simulated through the model in the frequency domain (the hold's half sample
included, as ``motcomp identify`` does), the residual judged after a lead-in.  Ordinary driving
often holds one frequency (a slalom's 0.31 Hz): then ``Td`` and ``Tp1`` are not told apart
(their estimates correlate beyond :data:`MAX_CORRELATION`), and ``Tp1`` is held at the config
model's while ``K`` and ``Td`` are fitted -- the phase delay and gain *in the band*, which is
what the compensator's delivered response depends on, are identified either way.  Standard
errors come from the Jacobian and the residual's long-run covariance.

The mismatch is what the difference between the estimate ``P`` and the compensator's model ``M``
does to the delivered response: the compensator makes ``M`` follow its design, so the platform
delivers ``P / M`` times it.  ``residual_delay_ms`` = phase delay of ``P / M``, ``gain_error`` =
``|P / M| - 1``, at the driven frequency (in the configured band) where the data determine the
residual delay best -- a delay is a phase over a frequency, and the driving's low end (a
slalom's 0.3 Hz) tells it least.

Nothing here reads a clock or raises on data: a window that cannot tell says why
(``informative`` false, ``reason``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from motcomp.core.models import P1D, ProcessModel
from motcomp.jsonsafe import finite
from motcomp.record.session import output_in_force, pairing_phase_ms

__all__ = ["MAX_CORRELATION", "EstimateSettings", "LiveWindow", "estimate_axis", "mismatch"]

MAX_CORRELATION = 0.98
"""|correlation| of the ``Td`` and ``Tp1`` estimates beyond which the data do not tell them
apart (the same threshold as ``motcomp identify``'s report)."""
LEAD_IN_S = 2.5
"""The start of a window simulated but not judged: the simulation starts in a steady state,
and the P1D's memory of what came before fades (13 time constants of the rails' 186 ms; the
filter's own transient is shorter)."""
DRIVEN_DB = 0.1
"""A frequency of the band is driven where the command's acceleration power there is at least
this share of its peak in the band (10 dB)."""
TD_GRID_S = np.arange(0.0, 0.2501, 0.01)
"""The coarse delay grid the fit starts from (the delay range of ``motcomp identify``; the
filtered signals vary on a scale of 100 ms, the fit refines from the best point)."""


@dataclass(frozen=True)
class EstimateSettings:
    """What a window must hold to be judged, and where (``[supervision]`` of the config)."""

    window_s: float = 15.0
    band_hz: tuple[float, float] = (0.1, 2.0)
    """The driver's band: the mismatch is judged at the motion's centre frequency in it."""
    fit_max_hz: float = 5.0
    """Highest frequency fitted (the P1D describes the platform below it)."""
    min_motion: float = 0.05
    """Least RMS of the command's acceleration in the band (m/s^2 or rad/s^2)."""
    max_delay_se_ms: float = 1.0
    """Largest standard error of the residual delay for a window to be informative."""
    min_coverage: float = 0.8
    """Least part of the window the feedback (paired with outputs) must cover."""
    min_fit: float = 0.5
    """Least share of the in-band acceleration the fitted model explains (1 - |res|^2/|A|^2)."""
    stall_s: float = 0.02
    """A gap between two feedback samples, or between two outputs, longer than this is a stall
    of the host (or of the platform's link) always cut out (:func:`_grid`)."""
    stall_area: float = 1e-6
    """A shorter gap is cut too when the command's change over it, held for it, exceeds this
    (m s or rad s): the error of the platform's input had the stall held it stale."""
    settle_s: float = 0.4
    """How long after a stall its samples are cut: the fit's filter and the platform's own
    memory carry its error this long."""
    min_judged: float = 0.35
    """Least part of the window (after the lead-in) left to judge once the stalls are cut (a
    third: 4.4 s of a 15 s window; the residual delay's standard error says what is left)."""


def mismatch(est: ProcessModel, model: ProcessModel, f_hz: float) -> tuple[float, float]:
    """``(residual delay s, gain error)`` of the delivered response ``P / M`` at ``f_hz``: the
    phase delay of ``est / model`` (the difference of their unwrapped phase delays) and
    ``|est / model| - 1``."""
    delay, gain = _mismatch(est, model, np.array([f_hz]))
    return float(delay[0]), float(gain[0])


def _mismatch(est: ProcessModel, model: ProcessModel, f_hz: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`mismatch` at each of ``f_hz``."""
    delay = np.asarray(est.phase_delay(f_hz)) - np.asarray(model.phase_delay(f_hz))
    return delay, np.asarray(est.magnitude(f_hz)) / np.asarray(model.magnitude(f_hz)) - 1.0


@dataclass(frozen=True)
class _Signals:
    """The window low-passed (the same filter on both) and decimated."""

    v: np.ndarray
    """The command's second difference."""
    y: np.ndarray
    """The measured acceleration, mean removed."""
    rate: float
    hold_s: float
    """Half the recorded period: the hold's lag."""
    judged: np.ndarray
    """Which samples' residuals are judged: after the lead-in, outside the stalls' cuts."""
    lags: int
    """Correlation length of the residual (samples) for its long-run covariance."""


@dataclass(frozen=True)
class _Grid:
    """The window on a uniform grid at the feedback's rate."""

    rate: float
    cmd: np.ndarray
    """The output in force at each grid instant: what the platform held."""
    acc: np.ndarray
    """The measured acceleration, interpolated at the grid instants."""
    keep: np.ndarray
    """The grid instants outside the stalls' cuts."""
    stalls: int
    """Stretches cut out (overlapping cuts count once)."""
    cut_s: float


def _grid(t_out: np.ndarray, u_out: np.ndarray, t_fb: np.ndarray, acc: np.ndarray,
          settings: EstimateSettings) -> _Grid:
    """The window on a uniform grid, its stalls cut out.

    ``t_fb`` (increasing, every sample with an output in force) and ``acc``: the feedback;
    the grid runs from its first sample to its last at its median rate (rounded to whole
    hertz within 0.1 %).  The command is known at every grid instant (the outputs in force),
    the acceleration where the feedback is.  A gap of the feedback or of the outputs (longer
    than 1.5 of their median periods) is a stall, cut -- the grid instants from its start to
    ``settings.settle_s`` after its end, ``keep`` false -- when half the command's change over
    it times its length exceeds ``settings.stall_area``, or it lasts longer than
    ``settings.stall_s``.
    """
    new = np.concatenate([[True], np.diff(t_fb) > 0])  # a repeated stamp: its first sample
    t_fb, acc = t_fb[new], acc[new]
    d = np.diff(t_fb)
    rate = 1.0 / float(np.median(d))
    if abs(rate - round(rate)) <= 1e-3 * rate:
        rate = float(round(rate))
    n = math.floor((t_fb[-1] - t_fb[0]) * rate + 1e-9) + 1
    t = t_fb[0] + np.arange(n) / rate
    cmd = u_out[np.searchsorted(t_out, t, side="right") - 1]
    a = np.interp(t, t_fb, acc)
    # the outputs around the window: a loop stall just before it reaches into it
    i0 = max(int(np.searchsorted(t_out, t[0] - settings.settle_s)) - 1, 0)
    i1 = int(np.searchsorted(t_out, t[-1], side="right"))
    to = t_out[i0:i1]
    cut_from: list[np.ndarray] = []
    cut_to: list[np.ndarray] = []
    for ts in (t_fb, to):
        if ts.size < 3:
            continue
        dt = np.diff(ts)
        i = np.flatnonzero(dt > 1.5 * float(np.median(dt)))
        a_, b_ = ts[i], ts[i + 1]
        # the command's motion the stall held back from the platform: its change over the
        # gap, held stale for the gap (the area of the input's error, m s)
        ua = u_out[np.maximum(np.searchsorted(t_out, a_, side="right") - 1, 0)]
        ub = u_out[np.maximum(np.searchsorted(t_out, b_, side="right") - 1, 0)]
        area = 0.5 * np.abs(ub - ua) * (b_ - a_)
        cut = (area > settings.stall_area) | (b_ - a_ > settings.stall_s)
        cut_from.append(a_[cut])
        cut_to.append(b_[cut])
    starts = np.concatenate(cut_from) if cut_from else np.zeros(0)
    ends = np.concatenate(cut_to) if cut_to else np.zeros(0)
    edges = np.zeros(n + 1)
    np.add.at(edges, np.searchsorted(t, starts), 1.0)
    np.add.at(edges, np.searchsorted(t, ends + settings.settle_s), -1.0)
    keep = np.cumsum(edges[:-1]) < 0.5
    runs = int(np.count_nonzero(np.diff(np.concatenate([[1], keep.astype(np.int8)])) == -1))
    return _Grid(rate=rate, cmd=cmd, acc=a, keep=keep, stalls=runs,
                 cut_s=float(np.count_nonzero(~keep)) / rate)


def _signals(cmd: np.ndarray, acc: np.ndarray, rate: float, keep: np.ndarray,
             settings: EstimateSettings) -> _Signals:
    """``keep``: the grid samples outside the stalls' cuts."""
    from scipy import signal

    from motcomp.ident.fit import second_difference

    v = second_difference(cmd, rate)
    v[0], v[-1] = v[1], v[-2]  # the command moves on at the window's ends: it is not held
    y = acc - float(np.mean(acc[keep] if keep.any() else acc))  # all cut: judged by no sample
    cutoff = settings.fit_max_hz
    # one causal filter on both (it commutes with the platform's model), started in the
    # steady state of each signal's first value: its transient lies in the lead-in
    sos = signal.butter(4, cutoff, btype="low", fs=rate, output="sos")
    zi = signal.sosfilt_zi(sos)
    m = max(1, math.floor(rate / (10.0 * cutoff)))
    vf = signal.sosfilt(sos, v, zi=zi * v[0])[0][::m]
    yf = signal.sosfilt(sos, y, zi=zi * y[0])[0][::m]
    r = rate / m
    judged = keep[::m].copy()
    judged[:math.ceil(LEAD_IN_S * r)] = False
    return _Signals(v=vf, y=yf, rate=r, hold_s=0.5 / rate, judged=judged,
                    lags=math.ceil(2.0 * r / cutoff))


class _OutputError:
    """``y = K e^{-Td s} / (1 + Tp1 s) v`` -- or, with ``shape``, ``K e^{-Td s} H(s) v`` where
    ``H`` is ``shape``'s delay-free response over its gain -- simulated in the frequency domain
    over a circular buffer whose past (before the window) is ``v``'s first value held: the
    window starts in the steady state of that value, and the lead-in, which is not judged,
    holds the error of that assumption."""

    def __init__(self, s: _Signals, shape: ProcessModel | None = None) -> None:
        n = s.v.size
        self.n = n
        self.size = _fft_len(2 * n)
        # after the window, v's last value, a raised-cosine ramp to its first, and that
        # (a jump would ring through the fractional delay into the window)
        pad = self.size - n
        ramp = 0.5 - 0.5 * np.cos(np.pi * np.clip((np.arange(pad) - pad / 4) / (pad / 2), 0, 1))
        padded = np.concatenate([s.v, s.v[-1] + (s.v[0] - s.v[-1]) * ramp])
        self.f = np.fft.rfftfreq(self.size, 1.0 / s.rate)
        self.V = np.fft.rfft(padded) * np.exp(-2j * np.pi * self.f * s.hold_s)
        self.w = 2j * np.pi * self.f
        self.s = s
        self.shape = None
        if shape is not None:
            num, den = shape.rational()
            self.shape = np.polyval(num, self.w) / np.polyval(den, self.w) / shape.gain

    def predict(self, k: float, td: float, tp: float) -> np.ndarray:
        """The simulated acceleration (``tp`` unused with a shape)."""
        w = self.w
        h = 1.0 / (1.0 + w * tp) if self.shape is None else self.shape
        return np.fft.irfft(k * np.exp(-w * td) * h * self.V, self.size)[:self.n]

    def residual(self, theta: np.ndarray, tp: float | None = None) -> np.ndarray:
        """Measured minus predicted over the judged samples, the best offset removed (the
        accelerometer's bias)."""
        e = (self.s.y - self.predict(theta[0], theta[1], theta[2] if tp is None else tp)
             )[self.s.judged]
        return np.asarray(e - e.mean())

    def gain_for(self, td: float, tp: float) -> float:
        """The least-squares ``K`` for given delays (with the offset)."""
        g = self.predict(1.0, td, tp)[self.s.judged]
        y = self.s.y[self.s.judged]
        g, y = g - g.mean(), y - y.mean()
        return float(g @ y) / max(float(g @ g), 1e-300)


def _shaped(model: ProcessModel) -> bool:
    """A model whose dynamics the fit can hold: a gain ``K`` and an exact delay ``Td``."""
    par = model.params()
    return (dataclasses.is_dataclass(model) and {"K", "Td"} <= set(par)
            and model.dead_time_s == model.pure_delay_s and model.gain == par["K"])


def _fft_len(n: int) -> int:
    size = 1
    while size < n:
        size *= 2
    return size


def _sandwich(jac: np.ndarray, e: np.ndarray, lags: int, judged: np.ndarray) -> np.ndarray:
    """The parameters' covariance for residuals ``e`` of the ``judged`` samples, correlated
    over ``lags`` samples (a cut is a stretch of zero scores: the correlation does not jump
    over it)."""
    from motcomp.ident.fit import long_run_cov

    try:
        inv = np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return np.full((jac.shape[1], jac.shape[1]), np.inf)
    scores = np.zeros((jac.shape[1], judged.size))
    scores[:, judged] = jac.T * e[None, :]
    return np.asarray(inv @ long_run_cov(scores, lags) @ inv)


def estimate_axis(t_out: np.ndarray, u_out: np.ndarray, t_fb: np.ndarray, acc: np.ndarray,
                  model: ProcessModel, settings: EstimateSettings = EstimateSettings(),
                  axis: str = "axis") -> dict[str, Any]:
    """The platform of one axis over one window, and its mismatch with ``model``.

    A P1D ``model``: a P1D is fitted (``K``, ``Td``, ``Tp1``; ``Tp1`` held at the model's when
    the data do not tell it from ``Td``).  A model of another kind with a gain and an exact
    delay (P2D, P2UZD): its dynamics are held and ``K``, ``Td`` fitted -- a P1D cannot stand
    for them in the band.  Any other (OE): its P1D reduction (``to_p1d``) is the model.

    ``t_out``/``u_out``: the service's outputs (frame ``t`` in s, increasing; the position
    sent); ``t_fb``/``acc``: the feedback's ``t`` and measured acceleration over the window
    (its first :data:`LEAD_IN_S` is a lead-in: simulated, not judged).  Returns the figures of
    docs/SUPERVISION.md (``informative``, ``reason``, ``estimate``, ``residual_delay_ms``,
    ``pairing_phase_ms`` -- the median time from the output in force to the feedback sample...);
    never raises on data.
    """
    from scipy import optimize  # here, not at import: the service imports this module for
    # its settings and never estimates (scipy would add some 70 MB to its memory)

    out: dict[str, Any] = {"informative": False, "reason": "", "model": model.spec()}
    keep = np.isfinite(t_fb) & np.isfinite(acc)
    t_fb, acc = t_fb[keep], acc[keep]
    if t_out.size < 2:
        out["reason"] = "no outputs in the window"
        return out
    if t_fb.size < 16:
        out["reason"] = f"no feedback acceleration of {axis} in the window"
        return out
    k, known = output_in_force(t_out, np.full(t_out.size, np.inf), t_fb)
    if known.any():
        out["pairing_phase_ms"] = pairing_phase_ms(t_fb[known], t_out[k[known]])
    t_fb, acc = t_fb[known], acc[known]
    span = float(t_fb[-1] - t_fb[0]) if t_fb.size else 0.0
    out["span_s"] = span
    if span < settings.min_coverage * settings.window_s:
        out["reason"] = (f"{span:.1f} s of feedback paired with outputs (needs "
                         f"{settings.min_coverage * settings.window_s:.1f} s)")
        return out
    grid = _grid(t_out, u_out, t_fb, acc, settings)
    out["stalls"] = grid.stalls
    out["cut_s"] = grid.cut_s
    if np.ptp(grid.cmd) <= 1e-12 * max(float(np.max(np.abs(grid.cmd))), 1.0):
        out["reason"] = f"the command is constant ({grid.cmd[0]:.6g}): nothing moved {axis}"
        return out
    sig = _signals(grid.cmd, grid.acc, grid.rate, grid.keep, settings)
    lead = math.ceil(LEAD_IN_S * sig.rate)
    judged_s = float(np.count_nonzero(sig.judged)) / sig.rate
    out["judged_s"] = judged_s
    need = settings.min_judged * (sig.v.size / sig.rate - LEAD_IN_S)
    if np.count_nonzero(sig.judged) < 4 * sig.lags or judged_s < need:
        out["reason"] = (f"{grid.stalls} stretch(es) of stalls of the host or the platform's "
                         f"link (stalls less than {settings.settle_s:g} s apart run together) "
                         f"cut out {grid.cut_s:.1f} s of the window: {judged_s:.1f} s left to "
                         f"judge (needs {need:.1f} s)" if grid.stalls else
                         f"{span:.1f} s of data is too short")
        return out
    judged = sig.v[lead:]  # the motion: the command is known over the whole window
    # the motion in the band: its RMS and centre frequency, from the command's spectrum
    lo_band, hi_band = settings.band_hz
    f = np.fft.rfftfreq(judged.size, 1.0 / sig.rate)
    hann = np.hanning(judged.size)  # its leakage falls fast: the centre is not pulled up
    power = np.abs(np.fft.rfft(hann * (judged - judged.mean()))) ** 2
    band = (f >= lo_band) & (f <= hi_band)
    # Parseval, one-sided, the taper's power removed
    motion = (math.sqrt(2.0 * float(power[band].sum()) / (judged.size * float(hann @ hann)))
              if band.any() else 0.0)
    out["motion_rms"] = motion
    if not motion >= settings.min_motion:
        out["reason"] = (f"too little motion in {lo_band:g}-{hi_band:g} Hz (command "
                         f"acceleration RMS {motion:.3g} < {settings.min_motion:g})")
        return out
    # the driven frequencies: where the command's acceleration spectrum (smoothed over five
    # bins) is within 10 dB of its peak in the band
    smooth = np.convolve(power[band], np.ones(5) / 5.0, mode="same")
    centre = float((f[band] * power[band]).sum() / power[band].sum())
    driven = np.append(f[band][smooth >= DRIVEN_DB * float(smooth.max())], centre)
    if not isinstance(model, P1D) and not _shaped(model):
        model = model.to_p1d()
        out["model"] = model.spec()
    shaped = not isinstance(model, P1D)
    oe = _OutputError(sig, model if shaped else None)
    tp0 = float(model.Tp1) if isinstance(model, P1D) else 0.0
    coarse = [(float(np.sum(oe.residual(np.array([oe.gain_for(d, tp0), d, tp0])) ** 2)), d)
              for d in TD_GRID_S]
    td0 = min(coarse)[1]
    x0 = np.array([oe.gain_for(td0, tp0), td0, tp0])
    # K of either sign (an accelerometer mounted the other way round), never zero
    lo, hi = np.array([-20.0, 0.0, 1e-4]), np.array([20.0, 0.25, 2.0])
    corr = math.nan
    if not shaped:
        full = optimize.least_squares(oe.residual, np.clip(x0, lo, hi), bounds=(lo, hi),
                                      x_scale=[1.0, 0.01, 0.05])
        cov = _sandwich(full.jac, full.fun, sig.lags, sig.judged)
        corr = (cov[1, 2] / math.sqrt(cov[1, 1] * cov[2, 2])
                if cov[1, 1] > 0 and cov[2, 2] > 0 else 1.0)
    if not shaped and abs(corr) <= MAX_CORRELATION and np.all(np.isfinite(cov)):
        theta, identified, fun = full.x, "K, Td, Tp1", full.fun
    else:  # one frequency, or a shape held: K and Td fitted
        held = optimize.least_squares(lambda th: oe.residual(th, tp0), np.clip(x0[:2], lo[:2],
                                      hi[:2]), bounds=(lo[:2], hi[:2]), x_scale=[1.0, 0.01])
        cov = np.zeros((3, 3))
        cov[:2, :2] = _sandwich(held.jac, held.fun, sig.lags, sig.judged)
        theta = np.array([held.x[0], held.x[1], tp0])
        identified, fun = ("K, Td (the model's dynamics held)" if shaped
                           else "K, Td (Tp1 held at the model's)"), held.fun

    def as_model(th: np.ndarray) -> ProcessModel:
        if shaped:
            return dataclasses.replace(model, K=float(th[0]), Td=float(th[1]))  # type: ignore[type-var]
        return P1D(K=float(th[0]), Td=float(th[1]), Tp1=float(th[2]))

    est = as_model(theta)
    y_judged = sig.y[sig.judged] - sig.y[sig.judged].mean()
    explained = 1.0 - float(fun @ fun) / max(float(y_judged @ y_judged), 1e-300)
    # the mismatch at each driven frequency, with its standard errors (delta method); judged
    # where the driving determines it best
    delays, gains = _mismatch(est, model, driven)
    grads = np.zeros((2, driven.size, 3))
    for j, step in enumerate((1e-4, 1e-5, 1e-5)[:2 if shaped else 3]):
        th = theta.copy()
        th[j] += step
        d2, g2 = _mismatch(as_model(th), model, driven)
        grads[0, :, j], grads[1, :, j] = (d2 - delays) / step, (g2 - gains) / step
    ses = np.sqrt(np.maximum(np.einsum("xij,jk,xik->xi", grads, cov, grads), 0.0))
    if identified == "K, Td, Tp1":
        best = int(np.argmin(np.where(np.isfinite(ses[0]), ses[0], np.inf)))
    else:  # the dynamics held: the data tell the delay at the motion's centre only
        best = driven.size - 1
    fc = float(driven[best])
    out["at_hz"] = fc
    delay, gain_err = float(delays[best]), float(gains[best])
    se = ses[:, best]
    out.update({
        "estimate": {"spec": est.spec(), "K": float(theta[0]), "Td_ms": float(theta[1]) * 1e3,
                     "Tp1_ms": None if shaped else float(theta[2]) * 1e3,
                     "K_se": math.sqrt(max(cov[0, 0], 0.0)),
                     "Td_se_ms": math.sqrt(max(cov[1, 1], 0.0)) * 1e3,
                     "Tp1_se_ms": None if shaped else math.sqrt(max(cov[2, 2], 0.0)) * 1e3,
                     "identified": identified, "td_tp1_correlation": float(corr),
                     "phase_delay_ms": float(est.phase_delay([fc])[0]) * 1e3,
                     "explained": explained},
        "residual_delay_ms": delay * 1e3, "residual_delay_se_ms": float(se[0]) * 1e3,
        "gain_error": gain_err, "gain_error_se": float(se[1]),
    })
    if explained < settings.min_fit:
        out["reason"] = (f"the {'model' if shaped else 'P1D'} explains {100 * explained:.0f} % "
                         f"of the measured acceleration (needs {100 * settings.min_fit:.0f} %)")
    elif not se[0] * 1e3 <= settings.max_delay_se_ms:  # NaN too: an undetermined figure
        out["reason"] = (f"the residual delay is uncertain (+-{se[0] * 1e3:.2f} ms > "
                         f"{settings.max_delay_se_ms:g} ms)")
    else:
        out["informative"] = True
    return out


class LiveWindow:
    """The last ``keep_s`` of the service's outputs and feedback for the axes ``axes``, fed in
    chunks.

    :meth:`add` takes a chunk: ``t_out`` (s, the outputs' frame clock) and ``u`` (one column
    per axis of ``axes``), ``t_fb`` (the feedback's ``t``) and ``acc`` (one column per axis,
    NaN where absent); :meth:`estimate` runs :func:`estimate_axis` on each axis.
    """

    def __init__(self, keep_s: float, axes: list[str]) -> None:
        self.keep_s = float(keep_s)
        self.axes = list(axes)
        self.t_out = np.zeros(0)
        self.u = np.zeros((0, len(axes)))
        self.t_fb = np.zeros(0)
        self.acc = np.zeros((0, len(axes)))

    def add(self, t_out: np.ndarray, u: np.ndarray, t_fb: np.ndarray, acc: np.ndarray) -> None:
        """Append a chunk.  Outputs older than the last kept one (a restarted clock) start the
        window again; feedback is kept in time order (its senders' clocks may step)."""
        n = len(self.axes)
        if t_out.size and self.t_out.size and t_out[0] < self.t_out[-1]:
            self.__init__(self.keep_s, self.axes)  # type: ignore[misc]
        self.t_out = np.concatenate([self.t_out, t_out])
        self.u = np.concatenate([self.u, u.reshape(-1, n)])
        t_fb = np.concatenate([self.t_fb, t_fb])
        acc = np.concatenate([self.acc, acc.reshape(-1, n)])
        if t_fb.size > 1 and np.any(t_fb[1:] < t_fb[:-1]):
            order = np.argsort(t_fb, kind="stable")
            t_fb, acc = t_fb[order], acc[order]
        end = max(self.t_out[-1] if self.t_out.size else -math.inf,
                  t_fb[-1] if t_fb.size else -math.inf)
        a = int(np.searchsorted(self.t_out, end - self.keep_s))
        b = int(np.searchsorted(t_fb, end - self.keep_s))
        self.t_out, self.u = self.t_out[a:], self.u[a:]
        self.t_fb, self.acc = t_fb[b:], acc[b:]

    def estimate(self, models: dict[str, ProcessModel], settings: EstimateSettings
                 ) -> dict[str, dict[str, Any]]:
        """Per axis, :func:`estimate_axis` against ``models[axis]`` over the last
        ``settings.window_s`` of feedback, with the window's bounds (``from_t``, ``to_t``)."""
        res: dict[str, dict[str, Any]] = {}
        if not self.t_fb.size:
            return {a: {"informative": False, "reason": "no feedback received",
                        "model": models[a].spec()} for a in self.axes}
        end = float(self.t_fb[-1])
        start = end - settings.window_s
        sel = self.t_fb >= start
        for j, axis in enumerate(self.axes):
            try:
                fig = estimate_axis(self.t_out, self.u[:, j], self.t_fb[sel], self.acc[sel, j],
                                    models[axis], settings, axis)
            except Exception as exc:  # a figure must never stop supervision
                fig = {"informative": False, "model": models[axis].spec(),
                       "reason": f"internal: {type(exc).__name__}: {str(exc)[:80]}"}
            fig["from_t"], fig["to_t"] = start, end
            res[axis] = finite(fig)
        return res
