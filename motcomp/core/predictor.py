"""The predictive prefilter: phase lead over the driver band, for delay-dominated axes.

A pure delay cannot be cancelled by a PID around a model, but the compensator is feed-forward:
nothing measured comes back, so what limits a prefilter is a trade-off, not stability.  The
driver's inputs are band-limited (0-2 Hz), so the reference can be predicted some tens of
milliseconds ahead at the price of some gain above the band.  Per axis::

     r --+--> F(z) = d + sum_k c_k L_k(z) --> r_pred --+
         |                                              (blend w) --> r' --> compensator
         +--------------------------------------------> r --------+
         |
         +--> band monitor: out-of-band / in-band amplitude --> w: 1 (predict) <-> 0 (fallback)

``L_k`` are the discrete Laguerre functions of pole ``a = exp(-2 pi pole_hz / rate_hz)``::

    L_k(z) = sqrt(1 - a^2) / (1 - a z^-1) * ((z^-1 - a) / (1 - a z^-1))^k,   k = 0 .. N-1

an orthonormal basis of stable filters, so that the coefficients ``(d, c_0 .. c_{N-1})`` are
found by a linear programme (:mod:`motcomp.design.predictor`) and the filter is stable whatever
they are.  Realisation (``l_k`` the output of ``L_k``, computed in order of ``k``)::

    l_0[n] = a l_0[n-1] + sqrt(1 - a^2) r[n]
    l_k[n] = a l_k[n-1] + l_{k-1}[n-1] - a l_{k-1}[n]
    r_pred[n] = d r[n] + sum_k c_k l_k[n]

written as ``l[n] = A l[n-1] + B r[n]`` (A lower triangular).  A designed filter has
``F(1) = 1``: a constant reference is passed unchanged.

Band monitor and fallback (the rule; docs/PREDICTION.md has the why and the measurements)::

    hi[n]   = |HP2(r)|,  2nd-order Butterworth high-pass at HIGH_CUT x the design band's top
    lo[n]   = |HP1(r)|,  1st-order high-pass at LOW_CUT_HZ (removes the offset)
    env     = peak hold with exponential decay over ENVELOPE_S, of each
    ratio   = env_hi / (env_lo + floor)
    ratio > fallback_ratio                         -> fallback (w fades to 0 over fade_out_s)
    ratio < resume_ratio for resume_after_s        -> predict  (w fades to 1 over fade_in_s)
    the caller's ``live`` False (the shaper's mode)  -> held off (no fallback counted or
                                                       flagged; w fades to 0 over fade_out_s)
    the caller's ``wanted`` False (a switch-off)     -> held off, w fading over fade_in_s: no
                                                       alarm, and the compensator blends its
                                                       own switch over as long or longer

``r' = r + w (r_pred - r)``; ``w`` moves along the minimum-jerk blend from wherever it is, so
the switch is continuous in position and velocity both ways.  The filter runs in fallback too,
so that it is warm when prediction resumes.  A change of the parameters (a reload) starts the new
filter of a changed axis at rest at the current reference, in fallback (prediction resumes as
after a fallback), and fades the difference between the old and the new output out over
``fade_in_s``: no jump; an unchanged axis keeps its state (a prefilter removed altogether
drops its axis' lead at once: set ``predict = false`` first).  Non-finite reference on an axis: the
filter and the monitor are advanced with its last finite value, and the value is returned as
given (the compensator holds the last finite reference itself).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from mypy_extensions import mypyc_attr
from numpy.typing import ArrayLike

from motcomp.core.lti import ComplexArray, FloatArray
from motcomp.core.minjerk import min_jerk_between, min_jerk_weight
from motcomp.core.native import frozen_reduce
from motcomp.errors import ConfigError

__all__ = [
    "ENVELOPE_S",
    "HIGH_CUT",
    "LOW_CUT_HZ",
    "MonitorParams",
    "Prediction",
    "PredictorParams",
    "laguerre_basis",
    "predictor_freqresp",
    "realisation",
]

HIGH_CUT = 3.0
"""The monitor's high-pass corner, in multiples of the design band's top: a sine at the band's
top reads a ratio of 0.11, at 1.2x the top 0.15 (``resume_ratio``), at 1.7x 0.3
(``fallback_ratio``)."""
LOW_CUT_HZ = 0.05
"""Corner of the in-band amplitude's high-pass (removes the reference's offset)."""
ENVELOPE_S = 0.2
"""Decay time constant of the band monitor's peak-hold envelopes."""
WARM_SETTLE_S = 0.5
"""After :meth:`Prediction.warm`, the band monitor's filters start at rest under a moving
reference: their transient is not judged for this long."""
MAX_ORDER = 64
"""Largest number of Laguerre functions of a predictor."""
TINY_STATE = 1e-200
FLUSH_EVERY = 1024
"""Every FLUSH_EVERY steps the prefilters' states smaller than TINY_STATE are set to 0: an axis
at rest at neutral decays them into subnormal numbers, which some CPUs compute about 70 times
slower (the six hexapod prefilters' step: 2.5 us, 170 us with subnormal states).  From
TINY_STATE to a subnormal takes tens of thousands of steps; nothing it drops is measurable."""


