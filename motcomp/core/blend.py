"""The blend from a held path to a live one, continuous to the jerk at both ends.

A blend adds to the live path ``x(t)`` a difference ``e(t)`` that starts as the held path's
difference to it -- in position ``g``, velocity ``r``, acceleration ``a`` and jerk ``j`` -- and
ends at zero in all four, over ``T`` (``s = (t - t0) / T`` in [0, 1])::

    e = g B0(s) + r T B1(s) + a T^2 B2(s) + j T^3 B3(s)

with ``B_k^(m)(0) = 1 if m == k else 0`` and ``B_k^(m)(1) = 0`` for ``m`` = 0..3.  The reference
``x + e`` leaves the held path and meets the live one with no step in position, velocity,
acceleration or jerk: the pseudo open-loop compensator's command carries about ``Tp1`` times the
reference's jerk, so a jerk step at a blend's end is a step of the command's acceleration (the
quintic blends this replaces: 3-4 m/s^2 on the rails after every start and resume).

``B2 = s^2/2 (1-s)^4 (1+4s)`` and ``B3 = s^3/6 (1-s)^4`` are the septic Hermite basis.  ``B0``
and ``B1`` are the septic Hermite basis plus ``s^4 (1-s)^4 Q_k(s)`` (which keeps the end
conditions): ``Q_k`` minimises ``max |B''| + 0.1 max |B'''|`` (a linear programme on a grid,
docs/TUNING.md, "Blends into live input"), for a shorter blend within the same acceleration
and a smaller excursion: peak ``|B0''|`` 6.29 (7.51 for the septic alone), ``|B1''|`` 3.49
(5.03; the quintic ``s (1 - m(s))`` of the blends before: 4.62), ``max |B1|`` 0.227.

:func:`blend_duration` is the shortest ``T`` no shorter than asked for which the position and
velocity terms need at most a given acceleration; the acceleration and jerk terms only carry
the held path's own over to the live one's, clipped by :func:`blend_coefficients` so that an
estimate's error cannot swing the blend (the shaper carries the jerk over a shorter time than
the rest: its excursion grows as ``j T^3``).  :func:`local_cubic` estimates the live path's
velocity, acceleration and jerk from its last ticks and says how far they are from a cubic.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.polynomial import polynomial as npp

__all__ = ["B3_ACC_PEAK", "BLEND_ACC_PEAK", "BLEND_ACC_SHARE", "BLEND_MERGE_PEAK", "BLEND_TERMS",
           "blend_coefficients", "blend_duration", "carried_acceleration", "horner",
           "jerk_duration", "local_cubic"]


BLEND_ACC_SHARE = 0.25
"""A blend may take this share of an axis' acceleration limit (``ShaperParams.blend_acc``, set
by :func:`motcomp.config.tick_params`): the compensator multiplies the reference's acceleration
in the band by up to its peak gain (+8 dB, 2.5x), and the live motion has its own, so that the
limiter need not cut a blend (the rails' slalom rejoined over 0.5 s at full speed: the limiter
acted for 1.2 s, the platform 40 ms ahead of the motion for a second after)."""


def _mul(a: Sequence[float], b: Sequence[float]) -> list[float]:
    out = [0.0] * (len(a) + len(b) - 1)
    for i, x in enumerate(a):
        for k, y in enumerate(b):
            out[i + k] += x * y
    return out


def _add(a: Sequence[float], b: Sequence[float]) -> list[float]:
    n = max(len(a), len(b))
    return [(a[i] if i < len(a) else 0.0) + (b[i] if i < len(b) else 0.0) for i in range(n)]


def _der(c: Sequence[float]) -> list[float]:
    return [k * c[k] for k in range(1, len(c))] or [0.0]


_EDGE = _mul(_mul(_mul([0.0, 1.0], [0.0, 1.0]), _mul([0.0, 1.0], [0.0, 1.0])),
             _mul(_mul([1.0, -1.0], [1.0, -1.0]), _mul([1.0, -1.0], [1.0, -1.0])))
"""``s^4 (1 - s)^4``: zero to the third derivative at both ends."""
_Q0 = (-53.5, 254.3, -442.2, 294.8)
_Q1 = (-25.4, 87.6, -40.5, -23.3, 27.9)
B0: tuple[float, ...] = tuple(_add([1.0, 0.0, 0.0, 0.0, -35.0, 84.0, -70.0, 20.0],
                                   _mul(_EDGE, _Q0)))
B1: tuple[float, ...] = tuple(_add([0.0, 1.0, 0.0, 0.0, -20.0, 45.0, -36.0, 10.0],
                                   _mul(_EDGE, _Q1)))
B2: tuple[float, ...] = (0.0, 0.0, 0.5, 0.0, -5.0, 10.0, -7.5, 2.0)
B3: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0 / 6.0, -2.0 / 3.0, 1.0, -2.0 / 3.0, 1.0 / 6.0)
"""The blend's basis, coefficients of ``s^0, s^1, ...`` (module docstring)."""

GRID = 64
""":func:`blend_duration` checks the acceleration at ``GRID + 1`` points of the blend."""
_ACC0 = _der(_der(B0))
_ACC1 = _der(_der(B1))


def horner(c: Sequence[float], s: float) -> float:
    """The polynomial with coefficients ``c`` (of ``s^0, s^1, ...``) at ``s``."""
    out = 0.0
    for k in range(len(c) - 1, -1, -1):
        out = out * s + c[k]
    return out


_BASES = (B0, B1, B2, B3)
BLEND_TERMS = max(len(c) for c in _BASES)
"""How many coefficients :func:`blend_coefficients` gives."""
_GRID_ACC = tuple(tuple(horner(_der(_der(c)), k / GRID) for c in _BASES)
                  for k in range(GRID + 1))
