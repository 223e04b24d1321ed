"""Design of the predictive prefilter (:mod:`motcomp.core.predictor`) by linear programming.

The prefilter ``F(z) = x_0 + sum_k x_{k+1} L_k(z)`` (Laguerre functions of pole ``a``) sits before
the compensator: ``T = P F_pid F`` is delivered, ``F_pid F`` is commanded (``F_pid = 1`` on a
bypassed axis).  Every response is linear in ``x``: ``T(f) = G(f) B(f) x`` with ``G = P F_pid``
and ``B`` the basis row (:func:`~motcomp.core.predictor.laguerre_basis`).  For a target delay
``tau`` (``w = 2 pi f``; ``f_b`` a band grid, ``f_a`` a grid to Nyquist, ``f_h >= hf_from_hz``)::

    find x   s.t.  B(1) x = 1                                       F(1) = 1 exactly
                   Im(T e^{+j w tau}) >= 0,  Im(T e^{-j w tau}) <= 0   |phase delay| <= tau, f_b
                   Re T >= 10^(-gain_error_db/20)                      in-band gain, lower
                   Re(T e^{-j phi}) <= 10^(+gain_error_db/20)          in-band gain, upper
                                      (phi: 7 angles across the cone [-w tau, w tau])
                   Re(T e^{-j 2 pi m/16}) <= 10^(peak_db/20) cos(pi/16),  m = 0..15,   f_a
                   Re(F_pid B x e^{-j 2 pi m/16}) <= hf cos(pi/16),       m = 0..15,   f_h
                   -overshoot <= y[n] / y_inf - ... <= 1 + overshoot      (optional step)

where ``y = P F_pid F r`` is the delivered response to a minimum-jerk step ``r`` of rise time
``step_rise_s`` (0: the ideal step), simulated sample by sample and linear in ``x``.  The
smallest feasible ``tau`` is found by bisection (HiGHS), then, at that delay plus a hair, the
LP is solved once more minimising the command gain above ``hf_from_hz`` (an epigraph variable):
of the filters that achieve the delay, the quietest one.  Every design is re-checked on dense
grids with the exact responses (:func:`motcomp.design.frequency.evaluate`) and a longer step
simulation; a bound the LP's grids missed is tightened and the design solved again.

Examples
--------
>>> from motcomp.core.models import parse_model
>>> hexapod = parse_model("p2uzd:K=1,Td=0.0325,Tw=0.06399186527,Zeta=0.7,Tz=0.08764049978")
>>> d = design_predictor(hexapod, 1000.0, constraints=PredictorBounds(peak_db=6.0,
...                      hf_command_gain=3.0))                      # doctest: +SKIP
>>> round(d.worst_delay_ms, 1), d.params.order, d.params.pole_hz    # doctest: +SKIP
(5.4, 30, 0.7)
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from motcomp.core.loop import model_tf, pid_tf
from motcomp.core.lti import ComplexArray, FloatArray
from motcomp.core.minjerk import min_jerk
from motcomp.core.models import P1D, ProcessModel
from motcomp.core.pid import PIDGains
from motcomp.core.predictor import MAX_ORDER, PredictorParams, laguerre_basis
from motcomp.design.blas import with_one_blas_thread
from motcomp.design.frequency import HF_FROM_HZ, evaluate
from motcomp.errors import ConfigError

__all__ = [
    "DEFAULT_ORDER",
    "DEFAULT_POLE_HZ",
    "RESPONSE_RTOL",
    "PredictionOptions",
    "PredictorBounds",
    "PredictorCheck",
    "PredictorDesign",
    "check_chain",
    "design_predictor",
    "series_tf",
    "step_overshoot",
]

DEFAULT_ORDER = 30
"""Laguerre functions of a design (hexapod: 13.5 ms at 20, 5.4 ms at 30, 3.0 ms at 40 but 7x
slower; docs/TUNING.md)."""
DEFAULT_POLE_HZ = 0.7
"""Their pole (hexapod, 30 functions: 6.7 ms at 1 Hz, 9.5 ms at 1.5 Hz, 11.2 ms at 2 Hz)."""
POLYGON = 16
"""Sides of the polygon inscribed in a gain circle (conservative by ``1 - cos(pi/16)``, 0.17 dB)."""
CONE_TANGENTS = 7
"""Tangent lines of the in-band upper gain bound, spread across the phase cone."""
DELAY_TOL_S = 2e-5
"""Bisection stops when the bracket on ``tau`` is this narrow."""
RESPONSE_RTOL = 0.01
"""What "the same prefilter" means: the same problem on any machine gives filters whose
frequency responses differ by at most this share of their largest value (one step of the delay
search moves it by 0.5 %; measured across BLAS threads and 1e-12 changes of the plant: 1e-9)
and whose worst delays differ by at most one step of the search (``DELAY_TOL_S``, to which the
final 1 % hair adds 0.2 us at 20 ms)."""
DB_HAIR = 0.005
"""A dB bound the dense check finds exceeded by more than this is tightened (and re-solved)."""
REL_HAIR = 1e-3
"""The same for the HF command gain (relative) and the step's overshoot (fraction)."""
SETTLE_POLES = 6.0
"""The step window covers the rise, then ``(2 N + SETTLE_POLES) / (2 pi pole_hz)`` seconds:
past ``(2 N + 1)`` pole time constants the Laguerre functions only decay."""


