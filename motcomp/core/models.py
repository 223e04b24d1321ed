"""Process models of a motion platform axis: P1D, P2D, P2UZD and OE.

All models map the commanded position ``u`` to the delivered position ``y`` of one axis:

=========  ==================================================================================
kind       transfer function (parameters in SI: gains dimensionless, times in seconds)
=========  ==================================================================================
``p1d``    ``K e^{-Td s} / (1 + Tp1 s)``
``p2d``    ``K e^{-Td s} / ((1 + Tp1 s)(1 + Tp2 s))``
``p2uzd``  ``K e^{-Td s} (1 + Tz s) / ((1 + Tp1 s)(1 + Tp2 s))``, or underdamped
           ``K e^{-Td s} (1 + Tz s) / (1 + 2 Zeta Tw s + Tw^2 s^2)`` (MATLAB's P2DZU/P2DUZ)
``oe``     ``B(s)/A(s) * pade_n(Td)``: a rational model whose delay is an n-th order Pade
           approximant (``n = 0`` keeps the exact delay), as in the paper's OE fits
=========  ==================================================================================

Every model offers the frequency response, step response, phase delay
``tau_phi(f) = -phi(f) / (2 pi f)``, group delay ``tau_g = -d phi / d omega``, gain, the
bandwidths at -3 dB and -6 dB, and the exact zero-order-hold discretisation with a sub-sample
delay (:func:`motcomp.core.lti.discretize_zoh`).

A compact text form is used on the command line and in config files::

    p1d:K=1,Td=0.0175,Tp1=0.1858
    p2d:K=1,Td=0.03,Tp1=0.02,Tp2=0.005
    p2uzd:K=1,Td=0.0325,Tw=0.03,Zeta=0.7,Tz=0.02
    oe:num=[1],den=[0.01,1],Td=0.03,pade=1

Examples
--------
>>> m = parse_model("p1d:K=1,Td=0.0175,Tp1=0.1858")
>>> round(float(m.phase_delay(0.2)[0]) * 1e3, 1)
200.0
"""

from __future__ import annotations

import math
import re
from abc import ABC, abstractmethod
from dataclasses import MISSING, dataclass, fields
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike

from motcomp.core.lti import (
    ComplexArray,
    DiscreteLTI,
    FloatArray,
    discretize_zoh,
    rational_phase_continuous,
)
from motcomp.errors import ConfigError

__all__ = [
    "OE",
    "P1D",
    "P2D",
    "P2UZD",
    "ProcessModel",
    "format_model",
    "p1d_coefficients",
    "pade",
    "parse_model",
    "phase_delay_from_response",
]


def pade(dead_time_s: float, order: int) -> tuple[FloatArray, FloatArray]:
    """Pade approximant of ``exp(-T s)``, ``(num, den)`` highest power first.

    Coefficients: ``c_k = (2n-k)! n! / ((2n)! k! (n-k)!)``, numerator with alternating signs.
    ``order = 1`` gives the paper's ``(1 - T s/2)/(1 + T s/2)``.
    """
    if order < 0:
        raise ConfigError(f"Pade order must be >= 0, got {order}")
    if order == 0 or dead_time_s == 0:
        return np.array([1.0]), np.array([1.0])
    n = order
    c = [
        math.factorial(2 * n - k) * math.factorial(n)
        / (math.factorial(2 * n) * math.factorial(k) * math.factorial(n - k))
        * dead_time_s**k
        for k in range(n + 1)
    ]
    den = np.array(c[::-1])
    num = np.array([ck * (-1) ** k for k, ck in enumerate(c)][::-1])
    return num, den


def _finite_positive(name: str, value: float, kind: str, allow_zero: bool = False) -> None:
    ok = math.isfinite(value) and (value >= 0 if allow_zero else value > 0)
    if not ok:
        rule = ">= 0" if allow_zero else "> 0"
        raise ConfigError(f"{kind} parameter {name} must be finite and {rule}, got {value!r}")


