"""Process models against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from motcomp.core.lti import expm
from motcomp.core.models import OE, P1D, P2D, P2UZD, format_model, pade, parse_model
from motcomp.errors import ConfigError
from motcomp.presets import load_preset

F = np.array([0.05, 0.2, 0.5, 1.0, 2.0, 5.0, 20.0])


@pytest.mark.parametrize(("K", "Td", "Tp1"), [(1.0, 0.0175, 0.1857683128), (2.5, 0.03, 0.004),
                                              (0.8, 0.0, 0.05)])
def test_p1d_closed_forms(K: float, Td: float, Tp1: float) -> None:
    m = P1D(K=K, Td=Td, Tp1=Tp1)
    w = 2 * math.pi * F
    np.testing.assert_allclose(m.phase_delay(F), Td + np.arctan(w * Tp1) / w, rtol=1e-12)
    np.testing.assert_allclose(m.magnitude(F), K / np.sqrt(1 + (w * Tp1) ** 2), rtol=1e-12)
    np.testing.assert_allclose(m.group_delay(F), Td + Tp1 / (1 + (w * Tp1) ** 2), rtol=1e-12)
    assert m.bandwidth(-3) == pytest.approx(1 / (2 * math.pi * Tp1), rel=1e-9)
    assert m.bandwidth(-6) == pytest.approx(math.sqrt(3) / (2 * math.pi * Tp1), rel=1e-9)
    assert m.gain == K


def test_group_delay_is_derivative_of_phase() -> None:
    m = P2UZD(K=1.0, Td=0.02, Tz=0.05, Tw=0.04, Zeta=0.3)
    f = np.array([0.3, 1.0, 3.0])
    df = 1e-6
    num = -(m.phase(f + df) - m.phase(f - df)) / (2 * math.pi * 2 * df)
    np.testing.assert_allclose(m.group_delay(f), num, rtol=1e-6)


def test_step_responses_closed_forms() -> None:
    t = np.linspace(0, 1, 101)
    p1 = P1D(K=2.0, Td=0.03, Tp1=0.2)
    np.testing.assert_allclose(p1.step(t), np.where(t >= 0.03, 2 * (1 - np.exp(-(t - 0.03) / 0.2)),
                                                    0.0), atol=1e-12)
    T1, T2 = 0.2, 0.05
    p2 = P2D(K=1.5, Td=0.01, Tp1=T1, Tp2=T2)
    tt = np.clip(t - 0.01, 0, None)
    ref = 1.5 * (1 - (T1 * np.exp(-tt / T1) - T2 * np.exp(-tt / T2)) / (T1 - T2))
    np.testing.assert_allclose(p2.step(t), np.where(t >= 0.01, ref, 0.0), atol=1e-12)
    # underdamped second order, no zero: 1 - e^{-z wn t}(cos wd t + z/sqrt(1-z^2) sin wd t)
    Tw, z = 0.05, 0.3
    wn = 1 / Tw
    wd = wn * math.sqrt(1 - z * z)
    u = P2UZD(K=1.0, Td=0.0, Tz=0.0, Tw=Tw, Zeta=z)
    ref = 1 - np.exp(-z * wn * t) * (np.cos(wd * t) + z / math.sqrt(1 - z * z) * np.sin(wd * t))
    np.testing.assert_allclose(u.step(t), ref, atol=1e-12)


@pytest.mark.parametrize("Td", [0.0, 0.0004, 0.001, 0.0175, 0.0325, 0.02, 0.0203])
@pytest.mark.parametrize("rate", [1000.0, 500.0])
def test_discretisation_matches_continuous_step_at_samples(Td: float, rate: float) -> None:
    for m in (P1D(K=1.3, Td=Td, Tp1=0.12), P2D(K=1.0, Td=Td, Tp1=0.05, Tp2=0.01),
              P2UZD(K=1.0, Td=Td, Tz=0.02, Tw=0.03, Zeta=0.4)):
        d = m.discretize(rate)
        n = 300
        y = d.simulate(np.ones(n), u_before=0.0)
        t = np.arange(n) / rate
        np.testing.assert_allclose(y, m.step(t), atol=1e-12, err_msg=f"{m} at {rate} Hz")


def test_discrete_tf_freqresp_and_simulation_agree() -> None:
    m = P2UZD(K=1.0, Td=0.0123, Tz=0.02, Tw=0.03, Zeta=0.4)
    d = m.discretize(1000.0)
    num, den = d.tf()
    f = np.array([0.3, 3.0, 30.0])
    z = np.exp(2j * np.pi * f / 1000.0)
    np.testing.assert_allclose(np.polyval(num, z) / np.polyval(den, z), d.freqresp(f), rtol=1e-9)
    # a sine through the simulation has the gain and phase of the frequency response
    fs = 2.0
    k = np.arange(20000)
    y = d.simulate(np.sin(2 * np.pi * fs * k / 1000.0))
    tail = slice(10000, None)
    ph = 2 * np.pi * fs * k / 1000.0
    basis = np.column_stack([np.sin(ph), np.cos(ph)])
    a, b = np.linalg.lstsq(basis[tail], y[tail], rcond=None)[0]
    assert complex(a, b) * -1j * 1j == pytest.approx(complex(a, b))
    resp = d.freqresp(fs)[0]
    assert abs(complex(a, b)) == pytest.approx(abs(resp), rel=1e-8)
    assert math.atan2(b, a) == pytest.approx(np.angle(resp), abs=1e-8)


def test_expm_against_closed_forms() -> None:
    np.testing.assert_allclose(expm(np.diag([1.0, -2.0])), np.diag([math.e, math.exp(-2)]))
    th = 3.0
    rot = expm(np.array([[0.0, -th], [th, 0.0]]))
    np.testing.assert_allclose(rot, [[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]],
                               atol=1e-13)
    big = expm(np.array([[-50.0, 1.0], [0.0, -50.0]]))
    np.testing.assert_allclose(big, math.exp(-50) * np.array([[1.0, 1.0], [0.0, 1.0]]), rtol=1e-9)


def test_pade_coefficients() -> None:
    num, den = pade(0.1, 1)
    np.testing.assert_allclose(num, [-0.05, 1.0])
    np.testing.assert_allclose(den, [0.05, 1.0])
    num, den = pade(0.1, 2)  # (1 - Ts/2 + T^2 s^2/12)/(1 + Ts/2 + T^2 s^2/12)
    np.testing.assert_allclose(den, [0.01 / 12, 0.05, 1.0])
    np.testing.assert_allclose(num, [0.01 / 12, -0.05, 1.0])


def test_oe_with_pade_approximates_p1d() -> None:
    p = P1D(K=1.0, Td=0.0175, Tp1=0.1857683128)
    exact = OE(num=(1.0,), den=(0.1857683128, 1.0), Td=0.0175, pade_order=0)
    np.testing.assert_allclose(exact.phase_delay(F), p.phase_delay(F), rtol=1e-12)
    approx = OE(num=(1.0,), den=(0.1857683128, 1.0), Td=0.0175, pade_order=1)
    # first-order Pade: within 0.1 ms up to 2 Hz, 0.5 ms at 5 Hz
    np.testing.assert_allclose(approx.phase_delay(F[:5]), p.phase_delay(F[:5]), atol=1e-4)
    assert approx.phase_delay(5.0)[0] == pytest.approx(p.phase_delay(5.0)[0], abs=5e-4)
    assert approx.pure_delay_s == 0.0175 and approx.dead_time_s == 0.0


def test_spec_round_trip_and_errors() -> None:
    for spec in ("p1d:K=1,Td=0.0175,Tp1=0.1858", "p2d:K=1,Td=0.03,Tp1=0.02,Tp2=0.005",
                 "p2uzd:K=1,Td=0.0325,Tw=0.03,Zeta=0.7,Tz=0.02",
                 "p2uzd:K=1,Td=0.01,Tp1=0.1,Tp2=0.02,Tz=-0.01",
                 "oe:num=[1,2],den=[0.01,0.3,1],Td=0.03,pade=2"):
        m = parse_model(spec)
        assert parse_model(format_model(m)) == m
    assert parse_model("P2DZU:K=1,Td=0.01,Tw=0.05,Zeta=0.5,Tz=0").kind == "p2uzd"
    cases = {
        "p1d:K=1,Td=0.01": "missing parameter.*Tp1",
        "p1d:K=1,Td=0.01,Tp1=-2": "Tp1 must be finite and > 0, got -2",
        "p1d:K=1,Td=x,Tp1=2": "Td='x' is not a number",
        "p9d:K=1": "unknown kind 'p9d'",
        "p1d:K=1,Td=0.01,Tp1=0.1,Tz=1": "unknown parameter.*Tz",
        "p1d K=1": "not of the form",
        "p1d:K=1,Td=nan,Tp1=0.1": "not finite",
        "p2uzd:K=1,Td=0.01,Tz=0,Tp1=0.1,Tw=0.1,Zeta=1": "not both",
    }
    for spec, msg in cases.items():
        with pytest.raises(ConfigError, match=msg):
            parse_model(spec)


def test_to_p1d_matches_phase_delay_at_reference() -> None:
    h = P2UZD(K=1.0, Td=0.0325, Tz=0.0876, Tw=0.064, Zeta=0.7)
    p = h.to_p1d()
    assert p.Td == h.Td
    assert p.phase_delay(0.2)[0] == pytest.approx(h.phase_delay(0.2)[0], rel=1e-12)


def test_rails_preset_reproduces_table_1() -> None:
    rails = load_preset("rails")
    assert isinstance(rails.model, P1D)
    assert rails.model.phase_delay(0.2)[0] == pytest.approx(0.200, abs=0.5e-3)
    assert 0.015 <= rails.model.Td <= 0.020
    assert rails.model.bandwidth(-6) == pytest.approx(1.48, abs=0.01)


def test_hexapod_preset_meets_all_three_numbers_of_table_1() -> None:
    hexapod = load_preset("hexapod").model
    assert 0.030 <= hexapod.pure_delay_s <= 0.035
    assert hexapod.phase_delay(0.2)[0] == pytest.approx(0.035, abs=1e-6)
    assert hexapod.bandwidth(-6) == pytest.approx(7.0, abs=1e-6)
    # and no P1D can: 35 ms at 0.2 Hz with Td = 32.5 ms puts the -6 dB point above 100 Hz
    assert hexapod.to_p1d().bandwidth(-6) > 100