@dataclass(frozen=True)
class PredictorBounds:
    """Bounds of a prefilter design (dB, Hz, dimensionless gains); the fields of
    :class:`motcomp.design.optimal.Constraints` of the same names mean the same.

    ``hf_command_gain`` bounds ``|F_pid F|``, the total command, at and above ``hf_from_hz``.

    Raises
    ------
    ConfigError
        A non-finite or out-of-range bound.
    """

    peak_db: float = 6.0
    gain_error_db: float = 1.0
    band_hz: tuple[float, float] = (0.1, 2.0)
    hf_command_gain: float = 3.0
    hf_from_hz: float = HF_FROM_HZ

    def __post_init__(self) -> None:
        object.__setattr__(self, "band_hz", tuple(float(b) for b in self.band_hz))
        for name in ("peak_db", "gain_error_db", "hf_command_gain", "hf_from_hz"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v)):
                raise ConfigError(f"prediction: {name} must be a finite number, got {v!r}")
        if self.peak_db < 0 or self.gain_error_db <= 0 or self.hf_command_gain <= 0:
            raise ConfigError(f"prediction: need peak_db >= 0, gain_error_db > 0 and "
                              f"hf_command_gain > 0, got {self.peak_db}, {self.gain_error_db}, "
                              f"{self.hf_command_gain}")
        lo, hi = self.band_hz
        if not (len(self.band_hz) == 2 and 0 < lo < hi < self.hf_from_hz):
            raise ConfigError(f"prediction: band must satisfy 0 < low < high < hf_from_hz, got "
                              f"{list(self.band_hz)} and {self.hf_from_hz:g}")

    @classmethod
    def from_constraints(cls, c: Any) -> PredictorBounds:
        """The bounds of :class:`motcomp.design.optimal.Constraints` that apply here."""
        return cls(peak_db=c.peak_db, gain_error_db=c.gain_error_db, band_hz=tuple(c.band_hz),
                   hf_command_gain=c.hf_gain, hf_from_hz=c.hf_from_hz)


@dataclass(frozen=True)
class PredictionOptions:
    """What ``motcomp design --rule optimal`` does about prediction: ``mode`` "auto" (use it
    where it gains ``min_gain_ms`` of worst in-band delay under the same bounds), "on", "off".

    ``chain_hf_gain`` ("on" only): bound the whole chain's command gain above ``hf_from_hz``
    (um of command per um of input there) and minimise its worst delay within it, instead of
    holding the optimal PID's delay with the least command gain."""

    mode: str = "auto"
    order: int = DEFAULT_ORDER
    pole_hz: float = DEFAULT_POLE_HZ
    step_rise_s: float | None = None
    overshoot: float = 0.05
    chain_hf_gain: float | None = None

    def __post_init__(self) -> None:
        if self.mode not in ("auto", "on", "off"):
            raise ConfigError(f"prediction must be auto, on or off, got {self.mode!r}")
        if self.chain_hf_gain is not None:
            if self.mode != "on":
                raise ConfigError("a chain HF-gain bound (--chain-hf-gain) is designed with "
                                  "--prediction on only")
            if not (math.isfinite(self.chain_hf_gain) and self.chain_hf_gain > 0):
                raise ConfigError(f"chain HF-gain bound must be a positive number, got "
                                  f"{self.chain_hf_gain!r}")