class ProcessModel(ABC):
    """A continuous-time SISO process model ``H(s) e^{-Td s}`` with H rational.

    Subclasses define :meth:`rational` and the parameters; everything else derives from them.
    """

    kind: ClassVar[str]

    # --- definition -------------------------------------------------------------------------
    @abstractmethod
    def rational(self) -> tuple[FloatArray, FloatArray]:
        """``(num, den)`` of the delay-free part, highest power first."""

    @property
    @abstractmethod
    def dead_time_s(self) -> float:
        """Delay realised exactly as ``e^{-Td s}`` (0 for OE with a Pade delay)."""

    @property
    @abstractmethod
    def pure_delay_s(self) -> float:
        """The pure delay the model stands for (for OE, the one inside the Pade factor)."""

    @abstractmethod
    def params(self) -> dict[str, Any]:
        """Parameters by their conventional names (``K``, ``Td``, ``Tp1``, ...), SI units."""

    # --- derived ----------------------------------------------------------------------------
    @property
    def gain(self) -> float:
        """Static gain H(0)."""
        num, den = self.rational()
        if den[-1] == 0:
            return math.inf
        return float(num[-1] / den[-1])

    def freqresp(self, f_hz: ArrayLike) -> ComplexArray:
        """Complex frequency response at ``f_hz`` (Hz)."""
        num, den = self.rational()
        w = 2.0 * np.pi * np.atleast_1d(np.asarray(f_hz, dtype=float))
        s = 1j * w
        return np.asarray(np.polyval(num, s) / np.polyval(den, s) * np.exp(-s * self.dead_time_s))

    def magnitude(self, f_hz: ArrayLike) -> FloatArray:
        """``|H(j 2 pi f)|``."""
        return np.abs(self.freqresp(f_hz))

    def phase(self, f_hz: ArrayLike) -> FloatArray:
        """Unwrapped phase (rad) at ``f_hz`` > 0, continuous from 0 at DC for a positive gain."""
        num, den = self.rational()
        w = 2.0 * np.pi * np.atleast_1d(np.asarray(f_hz, dtype=float))
        return np.asarray(rational_phase_continuous(num, den, w) - w * self.dead_time_s)

    def phase_delay(self, f_hz: ArrayLike) -> FloatArray:
        """Phase delay ``tau_phi = -phi / omega`` (s)."""
        w = 2.0 * np.pi * np.atleast_1d(np.asarray(f_hz, dtype=float))
        return np.asarray(-self.phase(f_hz) / w)

    def group_delay(self, f_hz: ArrayLike) -> FloatArray:
        """Group delay ``tau_g = -d phi / d omega`` (s), exact from the polynomials.

        ``tau_g = Td - Re(N'(jw)/N(jw) - D'(jw)/D(jw))``.
        """
        num, den = self.rational()
        w = 2.0 * np.pi * np.atleast_1d(np.asarray(f_hz, dtype=float))
        s = 1j * w
        dn = np.polyder(num) if num.size > 1 else np.zeros(1)
        dd = np.polyder(den) if den.size > 1 else np.zeros(1)
        x = np.polyval(dn, s) / np.polyval(num, s) - np.polyval(dd, s) / np.polyval(den, s)
        return np.asarray(self.dead_time_s - x.real)

    def bandwidth(self, level_db: float = -3.0) -> float:
        """First frequency (Hz) where ``|H(f)| / |H(0)|`` falls to ``level_db`` and stays below.

        ``-3`` and ``-6`` mean the conventional half-power (``1/sqrt(2)``, -3.01 dB) and
        half-amplitude (``1/2``, -6.02 dB) points, so that a P1D's bandwidths are exactly
        ``1/(2 pi Tp1)`` and ``sqrt(3)/(2 pi Tp1)``; any other level is taken literally in dB.
        Scans a log grid from 1 mHz to 10 kHz, then bisects.  Returns ``inf`` if the gain never
        falls that low in that range.
        """
        if level_db >= 0:
            raise ConfigError(f"bandwidth level must be negative dB, got {level_db}")
        target = {-3.0: 1.0 / math.sqrt(2.0), -6.0: 0.5}.get(float(level_db),
                                                             10.0 ** (level_db / 20.0))
        ref = abs(self.gain)
        f = np.geomspace(1e-3, 1e4, 4001)
        rel = self.magnitude(f) / ref
        above = rel >= target
        if above.all():
            return math.inf
        # last index where the response is still at or above the level, then bisect after it
        idx = np.nonzero(above)[0]
        if idx.size == 0:
            return float(f[0])
        i = int(idx[-1])
        lo, hi = float(f[i]), float(f[i + 1])
        for _ in range(80):
            mid = math.sqrt(lo * hi)
            if float(self.magnitude(mid)[0]) / ref >= target:
                lo = mid
            else:
                hi = mid
        return math.sqrt(lo * hi)

    def step(self, t_s: ArrayLike) -> FloatArray:
        """Unit step response at times ``t_s`` (exact, by matrix exponentials)."""
        from motcomp.core.lti import expm, tf2ss

        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        a, b, c, d = tf2ss(*self.rational())
        n = a.shape[0]
        out = np.zeros(t.shape)
        tt = t - self.dead_time_s
        for i, ti in enumerate(tt):
            if ti < 0:
                continue
            if n == 0:
                out[i] = d
                continue
            aug = np.zeros((n + 1, n + 1))
            aug[:n, :n] = a * ti
            aug[:n, n:] = b * ti
            x = expm(aug)[:n, n]
            out[i] = float(c[0] @ x) + d
        return out

    def discretize(self, rate_hz: float) -> DiscreteLTI:
        """Exact ZOH discretisation at ``rate_hz`` with the sub-sample delay kept."""
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ConfigError(f"rate must be a positive finite number of Hz, got {rate_hz}")
        num, den = self.rational()
        return discretize_zoh(num, den, self.dead_time_s, 1.0 / rate_hz)

    def to_p1d(self, match_hz: float = 0.2) -> P1D:
        """P1D approximation: same gain and pure delay, same phase delay at ``match_hz``.

        This is how a second-order model becomes the compensator's internal P1D model: the
        compensator cancels the phase delay the driver feels, so that is what must match.
        """
        if isinstance(self, P1D):
            return self
        K = self.gain
        Td = self.pure_delay_s
        w = 2.0 * math.pi * match_hz
        lag = float(self.phase_delay(match_hz)[0]) - Td
        if lag <= 0:
            raise ConfigError(
                f"{self.kind} model has no lag beyond its pure delay at {match_hz} Hz "
                f"(phase delay {lag * 1e3:.2f} ms after Td); no P1D approximation"
            )
        # Td + atan(w Tp1)/w = tau  ->  Tp1 = tan(w (tau - Td)) / w
        if w * lag >= math.pi / 2:
            raise ConfigError(f"phase lag at {match_hz} Hz exceeds 90 deg; P1D cannot match it")
        return P1D(K=K, Td=Td, Tp1=math.tan(w * lag) / w)

    def spec(self) -> str:
        """The compact text form, e.g. ``p1d:K=1,Td=0.0175,Tp1=0.1858``."""
        return format_model(self)

    def __str__(self) -> str:
        return self.spec()


