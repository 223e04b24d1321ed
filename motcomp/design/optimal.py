"""Numerically optimised tuning of the pseudo open-loop PID (``motcomp design --rule optimal``).

The compensator sends ``u = F r`` with ``F = Cr/(1 + Cy M)`` (see
:mod:`motcomp.core.compensator`); the platform delivers ``T = P F``.  The tuning rules (ZN, CC)
null the low-frequency lag but over-amplify above the band; this module searches the gains
instead, as a constrained minimax problem (``tau_T`` = phase delay of T, ``f`` in Hz)::

    minimise    max_{f in band} |tau_T(f)|                       residual phase delay
    over        kp, ki, kd, tf   (and the setpoint weights b, c of the reference path)
    subject to  20 log10 |T(f)|       <= peak_db              for every f up to Nyquist
                |20 log10 |T(f)||     <= gain_error_db        in the band
                20 log10 |F(f) M(f)|  <= command_excess_db    in the band
                |F(f)|                <= max_command_gain     for every f
                |F(f)|                <= hf_command_gain      for f >= hf_from_hz
                |S(f)| = |1/(1 + Cy M)| <= max_sensitivity    for every f
                every pole of the discrete internal loop inside |z| <= 1 - 1e-4

Command amplification (what the actuator limits see) is bounded twice: in the driver band the
command may exceed the exact inverse of the model, ``r/M`` -- what *any* lag-free compensation
must send, and what the motion-cueing headroom has to be sized for -- by at most
``command_excess_db``; at every frequency it is at most ``max_command_gain`` times the reference
(reference steps, update staircases and noise reach the actuator multiplied by that), and above
``hf_from_hz`` (10 Hz: no driver input lives there, only the input stream's irregularities) by
``hf_command_gain``.
docs/TUNING.md explains the choice and the defaults.

Robust version
--------------
Given an uncertainty set of platforms ``P_m`` (default: K +-10 %, Td +-5 ms, time constants
+-20 %, 27 members), the same problem is solved for the worst member.  With a model error, a
feedforward compensator cannot remove the phase error the mismatch itself causes: an exact
inverse of M delivers ``P_m/M``, whose largest phase delay over the band is the member's *floor*.
The robust objective is the worst excess over the floor, ``max_m (max_f |tau_m(f)| - floor_m)``;
the peak-gain bound holds for every member, the gain-error bound for the nominal one (beyond its
own floor).  Since ``arg(P_m F) = arg(P_m/M) + arg(M F)`` exactly, the excess of every member is
at most the nominal residual delay.

Solution method
---------------
The frequency responses of all members are computed on a fixed grid by
:class:`~motcomp.design.fastloop.LoopGrid` (vectorised; finite-difference Jacobians are one
batched call; the poles are batched eigenvalues of companion matrices).  The minimax is solved
in epigraph form (minimise ``t`` subject to ``-t <= tau(f_i) <= t``) with SLSQP, each bound on
the grid taken as the smooth soft minimum of small frequency blocks (:class:`_Problem`), in log
coordinates for kp, ki, kd, tf and the reference path's gains ``kp b``, ``kd c``.  The starts
are fixed -- the best point of a deterministic (Halton) sample of the gain space, the ZN, CC,
AMIGO and SIMC gains, the second-best sample --, every one is solved on a ten times softer
problem, then refined, and the best is kept: the same inputs give gains within
:data:`GAIN_RTOL` on any machine.  Every candidate is re-checked on dense grids
(:func:`motcomp.design.frequency.evaluate` for the nominal plant, poles included); a peak or
command bound that the fixed grid missed by a little is tightened and the design re-solved.
docs/TUNING.md ("How it is solved") has the reasons and the figures.

No harm
-------
The uncompensated platform is always the reference point: the in-band gain error may not exceed
the platform's own (or the bound, whichever is larger), the result records what the design gains
over the platform, and bypass is recommended when the design is worse, gains less than
``min_gain_ms``, or the internal model is delay-dominated (``Tp1/Td < 1``, the hexapod): there
what is gained is prediction of a pure delay, not inversion of a lag.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from motcomp.core.models import OE, P1D, ProcessModel, p1d_coefficients
from motcomp.core.pid import PIDGains
from motcomp.core.tuning import RULES, tune
from motcomp.design.blas import with_one_blas_thread
from motcomp.design.fastloop import LoopGrid
from motcomp.design.frequency import HF_FROM_HZ, Evaluation, evaluate
from motcomp.errors import ConfigError

__all__ = [
    "GAIN_RTOL",
    "MS_HAIR",
    "Constraints",
    "MemberResult",
    "OptimalDesign",
    "OptimalOptions",
    "Uncertainty",
    "bypass_recommended",
    "member_table",
    "optimise",
    "perturb",
]

WEIGHT_MAX = 50.0
"""Largest setpoint weight b, c searched: a small ``kp`` with a large ``b`` is how the reference
path keeps a low gain above the band while the feedback path stays stiff."""
POLE_MARGIN = 1e-4
"""Largest admissible pole modulus of the internal loop is ``1 - POLE_MARGIN``."""
DELAY_DOMINATED_RATIO = 1.0
"""Below this ``Tp1/Td`` of the internal model the plant is delay-dominated: its lag is too
small for compensation to be worth the prediction of its pure delay."""


@dataclass(frozen=True)
class Constraints:
    """Bounds of the optimised design (dB, Hz, dimensionless gains).

    Raises
    ------
    ConfigError
        If a bound is non-finite or out of its meaningful range.
    """

    peak_db: float = 8.0
    gain_error_db: float = 1.0
    command_excess_db: float = 0.5
    max_command_gain: float = 60.0
    max_sensitivity: float = 4.0
    band_hz: tuple[float, float] = (0.1, 2.0)
    hf_command_gain: float | None = None
    """Bound on ``|F|`` at and above ``hf_from_hz``; None: ``max_command_gain`` (no extra
    bound)."""
    hf_from_hz: float = HF_FROM_HZ

    def __post_init__(self) -> None:
        if self.hf_command_gain is None:
            object.__setattr__(self, "hf_command_gain", self.max_command_gain)
        for f in fields(self):
            if f.name == "band_hz":
                continue
            v = getattr(self, f.name)
            if not (isinstance(v, int | float) and math.isfinite(v)):
                raise ConfigError(f"optimal: {f.name} must be a finite number, got {v!r}")
        if self.peak_db < 0:
            raise ConfigError(f"optimal: peak_db must be >= 0 dB, got {self.peak_db}")
        if self.gain_error_db <= 0:
            raise ConfigError(f"optimal: gain_error_db must be > 0 dB, got {self.gain_error_db}")
        if self.max_command_gain <= 1:
            raise ConfigError(f"optimal: max_command_gain must be > 1, got "
                              f"{self.max_command_gain}")
        if self.hf_gain <= 0:
            raise ConfigError(f"optimal: hf_command_gain must be > 0, got "
                              f"{self.hf_command_gain}")
        if self.max_sensitivity <= 1:
            raise ConfigError(f"optimal: max_sensitivity must be > 1, got {self.max_sensitivity}")
        lo, hi = self.band_hz
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
            raise ConfigError(f"optimal: band must satisfy 0 < low < high, got {self.band_hz}")
        if not self.hf_from_hz > hi:
            raise ConfigError(f"optimal: hf_from_hz must lie above the band ({hi:g} Hz), got "
                              f"{self.hf_from_hz}")

    @property
    def hf_gain(self) -> float:
        """:attr:`hf_command_gain`, resolved (a number)."""
        assert self.hf_command_gain is not None
        return self.hf_command_gain

    def as_dict(self) -> dict[str, Any]:
        return {f.name: (list(getattr(self, f.name)) if f.name == "band_hz"
                         else getattr(self, f.name)) for f in fields(self)}


def perturb(model: ProcessModel, gain: float = 1.0, dead_time_s: float = 0.0,
            time_scale: float = 1.0) -> ProcessModel:
    """``model`` with its gain times ``gain``, its delay plus ``dead_time_s`` and every time
    constant times ``time_scale`` (the dynamics slowed down by that factor).

    For OE models the time scaling is ``s -> time_scale s`` on the polynomials.

    Raises
    ------
    ConfigError
        If the perturbed delay is negative or a factor is not positive.
    """
    if not (gain > 0 and time_scale > 0):
        raise ConfigError(f"perturbation factors must be > 0, got gain={gain}, "
                          f"time_scale={time_scale}")
    if isinstance(model, OE):
        n = len(model.num)
        d = len(model.den)
        num = tuple(gain * v * time_scale ** (n - 1 - i) for i, v in enumerate(model.num))
        den = tuple(v * time_scale ** (d - 1 - i) for i, v in enumerate(model.den))
        return replace(model, num=num, den=den, Td=model.Td + dead_time_s)
    changes: dict[str, Any] = {"K": model.K * gain,  # type: ignore[attr-defined]
                               "Td": model.Td + dead_time_s}  # type: ignore[attr-defined]
    for name in ("Tp1", "Tp2", "Tz", "Tw"):
        value = getattr(model, name, None)
        if value is not None:
            changes[name] = value * time_scale
    if changes["Td"] < 0:
        raise ConfigError(f"perturbed dead time is negative ({changes['Td']} s)")
    return replace(model, **changes)  # type: ignore[type-var]


@dataclass(frozen=True)
class Uncertainty:
    """A box of platform models around the nominal one: K x (1 +- gain_rel), Td +- dead_time_s,
    time constants x (1 +- time_constant_rel); its members are the 3^3 combinations of
    (minus, nominal, plus), nominal first."""

    gain_rel: float = 0.10
    dead_time_s: float = 0.005
    time_constant_rel: float = 0.20

    def __post_init__(self) -> None:
        for name in ("gain_rel", "time_constant_rel"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 <= v < 1):
                raise ConfigError(f"uncertainty {name} must be in [0, 1), got {v!r}")
        if not (math.isfinite(self.dead_time_s) and self.dead_time_s >= 0):
            raise ConfigError(f"uncertainty dead_time_s must be >= 0, got {self.dead_time_s!r}")

    def members(self, plant: ProcessModel) -> list[tuple[str, ProcessModel]]:
        """``(label, model)`` of every member; labels like ``K+10% Td-5ms T+20%``."""
        out: list[tuple[str, ProcessModel]] = []
        levels = (0, -1, 1)
        for sk in levels:
            for sd in levels:
                for st in levels:
                    if (sk, sd, st) != (0, 0, 0) and (
                            (sk and not self.gain_rel) or (sd and not self.dead_time_s)
                            or (st and not self.time_constant_rel)):
                        continue
                    label = " ".join(part for part in (
                        _label("K", sk, f"{self.gain_rel * 100:g}%"),
                        _label("Td", sd, f"{self.dead_time_s * 1e3:g}ms"),
                        _label("T", st, f"{self.time_constant_rel * 100:g}%")) if part)
                    # a delay shorter than the error is clipped at zero delay
                    shift = max(sd * self.dead_time_s, -plant.pure_delay_s)
                    model = perturb(plant, 1 + sk * self.gain_rel, shift,
                                    1 + st * self.time_constant_rel)
                    out.append((label or "nominal", model))
        return out

    def as_dict(self) -> dict[str, float]:
        return {"gain_rel": self.gain_rel, "dead_time_s": self.dead_time_s,
                "time_constant_rel": self.time_constant_rel}


@dataclass(frozen=True)
class OptimalOptions:
    """Everything :func:`optimise` takes besides the plant, model and rate."""

    constraints: Constraints = field(default_factory=Constraints)
    uncertainty: Uncertainty | None = None
    setpoint_weights: bool = True
    min_gain_ms: float = 5.0


def _label(name: str, sign: int, size: str) -> str:
    return "" if sign == 0 else f"{name}{'+' if sign > 0 else '-'}{size}"


@dataclass
class MemberResult:
    """One member of the uncertainty set under a design (ms, dB)."""

    label: str
    model: str
    floor_ms: float
    residual_ms: float
    excess_ms: float
    peak_gain_db: float
    gain_error_db: float
    zn_residual_ms: float | None = None
    zn_peak_gain_db: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class OptimalDesign:
    """The result of :func:`optimise` (delays in ms, gains in dB)."""

    gains: PIDGains
    model: P1D  # the internal model the gains are for
    constraints: Constraints
    rate_hz: float
    evaluation: Evaluation  # nominal plant, dense grid, poles
    command_excess_db: float
    feasible: bool
    violations: list[str]
    uncompensated_delay_ms: float
    best_gain_ms: float
    delay_dominated: bool
    recommend_bypass: bool
    setpoint_weights: bool
    members: list[MemberResult] = field(default_factory=list)
    uncertainty: Uncertainty | None = None
    starts: list[dict[str, Any]] = field(default_factory=list)
    elapsed_s: float = 0.0
    warnings: list[str] = field(default_factory=list)

    @property
    def robust(self) -> bool:
        return self.uncertainty is not None

    def summary(self) -> dict[str, Any]:
        """The ``optimal`` block of the design JSON."""
        ev = self.evaluation
        out: dict[str, Any] = {
            "constraints": self.constraints.as_dict(),
            "setpoint_weights": self.setpoint_weights,
            "feasible": self.feasible,
            "violations": self.violations,
            "values": {
                "max_residual_delay_ms": ev.max_residual_delay_ms,
                "peak_gain_db": ev.peak_gain_db,
                "gain_error_db": ev.gain_error_db,
                "command_excess_db": self.command_excess_db,
                "peak_command_gain": ev.peak_command_gain,
                "hf_command_gain": ev.hf_command_gain,
                "ms": ev.ms,
                "max_pole_modulus": ev.max_pole_modulus,
            },
            "uncompensated_delay_ms": self.uncompensated_delay_ms,
            "best_gain_ms": self.best_gain_ms,
            "lag_ms": self.model.Tp1 * 1e3,
            "delay_dominated": self.delay_dominated,
            "recommendation": "bypass" if self.recommend_bypass else "compensate",
            "elapsed_s": self.elapsed_s,
            "starts": self.starts,
        }
        if self.uncertainty is not None:
            out["robust"] = {
                "uncertainty": self.uncertainty.as_dict(),
                "members": [m.as_dict() for m in self.members],
                "worst_peak_gain_db": max(m.peak_gain_db for m in self.members),
                "worst_excess_ms": max(m.excess_ms for m in self.members),
            }
        return out


def command_excess_db(gains: PIDGains, model: P1D, rate_hz: float,
                      band_hz: tuple[float, float]) -> float:
    """Largest ``20 log10 |F M|`` over the band (dense grid): how far the command exceeds the
    exact inverse ``r/M`` of the internal model."""
    grid = LoopGrid(model, [model], rate_hz, band_hz, n_band=400, n_high=50)
    r = grid(gains.kp, gains.ki, gains.kd, gains.tf, gains.b, gains.c)
    return float(np.max(r.excess_db))


# --- the optimisation problem ---------------------------------------------------------------

SOFT_DELAY_MS = 0.01
"""Largest amount by which a soft block minimum of delay rows (ms) lies below the hard one."""
SOFT_DB = 0.01
"""The same for the rows in dB (peak, in-band gain error, command excess)."""
SOFT_REL = 1e-3
"""The same for the relative rows (command gain, HF command gain, sensitivity)."""
WEIGHT_MIN = 1e-3
"""Smallest setpoint weight searched (the reference gains are log coordinates)."""
MAX_ITER = 300
"""SLSQP iterations per start (the smooth problem converges in 10-100)."""
COARSE_SOFTNESS = 10.0
"""Each start is first solved with the soft minima this many times softer (0.1 ms, 0.1 dB,
1 %): a smoother problem, with fewer local optima for the starts to end in; then refined."""
START_TIE_MS = 1e-4
"""Starts whose objectives differ by less than this are equivalent: the first in the fixed
order of starts is kept."""
MS_HAIR = 0.005
"""How far above ``max_sensitivity`` a design's Ms may read on the dense grid of its evaluation
and still meet the bound (the optimiser's grid is coarser): beyond it the design report says
"BEYOND the bound" and the Pareto table "no"."""
GAIN_RTOL = 1e-4
"""What "the same design" means: the same problem, on any x86-64 CPU, BLAS and thread count,
gives gains within this relative tolerance of each other (measured across BLAS threads, a
1e-12 change of the starts or of the model and another summation order: 1e-7;
tests/test_optimal_determinism.py)."""


class _Problem:
    """The smooth problem SLSQP solves, in the variables ``y = [ln kp, ln ki, ln kd, ln tf,
    (ln kp b, ln kd c,) t_ms]``.

    The reference path's gains ``kp b`` and ``kd c`` are variables of their own: the command
    depends on them far more than on the split of each between the paths, and in these
    coordinates the set of near-optimal gains is a straight valley (``kd`` shrinking, ``kd c``
    fixed) that ends on the bound ``c <= WEIGHT_MAX``, a linear constraint.  Every bound on a
    frequency grid becomes one constraint per small block of frequencies, the block's soft
    minimum (:func:`_softmin`): smooth, and below the block's minimum by at most
    :data:`SOFT_DELAY_MS`, :data:`SOFT_DB` or :data:`SOFT_REL`, so each bound is met with that
    margin on the grid.  A smooth problem has one optimum where the hard minimax has a ragged
    floor of near-equal corners: every start that converges reaches the same gains.
    """

    def __init__(self, grid: LoopGrid, c: Constraints, weights: bool,
                 peak_db: float, floor_ms: np.ndarray, gain_limit_db: float,
                 softness: float = 1.0) -> None:
        self.grid = grid
        self.soft = (SOFT_DELAY_MS * softness, SOFT_DB * softness, SOFT_REL * softness)
        self.c = c
        self.weights = weights
        self.peak_db = peak_db
        self.floor_ms = floor_ms[:, None, None]  # (m, 1, 1)
        self.gain_limit_db = gain_limit_db
        self.n_gain = 6 if weights else 4
        self.hi = slice(grid.band.start, None)  # peak constraints from the band upwards
        self.hf = grid.f >= c.hf_from_hz
        self._value_key: bytes | None = None
        self._value = np.zeros(0)
        self._band_blocks = _blocks(grid.f_band.size, 3)
        self._n_delay_rows = grid.p.shape[0] * 2 * self._band_blocks
        model = grid.model
        self._model_coef = p1d_coefficients(model, grid.h)
        K = abs(model.K)
        h = grid.h
        gain_bounds = [
            (math.log(1e-3 / K), math.log(1e3 / K)),
            (math.log(1e-2 / K), math.log(1e5 / K)),
            (math.log(1e-7 / K), math.log(10.0 / K)),
            (math.log(0.1 * h), math.log(1.0)),
        ]
        if weights:  # ln kp b and ln kd c; their ratio to kp, kd is a linear constraint
            w_lo, w_hi = math.log(WEIGHT_MIN), math.log(WEIGHT_MAX)
            gain_bounds += [(gain_bounds[0][0] + w_lo, gain_bounds[0][1] + w_hi),
                            (gain_bounds[2][0] + w_lo, gain_bounds[2][1] + w_hi)]
        self.bounds = [*gain_bounds, (0.0, 1e4)]
        self._lo = np.array([b[0] for b in self.bounds])
        self._hi = np.array([b[1] for b in self.bounds])

    def gains(self, y: np.ndarray) -> PIDGains:
        g = np.exp(np.asarray(y[:4], dtype=float))
        b = c = 1.0
        if self.weights:
            b = min(max(math.exp(float(y[4]) - float(y[0])), 0.0), WEIGHT_MAX)
            c = min(max(math.exp(float(y[5]) - float(y[2])), 0.0), WEIGHT_MAX)
        return PIDGains(float(g[0]), float(g[1]), float(g[2]), float(g[3]), b, c)

    def x_of(self, g: PIDGains, t_ms: float) -> np.ndarray:
        head = [math.log(g.kp), math.log(g.ki), math.log(g.kd), math.log(g.tf)]
        if self.weights:
            b = min(max(g.b, WEIGHT_MIN), WEIGHT_MAX)
            c = min(max(g.c, WEIGHT_MIN), WEIGHT_MAX)
            head += [head[0] + math.log(b), head[2] + math.log(c)]
        return np.clip(np.array([*head, t_ms]), self._lo, self._hi)

    def _weights_of(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not self.weights:
            ones = np.ones(Y.shape[0])
            return ones, ones
        # not clipped: SLSQP's finite differences must see the weights move at their bounds
        return np.exp(Y[:, 4] - Y[:, 0]), np.exp(Y[:, 5] - Y[:, 2])

    def _batch(self, Y: np.ndarray) -> np.ndarray:
        """Constraint vectors (>= 0 when satisfied) of the rows of ``Y``."""
        G = np.exp(Y[:, :4])
        b, c = self._weights_of(Y)
        r = self.grid(G[:, 0], G[:, 1], G[:, 2], G[:, 3], b, c)
        t = Y[:, -1][None, :, None]
        tau = r.delay_s * 1e3  # (m, k, nb)
        k = Y.shape[0]
        band = self.grid.band
        nbl = self._band_blocks
        soft_ms, soft_db, soft_rel = self.soft
        dly = np.concatenate([_softmin(t + self.floor_ms - tau, nbl, soft_ms),
                              _softmin(t + self.floor_ms + tau, nbl, soft_ms)], axis=-1)
        gain = r.gain_db[0][:, band]
        parts = [
            np.moveaxis(dly, 1, 0).reshape(k, -1),
            np.moveaxis(_softmin(self.peak_db - r.gain_db[:, :, self.hi], 40, soft_db), 1, 0
                        ).reshape(k, -1),
            _softmin(self.gain_limit_db - gain, nbl, soft_db),
            _softmin(self.gain_limit_db + gain, nbl, soft_db),
            _softmin(self.c.command_excess_db - r.excess_db, nbl, soft_db),
            _softmin(1.0 - r.command / self.c.max_command_gain, 40, soft_rel),
            _softmin(1.0 - r.command[:, self.hf] / self.c.hf_gain, 40, soft_rel),
            _softmin(1.0 - r.sensitivity / self.c.max_sensitivity, 40, soft_rel),
        ]
        rho = self.pole_modulus(G[:, 0], G[:, 1], G[:, 2], G[:, 3])[:, None]
        parts.append(100.0 * (1.0 - POLE_MARGIN - rho))
        return np.concatenate(parts, axis=1)

    def pole_modulus(self, kp: np.ndarray, ki: np.ndarray, kd: np.ndarray, tf: np.ndarray
                     ) -> np.ndarray:
        """Largest pole modulus of the internal loop for each gain set (batched).

        The characteristic polynomial of :func:`motcomp.core.loop.poles` written out:
        ``Dc(z) (z - phi) z^d + Nc(z) (g0 z + g1)`` with ``Dc = (z - 1)(z - a_d)`` and
        ``Nc = kp Dc + ki h (z - a_d) + b_d (z - 1)^2``; its roots are the eigenvalues of the
        companion matrices, computed in one call.
        """
        phi, g0, g1, d = self._model_coef
        h = self.grid.h
        ad = tf / (tf + h)
        bd = kd / (tf + h)
        dc = np.stack([np.ones_like(ad), -(1.0 + ad), ad], axis=1)
        nc = kp[:, None] * dc + np.stack([np.zeros_like(ad), ki * h, -ki * h * ad], axis=1) \
            + bd[:, None] * np.array([1.0, -2.0, 1.0])
        a = np.zeros((kp.size, 4))
        a[:, :3] += dc
        a[:, 1:] -= phi * dc
        bpoly = np.zeros((kp.size, 4))
        bpoly[:, :3] += g0 * nc
        bpoly[:, 1:] += g1 * nc
        char = np.zeros((kp.size, d + 4))
        char[:, :4] += a
        char[:, -4:] += bpoly
        n = char.shape[1] - 1
        comp = np.zeros((kp.size, n, n))
        comp[:, 0, :] = -char[:, 1:] / char[:, :1]
        comp[:, np.arange(1, n), np.arange(n - 1)] = 1.0
        return np.asarray(np.max(np.abs(np.linalg.eigvals(comp)), axis=1))

    def _values(self, xt: np.ndarray) -> np.ndarray:
        key = xt.tobytes()
        if key != self._value_key:
            self._value = self._batch(xt[None, :])[0]
            self._value_key = key
        return self._value

    def cons(self, xt: np.ndarray) -> np.ndarray:
        return self._values(np.asarray(xt, dtype=float))

    def cons_jac(self, xt: np.ndarray) -> np.ndarray:
        """Forward differences in the gain coordinates, one batched evaluation; ``t`` enters
        the delay rows only, with slope +1."""
        xt = np.asarray(xt, dtype=float)
        n = self.n_gain
        eps = 1e-6
        X = np.repeat(xt[None, :], n, axis=0)
        X[np.arange(n), np.arange(n)] += eps
        v0 = self._values(xt)
        V = self._batch(X)
        jac = np.zeros((v0.size, xt.size))
        jac[:, :n] = ((V - v0) / eps).T
        jac[: self._n_delay_rows, n] = 1.0
        return jac

    def objective_ms(self, g: PIDGains) -> float:
        """Worst excess over the floor of ``g`` on the grid (what ``t`` converges to)."""
        r = self.grid(g.kp, g.ki, g.kd, g.tf, g.b, g.c)
        return float(np.max(r.max_delay_ms()[:, 0] - self.floor_ms[:, 0, 0]))

    def solve(self, start: PIDGains, maxiter: int = MAX_ITER) -> tuple[PIDGains, int, int]:
        from scipy.optimize import minimize  # the offline stack is imported lazily

        t0 = max(self.objective_ms(start), 0.0) + 1.0
        x0 = self.x_of(start, t0)
        n = x0.size
        grad = np.zeros(n)
        grad[-1] = 1.0
        constraints: list[dict[str, Any]] = [
            {"type": "ineq", "fun": self.cons, "jac": self.cons_jac}]
        if self.weights:  # WEIGHT_MIN <= b, c <= WEIGHT_MAX
            lin = np.zeros((4, n))
            lin[0, [0, 4]] = (1.0, -1.0)
            lin[1, [0, 4]] = (-1.0, 1.0)
            lin[2, [2, 5]] = (1.0, -1.0)
            lin[3, [2, 5]] = (-1.0, 1.0)
            floor = np.array([-math.log(WEIGHT_MAX), math.log(WEIGHT_MIN)] * 2)
            constraints.append({"type": "ineq", "fun": lambda x: lin @ x - floor,
                                "jac": lambda x: lin})
        res = minimize(lambda x: float(x[-1]), x0, jac=lambda x: grad, method="SLSQP",
                       bounds=self.bounds, constraints=constraints,
                       options={"maxiter": maxiter, "ftol": 1e-10})
        return self.gains(res.x), int(res.status), int(res.nit)


def bypass_recommended(residual_ms: float, uncompensated_ms: float, internal: P1D,
                       min_gain_ms: float, worse: bool = False) -> bool:
    """The one bypass rule: compensation is not worth it when the residual delay over the band
    is no better than the uncompensated one, or gains less than ``min_gain_ms``, or the
    platform is delay-dominated (``Tp1 < DELAY_DOMINATED_RATIO * Td``), or ``worse`` (a
    caller's further reason: a gain error, an unstable lag)."""
    return (worse or residual_ms > uncompensated_ms
            or uncompensated_ms - residual_ms < min_gain_ms
            or internal.Tp1 < DELAY_DOMINATED_RATIO * internal.Td)


def _blocks(n: int, size: int) -> int:
    return max(1, n // size)


def _softmin(a: np.ndarray, nblocks: int, tol: float) -> np.ndarray:
    """Soft minimum over ``nblocks`` contiguous blocks of the last axis (a short last block is
    padded with its last value): ``m - ln(sum exp(-beta (a - m)))/beta`` with ``m`` the block's
    minimum and ``beta = ln(size)/tol``, which lies in ``[m - tol, m]``.  Smooth where the hard
    minimum has a corner at every change of the binding frequency; the fixed grid is dense
    enough that a block's minimum is where the bound binds."""
    n = a.shape[-1]
    nb = min(nblocks, n)
    size = -(-n // nb)
    if nb * size > n:
        a = np.concatenate([a, np.repeat(a[..., -1:], nb * size - n, axis=-1)], axis=-1)
    blocks = a.reshape(*a.shape[:-1], nb, size)
    m = blocks.min(axis=-1)
    if size == 1:
        return np.asarray(m)
    beta = math.log(size) / tol
    return np.asarray(m - np.log(np.sum(np.exp(-beta * (blocks - m[..., None])), axis=-1)) / beta)


def _rule_starts(model: P1D) -> list[tuple[str, PIDGains]]:
    """The classical rules' gains (those that apply), as starting points."""
    out: list[tuple[str, PIDGains]] = []
    for rule in RULES:
        try:
            g = tune(rule, model).gains
        except ConfigError:
            continue
        if g.kd <= 0 or g.tf <= 0:  # SIMC is a PI: give it a small derivative to start from
            g = replace(g, kd=0.1 * g.kp * model.Td, tf=0.01 * model.Td + 1e-4)
        out.append((rule, g))
    return out


SCREEN_POINTS = 1024
"""Size of each of the two deterministic (Halton) screening samples of the gain space."""
_PRIMES = (2, 3, 5, 7, 11, 13)


def _halton(n: int, dim: int, shift: float) -> np.ndarray:
    """``(n, dim)`` points of the Halton sequence (bases 2, 3, 5, ...; from index 1), rotated by
    ``shift`` times the golden ratio's fraction in every coordinate: the same numbers on every
    machine (integer digit arithmetic, exact binary fractions)."""
    out = np.zeros((n, dim))
    idx = np.arange(1, n + 1)
    for j, base in enumerate(_PRIMES[:dim]):
        k = idx.copy()
        scale = 1.0
        while np.any(k):
            scale /= base
            out[:, j] += (k % base) * scale
            k //= base
    rotation = shift * 0.6180339887498949 * np.arange(1, dim + 1)
    return np.asarray(np.mod(out + rotation, 1.0))


def _screen(problem: _Problem, n_best: int = 2) -> list[tuple[str, PIDGains]]:
    """The best points of a fixed sample of the gain space, scored on the nominal plant as
    residual delay + 10 ms per unit of constraint violation (unstable points excluded).

    Two boxes, scaled by the model (``s = (0.5 + Tp1/Td)/K``):

    * the classical one: ``kp in [0.03, 30] s``, ``Ti = kp/ki`` in ``[0.1 Td, 10 (Td + Tp1)]``,
      ``Td_pid = kd/kp`` in ``[0.01 Td, 10 Td]``, ``N = Td_pid/tf`` in ``[1, 30]`` and, with
      setpoint weights, ``b, c`` in ``[0, 5]``;
    * with setpoint weights, a two-degree-of-freedom one, where the feedback path may be soft
      and the reference path is sampled for itself: ``kp in [0.003, 30] s``,
      ``ki in [0.1, 100] s/Td``, ``kd in [0.01, 10] s Td``, ``tf in [0.1 h, 2 Td]``, the
      reference gain ``kp b in [0.01, 3] s`` and ``c in [0, 5]``.  A bounded command gain
      above the band (``hf_command_gain``) puts the optimum there.
    """
    model = problem.grid.model
    L = max(model.Td, 5.0 * problem.grid.h)
    T = model.Tp1
    h = problem.grid.h
    scale = (0.5 + T / L) / model.K
    dim = 6 if problem.weights else 4
    u = _halton(SCREEN_POINTS, dim, 1.0)

    def logu(col: np.ndarray, lo: float, hi: float) -> np.ndarray:
        return np.asarray(np.exp(math.log(lo) + col * (math.log(hi) - math.log(lo))))

    kp = logu(u[:, 0], 0.03, 30.0) * scale
    ti = logu(u[:, 1], 0.1 * L, 10.0 * (L + T))
    td = logu(u[:, 2], 0.01 * L, 10.0 * L)
    n = logu(u[:, 3], 1.0, 30.0)
    ki, kd = kp / ti, kp * td
    tf = np.maximum(td / n, 0.1 * h)
    b = 5.0 * u[:, 4] if problem.weights else np.ones(kp.size)
    cw = 5.0 * u[:, 5] if problem.weights else np.ones(kp.size)
    if problem.weights:
        w = _halton(SCREEN_POINTS, dim, 2.0)
        kp2 = logu(w[:, 0], 0.003, 30.0) * scale
        kp = np.concatenate([kp, kp2])
        ki = np.concatenate([ki, logu(w[:, 1], 0.1, 100.0) * scale / L])
        kd = np.concatenate([kd, logu(w[:, 2], 0.01, 10.0) * scale * L])
        tf = np.concatenate([tf, logu(w[:, 3], 0.1 * h, 2.0 * L)])
        b = np.concatenate([b, np.minimum(logu(w[:, 4], 0.01, 3.0) * scale / kp2, WEIGHT_MAX)])
        cw = np.concatenate([cw, 5.0 * w[:, 5]])
    logs = np.log(np.stack([kp, ki, kd, tf], axis=1))
    cols = [logs]
    if problem.weights:
        weights = np.clip(np.stack([b, cw], axis=1), WEIGHT_MIN, WEIGHT_MAX)
        cols.append(logs[:, [0, 2]] + np.log(weights))
    Y = np.clip(np.concatenate([*cols, np.zeros((kp.size, 1))], axis=1), problem._lo,
                problem._hi)
    scores = np.empty(kp.size)
    for i in range(0, kp.size, 128):
        V = problem._batch(Y[i:i + 128])
        t_need = -np.min(V[:, : problem._n_delay_rows], axis=1)  # delay rows are t - |tau|
        rest = V[:, problem._n_delay_rows:]
        violation = np.sum(np.clip(-rest, 0.0, None), axis=1)
        scores[i:i + 128] = t_need + 10.0 * violation
        unstable = rest[:, -1] < 0
        scores[i:i + 128][unstable] = np.inf
    order = np.argsort(scores, kind="stable")
    out: list[tuple[str, PIDGains]] = []
    for j in order[:n_best]:
        if np.isfinite(scores[j]):
            out.append((f"screen{len(out) + 1}", problem.gains(Y[j])))
    return out


def _check(gains: PIDGains, model: P1D, dense: LoopGrid, c: Constraints, rate_hz: float,
           gain_limit_db: float, peak_db: float
           ) -> tuple[Evaluation, float, list[str], dict[str, float]]:
    """Check a candidate on dense grids: the nominal plant with
    :func:`~motcomp.design.frequency.evaluate` (poles included), the other members with a dense
    :class:`LoopGrid`.  Returns the nominal evaluation, the worst excess over the floor, the
    violated bounds and by how much each bound is exceeded."""
    nominal = evaluate(gains, model, dense.plants[0], rate_hz=rate_hz, band_hz=c.band_hz,
                       hf_from_hz=c.hf_from_hz)
    r = dense(gains.kp, gains.ki, gains.kd, gains.tf, gains.b, gains.c)
    floors = np.max(np.abs(dense.floor_delay_s()), axis=1) * 1e3
    worst = float(np.max(r.max_delay_ms()[:, 0] - floors)) if len(dense.plants) > 1 else \
        nominal.max_residual_delay_ms
    over = {
        "peak_db": max(float(np.max(r.gain_db)), nominal.peak_gain_db) - peak_db,
        "gain_error_db": nominal.gain_error_db - gain_limit_db,
        "command_excess_db": float(np.max(r.excess_db)) - c.command_excess_db,
        "max_command_gain": nominal.peak_command_gain / c.max_command_gain - 1.0,
        "hf_command_gain": nominal.hf_command_gain / c.hf_gain - 1.0,
        "max_sensitivity": nominal.ms / c.max_sensitivity - 1.0,
    }
    violations = []
    if not nominal.stable:
        violations.append(f"internal loop unstable (pole modulus {nominal.max_pole_modulus:.5f})")
    for name, amount in over.items():
        tol = 0.02 if name.endswith("_db") else 2e-3  # dB, or relative
        if amount > tol:
            unit = " dB" if name.endswith("_db") else " (relative)"
            violations.append(f"{name} exceeded by {amount:.3g}{unit}")
    return nominal, worst, violations, over


@with_one_blas_thread
def optimise(plant: ProcessModel, model: P1D | None = None, rate_hz: float = 1000.0,
             constraints: Constraints | None = None, uncertainty: Uncertainty | None = None,
             setpoint_weights: bool = True, min_gain_ms: float = 5.0,
             progress: Callable[[int, int, str], None] | None = None) -> OptimalDesign:
    """Optimised gains for ``plant`` (see the module docstring for the problem solved).

    Parameters
    ----------
    plant
        The platform; the delivered response is computed with it.
    model
        The compensator's internal P1D model (default: ``plant.to_p1d()``).
    rate_hz
        Loop rate; the discrete loop is what is optimised and checked.
    constraints
        Bounds (default :class:`Constraints`).
    uncertainty
        If given, the robust design over ``uncertainty.members(plant)``.
    setpoint_weights
        Optimise the setpoint weights b, c too (True) or keep a plain PID (b = c = 1).
    min_gain_ms
        Recommend bypass if the design gains less than this over the uncompensated platform.
    progress
        Called as ``progress(done, total, note)`` after the screening, each start and the
        refinement.

    Raises
    ------
    ConfigError
        For a model with a non-positive gain or a bad rate, band or bound.
    """
    t_start = time.perf_counter()
    c = constraints or Constraints()
    internal = model or plant.to_p1d()
    if not internal.K > 0:
        raise ConfigError(f"optimal tuning needs a positive model gain K, got {internal.K}")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ConfigError(f"rate must be a positive finite number of Hz, got {rate_hz}")
    labelled = uncertainty.members(plant) if uncertainty is not None else [("nominal", plant)]
    plants = [p for _, p in labelled]
    grid = LoopGrid(internal, plants, rate_hz, c.band_hz)
    floor_ms = np.max(np.abs(grid.floor_delay_s()), axis=1) * 1e3
    floor_gain = float(np.max(np.abs(grid.floor_gain_db()[0])))
    if uncertainty is None:
        floor_ms = np.zeros(1)  # nominal: the objective is the delivered delay itself
    uncomp_gain = float(np.max(np.abs(grid.plant_gain_db()[0, grid.band])))
    # the bound beyond what the model mismatch causes, and never worse than no compensation
    gain_limit = min(c.gain_error_db + floor_gain, max(c.gain_error_db, uncomp_gain))
    uncomp_ms = float(np.max(np.abs(grid.plant_delay_s()[0]))) * 1e3

    dense = LoopGrid(internal, plants, rate_hz, c.band_hz, n_band=400, n_high=4000)
    screen_problem = _Problem(LoopGrid(internal, plants[:1], rate_hz, c.band_hz),
                              c, setpoint_weights, c.peak_db, np.zeros(1), gain_limit,
                              COARSE_SOFTNESS)
    rules = _rule_starts(internal)
    total = 2 + len(rules) + 2  # screening, the starts, the final check
    if progress is not None:
        progress(0, total, "screening the gain space")
    screened = _screen(screen_problem)
    starts = screened[:1] + rules + screened[1:]
    total = 2 + len(starts)
    if progress is not None:
        progress(1, total, f"screened; {len(starts)} starts")
    # every start (none is skipped on what an earlier one found, so that the result does not
    # hang on the order in which near-equal starts finish) solved on the coarse problem, whose
    # smoother floor has fewer local optima, then refined on the sharp one
    coarse = _Problem(grid, c, setpoint_weights, c.peak_db, floor_ms, gain_limit,
                      COARSE_SOFTNESS)
    records: list[dict[str, Any]] = []
    best: tuple[int, float, PIDGains, Evaluation, list[str]] | None = None
    for i, (name, g0) in enumerate(starts):
        g, _, _ = coarse.solve(g0)
        target = c
        for _ in range(3):
            problem = _Problem(grid, target, setpoint_weights, target.peak_db, floor_ms,
                               gain_limit)
            g, status, nit = problem.solve(g)
            nominal, objective, violations, over = _check(g, internal, dense, c, rate_hz,
                                                          gain_limit, c.peak_db)
            # a small excess is the fixed grid missing a sharp peak: that bound is tightened
            # and the start solved again; a large one is a start that did not converge, which
            # tightening would not help
            missed_peak = 0.02 < over["peak_db"] < 0.5
            missed_cmd = 2e-3 < over["max_command_gain"] < 0.05
            missed_hf = 2e-3 < over["hf_command_gain"] < 0.05
            if not nominal.stable or not (missed_peak or missed_cmd or missed_hf):
                break
            target = replace(
                target,
                peak_db=max(target.peak_db - missed_peak * (over["peak_db"] + 0.01), 0.0),
                max_command_gain=target.max_command_gain
                / (1.0 + missed_cmd * (over["max_command_gain"] + 1e-3)),
                hf_command_gain=target.hf_gain
                / (1.0 + missed_hf * (over["hf_command_gain"] + 1e-3)))
        records.append({"start": name, "status": status, "iterations": nit,
                        "objective_ms": objective, "feasible": not violations})
        # fewest violations, then the least objective, the earlier among equivalent ones
        if best is None or len(violations) < best[0] or (
                len(violations) == best[0] and objective < best[1] - START_TIE_MS):
            best = (len(violations), objective, g, nominal, violations)
        if progress is not None:
            progress(1 + i + 1, total, f"start {i + 1} of {len(starts)} ({name}): "
                     f"{objective:.2f} ms{', bounds not met' if violations else ''}; best "
                     f"{best[1]:.2f} ms")
    assert best is not None
    _, objective, g, nominal, violations = best
    if progress is not None:
        progress(total, total, f"best: {objective:.2f} ms")
    gains = g
    gain_ms = uncomp_ms - nominal.max_residual_delay_ms
    worse = (nominal.max_residual_delay_ms > uncomp_ms
             or nominal.gain_error_db > max(gain_limit, nominal.uncorrected_gain_error_db))
    delay_dominated = internal.Tp1 < DELAY_DOMINATED_RATIO * internal.Td
    bypass = bypass_recommended(nominal.max_residual_delay_ms, uncomp_ms, internal, min_gain_ms,
                                worse)
    warnings: list[str] = []
    if violations:
        warnings.append("WARNING: no design meets every bound; best compromise violates: "
                        + "; ".join(violations))
    if worse:
        warnings.append(
            f"WARNING: no design within the bounds improves on the uncompensated platform "
            f"({nominal.max_residual_delay_ms:.1f} ms vs {uncomp_ms:.1f} ms residual delay). "
            "Recommendation: bypass this axis.")
    elif delay_dominated:
        warnings.append(
            f"WARNING: delay-dominated plant (internal model Tp1/Td = "
            f"{internal.Tp1 / internal.Td:.3g}): its lag Tp1 = {internal.Tp1 * 1e3:.1f} ms is "
            f"small beside its pure delay Td = {internal.Td * 1e3:.1f} ms. Within the bounds the "
            f"residual delay falls at best from {uncomp_ms:.1f} to "
            f"{nominal.max_residual_delay_ms:.1f} ms, but that gain is prediction: it holds only "
            "as well as Td and the platform model are known (an error in Td shifts the residual "
            f"one for one) and is paid for by a {nominal.peak_gain_db:+.1f} dB peak at "
            f"{nominal.peak_gain_hz:.1f} Hz. Recommendation: bypass this axis.")
    elif gain_ms < min_gain_ms:
        warnings.append(
            f"WARNING: compensation gains little on this plant: at best "
            f"{nominal.max_residual_delay_ms:.1f} ms residual delay vs {uncomp_ms:.1f} ms "
            f"uncompensated (gain {gain_ms:.1f} ms, below {min_gain_ms:g} ms) within the bounds."
            " Recommendation: bypass this axis.")
    members: list[MemberResult] = []
    if uncertainty is not None:
        members = member_table(gains, internal, labelled, rate_hz, c.band_hz)
    return OptimalDesign(
        gains=gains, model=internal, constraints=c, rate_hz=rate_hz, evaluation=nominal,
        command_excess_db=command_excess_db(gains, internal, rate_hz, c.band_hz),
        feasible=not violations, violations=violations, uncompensated_delay_ms=uncomp_ms,
        best_gain_ms=gain_ms, delay_dominated=delay_dominated, recommend_bypass=bypass,
        setpoint_weights=setpoint_weights, members=members, uncertainty=uncertainty,
        starts=records, elapsed_s=time.perf_counter() - t_start, warnings=warnings,
    )


def member_table(gains: PIDGains, model: P1D, labelled: Sequence[tuple[str, ProcessModel]],
                 rate_hz: float, band_hz: tuple[float, float],
                 evaluations: Sequence[Evaluation] | None = None,
                 compare: PIDGains | None = None) -> list[MemberResult]:
    """Residual delay, floor and peak of ``gains`` for every member (and of ``compare``, by
    default the ZN gains when they exist)."""
    plants = [p for _, p in labelled]
    grid = LoopGrid(model, plants, rate_hz, band_hz, n_band=400, n_high=50)
    floors = np.max(np.abs(grid.floor_delay_s()), axis=1) * 1e3
    evs = list(evaluations) if evaluations is not None else [
        evaluate(gains, model, p, rate_hz=rate_hz, band_hz=band_hz) for p in plants]
    if compare is None:
        try:
            compare = tune("zn", model).gains
        except ConfigError:
            compare = None
    out = []
    for (label, p), ev, fl in zip(labelled, evs, floors, strict=True):
        row = MemberResult(label=label, model=p.spec(), floor_ms=float(fl),
                           residual_ms=ev.max_residual_delay_ms,
                           excess_ms=ev.max_residual_delay_ms - float(fl),
                           peak_gain_db=ev.peak_gain_db, gain_error_db=ev.gain_error_db)
        if compare is not None:
            zev = evaluate(compare, model, p, rate_hz=rate_hz, band_hz=band_hz)
            row.zn_residual_ms = zev.max_residual_delay_ms
            row.zn_peak_gain_db = zev.peak_gain_db
        out.append(row)
    return out