@dataclass
class PredictorCheck:
    """Dense-grid metrics of ``T = P F_pid F`` (ms, dB; overshoots as fractions of the final
    value, None if not simulated)."""

    max_delay_ms: float
    max_delay_hz: float
    gain_error_db: float
    peak_gain_db: float
    peak_gain_hz: float
    hf_command_gain: float
    ideal_step_overshoot: float
    design_step_overshoot: float | None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class PredictorDesign:
    """The result of :func:`design_predictor`: the filter, what it achieves (``check``, dense
    grids), what the same chain does without it (``without``) and how it was found."""

    params: PredictorParams
    worst_delay_ms: float
    """Largest ``|phase delay|`` of ``T`` over the band, dense grid (the design's objective)."""
    lp_delay_ms: float
    """The delay the LP was solved for (its grid's bound)."""
    check: PredictorCheck
    without: PredictorCheck
    bounds: PredictorBounds
    step_rise_s: float | None
    overshoot: float
    series: str  # "pid" or "bypass"
    rounds: int
    elapsed_s: float
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """The ``prediction`` block of the design JSON."""
        return {
            "params": self.params.to_config(),
            "order": self.params.order,
            "series": self.series,
            "bounds": {**asdict(self.bounds), "band_hz": list(self.bounds.band_hz)},
            "step_rise_s": self.step_rise_s,
            "overshoot": self.overshoot,
            "worst_delay_ms": self.worst_delay_ms,
            "lp_delay_ms": self.lp_delay_ms,
            "with": self.check.as_dict(),
            "without": self.without.as_dict(),
            "rounds": self.rounds,
            "elapsed_s": self.elapsed_s,
            "notes": list(self.notes),
        }


def series_tf(plant: ProcessModel, rate_hz: float, series: tuple[PIDGains, P1D] | None
              ) -> tuple[tuple[FloatArray, FloatArray], tuple[FloatArray, FloatArray]]:
    """``((num, den) of P, (num, den) of F_pid)`` in ``z`` at ``rate_hz`` (``F_pid = 1`` without
    a PID): ``F_pid = Cr / (1 + Cy M) = nr dm / (d dm + ny nm)``."""
    h = 1.0 / rate_hz
    pn, pden = plant.discretize(rate_hz).tf()
    if series is None:
        return (np.asarray(pn, float), np.asarray(pden, float)), (np.ones(1), np.ones(1))
    gains, model = series
    (nr, d), (ny, _) = pid_tf(gains, h)
    nm, dm = model_tf(model, h)
    num = np.polymul(nr, dm)
    den = np.polyadd(np.polymul(d, dm), np.polymul(ny, nm))
    return (np.asarray(pn, float), np.asarray(pden, float)), (num, den)


def _filt(num: FloatArray, den: FloatArray, x: FloatArray) -> FloatArray:
    """Apply ``num(z)/den(z)`` (polynomials in ``z``, proper) to ``x``."""
    from scipy.signal import lfilter

    num = np.trim_zeros(np.asarray(num, float), "f")
    den = np.trim_zeros(np.asarray(den, float), "f")
    b = np.concatenate([np.zeros(len(den) - len(num)), num])
    return np.asarray(lfilter(b, den, x))


def _step_input(rise_s: float, n: int, rate_hz: float) -> FloatArray:
    """Unit minimum-jerk step of rise time ``rise_s`` (0: the ideal step) over ``n`` samples."""
    t = np.arange(n) / rate_hz
    if rise_s <= 0:
        return np.ones(n)
    return np.asarray(min_jerk(np.clip(t / rise_s, 0.0, 1.0)), dtype=float)


def _basis_responses(s: FloatArray, pole: float, order: int) -> FloatArray:
    """``(len(s), order + 1)``: ``s`` through ``1, L_0, ..., L_{N-1}`` (the Laguerre recursion)."""
    from scipy.signal import lfilter

    cols = [s, np.asarray(lfilter([math.sqrt(1.0 - pole * pole)], [1.0, -pole], s))]
    for _ in range(order - 1):
        cols.append(np.asarray(lfilter([-pole, 1.0], [1.0, -pole], cols[-1])))
    return np.stack(cols, axis=1)


