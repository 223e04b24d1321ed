"""The optimised tuning: the numbers it promises, checked independently.

Every design is re-evaluated here with :func:`motcomp.design.frequency.evaluate` (dense grid,
poles) or simulated through the real :class:`~motcomp.core.compensator.Compensator` with its
limiter; nothing is taken from the optimiser's own report.
"""

from __future__ import annotations

import numpy as np
import pytest

from motcomp.core.loop import stability
from motcomp.core.tuning import tune
from motcomp.design.fastloop import LoopGrid
from motcomp.design.frequency import evaluate
from motcomp.design.optimal import (
    GAIN_RTOL,
    Constraints,
    OptimalDesign,
    Uncertainty,
    optimise,
)
from motcomp.design.timedomain import simulate_compensated, slalom, swept_sine
from motcomp.errors import ConfigError
from motcomp.presets import load_preset
from tests.conftest import RAILS

ZN = tune("zn", RAILS).gains
RAILS_LIMITS = load_preset("rails").axis_limits("rails_y")


@pytest.fixture(scope="module")
def nominal() -> OptimalDesign:
    return optimise(RAILS, rate_hz=1000.0)


@pytest.fixture(scope="module")
def robust() -> OptimalDesign:
    return optimise(RAILS, rate_hz=1000.0, uncertainty=Uncertainty())


def test_rails_nominal_beats_zn_on_both_axes(nominal: OptimalDesign) -> None:
    ev = evaluate(nominal.gains, RAILS, rate_hz=1000.0)
    zn = evaluate(ZN, RAILS, rate_hz=1000.0)
    # the targets: <= 3 ms, <= 8 dB, <= 1 dB in band; ZN: 4.08 ms, +11.6 dB
    assert ev.max_residual_delay_ms <= 3.0
    assert ev.peak_gain_db <= 8.0 + 0.02
    assert ev.gain_error_db <= 1.0
    assert ev.max_residual_delay_ms < zn.max_residual_delay_ms - 1.0
    assert ev.peak_gain_db < zn.peak_gain_db - 3.0
    # measured: 0.18 ms at +8.0 dB, 0.50 dB in band, |F| <= 60 (ZN: 130)
    assert ev.max_residual_delay_ms == pytest.approx(0.18, abs=0.1)
    assert ev.peak_command_gain <= 60.0 * 1.002 < zn.peak_command_gain
    assert ev.stable and stability(nominal.gains, RAILS, 1000.0)[1] < 1.0 - 1e-4
    assert nominal.feasible and not nominal.recommend_bypass and not nominal.violations


def test_command_excess_bound_holds_in_band(nominal: OptimalDesign) -> None:
    """|F M| <= +0.5 dB in the band, i.e. the command is at most 6 % above the exact inverse
    r/M, computed here from the model's closed-form response and the delivered response."""
    ev_grid = np.geomspace(0.1, 2.0, 300)
    from motcomp.design.frequency import loop_response

    resp = loop_response(nominal.gains, RAILS, RAILS, np.concatenate(
        [np.geomspace(1e-3, 0.09, 50), ev_grid]), 1000.0)
    f_m = resp.command[50:] * RAILS.freqresp(ev_grid)  # continuous M: within 0.01 dB here
    assert float(np.max(20 * np.log10(np.abs(f_m)))) <= 0.5 + 0.03


def test_deterministic(nominal: OptimalDesign) -> None:
    again = optimise(RAILS, rate_hz=1000.0)
    for name in ("kp", "ki", "kd", "tf", "b", "c"):
        assert getattr(again.gains, name) == pytest.approx(getattr(nominal.gains, name),
                                                           rel=GAIN_RTOL), name


def test_setpoint_weights_are_the_extra_degree_of_freedom_for_6db() -> None:
    """<= 3 ms at <= 6 dB: reached with the setpoint weights, not with a plain PID."""
    c = Constraints(peak_db=6.0)
    weighted = optimise(RAILS, constraints=c)
    ev = evaluate(weighted.gains, RAILS, rate_hz=1000.0)
    assert ev.max_residual_delay_ms <= 3.0 and ev.peak_gain_db <= 6.02
    assert weighted.gains.c != 1.0
    plain = optimise(RAILS, constraints=c, setpoint_weights=False)
    assert plain.gains.b == plain.gains.c == 1.0
    assert evaluate(plain.gains, RAILS, rate_hz=1000.0).max_residual_delay_ms > 3.0


def test_robust_peak_for_every_member_and_excess_over_floor(robust: OptimalDesign) -> None:
    members = Uncertainty().members(RAILS)
    grid = LoopGrid(RAILS, [p for _, p in members], 1000.0, n_band=400, n_high=10)
    floors = np.max(np.abs(grid.floor_delay_s()), axis=1) * 1e3
    for (label, plant), floor in zip(members, floors, strict=True):
        ev = evaluate(robust.gains, RAILS, plant, rate_hz=1000.0)
        assert ev.peak_gain_db <= 8.0 + 0.02, label
        assert ev.max_residual_delay_ms <= floor + 2.0, label
    # the floor of the Tp1 +20 % member near 0.2 Hz is the ~35 ms of REFERENCE; the worst
    # floors (Td and Tp1 both off) exceed 40 ms whatever the gains
    assert max(floors) > 40.0
    table = {m.label: m for m in robust.members}
    assert table["T+20%"].floor_ms == pytest.approx(37.0, abs=3.0)
    assert all(m.zn_residual_ms is not None for m in robust.members)
    # ZN over-amplifies more than 11 dB on the fastest member, the robust design stays <= 8
    assert max(m.zn_peak_gain_db or 0.0 for m in robust.members) > 11.0
    assert max(m.peak_gain_db for m in robust.members) <= 8.02


