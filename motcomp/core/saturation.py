"""Per-axis position, velocity and acceleration limits, enforced sample to sample.

The emitted sequence ``u[k]`` satisfies, for every k (to floating-point rounding):

* ``p_min <= u[k] <= p_max``
* ``|v[k]| <= v_max`` with ``v[k] = (u[k] - u[k-1]) / h``
* ``|a[k]| <= a_max`` with ``a[k] = (v[k] - v[k-1]) / h``

Clipping position, velocity and acceleration one after the other is not enough: an axis moving
fast towards its end stop may be unable to stop in time without breaking the acceleration limit.
So the velocity chosen at each sample is also bounded by the *braking* condition

.. math::

    u[k-1] + v h + \\frac{v^2}{2 a_{max}} \\le p_{max} \\quad (v \\ge 0)

(and its mirror towards ``p_min``), i.e. ``v <= -a h + sqrt((a h)^2 + 2 a (p_max - u[k-1]))``.
``v^2/(2a)`` bounds the discrete braking distance from above (the exact sum is
``v^2/(2a) - (a h^2/2)(theta^2 + m)`` for ``v = (m + theta) a h``), and full braking
``v' = v - a h`` from a state that meets the condition meets it again.  Hence, from any state that
meets it (e.g. at rest inside the limits), the intersection of the four velocity intervals is never
empty and every limit holds for ever.

If a state does not meet the condition (limits narrowed by a live reload), acceleration wins:
the axis brakes at ``a_max`` and moves back into the allowed range within the velocity and
acceleration limits, with the position flag raised while it is outside.  A target outside the
range is treated as the nearest end of the range.

The limiter also *tracks* its target: after a limit has left the output behind, it closes the gap
braking relative to the target, so it meets the target without overshoot (see :func:`limit_axis`).

Flags (bit field per axis, every bound that changed the value this sample): :data:`POS` the
position/braking bound, :data:`VEL` the velocity limit, :data:`ACC` the acceleration limit,
:data:`RECOVER` catch-up braking towards the target.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from math import isfinite

import numpy as np
from numpy.typing import ArrayLike

from motcomp.core.lti import FloatArray
from motcomp.errors import ConfigError

__all__ = [
    "ACC",
    "LIMIT_BITS",
    "POS",
    "RECOVER",
    "VEL",
    "AxisLimits",
    "Saturator",
    "axis_constants",
    "check_position",
    "flag_names",
    "limit_axis",
]

POS = 1
VEL = 2
ACC = 4
RECOVER = 16
CATCHUP_SHARE = 0.25
"""Share of ``a_max`` the catch-up braking plans with; the rest stays free to follow the
target's own accelerations.  Measured on the rails (6 m/s^2, ZN compensator on a 0.1-3 Hz sweep
that saturates above ~2.2 Hz): with the full share the output overshoots its infeasible target
(0.058 m for 0.050 m), with 0.5 it still does, with 0.25 it stays below it (0.047 m); a 0.5 m
step is then met without overshoot in 1.0 s instead of 0.8 s."""
_GAP_TOL = 1e-12  # m or rad: gaps below this are rounding, not a lag to recover


LIMIT_BITS = POS | VEL | ACC


def flag_names(bits: int) -> list[str]:
    """Names of the bits set in a flag field: ``pos``, ``vel``, ``acc``, ``recover``,
    ``nonfinite``."""
    names = ((POS, "pos"), (VEL, "vel"), (ACC, "acc"), (8, "nonfinite"), (RECOVER, "recover"))
    return [name for bit, name in names if bits & bit]


@dataclass(frozen=True)
class AxisLimits:
    """Limits of each axis (arrays of equal length, axis units: m or rad).

    Raises
    ------
    ConfigError
        Naming the axis and value, if a limit is non-finite, ``p_min >= p_max`` (inverted or empty
        range), or a velocity/acceleration limit is not > 0.
    """

    p_min: FloatArray
    p_max: FloatArray
    v_max: FloatArray
    a_max: FloatArray
    names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        arrays = {}
        for key in ("p_min", "p_max", "v_max", "a_max"):
            arr = np.array(getattr(self, key), dtype=float, ndmin=1)
            arr.setflags(write=False)
            arrays[key] = arr
            object.__setattr__(self, key, arr)
        n = arrays["p_min"].size
        if any(a.size != n for a in arrays.values()):
            raise ConfigError("limits: p_min, p_max, v_max and a_max must have the same length")
        names = self.names or tuple(f"axis{i}" for i in range(n))
        if len(names) != n:
            raise ConfigError(f"limits: {len(names)} names for {n} axes")
        object.__setattr__(self, "names", tuple(names))
        for i, name in enumerate(names):
            for key, arr in arrays.items():
                if not math.isfinite(arr[i]):
                    raise ConfigError(f"limits of {name}: {key} must be finite, got {arr[i]!r}")
            if not arrays["p_min"][i] < arrays["p_max"][i]:
                raise ConfigError(
                    f"limits of {name}: position range is inverted or empty "
                    f"(p_min={arrays['p_min'][i]!r} >= p_max={arrays['p_max'][i]!r})"
                )
            for key in ("v_max", "a_max"):
                if not arrays[key][i] > 0:
                    raise ConfigError(
                        f"limits of {name}: {key} must be > 0, got {arrays[key][i]!r}")

    @property
    def size(self) -> int:
        return int(self.p_min.size)

    @classmethod
    def uniform(cls, n: int, p: float, v: float, a: float) -> AxisLimits:
        """``n`` axes with ``|u| <= p``, ``|v| <= v``, ``|a| <= a``."""
        return cls(np.full(n, -p), np.full(n, p), np.full(n, v), np.full(n, a))

    def contains(self, position: ArrayLike) -> np.ndarray:
        """Boolean mask of axes whose ``position`` lies within ``[p_min, p_max]``."""
        x = np.asarray(position, dtype=float)
        return np.asarray((x >= self.p_min) & (x <= self.p_max))


def axis_constants(limits: AxisLimits, dt_s: float) -> list[tuple[float, ...]]:  # 13 floats
    """Per-axis constants of :func:`limit_axis`, precomputed once per (limits, rate)."""
    h = float(dt_s)
    out: list[tuple[float, ...]] = []
    for i in range(limits.size):
        a = float(limits.a_max[i])
        ah = a * h
        ahc = CATCHUP_SHARE * ah  # catch-up braking plans with a share of the acceleration
        out.append((h, 1.0 / h, float(limits.p_min[i]), float(limits.p_max[i]),
                    float(limits.v_max[i]), ah, ah * ah, 2.0 * a, 1.0 / (2.0 * a),
                    ahc, ahc * ahc, 2.0 * CATCHUP_SHARE * a, 1.0 / (2.0 * CATCHUP_SHARE * a)))
    return out


def limit_axis(target: float, target_prev: float, u0: float, v0: float,
               const: tuple[float, ...]) -> tuple[float, float, int]:
    """One sample of one axis: ``(u, v, flags)``.

    Parameters
    ----------
    target
        Desired position now; a non-finite target holds the last command.
    target_prev
        Desired position at the previous sample (its change gives the target's velocity).
    u0, v0
        Last emitted position and velocity.
    const
        The axis' constants from :func:`axis_constants`.

    Notes
    -----
    Order of the bounds on the velocity ``v`` of this sample:

    1. *Catch-up braking* (soft): when a limit has left the output behind the target, close the
       gap no faster than allows stopping *relative to the target* (a wall moving at the target's
       velocity) with :data:`CATCHUP_SHARE` of the acceleration limit, so the output meets the
       target without overshoot (flag :data:`RECOVER`).
       Without it an acceleration-limited output that chases a step overshoots and oscillates
       around it for ever.  When the target is feasible the gap is zero and this never acts:
       the target passes through unchanged.
    2. Position braking bound and velocity limit (hard).
    3. Acceleration limit (hard, always wins).

    The ``sqrt`` of a braking bound is only evaluated when the cheap test
    ``w (h + w/(2a)) > room`` says the bound is reached.
    """
    (h, inv_h, p_min, p_max, v_max, ah, ah2, two_a, inv_two_a,
     ahc, ahc2, two_ac, inv_two_ac) = const
    if not isfinite(target):  # never propagated: hold the last command
        target = u0
    # a target beyond the range means "go to the end stop"; an axis left outside by narrowed
    # limits is driven back in
    if target > p_max:
        target = p_max
    elif target < p_min:
        target = p_min
    if target_prev > p_max:
        target_prev = p_max
    elif target_prev < p_min:
        target_prev = p_min
    vel = (target - u0) * inv_h
    fl = POS if (u0 > p_max or u0 < p_min) else 0
    # 1. catch-up braking, in the frame of the target, planned with CATCHUP_SHARE of a_max
    v_t = (target - target_prev) * inv_h
    gap = target_prev - u0
    w = vel - v_t
    if w > 0.0:
        if w * (h + w * inv_two_ac) > gap + _GAP_TOL:
            vel = v_t + math.sqrt(ahc2 + two_ac * (gap if gap > 0.0 else 0.0)) - ahc
            fl = RECOVER
    elif w < 0.0 and -w * (h - w * inv_two_ac) > -gap + _GAP_TOL:
        vel = v_t + ahc - math.sqrt(ahc2 + two_ac * (-gap if gap < 0.0 else 0.0))
        fl = RECOVER
    # 2. position braking and velocity
    if vel > 0.0:
        room = p_max - u0
        if vel * (h + vel * inv_two_a) > room:
            vel = math.sqrt(ah2 + two_a * (room if room > 0.0 else 0.0)) - ah
            fl |= POS
        if vel > v_max:
            vel = v_max
            fl |= VEL
    elif vel < 0.0:
        room = u0 - p_min
        if -vel * (h - vel * inv_two_a) > room:
            vel = ah - math.sqrt(ah2 + two_a * (room if room > 0.0 else 0.0))
            fl |= POS
        if vel < -v_max:
            vel = -v_max
            fl |= VEL
    # 3. acceleration
    if vel > v0 + ah:
        vel = v0 + ah
        fl |= ACC
    elif vel < v0 - ah:
        vel = v0 - ah
        fl |= ACC
    if not fl:
        return target, vel, 0  # feasible: the target passes through bit-exactly
    u = u0 + vel * h
    # rounding guard only; an axis already outside (limits narrowed live) is not teleported
    if u > p_max and u0 <= p_max:
        u = p_max
    elif u < p_min and u0 >= p_min:
        u = p_min
    return u, (u - u0) * inv_h, fl


class Saturator:
    """Stateful limiter for all axes at sample period ``dt_s`` (see module docstring).

    ``step(u_des)`` returns the next emitted positions; :attr:`flags` holds the bits of the last
    step.  State: the last emitted position and velocity of each axis.
    """

    def __init__(self, limits: AxisLimits, dt_s: float, position: ArrayLike | None = None) -> None:
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ConfigError(f"sample period must be a positive finite number of s, got {dt_s!r}")
        self.dt_s = float(dt_s)
        self.n = limits.size
        self.limits = limits
        self._const = axis_constants(limits, self.dt_s)
        self.u: list[float] = [0.0] * self.n
        self.v: list[float] = [0.0] * self.n
        self.target: list[float] = [0.0] * self.n
        self.flags: list[int] = [0] * self.n
        self.reset(np.zeros(self.n) if position is None else position)

    def set_limits(self, limits: AxisLimits) -> None:
        """Swap limits (between two steps).  The state is kept; see the module docstring for an
        axis left outside the new range."""
        if limits.size != self.n:
            raise ConfigError(f"limits for {limits.size} axes, saturator has {self.n}")
        self._const = axis_constants(limits, self.dt_s)
        self.limits = limits

    def reset(self, position: ArrayLike, velocity: ArrayLike | None = None) -> None:
        """Set the state; ``position`` must be finite and within the limits."""
        p = check_position(self.limits, position)
        self.u = p.tolist()
        self.target = p.tolist()
        vel = np.zeros(self.n) if velocity is None else np.array(velocity, dtype=float)
        self.v = vel.tolist()
        self.flags = [0] * self.n

    def step(self, u_des: ArrayLike) -> list[float]:
        """Limit the desired positions (finite) and return the emitted ones."""
        target = np.asarray(u_des, dtype=float).tolist()
        out = [0.0] * self.n
        for i, const in enumerate(self._const):
            out[i], self.v[i], self.flags[i] = limit_axis(target[i], self.target[i], self.u[i],
                                                          self.v[i], const)
        self.target = target
        self.u = out[:]
        return out


def check_position(limits: AxisLimits, position: ArrayLike) -> np.ndarray:
    """``position`` as a float array, checked finite, of the right size and within the limits.

    Raises
    ------
    ConfigError
        Naming the axis and the value.
    """
    p = np.array(position, dtype=float, ndmin=1)
    if p.shape != (limits.size,):
        raise ConfigError(f"position must have {limits.size} values, got shape {p.shape}")
    for i, name in enumerate(limits.names):
        if not math.isfinite(p[i]):
            raise ConfigError(f"position of {name} must be finite, got {p[i]!r}")
        if not limits.p_min[i] <= p[i] <= limits.p_max[i]:
            raise ConfigError(f"position of {name} = {p[i]!r} is outside "
                              f"[{limits.p_min[i]}, {limits.p_max[i]}]")
    return p