def step_overshoot(plant: ProcessModel, rate_hz: float, series: tuple[PIDGains, P1D] | None,
                   predictor: PredictorParams | None, rise_s: float,
                   duration_s: float = 6.0) -> float:
    """Largest excursion of the delivered response to a unit min-jerk step (``rise_s = 0``: the
    ideal step) beyond ``[0, y_inf]``, as a fraction of ``y_inf = P(1) F_pid(1)``."""
    (pn, pden), (fn, fd) = series_tf(plant, rate_hz, series)
    n = round((rise_s + duration_s) * rate_hz)
    s = _filt(fn, fd, _filt(pn, pden, _step_input(rise_s, n, rate_hz)))
    if predictor is not None:
        s = _basis_responses(s, predictor.pole, predictor.order) @ np.asarray(predictor.coeffs)
    y_inf = float(np.polyval(pn, 1.0) / np.polyval(pden, 1.0)
                  * np.polyval(fn, 1.0) / np.polyval(fd, 1.0))
    y = s / y_inf
    return float(max(np.max(y) - 1.0, -np.min(y), 0.0))


class _LP:
    """The linear programme's matrices for one plant, series and basis (see the module
    docstring); :meth:`solve` for a delay and bounds."""

    def __init__(self, plant: ProcessModel, rate_hz: float,
                 series: tuple[PIDGains, P1D] | None, order: int, pole: float,
                 band_hz: tuple[float, float], hf_from_hz: float,
                 step_rise_s: float | None, pole_hz: float) -> None:
        (pn, pden), (fn, fd) = series_tf(plant, rate_hz, series)
        self.order = order
        self._work: dict[tuple[int, ...], np.ndarray] = {}
        h = 1.0 / rate_hz
        nyq = 0.5 * rate_hz * 0.999

        def g_and_f(f: FloatArray) -> tuple[ComplexArray, ComplexArray, ComplexArray]:
            z = np.exp(2j * np.pi * f * h)
            fpid = np.asarray(np.polyval(fn, z) / np.polyval(fd, z), dtype=complex)
            g = np.asarray(np.polyval(pn, z) / np.polyval(pden, z) * fpid, dtype=complex)
            return g, fpid, laguerre_basis(pole, order, z)

        lo, hi = band_hz
        self.fb = np.geomspace(lo, hi, 120)
        g, _, b = g_and_f(self.fb)
        self.tb = g[:, None] * b
        self.w = 2.0 * np.pi * self.fb
        fa = np.geomspace(0.01, nyq, 400)
        g, fpid, b = g_and_f(fa)
        self.ta = g[:, None] * b
        # above hf_from_hz, |T| <= |P| |F_pid F|: what the HF rows bound (see solve)
        self.plant_hf = np.where(fa >= hf_from_hz, np.abs(g / fpid), np.inf)
        fh = np.geomspace(hf_from_hz, nyq, 200)
        _, fpid, b = g_and_f(fh)
        self.ch = fpid[:, None] * b
        self.eq = laguerre_basis(pole, order, [1.0]).real
        self.y_inf = float(np.polyval(pn, 1.0) / np.polyval(pden, 1.0)
                           * np.polyval(fn, 1.0) / np.polyval(fd, 1.0))
        self.step: FloatArray | None = None
        if step_rise_s is not None:
            settle = (2 * order + SETTLE_POLES) / (2.0 * np.pi * pole_hz)
            n = round((step_rise_s + settle) * rate_hz)
            s = _filt(fn, fd, _filt(pn, pden, _step_input(step_rise_s, n, rate_hz)))
            y = _basis_responses(s, pole, order) / self.y_inf
            dense = round((step_rise_s + 0.5) * rate_hz)
            # every 2nd sample through the rise and 0.5 s after, every 20th in the slow tail
            keep = np.r_[np.arange(0, min(dense, n), 2), np.arange(min(dense, n), n, 20)]
            self.step = y[keep]

    @staticmethod
    def _polygon(rows: ComplexArray, bound: float) -> tuple[FloatArray, FloatArray]:
        phis = 2.0 * np.pi * np.arange(POLYGON) / POLYGON
        a = np.concatenate([(rows * np.exp(-1j * p)).real for p in phis])
        return a, np.full(a.shape[0], bound * math.cos(math.pi / POLYGON))

    def solve(self, tau_s: float, b: PredictorBounds, overshoot: float,
              minimise_hf: bool = False) -> FloatArray | None:
        """Coefficients meeting every bound at delay ``tau_s`` (None if infeasible); with
        ``minimise_hf`` the ones of least command gain above ``hf_from_hz``."""
        n = self.order + 1
        rows: list[FloatArray] = []
        rhs: list[FloatArray] = []
        rot = np.exp(1j * self.w * tau_s)[:, None]
        rows += [-(self.tb * rot).imag, (self.tb / rot).imag]
        rhs += [np.zeros(len(self.fb)), np.zeros(len(self.fb))]
        g_lo, g_hi = 10 ** (-b.gain_error_db / 20), 10 ** (b.gain_error_db / 20)
        rows.append(-self.tb.real)
        rhs.append(np.full(len(self.fb), -g_lo))
        for s in np.linspace(-1.0, 1.0, CONE_TANGENTS):
            rows.append((self.tb * np.exp(-1j * s * self.w * tau_s)[:, None]).real)
            rhs.append(np.full(len(self.fb), g_hi))
        peak = 10 ** (b.peak_db / 20)
        implied = self.plant_hf * b.hf_command_gain / math.cos(math.pi / POLYGON)
        a, r = self._polygon(self.ta[implied > peak * math.cos(math.pi / POLYGON)], peak)
        rows.append(a)
        rhs.append(r)
        if self.step is not None:
            rows += [self.step, -self.step]
            rhs += [np.full(len(self.step), 1.0 + overshoot),
                    np.full(len(self.step), overshoot)]
        a_hf, r_hf = self._polygon(self.ch, b.hf_command_gain)
        a_ub = np.vstack(rows)
        b_ub = np.concatenate(rhs)
        if minimise_hf:
            # x plus t: |F_pid F| <= t (polygon) at f >= hf_from_hz, t <= the bound; minimise t
            col = np.full((a_hf.shape[0], 1), -math.cos(math.pi / POLYGON))
            a_ub = np.vstack([np.hstack([a_ub, np.zeros((a_ub.shape[0], 1))]),
                              np.hstack([a_hf, col])])
            b_ub = np.concatenate([b_ub, np.zeros(a_hf.shape[0])])
            cost = np.zeros(n + 1)
            cost[-1] = 1.0
            bounds = [(None, None)] * n + [(0.0, b.hf_command_gain)]
            a_eq = np.hstack([self.eq, np.zeros((1, 1))])
        else:
            a_ub = np.vstack([a_ub, a_hf])
            b_ub = np.concatenate([b_ub, r_hf])
            cost = np.zeros(n)
            bounds = [(None, None)] * n
            a_eq = self.eq
        work = self._work.get(a_ub.shape)
        x, self._work[a_ub.shape] = _row_generation(cost, a_ub, b_ub, a_eq, bounds, work)
        return None if x is None else np.asarray(x[:n], dtype=float)