@dataclass(frozen=True)
class PredictorParams:
    """One axis' prefilter ``F(z) = d + sum_k c_k L_k(z)`` (see the module docstring).

    Parameters
    ----------
    pole_hz
        Pole of the Laguerre functions (Hz; ``a = exp(-2 pi pole_hz / rate_hz)``).
    coeffs
        ``(d, c_0, ..., c_{N-1})``, ``1 <= N <= MAX_ORDER``.
    rate_hz
        Loop rate the filter was designed for (its coefficients hold at that rate only).
    band_hz
        The driver band it was designed for; the monitor watches above ``HIGH_CUT x band_hz[1]``.

    Raises
    ------
    ConfigError
        Non-finite values, a pole outside ``(0, rate/2)``, an empty or too long basis, a band
        that is not ``0 < low < high < rate/8``, or ``|F(1) - 1| > 1e-6``.
    """

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return frozen_reduce(self)

    pole_hz: float
    coeffs: tuple[float, ...]
    rate_hz: float
    band_hz: tuple[float, ...] = (0.1, 2.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "coeffs", tuple(float(c) for c in self.coeffs))
        object.__setattr__(self, "band_hz", tuple(float(b) for b in self.band_hz))
        for name, v in (("pole_hz", self.pole_hz), ("rate_hz", self.rate_hz)):
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ConfigError(f"prediction.{name} must be a positive finite number, got {v!r}")
        if not self.pole_hz < self.rate_hz / 2:
            raise ConfigError(f"prediction.pole_hz = {self.pole_hz:g} must lie below the "
                              f"Nyquist frequency {self.rate_hz / 2:g} Hz")
        n = len(self.coeffs) - 1
        if not 1 <= n <= MAX_ORDER:
            raise ConfigError(f"prediction.coeffs must hold 2 to {MAX_ORDER + 1} numbers "
                              f"(d, then one per Laguerre function), got {n + 1}")
        bad = [i for i, c in enumerate(self.coeffs) if not math.isfinite(c)]
        if bad:
            raise ConfigError(f"prediction.coeffs[{bad[0]}] is {self.coeffs[bad[0]]!r}")
        if not self.pole < 1.0:
            raise ConfigError(f"prediction.pole_hz = {self.pole_hz!r} is too small: the "
                              "discrete pole rounds to 1 (an integrator)")
        if len(self.band_hz) != 2:
            raise ConfigError(f"prediction.band_hz must be [low, high], got "
                              f"{list(self.band_hz)}")
        lo, hi = self.band_hz
        if not 0 < lo < hi < self.rate_hz / 8:
            raise ConfigError(f"prediction.band_hz must satisfy 0 < low < high < rate/8, got "
                              f"{list(self.band_hz)}")
        dc = self.dc_gain
        if not abs(dc - 1.0) <= 1e-6:
            raise ConfigError(f"prediction: the filter's static gain F(1) is {dc:.9g}, not 1 "
                              "(a predictor must pass a constant reference unchanged)")

    @property
    def order(self) -> int:
        """Number of Laguerre functions ``N``."""
        return len(self.coeffs) - 1

    @property
    def pole(self) -> float:
        """The discrete pole ``a``."""
        return math.exp(-2.0 * math.pi * self.pole_hz / self.rate_hz)

    @property
    def dc_gain(self) -> float:
        """``F(1)``, the static gain (1 for a designed filter)."""
        return float(predictor_freqresp(self, [0.0])[0].real)

    def to_config(self) -> dict[str, object]:
        """The ``prediction`` table of an axis (:mod:`motcomp.config`)."""
        return {"pole_hz": self.pole_hz, "rate_hz": self.rate_hz,
                "band_hz": list(self.band_hz), "coeffs": list(self.coeffs)}


