"""Vectorised frequency responses of many compensator designs at once, on one fixed grid.

The optimiser evaluates thousands of gain sets; :func:`motcomp.design.frequency.evaluate` is
exact but builds polynomials, roots and a 6400-point grid for each.  :class:`LoopGrid` computes
the same quantities with numpy broadcasting over ``(plants, gain sets, frequencies)`` on a fixed,
coarser grid, from the same z-domain algebra as :mod:`motcomp.core.loop` (the implemented
discrete PID and the exact ZOH models)::

    Cy(z) = kp + ki h/(z - 1) + b_d (z - 1)/(z - a_d)         a_d = tf/(tf+h), b_d = kd/(tf+h)
    Cr(z) = kp b + ki h/(z - 1) + b_d c (z - 1)/(z - a_d)
    F = Cr / (1 + Cy M),   T_m = P_m F,   S = 1/(1 + Cy M)

Phases are unwrapped as in :func:`~motcomp.design.frequency.loop_response`: ``arg T_m = arg P_m
+ arg Cr - arg(1 + Cy M)``, where ``arg P_m`` is exact (from poles and zeros) and the other two
are unwrapped along the grid from 1 mHz, anchored at ``-pi/2`` (integral action: both behave as
``ki h/(z - 1)`` there).  Only designs with integral action (``ki > 0``) are evaluated.

The grid: 24 points from 1 mHz to the band (for the unwrapping only), ``n_band`` points in the
band (delay, gain error, command excess), ``n_high`` points from the band to 0.999 Nyquist (peak
gain, command gain, sensitivity).  tests/test_optimal_fastloop.py checks it against
:func:`~motcomp.design.frequency.evaluate`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from motcomp.core.loop import model_tf
from motcomp.core.lti import ComplexArray, FloatArray, rational_phase_discrete
from motcomp.core.models import P1D, ProcessModel
from motcomp.errors import ConfigError

__all__ = ["LoopGrid", "Responses"]


@dataclass(frozen=True)
class Responses:
    """Responses of ``n`` gain sets with ``m`` plants; frequencies along the last axis.

    ``delay_s`` and ``excess_db`` are on :attr:`LoopGrid.f_band`, the others on
    :attr:`LoopGrid.f`.
    """

    delay_s: FloatArray  # (m, n, nb): phase delay of T_m in the band
    gain_db: FloatArray  # (m, n, nf): |T_m| in dB
    command: FloatArray  # (n, nf): |F|
    sensitivity: FloatArray  # (n, nf): |S|
    excess_db: FloatArray  # (n, nb): |F M| in dB, the command relative to the exact inverse 1/M

    def max_delay_ms(self) -> FloatArray:
        """``(m, n)``: largest |phase delay| over the band, ms."""
        return np.asarray(np.max(np.abs(self.delay_s), axis=-1) * 1e3)


class LoopGrid:
    """Fixed-grid evaluator of the compensator (internal model ``model``) on ``plants``.

    Parameters
    ----------
    model
        The compensator's internal P1D model M.
    plants
        The platforms P_m the delivered response is computed for (default: ``[model]``).
    rate_hz
        Loop rate; everything is evaluated at ``z = exp(j 2 pi f / rate_hz)``.
    band_hz
        The driver band (delay, gain error and command excess).
    """

    def __init__(self, model: P1D, plants: Sequence[ProcessModel] | None = None,
                 rate_hz: float = 1000.0, band_hz: tuple[float, float] = (0.1, 2.0),
                 n_band: int = 60, n_high: int = 300) -> None:
        lo, hi = band_hz
        nyquist = 0.5 * rate_hz
        if not 0 < lo < hi < 0.999 * nyquist:
            raise ConfigError(f"band must satisfy 0 < low < high < Nyquist ({nyquist:g} Hz), "
                              f"got {band_hz}")
        self.model = model
        self.plants = tuple(plants) if plants else (model,)
        self.rate_hz = float(rate_hz)
        self.h = 1.0 / self.rate_hz
        self.band_hz = (float(lo), float(hi))
        low = np.geomspace(min(1e-3, lo / 10), lo, 25)[:-1]
        band = np.geomspace(lo, hi, n_band)
        high = np.geomspace(hi, 0.999 * nyquist, n_high + 1)[1:]
        self.f = np.concatenate([low, band, high])
        self.band = slice(low.size, low.size + band.size)
        self.f_band = band
        self.w_band = 2.0 * np.pi * band
        self._n_phase = low.size + band.size  # phases are needed up to the band's top only
        theta = 2.0 * np.pi * self.f * self.h
        self.z: ComplexArray = np.exp(1j * theta)
        nm, dm = model_tf(model, self.h)
        self.m: ComplexArray = np.asarray(np.polyval(nm, self.z) / np.polyval(dm, self.z),
                                          dtype=complex)
        self.arg_m: FloatArray = rational_phase_discrete(nm, dm, theta)
        p_resp, p_arg = [], []
        for p in self.plants:
            pn, pd = p.discretize(self.rate_hz).tf()
            p_resp.append(np.polyval(pn, self.z) / np.polyval(pd, self.z))
            p_arg.append(rational_phase_discrete(pn, pd, theta))
        self.p: ComplexArray = np.array(p_resp)
        self.arg_p: FloatArray = np.array(p_arg)

    # --- what no compensator can change ------------------------------------------------------
    def plant_delay_s(self) -> FloatArray:
        """``(m, nb)``: phase delay of each plant alone (uncompensated) in the band."""
        return np.asarray(-self.arg_p[:, self.band] / self.w_band)

    def plant_gain_db(self) -> FloatArray:
        """``(m, nf)``: gain of each plant alone, dB."""
        return np.asarray(20.0 * np.log10(np.abs(self.p)))

    def floor_delay_s(self) -> FloatArray:
        """``(m, nb)``: phase delay of ``P_m / M``, what an exact inverse of M would deliver."""
        return np.asarray(-(self.arg_p[:, self.band] - self.arg_m[self.band]) / self.w_band)

    def floor_gain_db(self) -> FloatArray:
        """``(m, nb)``: gain of ``P_m / M`` in the band, dB."""
        return np.asarray(20.0 * np.log10(np.abs(self.p[:, self.band] / self.m[self.band])))

    # --- the designs -------------------------------------------------------------------------
    def __call__(self, kp: ArrayLike, ki: ArrayLike, kd: ArrayLike, tf: ArrayLike,
                 b: ArrayLike = 1.0, c: ArrayLike = 1.0) -> Responses:
        """Responses of the gain sets given as broadcastable 1-D arrays (or scalars)."""
        cols = np.broadcast_arrays(*(np.atleast_1d(np.asarray(v, dtype=float))
                                     for v in (kp, ki, kd, tf, b, c)))
        kp_, ki_, kd_, tf_, b_, c_ = (v[:, None] for v in cols)
        if np.any(ki_ <= 0):
            raise ConfigError("the fast evaluator needs integral action (ki > 0)")
        h = self.h
        z = self.z
        a_d = tf_ / (tf_ + h)
        b_d = kd_ / (tf_ + h)
        integ = ki_ * h / (z - 1.0)
        deriv = b_d * (z - 1.0) / (z - a_d)
        cy = kp_ + integ + deriv
        cr = kp_ * b_ + integ + c_ * deriv
        loop = 1.0 + cy * self.m
        f_cmd = cr / loop
        k = self._n_phase
        arg_f = _unwrap_from(cr[:, :k]) - _unwrap_from(loop[:, :k])
        arg_t = self.arg_p[:, None, self.band] + arg_f[None, :, self.band]
        delay = -arg_t / self.w_band
        gain = 20.0 * np.log10(np.abs(self.p[:, None, :] * f_cmd[None]))
        excess = 20.0 * np.log10(np.abs(f_cmd[:, self.band] * self.m[self.band]))
        return Responses(delay_s=np.asarray(delay), gain_db=np.asarray(gain),
                         command=np.abs(f_cmd), sensitivity=np.abs(1.0 / loop),
                         excess_db=np.asarray(excess))


def _unwrap_from(x: ComplexArray) -> FloatArray:
    """Phase of ``x`` unwrapped along the last axis, anchored at ``-pi/2`` at the first point."""
    ph = np.unwrap(np.angle(x), axis=-1)
    return np.asarray(ph + 2.0 * np.pi * np.round((-np.pi / 2 - ph[..., :1]) / (2.0 * np.pi)))