ROW_STRIDE = 16
"""The row generation's first working set: every ``ROW_STRIDE``-th row of the LP."""
ROW_TOL = 1e-9
"""A row the working set's solution violates by more than this joins the working set."""


def _row_generation(cost: FloatArray, a_ub: FloatArray, b_ub: FloatArray, a_eq: FloatArray,
                    bounds: Sequence[tuple[float | None, float | None]],
                    work: np.ndarray | None = None) -> tuple[FloatArray | None, np.ndarray]:
    """``linprog(cost, a_ub x <= b_ub, a_eq x = 1)`` solved on a working set of rows: every
    :data:`ROW_STRIDE`-th row first, then, round by round, every row the last solution violates
    (an exchange method).  The last solution meets every row, and no point that meets every row
    does better, since the working set's problem is a relaxation of the whole; a relaxation
    without a solution proves the whole has none.  Most of the rows (polygon sides and grid
    points far from where a bound binds) never enter: each LP is a fraction of the whole.
    ``work`` (a mask of the rows) is a first working set to start from, the last one of an LP of
    the same rows at another delay: its binding rows are near this one's.  Returns the solution
    (None if the LP has none) and the final working set."""
    from scipy.optimize import linprog

    work = np.zeros(a_ub.shape[0], dtype=bool) if work is None else work.copy()
    work[::ROW_STRIDE] = True
    while True:
        res = linprog(cost, A_ub=a_ub[work], b_ub=b_ub[work], A_eq=a_eq, b_eq=[1.0],
                      bounds=bounds, method="highs")
        if res.status != 0:
            return None, work
        x = np.asarray(res.x, dtype=float)
        violated = (a_ub @ x - b_ub > ROW_TOL) & ~work
        if not np.any(violated):
            return x, work
        work |= violated


