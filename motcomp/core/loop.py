"""Transfer functions of the implemented discrete compensator, and the stability of its loop.

These are the z-domain images of exactly the recursion in :mod:`motcomp.core.compensator`::

    C(z) = kp + ki h/(z - 1) + b_d (z - 1)/(z - a_d),   a_d = tf/(tf+h), b_d = kd/(tf+h)
    M(z) = (g0 z + g1) / ((z - phi) z^d)              (exact ZOH of the P1D, sub-sample delay)

``Cr`` (reference path) uses ``kp b`` and ``b_d c``; ``Cy`` (model path) ``kp`` and ``b_d``.
Without integral action the ``(z - 1)`` factor is left out of the common denominator.
The internal loop is stable iff every root of ``Dc(z) Dm(z) + Nc(z) Nm(z)`` lies strictly inside
the unit circle; this is checked from the roots, never from a frequency grid.
"""

from __future__ import annotations

import numpy as np

from motcomp.core.lti import ComplexArray, FloatArray
from motcomp.core.models import P1D, p1d_coefficients
from motcomp.core.pid import PIDGains

__all__ = ["STABILITY_MARGIN", "Poly", "model_tf", "pid_tf", "poles", "stability"]

STABILITY_MARGIN = 1e-9
"""A loop whose largest pole modulus is above ``1 - STABILITY_MARGIN`` is called unstable."""

Poly = tuple[FloatArray, FloatArray]


def pid_tf(g: PIDGains, dt_s: float) -> tuple[Poly, Poly]:
    """``((num_r, den), (num_y, den))``: ``Cr(z)`` and ``Cy(z)``, common denominator
    ``(z - 1)(z - a_d)``."""
    h = dt_s
    ad = g.tf / (g.tf + h)
    bd = g.kd / (g.tf + h)
    if g.ki == 0:
        # no integrator: no (z - 1) factor (it would cancel and leave a false pole at 1)
        den = np.array([1.0, -ad])

        def num(kp: float, kd_coef: float) -> FloatArray:
            return np.asarray(np.polyadd(kp * den, kd_coef * np.array([1.0, -1.0])))
    else:
        den = np.polymul([1.0, -1.0], [1.0, -ad])

        def num(kp: float, kd_coef: float) -> FloatArray:
            p = kp * den
            i = g.ki * h * np.array([1.0, -ad])
            d = kd_coef * np.polymul([1.0, -1.0], [1.0, -1.0])
            return np.asarray(np.polyadd(np.polyadd(p, i), d))

    return (num(g.kp * g.b, bd * g.c), den), (num(g.kp, bd), den)


def model_tf(model: P1D, dt_s: float) -> Poly:
    """``M(z) = (g0 z + g1) / ((z - phi) z^d)``: the compensator's own internal model."""
    phi, g0, g1, d = p1d_coefficients(model, dt_s)
    return np.array([g0, g1]), np.concatenate([[1.0, -phi], np.zeros(d)])


def poles(gains: PIDGains, model: P1D, dt_s: float) -> ComplexArray:
    """Roots of the internal loop's characteristic polynomial."""
    _, (nc, dc) = pid_tf(gains, dt_s)
    nm, dm = model_tf(model, dt_s)
    char = np.trim_zeros(np.polyadd(np.polymul(dc, dm), np.polymul(nc, nm)), "f")
    return np.asarray(np.roots(char)) if char.size > 1 else np.zeros(0, dtype=complex)


def stability(gains: PIDGains, model: P1D, rate_hz: float) -> tuple[bool, float]:
    """``(stable, largest pole modulus)`` of the discrete internal loop ``1 + Cy M = 0``."""
    p = poles(gains, model, 1.0 / rate_hz)
    rho = float(np.max(np.abs(p))) if p.size else 0.0
    return rho < 1.0 - STABILITY_MARGIN, rho
