"""The predictive prefilter's design (:mod:`motcomp.design.predictor`), checked against
computations independent of the design code: the Laguerre recursion run with
``scipy.signal.lfilter``, the plant's discretisation through ``scipy.signal.freqz``, dense
uniform grids and step responses simulated sample by sample."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import freqz, lfilter

from motcomp.core.models import parse_model
from motcomp.core.predictor import predictor_freqresp
from motcomp.design.frequency import evaluate
from motcomp.design.predictor import (
    RESPONSE_RTOL,
    PredictorBounds,
    PredictorDesign,
    design_predictor,
)
from motcomp.errors import ConfigError
from tests._laguerre import laguerre_filter

RATE = 1000.0
HEXAPOD = parse_model("p2uzd:K=1,Td=0.0325,Tw=0.06399186527,Zeta=0.7,Tz=0.08764049978")
BOUNDS = PredictorBounds(peak_db=6.0, gain_error_db=1.0, hf_command_gain=3.0)
HAIR_DB = 0.01


@pytest.fixture(scope="module")
def hexapod() -> PredictorDesign:
    return design_predictor(HEXAPOD, RATE, constraints=BOUNDS)


def plant_b_a() -> tuple[np.ndarray, np.ndarray]:
    """The hexapod's ZOH discretisation as ``lfilter``/``freqz`` coefficients in z^-1."""
    num, den = HEXAPOD.discretize(RATE).tf()
    num = np.trim_zeros(np.asarray(num, float), "f")
    return np.concatenate([np.zeros(len(den) - len(num)), num]), np.asarray(den, float)


def test_frequency_response_is_that_of_the_recursion(hexapod: PredictorDesign) -> None:
    p = hexapod.params
    impulse = np.zeros(80_000)
    impulse[0] = 1.0
    h = laguerre_filter(p, impulse)
    assert abs(h[-1000:]).max() < 1e-12  # decayed: the FIR truncation is exact enough
    f = np.array([0.0, 0.05, 0.1, 0.5, 1.0, 2.0, 5.0, 10.0, 50.0, 200.0, 499.0])
    _, ref = freqz(h, worN=f, fs=RATE)
    np.testing.assert_allclose(predictor_freqresp(p, f), ref, rtol=0, atol=1e-9)
    assert abs(h.sum() - 1.0) < 1e-9 and abs(p.dc_gain - 1.0) < 1e-12  # F(1) = 1


def test_hexapod_meets_the_bounds_on_independent_dense_grids(hexapod: PredictorDesign) -> None:
    p = hexapod.params
    b, a = plant_b_a()
    # phase delay: unwrapped along a uniform grid from (almost) DC, where T = 1
    f = np.linspace(1e-4, 2.0, 40_001)
    _, pz = freqz(b, a, worN=f, fs=RATE)
    t = pz * predictor_freqresp(p, f)
    delay_ms = -np.unwrap(np.angle(t)) / (2 * np.pi * f) * 1e3
    band = f >= 0.1
    worst = float(np.max(np.abs(delay_ms[band])))
    assert worst <= 10.0  # aim 5: 5.4 ms with 30 functions at 0.7 Hz (docs/TUNING.md)
    assert worst == pytest.approx(hexapod.worst_delay_ms, abs=0.02)
    assert np.max(np.abs(20 * np.log10(np.abs(t[band])))) <= 1.0 + HAIR_DB
    everywhere = np.geomspace(1e-3, 499.99, 60_000)
    _, pz = freqz(b, a, worN=everywhere, fs=RATE)
    fz = predictor_freqresp(p, everywhere)
    assert 20 * np.log10(np.max(np.abs(pz * fz))) <= 6.0 + HAIR_DB
    assert np.max(np.abs(fz[everywhere >= 10.0])) <= 3.0 * 1.001
    # the report's own dense check says the same
    ev = evaluate(None, None, HEXAPOD, rate_hz=RATE, predictor=p)
    assert ev.max_residual_delay_ms == pytest.approx(worst, abs=0.02)
    assert ev.hf_command_gain == pytest.approx(hexapod.check.hf_command_gain, rel=1e-3)


def test_step_bound_holds_in_simulation() -> None:
    d = design_predictor(HEXAPOD, RATE, constraints=BOUNDS, step_rise_s=0.2, overshoot=0.05)
    n = 30_000
    x = np.clip(np.arange(n) / (0.2 * RATE), 0.0, 1.0)
    r = x**3 * (10 - 15 * x + 6 * x * x)
    b, a = plant_b_a()
    y = lfilter(b, a, laguerre_filter(d.params, r))
    assert y[-1] == pytest.approx(1.0, abs=1e-6)
    assert y.max() <= 1.05 + 1e-3 and y.min() >= -0.05 - 1e-3
    assert d.check.design_step_overshoot == pytest.approx(max(y.max() - 1, -y.min()), abs=1e-4)
    # the bound costs delay: 16 ms rather than 5 (docs/TUNING.md's table)
    assert 10.0 < d.worst_delay_ms < 25.0


def test_bypass_evaluation_is_the_plant_alone() -> None:
    ev = evaluate(None, None, HEXAPOD, rate_hz=RATE)
    assert ev.max_residual_delay_ms == pytest.approx(ev.uncorrected_max_delay_ms)
    assert ev.hf_command_gain == 1.0 and ev.stable and ev.ms == 1.0


def test_infeasible_or_bad_inputs_raise_config_error() -> None:
    with pytest.raises(ConfigError, match="no filter of order 1"):
        design_predictor(HEXAPOD, RATE, order=1,
                         constraints=PredictorBounds(peak_db=0.0, gain_error_db=0.05,
                                                     hf_command_gain=1.0))
    with pytest.raises(ConfigError, match="order"):
        design_predictor(HEXAPOD, RATE, order=0)
    with pytest.raises(ConfigError, match="overshoot"):
        design_predictor(HEXAPOD, RATE, step_rise_s=0.2, overshoot=-0.1)
    with pytest.raises(ConfigError, match="band"):
        PredictorBounds(band_hz=(2.0, 0.1))


def test_design_is_deterministic(hexapod: PredictorDesign) -> None:
    again = design_predictor(HEXAPOD, RATE, constraints=BOUNDS)
    f = np.linspace(0.0, 499.0, 2000)
    ref = predictor_freqresp(hexapod.params, f)
    diff = np.abs(predictor_freqresp(again.params, f) - ref)
    assert np.max(diff) <= RESPONSE_RTOL * np.max(np.abs(ref))
