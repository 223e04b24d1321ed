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

A feasible target passes through bit-exactly; an infeasible one is approached without overshoot,
as a wall moving at the target's velocity (a third-order tracker's estimate, corrected towards
the target's own sample-to-sample velocity; see :func:`limit_axis`), and caught again.

Flags (bit field per axis, every bound that changed the value this sample): :data:`POS` the
position/braking bound, :data:`VEL` the velocity limit, :data:`ACC` the acceleration limit,
:data:`RECOVER` the target was not feasible (the output aims at the smoothed target).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from math import isfinite
from typing import Any

import numpy as np
from mypy_extensions import mypyc_attr
from numpy.typing import ArrayLike

from motcomp.core.lti import FloatArray
from motcomp.core.native import frozen_reduce
from motcomp.errors import ConfigError

__all__ = [
    "ACC",
    "LIMIT_BITS",
    "POS",
    "RECOVER",
    "TRACKER_HZ",
    "VEL",
    "AxisLimits",
    "Saturator",
    "Track",
    "at_rest",
    "axis_constants",
    "check_position",
    "flag_names",
    "limit_axis",
]

POS = 1
VEL = 2
ACC = 4
RECOVER = 16
TRACKER_HZ = 8.0
"""Natural frequency of the third-order tracker that estimates the velocity of an infeasible
target (capped at 0.2/h for low loop rates).  Measured (see :func:`limit_axis`): at 4 Hz the
jittery slalom ends 2.3 mm off and a bypass jump is rejoined in 1.9 s, at 8 Hz 0.7 mm and
0.6 s."""
CATCHUP_SHARE = 0.1
"""Share of ``a_max`` the catch-up braking plans with; the rest stays free to follow the
target's own accelerations.  Measured on the rails (6 m/s^2) with the ZN compensator's command
for 0.3 sin^3 references that need 2-3x the acceleration available: with 0.25 the output swings
up to 20 % beyond its target's amplitude, with 0.1 up to 9 % (none at 0.5 Hz), with 0.05 up to
5 %; a 0.5 m step is met without overshoot in 1.1 s, 1.56 s and 2.1 s.  For a platform with a
person in it extra motion is worse than a slower recovery."""


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

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return frozen_reduce(self)

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


def _tracker(f_hz: float, h: float) -> tuple[float, ...]:
    """Exact ZOH of the third-order tracker with a triple pole at ``w = 2 pi f``::

        p' = v + 3 w (T - p),  v' = a + 3 w^2 (T - p),  a' = w^3 (T - p)

    It follows a target of constant acceleration with no steady-state error in position or
    velocity.  Returns the 3x3 matrix row by row, then the 3 input gains (12 floats)."""
    from motcomp.core.lti import expm

    w = 2.0 * math.pi * f_hz
    aug = np.zeros((4, 4))
    aug[:3, :3] = np.array([[-3 * w, 1.0, 0.0], [-3 * w * w, 0.0, 1.0], [-(w**3), 0.0, 0.0]]) * h
    aug[:3, 3] = np.array([3 * w, 3 * w * w, w**3]) * h
    e = expm(aug)
    return (*(float(x) for x in e[:3, :3].ravel()), *(float(x) for x in e[:3, 3]))


def axis_constants(limits: AxisLimits, dt_s: float) -> list[tuple[float, ...]]:  # 24 values
    """Per-axis constants of :func:`limit_axis`, precomputed once per (limits, rate)."""
    h = float(dt_s)
    track = _tracker(min(TRACKER_HZ, 0.2 / h), h)
    out: list[tuple[float, ...]] = []
    for i in range(limits.size):
        a = float(limits.a_max[i])
        ah = a * h
        ahc = CATCHUP_SHARE * ah  # catch-up braking plans with a share of the acceleration
        out.append((h, 1.0 / h, float(limits.p_min[i]), float(limits.p_max[i]),
                    float(limits.v_max[i]), ah, ah * ah, 2.0 * a, 1.0 / (2.0 * a),
                    ahc, ahc * ahc, 2.0 * CATCHUP_SHARE * a, *track))
    return out