def _params(x: FloatArray, pole_hz: float, rate_hz: float,
            band_hz: tuple[float, float]) -> PredictorParams:
    """The filter of coefficients ``x``, its ``d`` corrected so that ``F(1) = 1`` to rounding."""
    a = math.exp(-2.0 * math.pi * pole_hz / rate_hz)
    dc = float((laguerre_basis(a, len(x) - 1, [1.0]).real @ x)[0])
    x = x.copy()
    x[0] += 1.0 - dc
    return PredictorParams(pole_hz=pole_hz, coeffs=tuple(float(v) for v in x), rate_hz=rate_hz,
                           band_hz=band_hz)


def check_chain(plant: ProcessModel, rate_hz: float, series: tuple[PIDGains, P1D] | None,
                p: PredictorParams | None, b: PredictorBounds, step_rise_s: float | None,
                duration_s: float = 6.0) -> PredictorCheck:
    """Dense-grid metrics of ``P F_pid F`` (either factor may be absent) against ``b``'s band
    and HF range, and its step overshoots (ideal step; min-jerk step of ``step_rise_s``)."""
    gains, model = series if series is not None else (None, None)
    ev = evaluate(gains, model, plant, rate_hz=rate_hz, band_hz=b.band_hz,
                  hf_from_hz=b.hf_from_hz, predictor=p)
    return PredictorCheck(
        max_delay_ms=ev.max_residual_delay_ms, max_delay_hz=ev.max_residual_delay_hz,
        gain_error_db=ev.gain_error_db, peak_gain_db=ev.peak_gain_db,
        peak_gain_hz=ev.peak_gain_hz, hf_command_gain=ev.hf_command_gain,
        ideal_step_overshoot=step_overshoot(plant, rate_hz, series, p, 0.0, duration_s),
        design_step_overshoot=None if step_rise_s is None else
        step_overshoot(plant, rate_hz, series, p, step_rise_s, duration_s))