def _saturated_samples(gains: object, f1_hz: float) -> tuple[int, float]:
    amp = 0.8 * min(2.6, 2.0 / (2 * np.pi * f1_hz), 6.0 / (2 * np.pi * f1_hz) ** 2)
    _, r = swept_sine(1000.0, 0.1, f1_hz, 60.0, amp)
    res = simulate_compensated(r, gains, RAILS, None, RAILS_LIMITS, 1000.0)  # type: ignore[arg-type]
    return res.saturated_samples_on, res.delay_on_s


@pytest.mark.slow
def test_time_domain_slalom_and_sweeps_with_saturation(nominal: OptimalDesign) -> None:
    _, r = slalom(1000.0)
    res = simulate_compensated(r, nominal.gains, RAILS, None, RAILS_LIMITS, 1000.0)
    assert res.reduction_s >= 0.190  # measured 195.1 ms (ZN: 192.4 ms)
    assert res.saturated_samples_on == 0
    # the `motcomp evaluate` sweep (0.1-3 Hz at 80 % of the plain limits) and a 0.1-2 Hz one:
    # every compensator saturates the acceleration limit there; no more than ZN does
    for f1 in (2.0, 3.0):
        sat_opt, delay_opt = _saturated_samples(nominal.gains, f1)
        sat_zn, delay_zn = _saturated_samples(ZN, f1)
        assert sat_opt <= sat_zn, f1
        assert delay_opt < delay_zn, f1


def test_hexapod_reports_the_bound_and_does_no_harm() -> None:
    hexapod = load_preset("hexapod").model
    d = optimise(hexapod)
    ev = evaluate(d.gains, hexapod.to_p1d(), hexapod, rate_hz=1000.0)
    assert d.delay_dominated and d.recommend_bypass
    assert any("delay-dominated" in w and "bypass" in w for w in d.warnings)
    # no harm: neither more delay nor more in-band gain error than the platform alone
    assert ev.max_residual_delay_ms <= ev.uncorrected_max_delay_ms
    assert ev.gain_error_db <= ev.uncorrected_gain_error_db + 0.02
    assert ev.peak_gain_db <= 8.02 and ev.stable
    assert d.uncompensated_delay_ms == pytest.approx(ev.uncorrected_max_delay_ms, abs=0.1)
    assert d.best_gain_ms == pytest.approx(
        ev.uncorrected_max_delay_ms - ev.max_residual_delay_ms, abs=0.1)


def test_hexapod_design_meets_its_bounds_and_a_looser_bound_is_never_worse() -> None:
    """The regression of issue 16: at +8 dB the optimiser returned "no design meets every
    bound" (67.5 to 48.2 ms) while +3 dB found 25.6 ms.  Now both are feasible, the looser bound
    is at least as good as the tighter one, and both still recommend bypass (the gain is
    prediction of a pure delay)."""
    hexapod = load_preset("hexapod").model
    loose = optimise(hexapod, constraints=Constraints(peak_db=8.0))
    tight = optimise(hexapod, constraints=Constraints(peak_db=3.0))
    for d, bound in ((loose, 8.0), (tight, 3.0)):
        assert d.feasible, d.violations
        assert d.evaluation.peak_gain_db <= bound + 0.02 and d.evaluation.stable
        assert d.recommend_bypass
    res_loose = loose.evaluation.max_residual_delay_ms
    res_tight = tight.evaluation.max_residual_delay_ms
    assert res_loose <= res_tight + 0.01
    assert res_loose < 10.0 and res_tight < 25.6  # 0.35 / 15.7 ms when measured


def test_hf_command_gain_bound_holds_and_costs_delay() -> None:
    """``hf_command_gain`` bounds |F| above 10 Hz on a dense grid; tighter costs delay."""
    rails = RAILS
    d25 = optimise(rails, constraints=Constraints(hf_command_gain=25.0))
    d10 = optimise(rails, constraints=Constraints(hf_command_gain=10.0))
    for d, g in ((d25, 25.0), (d10, 10.0)):
        assert d.feasible, d.violations
        assert d.evaluation.hf_command_gain <= g * 1.002
    assert (d25.evaluation.max_residual_delay_ms
            < d10.evaluation.max_residual_delay_ms)  # 2.0 < 14.2 ms when measured


def test_bad_bounds_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="gain_error_db"):
        Constraints(gain_error_db=0.0)
    with pytest.raises(ConfigError, match="band"):
        Constraints(band_hz=(2.0, 0.1))
    with pytest.raises(ConfigError, match="max_command_gain"):
        Constraints(max_command_gain=float("nan"))
    with pytest.raises(ConfigError, match="uncertainty"):
        Uncertainty(gain_rel=1.5)


def test_a_pareto_point_meets_the_sensitivity_bound_as_the_design_report_judges_it() -> None:
    """Every point the frontier marks as meeting the bounds has Ms within the report's hair of
    the bound (the hexapod's plain PID at 3 dB reads Ms 4.006 on the dense grid: marked as
    meeting them before, "BEYOND the bound" in ``motcomp design``'s report)."""
    from motcomp.design.optimal import MS_HAIR
    from motcomp.design.pareto import pareto

    hexapod = load_preset("hexapod").model
    result = pareto(hexapod, None, 1000.0, (3.0,))
    c = Constraints()
    assert result.points
    for q in result.points:
        if q.feasible:
            assert q.ms <= c.max_sensitivity + MS_HAIR, (q.label, q.ms)
    assert any(q.ms > c.max_sensitivity + MS_HAIR and not q.feasible for q in result.points)