Track = tuple[float, float, float, float, float]
"""The limiter's view of its target, per axis: the tracker's position, velocity and
acceleration, the target's last value, and the correction the tracker's velocity gets
(:func:`limit_axis`)."""


def at_rest(position: float, velocity: float = 0.0) -> Track:
    """The :data:`Track` of a target standing (or moving steadily) at ``position``."""
    return (position, velocity, 0.0, position, 0.0)


def limit_axis(target: float, u0: float, v0: float, track: Track, const: tuple[float, ...]
               ) -> tuple[float, float, Track, int]:
    """One sample of one axis: ``(u, v, track, flags)``.

    Parameters
    ----------
    target
        Desired position now; a non-finite target holds the last command.
    u0, v0
        Last emitted position and velocity.
    track
        The :data:`Track` of the previous sample (updated every sample).
    const
        The axis' constants from :func:`axis_constants`.

    Notes
    -----
    *Feasible* target (within the range, reachable with ``|v| <= v_max`` and ``|a| <= a_max``,
    leaving room to brake before the end stops): it is emitted bit-exactly.

    Otherwise the output aims at the target as at a wall moving with the target's velocity,
    and closes the gap no faster than allows stopping relative to that wall with
    :data:`CATCHUP_SHARE` of ``a_max`` (flag :data:`RECOVER`); then the hard bounds apply:
    position braking and velocity limit, and last the acceleration limit, which always wins.
    Once the gap is closed the target is feasible again and passes through exactly.

    The wall's velocity: the velocity a third-order tracker estimates (triple pole at
    :data:`TRACKER_HZ`; no lag for a target of constant acceleration) plus a correction that
    follows the target's own sample-to-sample velocity minus the tracker's.  The wall speeds
    up by at most the catch-up budget a sample (``CATCHUP_SHARE * a_max * h``) and slows down
    at once (to a stop, then by the budget beyond): a target that stops is a wall that stops.
    With its slowing down bounded too, the wall went on past a stopped target for up to 0.3 s
    and the output followed it (a 20 mm step rising in 0.1 s on the hexapod's 7 m/s^2: 62 %
    beyond the step, 10 % now: what the output cannot brake of its own speed).  On a smooth target
    the correction settles on the tracker's lag, so the wall moves exactly with the target,
    the gap closes and the target is caught again; on a rough one it moves by at most the
    budget per sample towards the median of the noise.  The tracker alone lags a smooth target
    with content up to 4 Hz by about 0.04 m/s: that held the output about 1 mm off it, limited,
    for 4 s after a stale-input episode; the cost, on targets rougher than any compensated
    command measured, is a rougher output (docs/IDENTIFICATION.md).

    Measured alternatives (rails limits; "jitter": the optimised compensator's command for the
    slalom with 50-150 us of input jitter, error against the jitter-free output): greedy
    clipping towards the raw target overshoots a step and oscillates for ever; the raw
    sample-to-sample velocity dithers on high-frequency content and loses the slow motion
    (0.3 m off a 0.3 m sine); a second-order smoothed velocity lags an accelerating target
    (6.8 mm peak, 1.6 mm rms with jitter); the tracker's: 0.7 mm peak, 0.2 mm rms.
    """
    (h, inv_h, p_min, p_max, v_max, ah, ah2, two_a, inv_two_a, ahc, ahc2, two_ac,
     f00, f01, f02, f10, f11, f12, f20, f21, f22, g0, g1, g2) = const
    if not isfinite(target):  # never propagated: hold the last command
        target = u0
    # a target beyond the range means "go to the end stop"; an axis left outside by narrowed
    # limits is driven back in
    if target > p_max:
        target = p_max
    elif target < p_min:
        target = p_min
    sp, sv, sa, tp, cv = track
    sp, sv, sa = (f00 * sp + f01 * sv + f02 * sa + g0 * target,
                  f10 * sp + f11 * sv + f12 * sa + g1 * target,
                  f20 * sp + f21 * sv + f22 * sa + g2 * target)
    w = sv + cv
    d = (target - tp) * inv_h - w  # the target's own velocity beyond the wall's
    # the wall speeds up by at most the budget a sample, and slows down at once (to a stop,
    # then by the budget beyond): a target that stops is a wall that stops
    lo = -ahc - w if w > 0.0 else -ahc
    hi = ahc - w if w < 0.0 else ahc
    cv += d if lo <= d <= hi else (hi if d > 0.0 else lo)
    track = (sp, sv, sa, target, cv)
    vel = (target - u0) * inv_h
    if v0 - ah <= vel <= v0 + ah and -v_max <= vel <= v_max and p_min <= u0 <= p_max and (
            vel * (h + vel * inv_two_a) <= p_max - u0 if vel > 0.0
            else -vel * (h - vel * inv_two_a) <= u0 - p_min):
        return target, vel, track, 0  # feasible: passes through bit-exactly
    fl = RECOVER
    # 1. the wall: the target moving at the tracker's velocity, corrected; it was at
    #    target - V h at the start of this step
    w = sv + cv
    v_t = w if -v_max <= w <= v_max else (v_max if w > 0.0 else -v_max)
    gap = target - v_t * h - u0
    if gap >= 0.0:
        vel = v_t + math.sqrt(ahc2 + two_ac * gap) - ahc
    else:
        vel = v_t + ahc - math.sqrt(ahc2 - two_ac * gap)
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
    if u0 > p_max or u0 < p_min:
        fl |= POS
    # 3. acceleration
    if vel > v0 + ah:
        vel = v0 + ah
        fl |= ACC
    elif vel < v0 - ah:
        vel = v0 - ah
        fl |= ACC
    u = u0 + vel * h
    # rounding guard only; an axis already outside (limits narrowed live) is not teleported
    if u > p_max and u0 <= p_max:
        u = p_max
    elif u < p_min and u0 >= p_min:
        u = p_min
    return u, (u - u0) * inv_h, track, fl


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
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
        self._axis_consts = axis_constants(limits, self.dt_s)
        self.u: list[float] = [0.0] * self.n
        self.v: list[float] = [0.0] * self.n
        self.track: list[Track] = [at_rest(0.0)] * self.n
        self.flags: list[int] = [0] * self.n
        self.reset(np.zeros(self.n) if position is None else position)

    def set_limits(self, limits: AxisLimits) -> None:
        """Swap limits (between two steps).  The state is kept; see the module docstring for an
        axis left outside the new range."""
        if limits.size != self.n:
            raise ConfigError(f"limits for {limits.size} axes, saturator has {self.n}")
        self._axis_consts = axis_constants(limits, self.dt_s)
        self.limits = limits

    def reset(self, position: ArrayLike, velocity: ArrayLike | None = None) -> None:
        """Set the state; ``position`` must be finite and within the limits."""
        p = check_position(self.limits, position)
        self.u = p.tolist()
        vel = np.zeros(self.n) if velocity is None else np.array(velocity, dtype=float)
        self.v = vel.tolist()
        self.track = [at_rest(pi, vi) for pi, vi in zip(self.u, self.v, strict=True)]
        self.flags = [0] * self.n

    def step(self, u_des: ArrayLike) -> list[float]:
        """Limit the desired positions (finite) and return the emitted ones."""
        target = np.asarray(u_des, dtype=float).tolist()
        out = [0.0] * self.n
        for i, const in enumerate(self._axis_consts):
            out[i], self.v[i], self.track[i], self.flags[i] = limit_axis(
                target[i], self.u[i], self.v[i], self.track[i], const)
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
