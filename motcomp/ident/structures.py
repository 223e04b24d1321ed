"""The model structures that identification fits, split for separable least squares.

Each structure writes its transfer function as a *linear* combination of a few regressor
systems whose shape depends on a small vector ``theta`` of nonlinear parameters and on the delay
``Td``::

    G(s) = sum_j c_j N_j(s; theta, Td) / D(s; theta, Td)

For fixed ``(theta, Td)`` the coefficients ``c`` (and the accelerometer bias) come from linear
least squares, so a search only ever moves ``theta`` (one or two numbers) and the delay:

=========  ==================================  ========================  =====================
kind       theta (internal, unconstrained)     regressors                linear coefficients
=========  ==================================  ========================  =====================
``p1d``    ``ln Tp1``                          ``1/(1+Tp1 s)``           ``K``
``p2d``    ``ln Tp1, ln Tp2``                  ``1/((1+Tp1 s)(1+Tp2 s))`` ``K``
``p2uzd``  ``ln Tw, ln Zeta``                  ``1/D, s/D``,             ``K, K Tz``
                                               ``D = 1 + 2 Zeta Tw s + Tw^2 s^2``
``oe``     ``ln Tw_i, ln Zeta_i`` per          ``s^j P_n(Td) / (A P_d(Td))``  ``b_j``
           second-order section of ``A``       ``j < n``
=========  ==================================  ========================  =====================

P2UZD's ``(Tw, Zeta)`` covers real poles (``Zeta >= 1``: ``Tp1,2 = Tw (Zeta +- sqrt(Zeta^2-1))``)
and the underdamped case (``Zeta < 1``) with one continuous parametrisation, so the fit decides.
OE is the paper's: an ``n``-th order rational ``B/A`` (``B`` of degree ``n - 1``) times the
Pade approximant of the delay (order 1 by default, ``(1 - Td s/2)/(1 + Td s/2)``); with Pade order
0 the delay is exact.  Its denominator is built from stable sections, so every candidate is
stable.

For the exact-delay structures the delay is a pure time shift of the regressors' responses; the
fit uses that to profile all integer-sample delays at once (see :mod:`motcomp.ident.fit`).
"""

from __future__ import annotations

import itertools
import math
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np

from motcomp.core.lti import FloatArray
from motcomp.core.models import OE, P1D, P2D, P2UZD, ProcessModel, pade
from motcomp.errors import ConfigError, ModelFitError

__all__ = ["STRUCTURES", "Structure", "make_structure"]

Regressor = tuple[FloatArray, FloatArray]
"""``(num, den)`` of one regressor system, highest power first."""

_ZETA_GRID = (0.3, 0.6, 1.2, 2.5, 6.0)


def _tc_grid(t_lo: float, t_hi: float, n: int) -> FloatArray:
    return np.asarray(np.log(np.geomspace(t_lo, t_hi, n)))


class Structure(ABC):
    """A fitted model structure (see the module notes)."""

    kind: ClassVar[str]
    order: ClassVar[int] = 0
    """Position in the preference order: simpler first."""

    shift_delay: bool = True
    """True when the delay is an exact time shift of the regressors' responses."""

    @property
    @abstractmethod
    def n_params(self) -> int:
        """Number of model parameters (delay included, bias excluded): the AIC's ``p``."""

    @abstractmethod
    def theta_grid(self, t_lo: float, t_hi: float) -> FloatArray:
        """Starting points ``(G, n_theta)`` spanning time constants in ``[t_lo, t_hi]``."""

    @abstractmethod
    def bounds(self, t_lo: float, t_hi: float) -> tuple[FloatArray, FloatArray]:
        """Bounds of ``theta``."""

    @abstractmethod
    def regressors(self, theta: FloatArray, delay_s: float) -> tuple[list[Regressor], float]:
        """The regressor systems and the exact dead time (s) to apply to all of them."""

    @abstractmethod
    def build(self, theta: FloatArray, delay_s: float, coef: FloatArray) -> ProcessModel:
        """The model for ``theta``, the delay and the linear coefficients.

        Raises
        ------
        ModelFitError
            If the coefficients give no valid model (e.g. a zero gain).
        """

    def natural(self, model: ProcessModel) -> dict[str, float]:
        """The reported parameters as a flat ``name -> value`` map (standard errors use it)."""
        return {k: float(v) for k, v in model.params().items()}

    @abstractmethod
    def from_natural(self, values: dict[str, float]) -> ProcessModel:
        """Inverse of :meth:`natural`."""

    def theta_of(self, model: ProcessModel) -> FloatArray:
        """``theta`` of a model of this structure (to restart a search from it)."""
        raise NotImplementedError


def _gain(coef: FloatArray, kind: str) -> float:
    K = float(coef[0])
    if not (math.isfinite(K) and K != 0.0):
        raise ModelFitError(f"{kind}: the fitted gain is {K!r}; the data show no response")
    return K


