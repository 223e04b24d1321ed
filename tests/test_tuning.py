"""Tuning rules against hand-computed values (formulas of REFERENCE.md / the paper)."""

from __future__ import annotations

import math

import pytest

from motcomp.core.models import P1D
from motcomp.core.pid import PIDGains
from motcomp.core.tuning import check_lag, standard_form, tune
from motcomp.errors import ConfigError

# plant A: K=2, Td=0.02, Tp1=0.3 -- values worked out by hand
#   ZN:    Kc = 1.2*0.3/(2*0.02) = 9,  Ti = 0.04, Td = 0.01
#   CC:    Kc = 0.5*15*(4/3 + 1/60) = 10.125, Ti = 0.02*32.4/13.5333.. = 0.0478817734,
#          Td = 0.08/11.1333.. = 0.0071856287
#   AMIGO: Kc = (0.2 + 6.75)/2 = 3.475, Ti = 0.02*0.248/0.05 = 0.0992,
#          Td = 0.003/0.306 = 0.0098039216
#   SIMC:  Kc = 0.3/(2*0.04) = 3.75, Ti = min(0.3, 0.16) = 0.16
PLANT_A = P1D(K=2.0, Td=0.02, Tp1=0.3)
HAND_A = {
    "zn": (9.0, 225.0, 0.09),
    "cc": (10.125, 211.458333333, 0.072754491018),
    "amigo": (3.475, 35.030241935, 0.034068627451),
    "simc": (3.75, 23.4375, 0.0),
}
# plant B: the rails preset (K=1, Td=17.5 ms, Tp1=185.77 ms)
PLANT_B = P1D(K=1.0, Td=0.0175, Tp1=0.1857683128)
HAND_B = {
    "zn": (12.738398592, 363.954245486, 0.11146098768),
    "cc": (14.403776213, 347.617424000, 0.090116882541),
    "amigo": (4.976899472, 65.932375637, 0.042350988698),
    "simc": (5.30766608, 37.911900571, 0.0),
}


@pytest.mark.parametrize(("plant", "hand"), [(PLANT_A, HAND_A), (PLANT_B, HAND_B)])
@pytest.mark.parametrize("rule", ["zn", "cc", "amigo", "simc"])
def test_gains_equal_hand_computed(plant: P1D, hand: dict, rule: str) -> None:
    g = tune(rule, plant).gains
    kp, ki, kd = hand[rule]
    assert g.kp == pytest.approx(kp, rel=1e-9)
    assert g.ki == pytest.approx(ki, rel=1e-9)
    assert g.kd == pytest.approx(kd, rel=1e-9, abs=1e-15)


def test_zn_matches_the_papers_parallel_wording() -> None:
    # paper: Kp = 1.2 Tp1/(K Td), "Ti = 2 Td / Kp" (i.e. ki = Kp/(2 Td)), "Td = 0.5 Td Kp" (= kd)
    g = tune("zn", PLANT_A).gains
    kp = 1.2 * 0.3 / (2 * 0.02)
    assert g.ki == pytest.approx(kp / (2 * 0.02))
    assert g.kd == pytest.approx(0.5 * 0.02 * kp)


def test_derivative_filter_is_td_over_n() -> None:
    t = tune("zn", PLANT_A, filter_n=8.0)
    assert t.gains.tf == pytest.approx(0.01 / 8.0)
    assert tune("simc", PLANT_A).gains.tf == 0.0


def test_standard_parallel_round_trip() -> None:
    g = PIDGains.from_standard(Kc=3.0, Ti=0.5, Td=0.02, N=10)
    assert (g.kp, g.ki, g.kd) == pytest.approx((3.0, 6.0, 0.06))
    assert g.tf == pytest.approx(0.002)
    std = g.to_standard()
    assert std == pytest.approx({"Kc": 3.0, "Ti": 0.5, "Td": 0.02, "N": 10.0})
    pi = PIDGains.from_standard(Kc=2.0)
    assert pi.ki == 0 and math.isinf(pi.to_standard()["Ti"])


@pytest.mark.parametrize("bad", [dict(kp=-1.0), dict(kp=1.0, ki=math.nan), dict(kp=1.0, tf=-0.1)])
def test_invalid_gains_rejected(bad: dict) -> None:
    with pytest.raises(ConfigError, match="PID gain"):
        PIDGains(**bad)


def test_hexapod_case_warns_loudly() -> None:
    hexapod = P1D(K=1.0, Td=0.0325, Tp1=0.0025)
    for rule in ("zn", "cc"):
        t = tune(rule, hexapod)
        assert any("lag-dominated" in w and "MORE" in w for w in t.warnings), t.warnings
        # and the residual lag 1/(K ki) is indeed far worse than the plant's own 35 ms
        assert 1.0 / t.gains.ki > 2 * (hexapod.Td + hexapod.Tp1)
    assert tune("zn", PLANT_B).warnings == []


def test_check_lag() -> None:
    assert check_lag(PIDGains(kp=1.0, ki=1.0), PLANT_B) is not None  # 1 s residual lag
    assert check_lag(PIDGains(kp=1.0, ki=1000.0), PLANT_B) is None


def test_rules_need_dead_time_and_known_name() -> None:
    with pytest.raises(ConfigError, match="dead time"):
        standard_form("zn", P1D(K=1.0, Td=0.0, Tp1=0.1))
    with pytest.raises(ConfigError, match="unknown tuning rule"):
        tune("foo", PLANT_A)
