"""The minimum-jerk (quintic) move, the shape of every fade and ramp in motcomp (the blends into
live input need one more order: :mod:`motcomp.core.blend`).

``s(x) = 10 x^3 - 15 x^4 + 6 x^5`` goes from 0 to 1 over ``x`` in [0, 1] with zero velocity
*and* acceleration at both ends, so a compensator that amplifies high frequencies sees no step
(a raised cosine has an acceleration step at its ends, which turns into a command spike).
Peak speed: ``1.875 * distance / duration``.
"""

from __future__ import annotations

import math
from typing import Any, overload

from numpy.typing import NDArray

__all__ = ["PEAK_ACC_FACTOR", "PEAK_DEPART_FACTOR", "PEAK_SPEED_FACTOR", "min_jerk",
           "min_jerk_between", "min_jerk_derivatives", "min_jerk_rate", "min_jerk_weight",
           "move_duration"]

PEAK_SPEED_FACTOR = 1.875
"""Peak of ``ds/dx``: a minimum-jerk move of ``distance`` over ``T`` peaks at 1.875 distance/T."""
PEAK_ACC_FACTOR = 10.0 / 3.0 ** 0.5
"""Peak of ``|d2s/dx2|`` (at ``x = (3 -+ sqrt 3) / 6``): 5.77 distance/T^2."""
_X_DEPART = (15.0 - 33.0 ** 0.5) / 24.0
PEAK_DEPART_FACTOR = 120.0 * _X_DEPART**2 - 300.0 * _X_DEPART**3 + 180.0 * _X_DEPART**4
"""Peak of ``|d2(x s)/dx2| = |120 x^2 - 300 x^3 + 180 x^4|`` (at ``x = (15 - sqrt 33) / 24``):
a weight ``s`` moving onto a path that departs at ``rate`` adds up to 4.62 rate/T."""


@overload
def min_jerk(x: float) -> float: ...
@overload
def min_jerk(x: NDArray[Any]) -> NDArray[Any]: ...
def min_jerk(x: Any) -> Any:
    """``10 x^3 - 15 x^4 + 6 x^5`` for a float or a numpy array ``x`` (not clipped)."""
    return x**3 * (10.0 - 15.0 * x + 6.0 * x * x)


def min_jerk_rate(x: float) -> float:
    """``d/dx`` of :func:`min_jerk`: ``30 x^2 (1 - x)^2``."""
    return 30.0 * x * x * (1.0 - x) ** 2


def min_jerk_derivatives(x: float) -> tuple[float, float, float]:
    """The first three derivatives of :func:`min_jerk` at ``x``: ``30 x^2 (1 - x)^2``,
    ``60 x (1 - x) (1 - 2 x)``, ``60 (1 - 6 x + 6 x^2)``."""
    return (min_jerk_rate(x), 60.0 * x * (1.0 - x) * (1.0 - 2.0 * x),
            60.0 * (1.0 - 6.0 * x + 6.0 * x * x))


def min_jerk_between(start: float, end: float, progress: float) -> float:
    """From ``start`` to ``end`` along :func:`min_jerk` at ``progress`` (in [0, 1]): a weight
    moved without a step of its rate or acceleration."""
    return start + (end - start) * min_jerk(progress)


def min_jerk_weight(progress: float) -> float:
    """1 -> 0 as ``progress`` goes 0 -> 1 (``1 - min_jerk``), clipped outside [0, 1]."""
    if progress >= 1.0:
        return 0.0
    if progress <= 0.0:
        return 1.0
    return 1.0 - min_jerk(progress)


def move_duration(distance: float, speed: float, acc: float = 0.0, min_s: float = 0.05) -> float:
    """The shortest minimum-jerk move over ``distance`` (at least ``min_s``) whose peak speed
    is at most ``speed`` (no bound for ``speed <= 0``) and peak acceleration at most ``acc``
    (no bound for ``acc <= 0``)."""
    d = min_s
    if speed > 0.0:
        d = max(d, PEAK_SPEED_FACTOR * abs(distance) / speed)
    if acc > 0.0:
        d = max(d, math.sqrt(PEAK_ACC_FACTOR * abs(distance) / acc))
    return d
