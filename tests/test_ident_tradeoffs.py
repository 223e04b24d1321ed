"""Parameters the data do not tell apart, from the estimates' covariance (closed forms), and the
delay convention of Table 1."""

from __future__ import annotations

import math

import numpy as np
import pytest

from motcomp.ident.fit import TRADEOFF_CORRELATION, _tradeoffs


def _cov(sd: list[float], corr: dict[tuple[int, int], float]) -> np.ndarray:
    c = np.diag(np.square(sd))
    for (i, j), r in corr.items():
        c[i, j] = c[j, i] = r * sd[i] * sd[j]
    return c


def test_a_delay_and_a_zero_that_move_together_fix_their_difference() -> None:
    names = ["K", "Td", "Tp1", "Tz"]
    values = np.array([1.0, 0.030, 0.150, 0.010])
    sd = [0.01, 10.0, 0.002, 10.0]  # Td and Tz: 10 s each, as a degenerate fit reports
    cov = _cov(sd, {(1, 3): 0.9999995})
    (t,) = _tradeoffs(names, values, cov)
    assert t["params"] == ["Td", "Tz"] and t["identified"] == "Td - Tz"
    assert t["value_ms"] == pytest.approx(20.0)
    # var(Td - Tz) = 2 s^2 (1 - r): 10 s each, r = 1 - 5e-7 -> 10 mms
    assert t["stderr_ms"] == pytest.approx(math.sqrt(2 * 100 * 5e-7) * 1e3, rel=1e-3)


def test_two_equal_poles_moving_against_each_other_fix_their_sum() -> None:
    names = ["K", "Td", "Tp1", "Tp2"]
    values = np.array([1.0, 0.02, 0.08, 0.07])
    cov = _cov([0.01, 0.001, 0.4, 0.4], {(2, 3): -0.999})
    (t,) = _tradeoffs(names, values, cov)
    assert t["identified"] == "Tp1 + Tp2" and t["value_ms"] == pytest.approx(150.0)
    assert t["stderr_ms"] == pytest.approx(math.sqrt(2 * 0.16 * 0.001) * 1e3, rel=1e-6)


def test_weak_correlations_and_mixed_kinds() -> None:
    names = ["K", "Td", "Tp1"]
    values = np.array([1.0, 0.02, 0.15])
    below = TRADEOFF_CORRELATION - 0.01
    assert _tradeoffs(names, values, _cov([0.01, 0.001, 0.002], {(1, 2): below})) == []
    (t,) = _tradeoffs(names, values, _cov([0.01, 0.001, 0.002], {(0, 1): -0.995}))
    assert t["params"] == ["K", "Td"] and "identified" not in t  # a gain and a time: no sum
    assert t["correlation"] == pytest.approx(-0.995)


def test_a_group_of_three_is_named_without_a_combination() -> None:
    names = ["b0", "a1", "a0", "Td"]
    cov = _cov([1.0, 1.0, 1.0, 0.001], {(0, 1): 0.999, (1, 2): 0.999, (0, 2): 0.998})
    (t,) = _tradeoffs(names, np.ones(4), cov)
    assert t["params"] == ["b0", "a1", "a0"] and "identified" not in t


def test_warnings_follow_from_the_data() -> None:
    """The phase-delay advice reads where the command's motion starts; only lines in the
    tremor band are called tremor."""
    from types import SimpleNamespace

    from motcomp.ident.fit import _warnings, lowest_motion_hz
    from motcomp.ident.report import _line_name

    rate = 1000.0
    t = np.arange(int(120 * rate)) / rate
    with_slow = 0.1 * np.sin(2 * np.pi * 0.16 * t) + 0.02 * np.sin(2 * np.pi * 2.0 * t)
    fast_only = sum(0.02 * np.sin(2 * np.pi * f * t) for f in (0.5, 1.0, 2.0, 4.0))
    assert lowest_motion_hz(with_slow, rate) == pytest.approx(0.16, abs=0.05)
    assert lowest_motion_hz(fast_only, rate) == pytest.approx(0.5, abs=0.05)
    assert lowest_motion_hz(np.zeros(30_000), rate) is None

    def warn(cmd: np.ndarray) -> str:
        prep = SimpleNamespace(rate_hz=rate, recording=SimpleNamespace(cmd=cmd,
                                                                       period_jitter_s=0.0))
        fit = SimpleNamespace(model=SimpleNamespace(gain=1.0), kind="p1d", at_bounds=[],
                              table1={"phase_delay_0p2hz_ms_stderr": 12.0})
        (w,) = _warnings(prep, fit)  # type: ignore[arg-type]
        return str(w)

    assert "although the command moves from 0.1" in warn(with_slow)
    assert "excite" not in warn(with_slow)
    text = warn(fast_only)
    assert "its motion starts at 0.4" in text and "--f-min 0.1" in text
    assert "multisine" not in text
    assert _line_name(14.0) == "14.00 Hz (tremor)" and _line_name(100.0) == "100.00 Hz"
