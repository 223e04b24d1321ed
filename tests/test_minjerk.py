"""The blend shapes of motcomp.core.minjerk against their polynomials (numpy's, apart)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.polynomial import Polynomial

from motcomp.core.minjerk import (
    MIN_SNAP_ACC,
    MIN_SNAP_MERGE,
    min_jerk,
    min_snap,
    min_snap_weight,
)

QUINTIC = Polynomial([0, 0, 0, 10, -15, 6])
SEPTIC = Polynomial([0, 0, 0, 0, 35, -84, 70, -20])
X = np.linspace(0.0, 1.0, 200_001)


def test_the_septic_rests_to_its_jerk_at_both_ends_and_the_quintic_does_not() -> None:
    """``m(0) = 0``, ``m(1) = 1``; its first three derivatives vanish at both ends; the quintic's
    third is 60 at both (the step a blend by it hands the compensator)."""
    for x in X[::1000]:
        assert min_snap(float(x)) == pytest.approx(SEPTIC(x), abs=1e-12)
        assert min_jerk(float(x)) == pytest.approx(QUINTIC(x), abs=1e-12)
    assert SEPTIC(0.0) == 0.0 and SEPTIC(1.0) == pytest.approx(1.0)
    for order in (1, 2, 3):
        d = SEPTIC.deriv(order)
        assert d(0.0) == 0.0 and d(1.0) == pytest.approx(0.0, abs=1e-9), order
    assert QUINTIC.deriv(3)(0.0) == 60.0 and QUINTIC.deriv(3)(1.0) == pytest.approx(60.0)


def test_the_weight_goes_from_one_to_zero_clipped() -> None:
    assert min_snap_weight(-0.5) == 1.0 and min_snap_weight(0.0) == 1.0
    assert min_snap_weight(1.0) == 0.0 and min_snap_weight(7.0) == 0.0
    assert min_snap_weight(0.5) == pytest.approx(0.5, abs=1e-15)  # odd about the middle
    w = np.array([min_snap_weight(float(x)) for x in X[::100]])
    assert np.all(np.diff(w) <= 0.0)


def test_the_peak_factors_are_the_polynomials_maxima() -> None:
    """``MIN_SNAP_ACC = max |m''|``, ``MIN_SNAP_MERGE = max |x m'' + 2 m'|`` over [0, 1] (the
    acceleration of ``g (1 - m)`` and of ``r t (1 - m(t / T))``, in units of g/T^2 and r/T)."""
    d1, d2 = SEPTIC.deriv(1), SEPTIC.deriv(2)
    acc, merge = np.max(np.abs(d2(X))), np.max(np.abs(X * d2(X) + 2.0 * d1(X)))
    assert abs(MIN_SNAP_ACC / acc - 1.0) < 1e-9, (MIN_SNAP_ACC, acc)
    assert abs(MIN_SNAP_MERGE / merge - 1.0) < 1e-9, (MIN_SNAP_MERGE, merge)