"""Per point of the grid, the second derivative of each basis function."""
BLEND_ACC_PEAK = max(abs(row[0]) for row in _GRID_ACC)
"""``max |B0''|`` on the grid (6.29): a gap ``g`` blended over ``T`` takes at most about
``BLEND_ACC_PEAK |g| / T^2`` of acceleration."""
BLEND_MERGE_PEAK = max(abs(row[1]) for row in _GRID_ACC)
"""``max |B1''|`` on the grid (3.49): a velocity difference ``r``: ``BLEND_MERGE_PEAK |r| / T``."""
B3_ACC_PEAK = max(abs(row[3]) for row in _GRID_ACC)
"""``max |B3''|`` on the grid (0.040)."""
_GRID_JERK = tuple(tuple(horner(_der(_der(_der(c))), k / GRID) for c in _BASES[:3])
                   for k in range(GRID + 1))
"""Per point of the grid, the third derivative of ``B0``, ``B1`` and ``B2``."""
JERK_STRETCH = 1.05
""":func:`jerk_duration` lengthens a blend in steps of this factor."""
JERK_LONGEST_S = 10.0
""":func:`jerk_duration` never lengthens a blend beyond this (s)."""


def blend_duration(g: float, r: float, acc: float, base: float) -> float:
    """The shortest ``T >= base`` over which the gap ``g`` and velocity difference ``r`` blend
    out (``g B0 + r T B1``) with an acceleration of at most ``acc`` at each of the ``GRID + 1``
    points checked (``base`` if ``acc <= 0``)."""
    if acc <= 0.0 or (g == 0.0 and r == 0.0):
        return base
    t = base
    for row in _GRID_ACC:
        a0, a1 = row[0], row[1]
        # |g a0 + r a1 T| <= acc T^2: beyond the larger root of acc T^2 -+ (r a1 T + g a0)
        for bb, cc in ((r * a1, g * a0), (-r * a1, -g * a0)):
            disc = bb * bb + 4.0 * acc * cc
            if disc > 0.0:
                t = max(t, (bb + math.sqrt(disc)) / (2.0 * acc))
    return t


def carried_acceleration(a: float, acc: float) -> float:
    """The acceleration difference ``a`` a blend carries over within the budget ``acc``:
    clipped to ``2 acc`` (no clip for ``acc <= 0``)."""
    return min(max(a, -2.0 * acc), 2.0 * acc) if acc > 0.0 else a


def jerk_duration(g: float, r: float, a: float, acc: float, jerk: float, base: float) -> float:
    """The shortest ``T >= base`` (in steps of :data:`JERK_STRETCH`, at most
    :data:`JERK_LONGEST_S`) over which the gap ``g``, velocity difference ``r`` and acceleration
    difference ``a`` (as :func:`carried_acceleration` carries it within ``acc``) blend out
    with a jerk of at most ``jerk``: ``|g B0^(3) / T^3 + r B1^(3) /
    T^2 + a B2^(3) / T|`` at each of the ``GRID + 1`` points (``base`` if ``jerk <= 0``; the jerk
    term's own ``j B3^(3)`` does not shrink with ``T``).  The pseudo open-loop compensator's
    command carries about its model's lag times the reference's jerk (docs/TUNING.md, "Blends
    into live input")."""
    if jerk <= 0.0 or base <= 0.0:
        return base
    a = carried_acceleration(a, acc)
    t = base
    while t < JERK_LONGEST_S:
        c0, c1, c2 = g / (t * t * t), r / (t * t), a / t
        if all(abs(c0 * b0 + c1 * b1 + c2 * b2) <= jerk for b0, b1, b2 in _GRID_JERK):
            return t
        t *= JERK_STRETCH
    return JERK_LONGEST_S


def blend_coefficients(g: float, r: float, a: float, j: float, duration: float,
                       acc: float = 0.0) -> list[float]:
    """The coefficients (of ``s^0, s^1, ...``, ``s = (t - t0) / duration``) of the difference
    that starts as ``(g, r, a, j)`` (position, velocity, acceleration, jerk) and ends at zero
    to the jerk at ``s = 1``.  With ``acc > 0`` the acceleration and jerk carried over are
    clipped so that neither term takes more than ``2 acc`` (an estimate's error cannot swing
    the blend: the jerk term's excursion grows as ``j T^3``)."""
    t = duration
    if acc > 0.0:
        a = carried_acceleration(a, acc)
        jmax = 2.0 * acc / (B3_ACC_PEAK * t) if t > 0.0 else 0.0
        j = min(max(j, -jmax), jmax)
    out = [0.0] * BLEND_TERMS
    for basis, w in ((B0, g), (B1, r * t), (B2, a * t * t), (B3, j * t * t * t)):
        for k, c in enumerate(basis):
            out[k] += w * c
    return out


def local_cubic(times: Sequence[float], values: Sequence[Sequence[float]]
                ) -> tuple[list[tuple[float, float, float]], float] | None:
    """The least-squares cubic through each column of ``values`` (one row of columns per
    instant of ``times``, the latest last): its velocity, acceleration and jerk at the latest
    instant, and the largest distance of any value from its column's cubic; None if ``times``
    do not span four distinct instants."""
    if len(set(times)) < 4:
        return None
    t = np.asarray(times, dtype=float)
    t = t - t[-1]
    span = float(np.max(np.abs(t)))
    x = np.asarray(values, dtype=float)
    c = npp.polyfit(t / span, x, 3)  # (4, columns), in t / span
    residual = float(np.max(np.abs(npp.polyval(t / span, c).T - x)))
    return [(float(c1) / span, 2.0 * float(c2) / span**2, 6.0 * float(c3) / span**3)
            for c1, c2, c3 in zip(c[1], c[2], c[3], strict=True)], residual