@dataclass(frozen=True)
class _GainDelay(ProcessModel):
    """The common part of the process models: a non-zero gain ``K`` and an exact pure delay
    ``Td`` >= 0 (s)."""

    K: float
    Td: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.K) and self.K != 0):
            raise ConfigError(f"{self.kind} parameter K must be finite and non-zero, "
                              f"got {self.K!r}")
        _finite_positive("Td", self.Td, self.kind, allow_zero=True)

    @property
    def dead_time_s(self) -> float:
        return self.Td

    @property
    def pure_delay_s(self) -> float:
        return self.Td


@dataclass(frozen=True)
class P1D(_GainDelay):
    """First order plus dead time: ``K e^{-Td s} / (1 + Tp1 s)``.

    Closed forms (paper, eq. 1): phase delay ``Td + atan(w Tp1)/w``, gain
    ``K (1 + w^2 Tp1^2)^{-1/2}``, -3 dB at ``1/(2 pi Tp1)``, -6 dB at ``sqrt(3)/(2 pi Tp1)``.
    """

    Tp1: float
    kind: ClassVar[str] = "p1d"

    def __post_init__(self) -> None:
        super().__post_init__()
        _finite_positive("Tp1", self.Tp1, "p1d")

    def rational(self) -> tuple[FloatArray, FloatArray]:
        return np.array([self.K]), np.array([self.Tp1, 1.0])

    def params(self) -> dict[str, Any]:
        return {"K": self.K, "Td": self.Td, "Tp1": self.Tp1}


