"""The optimiser's fast evaluators against independent computations.

:class:`LoopGrid` against :func:`motcomp.design.frequency.evaluate` (polynomials, a 6400-point
grid); the batched pole modulus against :func:`motcomp.core.loop.stability` (``np.roots`` of the
polynomial products); the floors and perturbations against closed forms.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from motcomp.core.loop import stability
from motcomp.core.models import P1D, P2UZD
from motcomp.core.pid import PIDGains
from motcomp.core.tuning import tune
from motcomp.design.fastloop import LoopGrid
from motcomp.design.frequency import evaluate
from motcomp.design.optimal import Constraints, Uncertainty, _Problem, perturb
from motcomp.presets import load_preset
from tests.conftest import RAILS

HEXAPOD = load_preset("hexapod").model

DESIGNS = {
    "zn": tune("zn", RAILS).gains,
    "amigo": tune("amigo", RAILS).gains,
    "weighted": PIDGains(kp=8.19, ki=318.6, kd=0.075, tf=0.00376, b=1.115, c=2.30),
    "low-weight": PIDGains(kp=4.0, ki=120.0, kd=0.04, tf=0.005, b=0.6, c=0.3),
}


@pytest.mark.parametrize("rate_hz", [1000.0, 2000.0])
@pytest.mark.parametrize("name", sorted(DESIGNS))
def test_loopgrid_matches_evaluate(name: str, rate_hz: float) -> None:
    g = DESIGNS[name]
    grid = LoopGrid(RAILS, [RAILS], rate_hz)
    r = grid(g.kp, g.ki, g.kd, g.tf, g.b, g.c)
    ev = evaluate(g, RAILS, rate_hz=rate_hz)
    assert r.max_delay_ms()[0, 0] == pytest.approx(ev.max_residual_delay_ms, abs=0.03)
    assert float(np.max(r.gain_db)) == pytest.approx(ev.peak_gain_db, abs=0.05)
    assert float(np.max(np.abs(r.gain_db[0, 0, grid.band]))) == pytest.approx(
        ev.gain_error_db, abs=0.02)
    # |F| can peak sharply near Nyquist (ZN at 2 kHz): the optimiser re-checks it densely
    assert float(np.max(r.command)) == pytest.approx(ev.peak_command_gain, rel=0.02)
    assert float(np.max(r.sensitivity)) == pytest.approx(ev.ms, rel=0.01)
    # with P = M the command relative to the exact inverse is the delivered response itself
    np.testing.assert_allclose(r.excess_db[0], r.gain_db[0, 0, grid.band], atol=1e-9)


def test_loopgrid_with_a_mismatched_plant_and_many_designs_at_once() -> None:
    """Hexapod: P2UZD platform, P1D internal model; three designs in one call."""
    m = HEXAPOD.to_p1d()
    designs = [tune(rule, m).gains for rule in ("cc", "amigo", "simc")]
    designs[2] = PIDGains(designs[2].kp, designs[2].ki, 1e-4, 1e-3)  # the fast grid needs kd>=0
    grid = LoopGrid(m, [HEXAPOD, m], 1000.0)
    r = grid([g.kp for g in designs], [g.ki for g in designs], [g.kd for g in designs],
             [g.tf for g in designs])
    for i, g in enumerate(designs):
        for j, plant in enumerate((HEXAPOD, m)):
            ev = evaluate(g, m, plant, rate_hz=1000.0)
            assert r.max_delay_ms()[j, i] == pytest.approx(ev.max_residual_delay_ms, abs=0.05)
            assert float(np.max(r.gain_db[j, i])) == pytest.approx(ev.peak_gain_db, abs=0.05)


def test_batched_pole_modulus_matches_roots() -> None:
    problem = _Problem(LoopGrid(RAILS), Constraints(), True, 8.0, np.zeros(1), 1.0)
    gains = [*DESIGNS.values(), PIDGains(kp=60.0, ki=500.0, kd=0.2, tf=0.0005)]
    rho = problem.pole_modulus(*(np.array([getattr(g, k) for g in gains])
                                 for k in ("kp", "ki", "kd", "tf")))
    for g, r in zip(gains, rho, strict=True):
        _, expected = stability(g, RAILS, 1000.0)
        assert r == pytest.approx(expected, abs=1e-9)
    assert rho[-1] > 1.0  # the wild gain set is unstable, and seen as such


def test_floor_of_a_time_constant_error_is_the_closed_form() -> None:
    """P/M for a P1D with Tp1 20 % too large: tau(f) = (atan(1.2 w T) - atan(w T))/w exactly
    (same delay, the ZOH half-sample cancels); REFERENCE: ~35 ms at 0.2 Hz."""
    plant = P1D(1.0, RAILS.Td, 1.2 * RAILS.Tp1)
    grid = LoopGrid(RAILS, [plant], 1000.0, band_hz=(0.1, 2.0))
    w = grid.w_band
    expected = (np.arctan(1.2 * w * RAILS.Tp1) - np.arctan(w * RAILS.Tp1)) / w
    np.testing.assert_allclose(grid.floor_delay_s()[0], expected, atol=2e-5)
    i = int(np.argmin(np.abs(grid.f_band - 0.2)))
    assert grid.floor_delay_s()[0, i] * 1e3 == pytest.approx(35.0, abs=3.0)
    # a gain error only: no phase floor, a flat gain floor of 20 log10(1.1)
    grid = LoopGrid(RAILS, [P1D(1.1, RAILS.Td, RAILS.Tp1)], 1000.0)
    np.testing.assert_allclose(grid.floor_delay_s(), 0.0, atol=1e-9)
    np.testing.assert_allclose(grid.floor_gain_db(), 20 * math.log10(1.1), atol=1e-9)


def test_perturb_scales_time_and_gain() -> None:
    """A time scale a maps H(j w) to H(j a w) for the delay-free part, whatever the model."""
    f = np.array([0.3, 1.0, 4.0])
    for model in (RAILS, HEXAPOD, P2UZD(K=2.0, Td=0.01, Tz=0.02, Tp1=0.1, Tp2=0.03)):
        p = perturb(model, gain=1.1, dead_time_s=0.005, time_scale=1.2)
        assert p.pure_delay_s == pytest.approx(model.pure_delay_s + 0.005)
        lhs = p.freqresp(f) * np.exp(2j * np.pi * f * p.dead_time_s)
        rhs = 1.1 * model.freqresp(1.2 * f) * np.exp(2j * np.pi * 1.2 * f * model.dead_time_s)
        np.testing.assert_allclose(lhs, rhs, rtol=1e-12)


def test_uncertainty_members() -> None:
    members = Uncertainty().members(RAILS)
    assert len(members) == 27 and members[0] == ("nominal", RAILS)
    labels = [lab for lab, _ in members]
    assert len(set(labels)) == 27 and "K+10% Td-5ms T+20%" in labels
    extremes = {(m.K, m.Td, m.Tp1) for _, m in members}  # type: ignore[attr-defined]
    assert (pytest.approx(0.9), pytest.approx(0.0225), pytest.approx(0.8 * RAILS.Tp1)) in [
        (k, td, tp) for k, td, tp in extremes]
    assert len(Uncertainty(0.1, 0.0, 0.0).members(RAILS)) == 3