@dataclass(frozen=True)
class MonitorParams:
    """The band monitor's thresholds and the fallback's blend times (one set for all axes).

    Raises
    ------
    ConfigError
        ``resume_ratio`` not below ``fallback_ratio``, or a negative or non-finite value.
    """

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return frozen_reduce(self)

    fallback_ratio: float = 0.3
    resume_ratio: float = 0.15
    resume_after_s: float = 0.5
    fade_out_s: float = 0.02
    fade_in_s: float = 0.5
    floor: float = 1e-4
    """Added to the in-band amplitude (axis units): motion smaller than this is not judged."""

    def __post_init__(self) -> None:
        for name in ("fallback_ratio", "resume_ratio", "resume_after_s", "fade_out_s",
                     "fade_in_s", "floor"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"prediction.{name} must be finite and >= 0, got {v!r}")
        if not 0 < self.resume_ratio < self.fallback_ratio:
            raise ConfigError(f"prediction: resume_ratio ({self.resume_ratio:g}) must lie in "
                              f"(0, fallback_ratio = {self.fallback_ratio:g})")
        if self.floor <= 0:
            raise ConfigError(f"prediction.floor must be > 0, got {self.floor!r}")


def laguerre_basis(pole: float, order: int, z: ArrayLike) -> ComplexArray:
    """``(len(z), order + 1)`` matrix: ``1, L_0(z), ..., L_{N-1}(z)`` (closed form)."""
    zi = 1.0 / np.asarray(z, dtype=complex)
    a = pole
    l0 = math.sqrt(1.0 - a * a) / (1.0 - a * zi)
    ap = (zi - a) / (1.0 - a * zi)
    cols = [np.ones_like(zi), l0]
    for _ in range(order - 1):
        cols.append(cols[-1] * ap)
    return np.stack(cols, axis=1)


def predictor_freqresp(p: PredictorParams, f_hz: ArrayLike) -> ComplexArray:
    """Exact frequency response ``F(e^{j 2 pi f / rate})`` of the prefilter."""
    f = np.atleast_1d(np.asarray(f_hz, dtype=float))
    z = np.exp(2j * np.pi * f / p.rate_hz)
    return np.asarray(laguerre_basis(p.pole, p.order, z) @ np.asarray(p.coeffs))


def realisation(p: PredictorParams) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """``(A, B, C, D)`` with ``l[n] = A l[n-1] + B r[n]``, ``r_pred[n] = C l[n] + D r[n]``."""
    n, a = p.order, p.pole
    s = math.sqrt(1.0 - a * a)

    def advance(prev: FloatArray, r: float) -> FloatArray:
        new = np.empty(n)
        new[0] = a * prev[0] + s * r
        for k in range(1, n):
            new[k] = a * prev[k] + prev[k - 1] - a * new[k - 1]
        return new

    eye = np.eye(n)
    big_a = np.stack([advance(eye[j], 0.0) for j in range(n)], axis=1)
    big_b = advance(np.zeros(n), 1.0)
    return big_a, big_b, np.asarray(p.coeffs[1:], dtype=float), float(p.coeffs[0])