@dataclass(frozen=True)
class P2D(_GainDelay):
    """Second order (two real poles) plus dead time: ``K e^{-Td s} / ((1+Tp1 s)(1+Tp2 s))``."""

    Tp1: float
    Tp2: float
    kind: ClassVar[str] = "p2d"

    def __post_init__(self) -> None:
        super().__post_init__()
        _finite_positive("Tp1", self.Tp1, "p2d")
        _finite_positive("Tp2", self.Tp2, "p2d")

    def rational(self) -> tuple[FloatArray, FloatArray]:
        return np.array([self.K]), np.polymul([self.Tp1, 1.0], [self.Tp2, 1.0])

    def params(self) -> dict[str, Any]:
        return {"K": self.K, "Td": self.Td, "Tp1": self.Tp1, "Tp2": self.Tp2}


@dataclass(frozen=True)
class P2UZD(_GainDelay):
    """Two poles, a zero and dead time.

    Real poles: ``K e^{-Td s}(1 + Tz s)/((1 + Tp1 s)(1 + Tp2 s))`` (set ``Tp1``, ``Tp2``).
    Underdamped: ``K e^{-Td s}(1 + Tz s)/(1 + 2 Zeta Tw s + Tw^2 s^2)`` (set ``Tw``, ``Zeta``).
    ``Tz`` may be negative (a right-half-plane zero) or zero.
    """

    Tz: float
    Tp1: float | None = None
    Tp2: float | None = None
    Tw: float | None = None
    Zeta: float | None = None
    kind: ClassVar[str] = "p2uzd"

    def __post_init__(self) -> None:
        super().__post_init__()
        if not math.isfinite(self.Tz):
            raise ConfigError(f"p2uzd parameter Tz must be finite, got {self.Tz!r}")
        real = self.Tp1 is not None or self.Tp2 is not None
        under = self.Tw is not None or self.Zeta is not None
        if real == under:
            raise ConfigError(
                "p2uzd needs either Tp1 and Tp2 (real poles) or Tw and Zeta (underdamped), "
                "not both and not neither"
            )
        if real:
            if self.Tp1 is None or self.Tp2 is None:
                raise ConfigError("p2uzd with real poles needs both Tp1 and Tp2")
            _finite_positive("Tp1", self.Tp1, "p2uzd")
            _finite_positive("Tp2", self.Tp2, "p2uzd")
        else:
            if self.Tw is None or self.Zeta is None:
                raise ConfigError("underdamped p2uzd needs both Tw and Zeta")
            _finite_positive("Tw", self.Tw, "p2uzd")
            _finite_positive("Zeta", self.Zeta, "p2uzd")

    @property
    def underdamped(self) -> bool:
        return self.Tw is not None

    def rational(self) -> tuple[FloatArray, FloatArray]:
        num = np.array([self.K * self.Tz, self.K]) if self.Tz != 0 else np.array([self.K])
        if self.Tw is not None and self.Zeta is not None:
            den = np.array([self.Tw**2, 2.0 * self.Zeta * self.Tw, 1.0])
        else:
            assert self.Tp1 is not None and self.Tp2 is not None
            den = np.polymul([self.Tp1, 1.0], [self.Tp2, 1.0])
        return num, den

    def params(self) -> dict[str, Any]:
        out: dict[str, Any] = {"K": self.K, "Td": self.Td}
        if self.underdamped:
            out.update(Tw=self.Tw, Zeta=self.Zeta)
        else:
            out.update(Tp1=self.Tp1, Tp2=self.Tp2)
        out["Tz"] = self.Tz
        return out


