"""The minimum-jerk (quintic) blend, the one shape of every fade, ramp and blend in motcomp.

``s(x) = 10 x^3 - 15 x^4 + 6 x^5`` goes from 0 to 1 over ``x`` in [0, 1] with zero velocity
*and* acceleration at both ends, so a compensator that amplifies high frequencies sees no step
(a raised cosine has an acceleration step at its ends, which turns into a command spike).
Peak speed: ``1.875 * distance / duration``.

A blend that the compensator follows closely needs one more order: the pseudo open-loop PID
inverts the platform's lag, so its command carries about ``Tp1`` times the reference's jerk,
and the quintic's jerk steps (``60 D / T^3`` at both ends) become steps of the command's
acceleration (3-4 m/s^2 on the rails at the end of a start-up blend into a slalom).  The
minimum-snap septic ``m(x) = 35 x^4 - 84 x^5 + 70 x^6 - 20 x^7`` has zero velocity,
acceleration *and* jerk at both ends: the blends into live input use it.
"""

from __future__ import annotations

import math
from typing import Any, Final, overload

from numpy.typing import NDArray

__all__ = ["MIN_SNAP_ACC", "MIN_SNAP_MERGE", "PEAK_SPEED_FACTOR", "min_jerk",
           "min_jerk_rate", "min_jerk_weight", "min_snap", "min_snap_weight"]

PEAK_SPEED_FACTOR = 1.875
"""Peak of ``ds/dx``: a minimum-jerk move of ``distance`` over ``T`` peaks at 1.875 distance/T."""


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


def min_jerk_weight(progress: float) -> float:
    """1 -> 0 as ``progress`` goes 0 -> 1 (``1 - min_jerk``), clipped outside [0, 1]."""
    if progress >= 1.0:
        return 0.0
    if progress <= 0.0:
        return 1.0
    return 1.0 - min_jerk(progress)


def min_snap(x: float) -> float:
    """``35 x^4 - 84 x^5 + 70 x^6 - 20 x^7`` (not clipped)."""
    return x**4 * (35.0 + x * (-84.0 + x * (70.0 - 20.0 * x)))


def min_snap_weight(progress: float) -> float:
    """1 -> 0 as ``progress`` goes 0 -> 1 (``1 - min_snap``), clipped outside [0, 1]."""
    if progress >= 1.0:
        return 0.0
    if progress <= 0.0:
        return 1.0
    return 1.0 - min_snap(progress)


def _snap_acc_peak() -> float:
    # m'' = 420 x^2 (1 - x)^2 (1 - 2 x), extreme where 5 x^2 - 5 x + 1 = 0
    x = (5.0 - math.sqrt(5.0)) / 10.0
    return 420.0 * x * x * (1.0 - x) ** 2 * (1.0 - 2.0 * x)


def _snap_merge_peak() -> float:
    # x m'' + 2 m' = 140 x^3 (1 - x)^2 (5 - 8 x), extreme where 48 x^2 - 57 x + 15 = 0
    r = math.sqrt(57.0 * 57.0 - 4.0 * 48.0 * 15.0)
    return max(abs(140.0 * x**3 * (1.0 - x) ** 2 * (5.0 - 8.0 * x))
               for x in ((57.0 - r) / 96.0, (57.0 + r) / 96.0))


MIN_SNAP_ACC: Final = _snap_acc_peak()
"""``max |m''|`` (7.513): a gap ``g`` faded out over ``T`` by ``1 - m`` peaks at
``MIN_SNAP_ACC |g| / T^2``."""
MIN_SNAP_MERGE: Final = _snap_merge_peak()
"""``max |x m'' + 2 m'|`` (5.811): a velocity difference ``r`` faded out as ``r t (1 - m(t/T))``
peaks at ``MIN_SNAP_MERGE |r| / T`` of acceleration."""
