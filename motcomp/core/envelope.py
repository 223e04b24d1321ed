"""The hardware envelope guard: the last clamp of every command the tick emits.

The limiter (:mod:`motcomp.core.saturation`) keeps the command within the operational limits, a
live value that a reload or a profile changes.  The guard is a second layer, independent of it
and of the config's live values: its parameters come from the hardware envelope, a restart key
that every operational limit lies inside (:mod:`motcomp.config`), and it keeps the emitted
sequence ``u[k]`` (period ``h``) of every axis within it, relative to its *own* previous outputs:

* ``p_min <= u[k] <= p_max``
* ``|v[k]| <= v_max`` with ``v[k] = (u[k] - u[k-1]) / h``
* ``|v[k] - v[k-1]| <= a_max h``
* the braking condition ``u[k] + v[k]^2 / (2 a_max) <= p_max`` for ``v[k] > 0`` (and its
  mirror), so that it can always stop inside the range (:mod:`motcomp.core.saturation` proves
  why this keeps the four feasible for ever, from rest inside the range)

each to within :data:`TOLERANCE_M` of position (a picometre: rounding, never motion).  A command
that meets them passes bit-exactly (the guard is then a no-op: an inner limiter that works never
lets it act, since its limits and braking lie inside the envelope's).  One that does not is
replaced by the nearest command that does, chasing the command (its last value, clamped to the
range, as a wall moving at its own velocity, approached without overshoot); a non-finite command
counts as its last value.  Each axis changed is counted (:attr:`EnvelopeGuard.acted`).

An axis that is not driven has an envelope of zero width: it stays at neutral (0).

Plain float math over the axis lists, no allocation: 1-2 us for 8 axes on the 2-core host of
docs/BENCHMARKS.md under load, about 2 % of ``tick.step`` (tools/bench_core.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from math import sqrt
from typing import Any

from mypy_extensions import mypyc_attr

from motcomp.core.native import frozen_reduce

__all__ = ["CHASE_SHARE", "TOLERANCE_M", "EnvelopeGuard", "EnvelopeParams"]

TOLERANCE_M = 1e-12
"""Slack of every bound, as a position (m or rad) within one period: the rounding of the
limiter's arithmetic must not count as an action."""

CHASE_SHARE = 0.5
"""Share of ``a_max`` the guard plans its approach to the command with, once it acted."""