@with_one_blas_thread
def design_predictor(plant: ProcessModel, rate_hz: float, *,
                     series: tuple[PIDGains, P1D] | None = None,
                     constraints: PredictorBounds | None = None, order: int = DEFAULT_ORDER,
                     pole_hz: float = DEFAULT_POLE_HZ, step_rise_s: float | None = None,
                     overshoot: float = 0.05, max_delay_ms: float | None = None,
                     delay_limit_ms: float | None = None, delay_hint_ms: float | None = None,
                     progress: Callable[[int, int, str], None] | None = None
                     ) -> PredictorDesign:
    """The prefilter of least worst in-band delay within ``constraints`` (module docstring).

    Parameters
    ----------
    plant
        The platform ``P`` (exact ZOH discretisation at ``rate_hz``).
    rate_hz
        Loop rate; the coefficients hold at that rate only.
    series
        ``(gains, internal model)`` of the PID the prefilter feeds, or None (bypassed axis).
    constraints
        Bounds (default :class:`PredictorBounds`: +6 dB peak, 1 dB, 3x above 10 Hz).
    order, pole_hz
        Number of Laguerre functions and their pole (Hz).
    step_rise_s, overshoot
        If ``step_rise_s`` is given, the delivered response to a minimum-jerk step of that rise
        time (0: the ideal step) stays within ``[-overshoot, 1 + overshoot]`` of its final value.
    max_delay_ms
        Instead of minimising the delay, hold it to this and minimise the command gain above
        ``hf_from_hz``.
    delay_limit_ms
        Search no filter of a worst delay above this (a ``ConfigError`` if none below it meets
        the bounds): a caller comparing chains stops a chain that cannot beat the best so far
        after one LP.
    delay_hint_ms
        A delay the least one is likely near (the chain's delay without the filter): the
        search tests it first.  It changes how fast the search ends, not where.
    progress
        Called as ``progress(done, total, note)`` after each LP of the search.

    Raises
    ------
    ConfigError
        Bad order, pole, rate or overshoot, or no filter of this basis meets the bounds.
    """
    t0 = time.perf_counter()
    b0 = constraints or PredictorBounds()
    if not (isinstance(order, int) and 1 <= order <= MAX_ORDER):
        raise ConfigError(f"prediction order must be 1-{MAX_ORDER}, got {order!r}")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ConfigError(f"rate must be a positive finite number of Hz, got {rate_hz}")
    if not (math.isfinite(pole_hz) and 0 < pole_hz < rate_hz / 2):
        raise ConfigError(f"prediction pole must lie in (0, {rate_hz / 2:g}) Hz, got {pole_hz}")
    if not b0.band_hz[1] < rate_hz / 8 or not b0.hf_from_hz < rate_hz / 2:
        raise ConfigError(f"prediction band {list(b0.band_hz)} / hf_from {b0.hf_from_hz:g} Hz "
                          f"do not fit a {rate_hz:g} Hz loop")
    if step_rise_s is not None and not (math.isfinite(step_rise_s) and step_rise_s >= 0):
        raise ConfigError(f"step rise time must be >= 0 s, got {step_rise_s}")
    if not (math.isfinite(overshoot) and overshoot >= 0):
        raise ConfigError(f"overshoot must be >= 0, got {overshoot}")
    pole = math.exp(-2.0 * math.pi * pole_hz / rate_hz)
    lp = _LP(plant, rate_hz, series, order, pole, b0.band_hz, b0.hf_from_hz, step_rise_s,
             pole_hz)
    duration = 2.0 * (2 * order + SETTLE_POLES) / (2.0 * np.pi * pole_hz) + 1.0
    without = check_chain(plant, rate_hz, series, None, b0, step_rise_s, duration)
    # the cone constraints need w tau < pi/2 over the band: the bracket's top
    tau_top = 0.24 / b0.band_hz[1]
    if delay_limit_ms is not None:
        tau_top = min(tau_top, max(delay_limit_ms, 0.0) / 1e3)
    lps = [0, 3 + math.ceil(math.log2(max(tau_top, DELAY_TOL_S) / DELAY_TOL_S))]
    infeasible = -1.0  # the largest delay found infeasible so far (none: -1)

    def feasible(tau_s: float, bounds: PredictorBounds, os_target: float) -> bool:
        nonlocal infeasible
        ok = lp.solve(tau_s, bounds, os_target) is not None
        if not ok:
            infeasible = max(infeasible, tau_s)
        lps[0] += 1
        if progress is not None:
            lps[1] = max(lps[1], lps[0] + 1)
            progress(lps[0], lps[1], f"{tau_s * 1e3:.3f} ms {'met' if ok else 'not met'}")
        return ok

    def note(text: str) -> None:
        lps[0] += 1
        if progress is not None:
            lps[1] = max(lps[1], lps[0] + 1)
            progress(lps[0], lps[1], text)

    def search(bounds: PredictorBounds, os_target: float) -> float:
        """The least delay the bounds admit (bisection, to DELAY_TOL_S), a hair above."""
        lo, hi = max(infeasible, 0.0), None
        hint = None if delay_hint_ms is None else delay_hint_ms / 1e3
        if hint is not None and lo < hint < tau_top:
            if feasible(hint, bounds, os_target):
                hi = hint
            else:
                lo = hint
        if hi is None:
            if not feasible(tau_top, bounds, os_target):
                raise ConfigError(
                    f"prediction: no filter of order {order} (pole {pole_hz:g} Hz) meets the "
                    f"bounds (peak {b0.peak_db:g} dB, gain error {b0.gain_error_db:g} dB, "
                    f"{b0.hf_command_gain:g}x above {b0.hf_from_hz:g} Hz"
                    + ("" if step_rise_s is None else
                       f", {overshoot:.0%} overshoot on a {step_rise_s:g} s step")
                    + f") even at {tau_top * 1e3:.3g} ms of delay"
                    + (": loosen them" if delay_limit_ms is None else ""))
            hi = tau_top
        if lo == 0.0 and infeasible < 0.0 and feasible(0.0, bounds, os_target):
            hi = 0.0
        if progress is not None:
            lps[1] = lps[0] + 3 + math.ceil(math.log2(max(hi - lo, DELAY_TOL_S) / DELAY_TOL_S))
        while hi - lo > DELAY_TOL_S:
            mid = 0.5 * (lo + hi)
            if feasible(mid, bounds, os_target):
                hi = mid
            else:
                lo = mid
        return hi * 1.01 + 2e-6  # a hair above the optimum, for the HF minimisation
    notes: list[str] = []
    b = b0
    os_target = overshoot
    params = None
    tau = 0.0
    rounds = 0
    tau_fixed = None if max_delay_ms is None else max_delay_ms / 1e3
    for rounds in range(1, 5):
        if tau_fixed is not None:
            tau = tau_fixed
            if lp.solve(tau, b, os_target) is None:
                raise ConfigError(
                    f"prediction: no filter of order {order} (pole {pole_hz:g} Hz) holds the "
                    f"delay to {max_delay_ms:g} ms within the bounds (peak {b0.peak_db:g} dB, "
                    f"gain error {b0.gain_error_db:g} dB, {b0.hf_command_gain:g}x above "
                    f"{b0.hf_from_hz:g} Hz)")
        else:
            tau = search(b, os_target)
        note(f"the least command gain at {tau * 1e3:.3f} ms")
        x = lp.solve(tau, b, os_target, minimise_hf=True)
        if x is None:  # pragma: no cover - the feasibility solve just succeeded
            x = lp.solve(tau, b, os_target)
        assert x is not None
        params = _params(x, pole_hz, rate_hz, b0.band_hz)
        note("checking on dense grids" + ("" if step_rise_s is None else " and the step"))
        chk = check_chain(plant, rate_hz, series, params, b0, step_rise_s, duration)
        over_peak = chk.peak_gain_db - b0.peak_db
        over_gain = chk.gain_error_db - b0.gain_error_db
        over_hf = chk.hf_command_gain / b0.hf_command_gain - 1.0
        over_os = (chk.design_step_overshoot or 0.0) - overshoot
        over_delay = 0.0 if max_delay_ms is None else chk.max_delay_ms - max_delay_ms
        if (max(over_peak, over_gain) <= DB_HAIR and max(over_hf, over_os) <= REL_HAIR
                and over_delay <= 1e-3):
            break
        notes.append(f"round {rounds}: the dense check exceeded a bound (peak {over_peak:+.3f} "
                     f"dB, gain error {over_gain:+.3f} dB, HF gain {over_hf:+.2%}, overshoot "
                     f"{over_os:+.4f}, delay {over_delay:+.4f} ms); tightened and solved again")

        def tighter(value: float, over: float, hair: float, margin: float) -> float:
            return value - (over + margin) if over > hair else value

        b = replace(b, peak_db=max(tighter(b.peak_db, over_peak, DB_HAIR, 0.005), 0.0),
                    gain_error_db=max(tighter(b.gain_error_db, over_gain, DB_HAIR, 0.002), 0.01),
                    hf_command_gain=b.hf_command_gain
                    / (1.0 + (over_hf + 1e-3 if over_hf > REL_HAIR else 0.0)))
        os_target = max(tighter(os_target, over_os, REL_HAIR, 1e-3), 0.0)
        if tau_fixed is not None and over_delay > 1e-3:
            tau_fixed = max(tau_fixed - (over_delay + 1e-3) / 1e3, 0.0)
    else:
        notes.append("WARNING: the dense check still exceeds a bound after 4 rounds")
    assert params is not None
    return PredictorDesign(
        params=params, worst_delay_ms=chk.max_delay_ms, lp_delay_ms=tau * 1e3, check=chk,
        without=without, bounds=b0, step_rise_s=step_rise_s, overshoot=overshoot,
        series="bypass" if series is None else "pid", rounds=rounds,
        elapsed_s=time.perf_counter() - t0, notes=notes)