@dataclass(frozen=True)
class OE(ProcessModel):
    """Rational model ``B(s)/A(s)`` with the delay as an n-th order Pade factor.

    ``num``/``den`` are the coefficients of B and A, highest power first.  With ``pade = 0`` the
    delay is kept exact instead.  The paper fits this form with ``pade = 1``.
    """

    num: tuple[float, ...]
    den: tuple[float, ...]
    Td: float = 0.0
    pade_order: int = 1
    kind: ClassVar[str] = "oe"

    def __post_init__(self) -> None:
        num = tuple(float(v) for v in self.num)
        den = tuple(float(v) for v in self.den)
        object.__setattr__(self, "num", num)
        object.__setattr__(self, "den", den)
        if not num or not den or not all(map(math.isfinite, num + den)):
            raise ConfigError(f"oe num/den must be non-empty lists of finite numbers: {num}, {den}")
        if all(v == 0 for v in den):
            raise ConfigError("oe denominator is zero")
        if len(np.trim_zeros(np.array(num), "f")) > len(np.trim_zeros(np.array(den), "f")):
            raise ConfigError(f"oe model is improper: num {num} has a higher degree than den {den}")
        _finite_positive("Td", self.Td, "oe", allow_zero=True)
        if self.pade_order < 0 or self.pade_order > 10:
            raise ConfigError(f"oe Pade order must be 0..10, got {self.pade_order}")

    def rational(self) -> tuple[FloatArray, FloatArray]:
        num = np.array(self.num, dtype=float)
        den = np.array(self.den, dtype=float)
        if self.pade_order > 0 and self.Td > 0:
            pn, pd = pade(self.Td, self.pade_order)
            return np.polymul(num, pn), np.polymul(den, pd)
        return num, den

    @property
    def dead_time_s(self) -> float:
        return self.Td if self.pade_order == 0 else 0.0

    @property
    def pure_delay_s(self) -> float:
        return self.Td

    def params(self) -> dict[str, Any]:
        return {"num": list(self.num), "den": list(self.den), "Td": self.Td,
                "pade": self.pade_order}


def phase_delay_from_response(f_hz: ArrayLike, phase_rad: ArrayLike) -> FloatArray:
    """``-phase / (2 pi f)``: phase delay (s) from an unwrapped phase (rad)."""
    f = np.asarray(f_hz, dtype=float)
    return np.asarray(-np.asarray(phase_rad, dtype=float) / (2.0 * np.pi * f))


# --- compact text form --------------------------------------------------------------------------

_KINDS: dict[str, type[ProcessModel]] = {"p1d": P1D, "p2d": P2D, "p2uzd": P2UZD, "oe": OE}
_SPEC_RE = re.compile(r"^\s*([A-Za-z0-9_]+)\s*:\s*(.*)$")
_ALIASES = {"p2dzu": "p2uzd", "p2duz": "p2uzd", "p2zud": "p2uzd"}


def _split_top(body: str) -> list[str]:
    """Split on commas outside brackets."""
    parts: list[str] = []
    depth = 0
    cur = ""
    for ch in body:
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth -= 1
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    if cur.strip():
        parts.append(cur)
    return parts