class P1DStructure(Structure):
    kind = "p1d"
    order = 0

    @property
    def n_params(self) -> int:
        return 3

    def theta_grid(self, t_lo: float, t_hi: float) -> FloatArray:
        return _tc_grid(t_lo, t_hi, 24)[:, None]

    def bounds(self, t_lo: float, t_hi: float) -> tuple[FloatArray, FloatArray]:
        return np.array([math.log(t_lo / 4)]), np.array([math.log(t_hi * 4)])

    def regressors(self, theta: FloatArray, delay_s: float) -> tuple[list[Regressor], float]:
        return [(np.array([1.0]), np.array([math.exp(theta[0]), 1.0]))], delay_s

    def build(self, theta: FloatArray, delay_s: float, coef: FloatArray) -> ProcessModel:
        return P1D(K=_gain(coef, self.kind), Td=delay_s, Tp1=math.exp(theta[0]))

    def from_natural(self, values: dict[str, float]) -> ProcessModel:
        return P1D(**values)

    def theta_of(self, model: ProcessModel) -> FloatArray:
        assert isinstance(model, P1D)
        return np.array([math.log(model.Tp1)])


class P2DStructure(Structure):
    kind = "p2d"
    order = 1

    @property
    def n_params(self) -> int:
        return 4

    def theta_grid(self, t_lo: float, t_hi: float) -> FloatArray:
        g = _tc_grid(t_lo, t_hi, 9)
        return np.array([(a, b) for a, b in itertools.combinations_with_replacement(g, 2)])

    def bounds(self, t_lo: float, t_hi: float) -> tuple[FloatArray, FloatArray]:
        lo, hi = math.log(t_lo / 4), math.log(t_hi * 4)
        return np.array([lo, lo]), np.array([hi, hi])

    def regressors(self, theta: FloatArray, delay_s: float) -> tuple[list[Regressor], float]:
        den = np.polymul([math.exp(theta[0]), 1.0], [math.exp(theta[1]), 1.0])
        return [(np.array([1.0]), den)], delay_s

    def build(self, theta: FloatArray, delay_s: float, coef: FloatArray) -> ProcessModel:
        t1, t2 = sorted((math.exp(theta[0]), math.exp(theta[1])), reverse=True)
        return P2D(K=_gain(coef, self.kind), Td=delay_s, Tp1=t1, Tp2=t2)

    def from_natural(self, values: dict[str, float]) -> ProcessModel:
        return P2D(**values)

    def theta_of(self, model: ProcessModel) -> FloatArray:
        assert isinstance(model, P2D)
        return np.log([model.Tp1, model.Tp2])


def _section_den(tw: float, zeta: float) -> FloatArray:
    return np.array([tw * tw, 2.0 * zeta * tw, 1.0])


class P2UZDStructure(Structure):
    kind = "p2uzd"
    order = 2

    @property
    def n_params(self) -> int:
        return 5

    def theta_grid(self, t_lo: float, t_hi: float) -> FloatArray:
        g = _tc_grid(t_lo, t_hi, 9)
        return np.array([(tw, math.log(z)) for tw in g for z in _ZETA_GRID])

    def bounds(self, t_lo: float, t_hi: float) -> tuple[FloatArray, FloatArray]:
        return (np.array([math.log(t_lo / 4), math.log(0.05)]),
                np.array([math.log(t_hi * 4), math.log(50.0)]))

    def regressors(self, theta: FloatArray, delay_s: float) -> tuple[list[Regressor], float]:
        den = _section_den(math.exp(theta[0]), math.exp(theta[1]))
        return [(np.array([1.0]), den), (np.array([1.0, 0.0]), den)], delay_s

    def build(self, theta: FloatArray, delay_s: float, coef: FloatArray) -> ProcessModel:
        K = _gain(coef, self.kind)
        tz = float(coef[1]) / K
        tw, zeta = math.exp(theta[0]), math.exp(theta[1])
        if zeta < 1.0:
            return P2UZD(K=K, Td=delay_s, Tz=tz, Tw=tw, Zeta=zeta)
        r = math.sqrt(zeta * zeta - 1.0)
        return P2UZD(K=K, Td=delay_s, Tz=tz, Tp1=tw * (zeta + r), Tp2=tw * (zeta - r))

    def from_natural(self, values: dict[str, float]) -> ProcessModel:
        return P2UZD(**values)

    def theta_of(self, model: ProcessModel) -> FloatArray:
        assert isinstance(model, P2UZD)
        if model.Tw is not None and model.Zeta is not None:
            return np.log([model.Tw, model.Zeta])
        assert model.Tp1 is not None and model.Tp2 is not None
        tw = math.sqrt(model.Tp1 * model.Tp2)
        return np.log([tw, (model.Tp1 + model.Tp2) / (2.0 * tw)])