def _highpass2(fc_hz: float, rate_hz: float) -> tuple[float, ...]:
    """Butterworth 2nd-order high-pass biquad ``(b0, b1, b2, a1, a2)`` (bilinear, prewarped)."""
    k = math.tan(math.pi * fc_hz / rate_hz)
    q = 1.0 / math.sqrt(2.0)
    norm = 1.0 / (1.0 + k / q + k * k)
    return (norm, -2.0 * norm, norm, 2.0 * (k * k - 1.0) * norm, (1.0 - k / q + k * k) * norm)


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Prediction:
    """The prefilters and band monitors of ``n`` axes, stepped once a tick.

    ``params[i]`` None: axis ``i`` is not predicted (its reference passes unchanged).
    """

    def __init__(self, params: Sequence[PredictorParams | None], monitor: MonitorParams,
                 rate_hz: float) -> None:
        self.n = len(params)
        self.rate_hz = float(rate_hz)
        self.dt_s = 1.0 / self.rate_hz
        self.params: tuple[PredictorParams | None, ...] = ()
        self.idx: list[int] = []
        """The predicted axes."""
        self.monitor = monitor
        self.ratio = [0.0] * self.n
        """The band monitor's last ratio per axis (0 where not predicted)."""
        self.weight = [0.0] * self.n
        """Share of the prediction in the reference per axis: 1 predicting, 0 fallen back."""
        self.fallbacks = [0] * self.n
        """Times the band monitor made each axis fall back (a switch-off is not counted)."""
        self.moving = 0
        """Bit ``i`` set: axis ``i``'s prediction faded in or out at the last step (its weight
        or the offset it blends out still moving)."""
        self._configure(params, None)

    # --- configuration ------------------------------------------------------------------------
    def _configure(self, params: Sequence[PredictorParams | None],
                   ref: Sequence[float] | None) -> None:
        if len(params) != self.n:
            raise ConfigError(f"{len(params)} predictors for {self.n} axes")
        for i, p in enumerate(params):
            if p is not None and abs(p.rate_hz - self.rate_hz) > 1e-9 * self.rate_hz:
                raise ConfigError(f"prediction of axis {i} was designed for {p.rate_hz:g} Hz, "
                                  f"the loop runs at {self.rate_hz:g} Hz: design it again")
        old_out = None if ref is None or not self.params else self._outputs(ref)
        kept = {i: self._axis_state(j) for j, i in enumerate(self.idx)
                if i < len(params) and params[i] == self.params[i]} if self.params else {}
        self.params = tuple(params)
        self.idx[:] = [i for i, p in enumerate(params) if p is not None]
        self.moving = 0
        m = len(self.idx)
        order = max((p.order for p in params if p is not None), default=1)
        self._a = np.zeros((m, order, order))
        self._b = np.zeros((m, order))
        self._c = np.zeros((m, order))
        self._d = np.zeros(m)
        hp = []
        for j, i in enumerate(self.idx):
            p = params[i]
            assert p is not None
            a, b, c, d = realisation(p)
            n = p.order
            self._a[j, :n, :n] = a
            self._b[j, :n] = b
            self._c[j, :n] = c
            self._d[j] = d
            hp.append(_highpass2(HIGH_CUT * p.band_hz[1], self.rate_hz))
        # one step of every prefilter as one product: [l'; y] = [[A, b], [c A, c b + d]] [l; r]
        self._step_m = np.zeros((m, order + 1, order + 1))
        self._step_m[:, :order, :order] = self._a
        self._step_m[:, :order, order] = self._b
        self._step_m[:, order, :order] = np.einsum("jk,jkl->jl", self._c, self._a)
        self._step_m[:, order, order] = np.einsum("jk,jk->j", self._c, self._b) + self._d
        self._hp = hp
        self._lo_a = math.exp(-2.0 * math.pi * LOW_CUT_HZ * self.dt_s)
        self._decay = math.exp(-self.dt_s / ENVELOPE_S)
        r = np.zeros(m) if ref is None else np.array([ref[i] for i in self.idx], dtype=float)
        self._seed(r)
        # per predicted axis: blend weight, its start and progress, the calm time, the mode
        self._w = [0.0] * m
        self._fallen = [False] * m
        self._w0 = [0.0] * m
        self._progress = [1.0] * m
        self._target = [0.0] * m
        self._calm = [0.0] * m
        self._offset = [0.0] * m
        self._offset_progress = [1.0] * m
        if old_out is not None and m:
            new_out = self._outputs(ref)  # type: ignore[arg-type]
            self._offset = [old_out[i] - new_out[i] for i in self.idx]
            self._offset_progress = [0.0] * m
        for j, i in enumerate(self.idx):
            if i in kept:
                self._set_axis_state(j, kept[i])
            else:
                self.weight[i] = 0.0
                self.ratio[i] = 0.0

    _STATE = ("_r_last", "_hp_x", "_hp_y", "_lo_y", "_env_hi", "_env_lo", "_pred", "_w", "_w0",
              "_progress", "_target", "_calm", "_offset", "_offset_progress", "_fallen")

    def _axis_state(self, j: int) -> dict[str, object]:
        """Every state of predicted axis ``j`` (row ``j`` of the arrays)."""
        n = self.params[self.idx[j]].order  # type: ignore[union-attr]
        out: dict[str, object] = {name: getattr(self, name)[j] for name in self._STATE}
        out["_l"] = self._x[j, :n].copy()
        return out

    def _set_axis_state(self, j: int, st: dict[str, object]) -> None:
        for name in self._STATE:
            getattr(self, name)[j] = st[name]
        lv = np.asarray(st["_l"])
        self._x[j, :lv.size] = lv

    def _seed(self, r: FloatArray) -> None:
        """Every filter at rest at the reference ``r`` (predicted axes)."""
        m, order = self._b.shape
        self._x = np.zeros((m, order + 1))  # the filters' states, then the input (step)
        for j in range(m):
            n = self.params[self.idx[j]].order  # type: ignore[union-attr]
            a = self._a[j, :n, :n]
            self._x[j, :n] = np.linalg.solve(np.eye(n) - a, self._b[j, :n]) * r[j]
        self._r_last: list[float] = r.tolist()
        self._hp_x: list[tuple[float, float]] = [(x, x) for x in r.tolist()]
        self._hp_y: list[tuple[float, float]] = [(0.0, 0.0)] * m
        self._lo_y = [0.0] * m
        self._env_hi = [0.0] * m
        self._env_lo = [0.0] * m
        self._pred: list[float] = r.tolist()
        self._settle = 0
        self._steps = 0

    def set_params(self, params: Sequence[PredictorParams | None], monitor: MonitorParams,
                   reference: Sequence[float]) -> None:
        """Swap parameters between two steps, bumplessly (see the module docstring);
        ``reference`` is the last reference stepped.  Unchanged parameters keep their state."""
        self.monitor = monitor
        if tuple(params) == self.params:
            return
        self._configure(params, reference)

    # --- the step -----------------------------------------------------------------------------
    def _outputs(self, ref: Sequence[float]) -> list[float]:
        """What :meth:`step` returned last, given the reference it was stepped with."""
        out = list(ref)
        for j, i in enumerate(self.idx):
            off = self._offset[j] * min_jerk_weight(self._offset_progress[j])
            out[i] = ref[i] + self._w[j] * (self._pred[j] - ref[i]) + off
        return out

    def step(self, reference: Sequence[float], live: bool | Sequence[bool] = True,
             wanted: bool | Sequence[bool] = True) -> list[float]:
        """Advance one sample with ``reference`` (``n`` values); return the reference to
        compensate.  ``live`` (one for all axes, or per axis) False forces the fallback: the
        reference is a hold, ramp or blend of the shaper's (``fade_out_s``).  ``wanted`` False
        likewise, over ``fade_in_s``: prediction is switched off (module docstring)."""
        if not self.idx:
            return list(reference)
        mon = self.monitor
        dt = self.dt_s
        idx = self.idx
        r_last = self._r_last
        r = [reference[i] for i in idx]
        finite = [x == x and abs(x) != math.inf for x in r]
        r = [x if ok else r_last[j] for j, (x, ok) in enumerate(zip(r, finite, strict=True))]
        # the prefilter (all predicted axes at once): the states and the output in one product
        state = self._x
        last = state.shape[1] - 1
        state[:, last] = r
        state = np.matmul(self._step_m, state[:, :, None])[:, :, 0]
        self._steps += 1
        if self._steps % FLUSH_EVERY == 0:
            state[np.abs(state) < TINY_STATE] = 0.0
        pred = state[:, last].tolist()
        self._x = state
        self._pred = pred
        # band monitor, rule and blend, per axis
        lo_a, decay, floor = self._lo_a, self._decay, mon.floor
        fb_ratio, rs_ratio, rs_after = mon.fallback_ratio, mon.resume_ratio, mon.resume_after_s
        inc_in = dt / mon.fade_in_s if mon.fade_in_s > 0 else 1.0
        inc_out = dt / mon.fade_out_s if mon.fade_out_s > 0 else 1.0
        hp, hx, hy = self._hp, self._hp_x, self._hp_y
        w, w0, prog, target, calm = self._w, self._w0, self._progress, self._target, self._calm
        off, off_p = self._offset, self._offset_progress
        fallen = self._fallen
        out = list(reference)
        moving = 0
        for j, i in enumerate(idx):
            x = r[j]
            b0, b1, b2, a1, a2 = hp[j]
            x1, x2 = hx[j]
            y1, y2 = hy[j]
            hi = b0 * x + b1 * x1 + b2 * x2 - a1 * y1 - a2 * y2
            hx[j] = (x, x1)
            hy[j] = (hi, y1)
            lo = lo_a * (self._lo_y[j] + x - r_last[j])
            self._lo_y[j] = lo
            e_hi = max(abs(hi), decay * self._env_hi[j])
            e_lo = max(abs(lo), decay * self._env_lo[j])
            self._env_hi[j] = e_hi
            self._env_lo[j] = e_lo
            ratio = e_hi / (e_lo + floor)
            judged = ratio
            if self._settle:
                judged = 0.0
            up = live if isinstance(live, bool) else bool(live[i])
            asked = wanted if isinstance(wanted, bool) else bool(wanted[i])
            on = up and asked
            calm[j] = calm[j] + dt if (on and judged < rs_ratio) else 0.0
            if not on or judged > fb_ratio:
                want = 0.0
            elif calm[j] >= rs_after:
                want = 1.0
            else:
                want = target[j]
            if not on:
                fallen[j] = False  # held off by the caller, not by the monitor
            if want != target[j]:
                if want == 0.0 and on:
                    self.fallbacks[i] += 1  # the monitor's, not a switch-off
                    fallen[j] = True
                elif want == 1.0:
                    fallen[j] = False
                w0[j] = w[j]
                prog[j] = 0.0
                target[j] = want
            if prog[j] < 1.0:
                moving |= 1 << i
                quick = target[j] < 0.5 and (asked or not up)  # a fallback, the input lost
                prog[j] = min(prog[j] + (inc_out if quick else inc_in), 1.0)
                w[j] = min_jerk_between(w0[j], target[j], prog[j])
            o = 0.0
            if off_p[j] < 1.0:
                moving |= 1 << i
                off_p[j] = min(off_p[j] + inc_in, 1.0)
                o = off[j] * min_jerk_weight(off_p[j])
            if finite[j]:
                out[i] = x + w[j] * (pred[j] - x) + o
            self.ratio[i] = ratio
            self.weight[i] = w[j]
        self._r_last = r
        self.moving = moving
        if self._settle:
            self._settle -= 1
        return out

    def warm(self, reference: Sequence[float], predicting: Sequence[bool]) -> None:
        """Every filter at rest at ``reference``, and the axes ``predicting`` predicting
        already (``weight`` 1), the others held off: a start mid-run.  The monitor does not
        judge for :data:`WARM_SETTLE_S` (its filters' transient)."""
        r = np.array([reference[i] for i in self.idx], dtype=float)
        self._seed(r)
        self._settle = round(WARM_SETTLE_S / self.dt_s)
        for j, i in enumerate(self.idx):
            self._weight_at(j, 1.0 if predicting[i] else 0.0)
            self._offset[j] = 0.0
            self._offset_progress[j] = 1.0
            self.ratio[i] = 0.0

    def _weight_at(self, j: int, on: float) -> None:
        """Predicted axis ``j``'s weight at ``on`` at once, no fade, the monitor's calm time
        and fallback cleared."""
        self._w[j] = self._w0[j] = self._target[j] = on
        self._progress[j] = 1.0
        self._calm[j] = 0.0
        self._fallen[j] = False
        self.weight[self.idx[j]] = on

    def hold_off(self) -> None:
        """Every predicted axis held off at once (weight 0, no fade): the input is lost and the
        compensator takes the plain reference (:mod:`motcomp.core.tick`, "Input loss"); the
        filters run on, and fade back in after the input returns (``fade_in_s``)."""
        for j in range(len(self.idx)):
            self._weight_at(j, 0.0)

    def fallen_back(self) -> list[bool]:
        """Per axis: the band monitor holds the prediction off (since it last fell back, until
        it resumes or the caller holds it off itself)."""
        out = [False] * self.n
        for j, i in enumerate(self.idx):
            out[i] = self._fallen[j]
        return out

    def predicting(self) -> list[bool]:
        """Per axis: a predictor is configured and not fallen back (its target is predict)."""
        out = [False] * self.n
        for j, i in enumerate(self.idx):
            out[i] = bool(self._target[j] > 0.5)
        return out