def _num(text: str, key: str, spec: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ConfigError(f"model spec {spec!r}: {key}={text!r} is not a number") from None
    if not math.isfinite(value):
        raise ConfigError(f"model spec {spec!r}: {key}={text!r} is not finite")
    return value


def parse_model(spec: str) -> ProcessModel:
    """Parse the compact text form, e.g. ``"p1d:K=1,Td=0.0175,Tp1=0.1858"``.

    Raises
    ------
    ConfigError
        Naming the spec, the key and the value when anything is wrong.
    """
    m = _SPEC_RE.match(spec)
    if not m:
        raise ConfigError(
            f"model spec {spec!r} is not of the form KIND:KEY=VALUE,... "
            f"(KIND one of {', '.join(_KINDS)})"
        )
    kind = _ALIASES.get(m.group(1).lower(), m.group(1).lower())
    if kind not in _KINDS:
        raise ConfigError(f"model spec {spec!r}: unknown kind {m.group(1)!r}; "
                          f"known kinds: {', '.join(_KINDS)}")
    values: dict[str, Any] = {}
    for part in _split_top(m.group(2)):
        if "=" not in part:
            raise ConfigError(f"model spec {spec!r}: {part.strip()!r} is not KEY=VALUE")
        key, _, text = part.partition("=")
        key = key.strip()
        text = text.strip()
        if key in values:
            raise ConfigError(f"model spec {spec!r}: {key} given twice")
        if kind == "oe" and key in ("num", "den"):
            if not (text.startswith("[") and text.endswith("]")):
                raise ConfigError(f"model spec {spec!r}: {key} must be a list like [1,2]")
            items = [s for s in text[1:-1].split(",") if s.strip()]
            values[key] = tuple(_num(s, key, spec) for s in items)
        elif kind == "oe" and key == "pade":
            try:
                values["pade_order"] = int(text)
            except ValueError:
                raise ConfigError(f"model spec {spec!r}: pade={text!r} is not an integer") from None
        else:
            values[key] = _num(text, key, spec)
    cls = _KINDS[kind]
    allowed = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    unknown = set(values) - allowed
    if unknown:
        shown = sorted(allowed - {"pade_order"} | ({"pade"} if kind == "oe" else set()))
        raise ConfigError(f"model spec {spec!r}: unknown parameter(s) {', '.join(sorted(unknown))}"
                          f" for {kind}; expected {', '.join(shown)}")
    required = {f.name for f in fields(cls)  # type: ignore[arg-type]
                if f.default is MISSING and f.default_factory is MISSING}
    missing = required - set(values)
    if missing:
        raise ConfigError(f"model spec {spec!r}: missing parameter(s) {', '.join(sorted(missing))}")
    try:
        return cls(**values)
    except TypeError as exc:
        raise ConfigError(f"model spec {spec!r}: {exc}") from None


def _fmt(v: float) -> str:
    return f"{v:.10g}"


def format_model(model: ProcessModel) -> str:
    """Inverse of :func:`parse_model`: ``parse_model(format_model(m)) == m`` to 10 digits."""
    parts = []
    for key, value in model.params().items():
        if isinstance(value, list):
            parts.append(f"{key}=[{','.join(_fmt(v) for v in value)}]")
        elif key == "pade":
            parts.append(f"pade={int(value)}")
        else:
            parts.append(f"{key}={_fmt(value)}")
    return f"{model.kind}:{','.join(parts)}"


def p1d_coefficients(model: P1D, dt_s: float) -> tuple[float, float, float, int]:
    """``(phi, g0, g1, d)`` of the exact ZOH discretisation of a P1D with sub-sample delay.

    With ``Td = (d-1) h + tau'``, ``0 < tau' <= h`` (``d = 0``, ``tau' = h`` for ``Td = 0``)::

        phi = exp(-h/Tp1)
        g0  = K (1 - exp(-(h - tau')/Tp1))
        g1  = K exp(-(h - tau')/Tp1) (1 - exp(-tau'/Tp1))
        x[k+1] = phi x[k] + g0 u[k-d+1] + g1 u[k-d]
    """
    h = dt_s
    ratio = model.Td / h
    d = math.ceil(ratio - 1e-12)
    if d <= 0:
        d, tau_p = 0, h
    else:
        tau_p = min(max(model.Td - (d - 1) * h, 0.0), h)
        if tau_p <= 1e-15 * h:
            tau_p = h
    phi = math.exp(-h / model.Tp1)
    e_rest = math.exp(-(h - tau_p) / model.Tp1)
    g0 = model.K * (1.0 - e_rest)
    g1 = model.K * e_rest * (1.0 - math.exp(-tau_p / model.Tp1))
    return phi, g0, g1, d


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