@dataclass(frozen=True)
class EnvelopeParams:
    """The envelope per axis (:data:`~motcomp.core.axes.AXES` order, axis units) at
    ``rate_hz``; an axis with ``v_max == 0`` is held at neutral (its range must be
    ``[0, 0]``)."""

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return frozen_reduce(self)

    p_min: tuple[float, ...]
    p_max: tuple[float, ...]
    v_max: tuple[float, ...]
    a_max: tuple[float, ...]
    rate_hz: float
    fast: tuple[tuple[float, ...], ...] = field(init=False, repr=False, compare=False)
    """Per axis, the bounds with their slack: ``(lo, hi, v_max, a_max h, 1 / (2 a_max),
    1 / h)``."""
    slow: tuple[tuple[float, ...], ...] = field(init=False, repr=False, compare=False)
    """Per axis, ``(lo, hi, v_max, a_max, h, 1 / h)``."""

    def __post_init__(self) -> None:
        n = len(self.p_min)
        if not len(self.p_max) == len(self.v_max) == len(self.a_max) == n:
            raise ValueError("envelope: p_min, p_max, v_max and a_max must have the same length")
        h = 1.0 / self.rate_hz
        fast, slow = [], []
        tol_v = TOLERANCE_M / h
        for lo, hi, v, a in zip(self.p_min, self.p_max, self.v_max, self.a_max, strict=True):
            if not (lo <= 0.0 <= hi and v >= 0.0 and a >= 0.0 and (v > 0.0) == (a > 0.0)
                    and (v > 0.0 or lo == hi == 0.0)):
                raise ValueError(f"envelope: invalid axis ({lo}, {hi}, {v}, {a})")
            fast.append((lo - TOLERANCE_M, hi + TOLERANCE_M, v + tol_v, a * h + tol_v,
                         0.5 / a if a > 0.0 else 0.0, 1.0 / h))
            slow.append((lo, hi, v, a, h, 1.0 / h))
        object.__setattr__(self, "fast", tuple(fast))
        object.__setattr__(self, "slow", tuple(slow))

    @property
    def n(self) -> int:
        return len(self.p_min)


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class EnvelopeGuard:
    """The guard's state: its last output and velocity per axis, and what it did."""

    def __init__(self, n: int) -> None:
        self.u = [0.0] * n
        """Last output per axis."""
        self.v = [0.0] * n
        """Last output's velocity per axis."""
        self.target = [0.0] * n
        """Per axis, the last command it changed (clamped to the range), the wall it chases
        (the last output otherwise: it was the command)."""
        self.acted = [0] * n
        """Outputs on which the guard changed each axis."""
        self.clamps = 0
        """Outputs on which it changed any axis."""
        self.applied = 0
        """Outputs seen."""
        self.acted_at = [-1] * n
        """Per axis, :attr:`applied` when it last changed it."""

    def reset(self, position: Sequence[float]) -> None:
        """At rest at ``position`` (a warm start)."""
        for i, x in enumerate(position):
            self.u[i] = self.target[i] = float(x)
            self.v[i] = 0.0
            self.acted_at[i] = -1

    def apply(self, p: EnvelopeParams, u: list[float]) -> bool:
        """Bound the command ``u`` in place (see the module docstring); True if it acted."""
        us, vs = self.u, self.v
        self.applied += 1
        acted = False
        i = 0  # a counter beside zip: cheaper than enumerate over nested tuples
        for x, (lo_t, hi_t, vmax_t, ah_t, k, inv_h) in zip(u, p.fast, strict=True):
            u0 = us[i]
            v = (x - u0) * inv_h
            dv = v - vs[i]
            if (lo_t <= x <= hi_t and -vmax_t <= v <= vmax_t and -ah_t <= dv <= ah_t
                    and (x + v * v * k <= hi_t if v > 0.0 else x - v * v * k >= lo_t)):
                us[i] = x
                vs[i] = v
            else:
                u[i] = self._chase(i, x, p.slow[i])
                self.acted[i] += 1
                self.acted_at[i] = self.applied
                acted = True
            i += 1  # noqa: SIM113
        if acted:
            self.clamps += 1
        return acted

    def _chase(self, i: int, x: float, c: tuple[float, ...]) -> float:
        """The output nearest the command ``x`` that meets every bound."""
        lo, hi, vmax, a, h, inv_h = c
        u0, v0 = self.u[i], self.v[i]
        x0 = self.target[i] if self.acted_at[i] == self.applied - 1 else u0
        x = x0 if x != x else min(max(x, lo), hi)  # NaN: the last command
        ah = a * h
        vt = (x - x0) * inv_h
        want = (x - u0) * inv_h
        # approach the command as a wall moving at vt, from where it was (x0), planning with
        # half of a_max: the other half follows the command's own accelerations
        ap = CHASE_SHARE * a
        aph = ap * h
        if want > vt:
            want = min(want, vt - aph + sqrt(aph * aph + 2.0 * ap * max(0.0, x0 - u0)))
        elif want < vt:
            want = max(want, vt + aph - sqrt(aph * aph + 2.0 * ap * max(0.0, u0 - x0)))
        v_hi = min(vmax, v0 + ah, -ah + sqrt(ah * ah + 2.0 * a * max(0.0, hi - u0)))
        v_lo = max(-vmax, v0 - ah, ah - sqrt(ah * ah + 2.0 * a * max(0.0, u0 - lo)))
        v = min(max(want, v_lo), v_hi) if v_lo <= v_hi else min(max(0.0, v0 - ah), v0 + ah)
        out = min(max(u0 + v * h, lo), hi)
        self.u[i] = out
        self.v[i] = (out - u0) * inv_h
        self.target[i] = x
        return out
