"""Linear time-invariant building blocks: realisations, exact ZOH discretisation, phase.

Pure numpy (no scipy), so that the real-time service can use it without importing the offline
stack.

Conventions
-----------
* Polynomials are numpy coefficient arrays, highest power first (``np.polyval`` order).
* A continuous SISO system is ``H(s) = num(s)/den(s) * exp(-dead_time_s * s)``.
* Discretisation is *exact* for a zero-order-hold input (the platform holds each setpoint for one
  period ``h``) and supports a fractional (sub-sample) dead time: with
  ``tau = (d - 1) h + tau'`` and ``0 < tau' <= h``,

  .. math::

      x_{k+1} = \\Phi x_k + \\Gamma_0 u_{k-d+1} + \\Gamma_1 u_{k-d}, \\qquad
      y_k = C x_k + D u_{k-d}

  with :math:`\\Phi = e^{Ah}`, :math:`\\Gamma_0 = \\int_0^{h-\\tau'} e^{As} ds\\,B` and
  :math:`\\Gamma_1 = e^{A(h-\\tau')} \\int_0^{\\tau'} e^{As} ds\\,B`
  (Astrom & Wittenmark, *Computer-Controlled Systems*, sec. 2.3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from motcomp.errors import ConfigError

FloatArray = NDArray[np.floating[Any]]
ComplexArray = NDArray[np.complexfloating[Any, Any]]

__all__ = [
    "DiscreteLTI",
    "discretize_zoh",
    "expm",
    "factor_phase_continuous",
    "factor_phase_discrete",
    "rational_phase_continuous",
    "rational_phase_discrete",
    "tf2ss",
]


def expm(a: ArrayLike) -> FloatArray:
    """Matrix exponential by scaling and squaring of a Taylor series.

    Accurate to a few ulps for the small, well-conditioned matrices of process models; the norm is
    scaled below 1/2 so that 20 Taylor terms leave a truncation error below 1e-25.
    """
    m = np.asarray(a, dtype=float)
    n = m.shape[0]
    if m.shape != (n, n):
        raise ValueError(f"expm needs a square matrix, got shape {m.shape}")
    norm = float(np.max(np.sum(np.abs(m), axis=1))) if n else 0.0
    squarings = max(0, math.ceil(math.log2(norm / 0.5))) if norm > 0.5 else 0
    scaled = m / (2.0**squarings)
    result = np.eye(n)
    term = np.eye(n)
    for k in range(1, 21):
        term = term @ scaled / k
        result = result + term
    for _ in range(squarings):
        result = result @ result
    return result


def tf2ss(num: ArrayLike, den: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """Controllable canonical realisation ``(A, B, C, D)`` of a proper ``num/den``.

    Raises
    ------
    ConfigError
        If the transfer function is improper or the denominator is zero.
    """
    num_a = np.atleast_1d(np.asarray(num, dtype=float))
    den_a = np.trim_zeros(np.atleast_1d(np.asarray(den, dtype=float)), "f")
    if den_a.size == 0:
        raise ConfigError("transfer function denominator is zero")
    num_a = np.trim_zeros(num_a, "f")
    if num_a.size == 0:
        num_a = np.zeros(1)
    n = den_a.size - 1
    if num_a.size - 1 > n:
        raise ConfigError(
            f"transfer function is improper: numerator degree {num_a.size - 1} > denominator "
            f"degree {n}"
        )
    lead = den_a[0]
    den_n = den_a / lead
    num_n = np.concatenate([np.zeros(n + 1 - num_a.size), num_a]) / lead
    d = float(num_n[0])
    if n == 0:
        return np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), d
    # strictly proper remainder: num_n - d * den_n
    rem = num_n - d * den_n
    a = np.zeros((n, n))
    a[0, :] = -den_n[1:]
    a[1:, :-1] = np.eye(n - 1)
    b = np.zeros((n, 1))
    b[0, 0] = 1.0
    c = rem[1:].reshape(1, n)
    return a, b, c, d


def _integral_terms(a: FloatArray, b: FloatArray, t: float) -> tuple[FloatArray, FloatArray]:
    """``(exp(A t), int_0^t exp(A s) ds B)`` from one augmented matrix exponential."""
    n = a.shape[0]
    aug = np.zeros((n + 1, n + 1))
    aug[:n, :n] = a * t
    aug[:n, n:] = b * t
    e = expm(aug)
    return e[:n, :n], e[:n, n:]


@dataclass(frozen=True)
class DiscreteLTI:
    """A SISO discrete system with a two-tap delayed input (exact ZOH of a delayed plant).

    ``x[k+1] = phi x[k] + gamma0 u[k-d+1] + gamma1 u[k-d]``, ``y[k] = C x[k] + D u[k-d]``.
    """

    phi: FloatArray
    gamma0: FloatArray
    gamma1: FloatArray
    c: FloatArray
    d_feed: float
    delay_samples: int
    dt_s: float

    @property
    def order(self) -> int:
        return int(self.phi.shape[0])

    def tf(self) -> tuple[FloatArray, FloatArray]:
        """Transfer function ``num(z)/den(z)`` in positive powers of z, delay included."""
        n = self.order
        d = self.delay_samples
        if n == 0:
            num = np.array([self.d_feed])
            den = np.concatenate([[1.0], np.zeros(d)])
            return num, den
        den_phi = np.poly(self.phi)
        # C (zI - Phi)^-1 G = [det(zI - Phi + G C) - det(zI - Phi)] for SISO
        n0 = np.poly(self.phi - self.gamma0 @ self.c) - den_phi
        n1 = np.poly(self.phi - self.gamma1 @ self.c) - den_phi
        # (z * n0 + n1) z^-d + D z^-d den  over den  ->  multiply by z^d
        num = np.polyadd(np.polyadd(np.concatenate([n0, [0.0]]), n1), self.d_feed * den_phi)
        den = np.concatenate([den_phi, np.zeros(d)])
        # the delayed two-tap form can leave num with degree n+1 when d == 0 (gamma0 == 0 then)
        num = np.trim_zeros(num, "f") if np.any(num) else np.zeros(1)
        return num, den

    def freqresp(self, f_hz: ArrayLike) -> ComplexArray:
        """Frequency response at ``z = exp(j 2 pi f h)``."""
        f = np.atleast_1d(np.asarray(f_hz, dtype=float))
        z = np.exp(1j * 2.0 * np.pi * f * self.dt_s)
        n = self.order
        out = np.empty(f.shape, dtype=complex)
        eye = np.eye(n)
        for i, zi in enumerate(z):
            g = self.gamma0[:, 0] * zi + self.gamma1[:, 0]
            val = self.d_feed
            if n:
                x = np.linalg.solve(zi * eye - self.phi, g)
                val = val + (self.c @ x)[0]
            out[i] = val * zi ** (-self.delay_samples)
        return out

    def simulate(self, u: ArrayLike, u_before: float = 0.0, x0: ArrayLike | None = None
                 ) -> FloatArray:
        """Output sequence for an input sequence; inputs before the first are ``u_before``.

        ``x0`` defaults to the steady state for a constant input ``u_before``.
        """
        u_a = np.asarray(u, dtype=float)
        n = self.order
        d = self.delay_samples
        padded = np.concatenate([np.full(d + 1, u_before), u_a])
        y = np.empty(u_a.size)
        x = self.steady_state(u_before) if x0 is None else np.asarray(x0, dtype=float).reshape(n)
        g0 = self.gamma0[:, 0]
        g1 = self.gamma1[:, 0]
        c = self.c[0] if n else np.zeros(0)
        for k in range(u_a.size):
            # padded index of u[j] is j + d + 1
            u_d = padded[k + 1]  # u[k-d]
            y[k] = (c @ x if n else 0.0) + self.d_feed * u_d
            u_d1 = padded[k + 2] if k + 2 < padded.size else u_a[-1]  # u[k-d+1]
            x = self.phi @ x + g0 * u_d1 + g1 * u_d
        return y

    def steady_state(self, u: float) -> FloatArray:
        """State at rest under a constant input ``u`` (zero for an integrating system)."""
        n = self.order
        if n == 0:
            return np.zeros(0)
        g = (self.gamma0[:, 0] + self.gamma1[:, 0]) * u
        try:
            return np.asarray(np.linalg.solve(np.eye(n) - self.phi, g), dtype=float)
        except np.linalg.LinAlgError:
            return np.zeros(n)


def discretize_zoh(num: ArrayLike, den: ArrayLike, dead_time_s: float, dt_s: float
                   ) -> DiscreteLTI:
    """Exact zero-order-hold discretisation of ``num/den * exp(-dead_time_s s)``.

    Parameters
    ----------
    num, den
        Continuous transfer function, highest power first, proper.
    dead_time_s
        Pure delay, >= 0; any real value (sub-sample parts are exact, not rounded).
    dt_s
        Sample period h > 0.

    Raises
    ------
    ConfigError
        For a non-positive or non-finite ``dt_s`` or a negative ``dead_time_s``.
    """
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise ConfigError(f"sample period must be a positive finite number of seconds, got {dt_s}")
    if not (math.isfinite(dead_time_s) and dead_time_s >= 0):
        raise ConfigError(f"dead time must be finite and >= 0 s, got {dead_time_s}")
    a, b, c, d_feed = tf2ss(num, den)
    n = a.shape[0]
    # tau = (d-1) h + tau', 0 < tau' <= h
    ratio = dead_time_s / dt_s
    d = math.ceil(ratio - 1e-12)
    if d <= 0:
        d = 0
        tau_p = dt_s
    else:
        tau_p = dead_time_s - (d - 1) * dt_s
        tau_p = min(max(tau_p, 0.0), dt_s)
        if tau_p <= 1e-15 * dt_s:  # exact multiple handled by ceil tolerance
            tau_p = dt_s
    if n == 0:
        return DiscreteLTI(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((0, 1)),
                           np.zeros((1, 0)), d_feed, d, dt_s)
    phi, _ = _integral_terms(a, b, dt_s)
    e_rest, g_rest = _integral_terms(a, b, dt_s - tau_p)
    _, g_tau = _integral_terms(a, b, tau_p)
    gamma0 = g_rest
    gamma1 = e_rest @ g_tau
    return DiscreteLTI(phi, gamma0, gamma1, c, d_feed, d, dt_s)


def factor_phase_continuous(roots: ArrayLike, w: ArrayLike) -> FloatArray:
    """Continuous phase (rad) of ``prod(s - r_i)`` along ``s = j w``, w > 0, relative to DC.

    Each factor is written ``-r (1 - s/r)``; ``arg(1 - jw/r)`` never crosses the branch cut for
    w > 0, so the sum is the unwrapped phase with no grid needed.  Roots at the origin add
    ``pi/2`` each.  The constant ``arg(prod(-r))`` is left out (it only fixes the sign of the gain).
    """
    r = np.atleast_1d(np.asarray(roots, dtype=complex))
    w_a = np.atleast_1d(np.asarray(w, dtype=float))
    out = np.zeros(w_a.shape)
    for ri in r:
        if abs(ri) < 1e-300:
            out += np.pi / 2
        else:
            out += np.angle(1.0 - 1j * w_a / ri)
    return out


def factor_phase_discrete(roots: ArrayLike, theta: ArrayLike) -> FloatArray:
    """Continuous phase (rad) of ``prod(z - r_i)`` along ``z = exp(j theta)``, 0 < theta < pi.

    For ``|r| < 1``: ``arg(e^{j theta} - r) = theta + arg(1 - r e^{-j theta})`` (no wrap);
    for ``|r| > 1``: ``arg(-r) + arg(1 - e^{j theta}/r)``; on the unit circle at ``r = 1``:
    ``theta/2 + pi/2``.  The result is continuous in theta and exact.
    """
    r = np.atleast_1d(np.asarray(roots, dtype=complex))
    th = np.atleast_1d(np.asarray(theta, dtype=float))
    ej = np.exp(1j * th)
    out = np.zeros(th.shape)
    for ri in r:
        mag = abs(ri)
        if abs(mag - 1.0) < 1e-12:
            # on the unit circle: arg(e^{j th} - e^{j a}) = (th + a)/2 + pi/2 for th > a
            a = float(np.angle(ri))
            out += (th + a) / 2.0 + np.pi / 2.0
        elif mag < 1.0:
            out += th + np.angle(1.0 - ri * np.conj(ej))
        else:
            out += np.angle(-ri) + np.angle(1.0 - ej / ri)
    return out


def _dc_offset(phase0: float, expected: float) -> float:
    """Multiple of 2 pi that brings ``phase0`` closest to ``expected``."""
    return 2.0 * np.pi * round((expected - phase0) / (2.0 * np.pi))


def rational_phase_continuous(num: ArrayLike, den: ArrayLike, w: ArrayLike) -> FloatArray:
    """Unwrapped phase (rad) of ``num(jw)/den(jw)`` for w > 0, exact (from the roots).

    Normalised so that as w -> 0 the phase tends to ``arg`` of the low-frequency asymptote
    ``c0 (jw)^m`` in (-pi, pi] (``c0`` real; ``m`` = zeros minus poles at the origin).
    """
    num_a = np.trim_zeros(np.atleast_1d(np.asarray(num, dtype=float)), "f")
    den_a = np.trim_zeros(np.atleast_1d(np.asarray(den, dtype=float)), "f")
    w_a = np.atleast_1d(np.asarray(w, dtype=float))
    zn = np.roots(num_a) if num_a.size > 1 else np.zeros(0)
    zd = np.roots(den_a) if den_a.size > 1 else np.zeros(0)
    ph = factor_phase_continuous(zn, w_a) - factor_phase_continuous(zd, w_a)
    # sign of the low-frequency constant: lowest non-zero coefficients
    c_num = num_a[np.nonzero(num_a)[0][-1]]
    c_den = den_a[np.nonzero(den_a)[0][-1]]
    if c_num / c_den < 0:
        ph = ph + np.pi
    m = int(np.count_nonzero(np.abs(zn) < 1e-300)) - int(np.count_nonzero(np.abs(zd) < 1e-300))
    expected = float(np.angle(np.sign(c_num / c_den) * (1j) ** m))
    ph0 = float(factor_phase_continuous(zn, [1e-12])[0] - factor_phase_continuous(zd, [1e-12])[0])
    ph0 += np.pi if c_num / c_den < 0 else 0.0
    return np.asarray(ph + _dc_offset(ph0, expected))


def rational_phase_discrete(num: ArrayLike, den: ArrayLike, theta: ArrayLike) -> FloatArray:
    """Unwrapped phase (rad) of ``num(z)/den(z)`` on ``z = e^{j theta}``, 0 < theta < pi, exact.

    Normalised like :func:`rational_phase_continuous`: continuous from the low-frequency
    asymptote, whose phase is taken in (-pi, pi].
    """
    num_a = np.trim_zeros(np.atleast_1d(np.asarray(num, dtype=float)), "f")
    den_a = np.trim_zeros(np.atleast_1d(np.asarray(den, dtype=float)), "f")
    th = np.atleast_1d(np.asarray(theta, dtype=float))
    zn = np.roots(num_a) if num_a.size > 1 else np.zeros(0)
    zd = np.roots(den_a) if den_a.size > 1 else np.zeros(0)
    lead = num_a[0] / den_a[0]
    ph = factor_phase_discrete(zn, th) - factor_phase_discrete(zd, th)
    ph = ph + (np.pi if lead < 0 else 0.0)
    # low-frequency asymptote: c0 (z - 1)^m, m = zeros minus poles at z = 1
    tiny = 1e-9
    h0 = np.polyval(num_a, np.exp(1j * tiny)) / np.polyval(den_a, np.exp(1j * tiny))
    ph0 = float(factor_phase_discrete(zn, [tiny])[0] - factor_phase_discrete(zd, [tiny])[0])
    ph0 += np.pi if lead < 0 else 0.0
    return np.asarray(ph + _dc_offset(ph0, float(np.angle(h0))))