class OEStructure(Structure):
    """``B(s)/A(s)`` of order ``n`` times a Pade delay of order ``pade_order`` (0: exact)."""

    kind = "oe"
    order = 3

    def __init__(self, n: int = 2, pade_order: int = 1) -> None:
        if not 1 <= n <= 4:
            raise ConfigError(f"OE order must be 1..4, got {n}")
        if not 0 <= pade_order <= 4:
            raise ConfigError(f"OE Pade order must be 0..4, got {pade_order}")
        self.n = n
        self.pade_order = pade_order
        self.shift_delay = pade_order == 0

    @property
    def n_params(self) -> int:
        return 2 * self.n + 1

    def _sections(self, theta: FloatArray) -> FloatArray:
        den = np.array([1.0])
        i = 0
        for _ in range(self.n // 2):
            den = np.polymul(den, _section_den(math.exp(theta[i]), math.exp(theta[i + 1])))
            i += 2
        if self.n % 2:
            den = np.polymul(den, [math.exp(theta[i]), 1.0])
        return den

    def theta_grid(self, t_lo: float, t_hi: float) -> FloatArray:
        # every grid point is simulated at every delay of the grid (no shift trick): keep it small
        g = _tc_grid(t_lo, t_hi, 8)
        zetas = [math.log(z) for z in _ZETA_GRID[1::2]]
        if self.n == 1:
            return g[:, None]
        if self.n == 2:
            return np.array([(tw, z) for tw in g for z in zetas])
        # higher orders: a coarser grid; the extra section starts 3x faster and well damped
        g = _tc_grid(t_lo, t_hi, 7)
        rows = []
        for tw in g:
            for z in zetas[::2]:
                extra = [tw - math.log(3.0)] + ([math.log(0.7)] if self.n == 4 else [])
                rows.append([tw, z, *extra])
        return np.array(rows)

    def bounds(self, t_lo: float, t_hi: float) -> tuple[FloatArray, FloatArray]:
        lo_t, hi_t = math.log(t_lo / 4), math.log(t_hi * 4)
        lo: list[float] = []
        hi: list[float] = []
        for _ in range(self.n // 2):
            lo += [lo_t, math.log(0.05)]
            hi += [hi_t, math.log(50.0)]
        if self.n % 2:
            lo.append(lo_t)
            hi.append(hi_t)
        return np.array(lo), np.array(hi)

    def regressors(self, theta: FloatArray, delay_s: float) -> tuple[list[Regressor], float]:
        a = self._sections(theta)
        pn, pd = pade(delay_s, self.pade_order)
        den = np.polymul(a, pd)
        regs = []
        for j in range(self.n):
            num = np.polymul(np.concatenate([[1.0], np.zeros(j)]), pn)
            regs.append((num, den))
        return regs, (delay_s if self.pade_order == 0 else 0.0)

    def build(self, theta: FloatArray, delay_s: float, coef: FloatArray) -> ProcessModel:
        a = self._sections(theta)
        b = np.asarray(coef[: self.n], dtype=float)[::-1]  # b_{n-1} ... b_0
        if not np.all(np.isfinite(b)) or not np.any(b != 0):
            raise ModelFitError("oe: the fitted numerator is zero; the data show no response")
        lead = a[0]
        return OE(num=tuple(b / lead), den=tuple(a / lead), Td=delay_s,
                  pade_order=self.pade_order)

    def natural(self, model: ProcessModel) -> dict[str, float]:
        assert isinstance(model, OE)
        out = {f"b{self.n - 1 - i}": v for i, v in enumerate(model.num)}
        out.update({f"a{self.n - 1 - i}": v for i, v in enumerate(model.den[1:])})
        out["Td"] = model.Td
        return out

    def from_natural(self, values: dict[str, float]) -> ProcessModel:
        num = tuple(values[f"b{j}"] for j in range(self.n - 1, -1, -1))
        den = (1.0, *(values[f"a{j}"] for j in range(self.n - 1, -1, -1)))
        return OE(num=num, den=den, Td=values["Td"], pade_order=self.pade_order)

    def theta_of(self, model: ProcessModel) -> FloatArray:
        """For ``n = 2``: the section of any model whose delay-free denominator is a stable
        quadratic (e.g. a fitted P2UZD, to start the OE search from it)."""
        _, den = model.rational()
        den = np.trim_zeros(np.asarray(den, dtype=float), "f")
        if self.n != 2 or den.size != 3 or not (den[-1] != 0):
            raise NotImplementedError
        a2, a1 = den[0] / den[-1], den[1] / den[-1]
        if not (a2 > 0 and a1 > 0):
            raise NotImplementedError
        tw = math.sqrt(a2)
        return np.log([tw, a1 / (2.0 * tw)])


STRUCTURES: tuple[str, ...] = ("p1d", "p2d", "p2uzd", "oe")


def make_structure(kind: str, oe_order: int = 2, oe_pade: int = 1) -> Structure:
    """The structure named ``kind``.

    Raises
    ------
    ConfigError
        For an unknown kind.
    """
    table: dict[str, Any] = {"p1d": P1DStructure, "p2d": P2DStructure, "p2uzd": P2UZDStructure}
    if kind == "oe":
        return OEStructure(oe_order, oe_pade)
    if kind not in table:
        raise ConfigError(f"unknown model kind {kind!r}; kinds: {', '.join(STRUCTURES)}")
    structure: Structure = table[kind]()
    return structure
