"""The predictive prefilter (:mod:`motcomp.core.predictor`) against closed forms and independent
computations: the Laguerre functions as cascades of their rational factors (scipy's ``lfilter``),
the band monitor as scipy's Butterworth high-pass and a hand-written peak hold, and the blend as
``r + w (F r - r)`` with the minimum-jerk weight."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import Any

import numpy as np
import pytest
from scipy import signal

from motcomp.core.minjerk import PEAK_SPEED_FACTOR, min_jerk
from motcomp.core.predictor import (
    ENVELOPE_S,
    HIGH_CUT,
    LOW_CUT_HZ,
    MAX_ORDER,
    TINY_STATE,
    MonitorParams,
    Prediction,
    PredictorParams,
    laguerre_basis,
    predictor_freqresp,
)
from motcomp.errors import ConfigError

RATE = 1000.0
H = 1.0 / RATE
MON = MonitorParams()
TAU_S = 0.03


# --- a realistic predictor, designed here (no motcomp.design) ---------------------------------
def design(tau_s: float = TAU_S, pole_hz: float = 2.0, order: int = 6, rate_hz: float = RATE,
           band_hz: tuple[float, float] = (0.1, 2.0), hf_weight: float = 0.02
           ) -> PredictorParams:
    """Least squares ``F ~ exp(+j w tau)`` over the band (``F ~ 1`` above 4 Hz with a small
    weight, to bound the high-frequency gain), ``F(1) = 1`` as a heavily weighted row, then
    normalised exactly by the real ``F(1)``."""
    a = math.exp(-2 * math.pi * pole_hz / rate_hz)
    f = np.linspace(band_hz[0], band_hz[1], 60)
    fh = np.geomspace(4.0, 0.49 * rate_hz, 60)
    rows = np.vstack([laguerre_basis(a, order, np.exp(2j * np.pi * f / rate_hz)),
                      hf_weight * laguerre_basis(a, order, np.exp(2j * np.pi * fh / rate_hz)),
                      1e4 * laguerre_basis(a, order, [1.0])])
    rhs = np.concatenate([np.exp(2j * np.pi * f * tau_s), hf_weight * np.ones(fh.size),
                          [1e4]])
    c, *_ = np.linalg.lstsq(np.vstack([rows.real, rows.imag]),
                            np.concatenate([rhs.real, rhs.imag]), rcond=None)
    dc = float((laguerre_basis(a, order, [1.0]) @ c).real[0])
    return PredictorParams(pole_hz=pole_hz, coeffs=tuple(c / dc), rate_hz=rate_hz,
                           band_hz=band_hz)


P = design()


# --- independent computations -------------------------------------------------------------------
def laguerre_outputs(pole: float, order: int, x: np.ndarray) -> np.ndarray:
    """``(order, len(x))``: ``x`` through ``L_0 .. L_{N-1}`` from rest, each the previous one
    through the all-pass ``(z^-1 - a) / (1 - a z^-1)``, the first ``sqrt(1-a^2) / (1 - a z^-1)``."""
    out = [signal.lfilter([math.sqrt(1 - pole * pole)], [1.0, -pole], x)]
    for _ in range(order - 1):
        out.append(signal.lfilter([-pole, 1.0], [1.0, -pole], out[-1]))
    return np.array(out)


def prefilter(p: PredictorParams, x: np.ndarray, rest: float = 0.0) -> np.ndarray:
    """``F(z) x`` from rest at ``rest`` (F(1) = 1: a constant passes unchanged)."""
    lk = laguerre_outputs(p.pole, p.order, x - rest)
    return rest + p.coeffs[0] * (x - rest) + np.asarray(p.coeffs[1:]) @ lk


def monitor_ratio(p: PredictorParams, x: np.ndarray, mon: MonitorParams = MON) -> np.ndarray:
    """The band monitor's ratio, from rest at 0: scipy's Butterworth high-pass at HIGH_CUT x the
    band's top, a first-order high-pass at LOW_CUT_HZ, each through a peak hold decaying over
    ENVELOPE_S."""
    b, a = signal.butter(2, HIGH_CUT * p.band_hz[1], "highpass", fs=p.rate_hz)
    hi = np.abs(signal.lfilter(b, a, x))
    al = math.exp(-2 * math.pi * LOW_CUT_HZ / p.rate_hz)
    lo = np.abs(signal.lfilter([al, -al], [1.0, -al], x))
    decay = math.exp(-1.0 / (p.rate_hz * ENVELOPE_S))
    env_hi, env_lo = np.empty_like(hi), np.empty_like(lo)
    eh = el = 0.0
    for n in range(x.size):
        eh = max(hi[n], decay * eh)
        el = max(lo[n], decay * el)
        env_hi[n], env_lo[n] = eh, el
    return env_hi / (env_lo + mon.floor)


def run(pred: Prediction, refs: np.ndarray, live: bool | Sequence[bool] | np.ndarray = True
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step ``pred`` through ``refs`` (samples x axes): outputs, weights and ratios."""
    refs = np.atleast_2d(refs.T).T
    out = np.empty_like(refs)
    w = np.empty_like(refs)
    ratio = np.empty_like(refs)
    for k, r in enumerate(refs.tolist()):
        lv = live if isinstance(live, bool) else [bool(v) for v in np.atleast_1d(live[k])]
        out[k] = pred.step(r, lv)
        w[k] = pred.weight
        ratio[k] = pred.ratio
    return out, w, ratio


def sine(f_hz: float, n: int, amp: float = 0.1) -> np.ndarray:
    return amp * np.sin(2 * np.pi * f_hz * np.arange(n) * H)


def blend_bound(r: np.ndarray, e: np.ndarray, w: np.ndarray, fade_s: float,
                offset: np.ndarray | float = 0.0) -> np.ndarray:
    """Largest first difference of ``r + w e + offset`` the rules allow, sample by sample:
    ``|dr| + w |de| + 1.875 dt / fade |e| + 1.875 dt / fade_in |offset|`` (the minimum-jerk
    blend's peak rate per sample), with a rounding margin."""
    dr, de = np.abs(np.diff(r)), np.abs(np.diff(e))
    rate = PEAK_SPEED_FACTOR * H / fade_s
    off = PEAK_SPEED_FACTOR * H / MON.fade_in_s * np.abs(np.broadcast_to(offset, r.shape)[:-1])
    return dr + w[1:] * de + rate * np.maximum(np.abs(e[1:]), np.abs(e[:-1])) + off + 1e-12


def first(mask: np.ndarray, start: int = 0) -> int:
    idx = np.flatnonzero(mask[start:])
    assert idx.size, "never"
    return start + int(idx[0])


def resume_index(ratio: np.ndarray, start: int, mon: MonitorParams = MON) -> int:
    """First sample from ``start`` on after which the ratio has stayed below ``resume_ratio``
    for ``resume_after_s`` (that sample included)."""
    need = round(mon.resume_after_s * RATE)
    calm = 0
    for n in range(start, ratio.size):
        calm = calm + 1 if ratio[n] < mon.resume_ratio else 0
        if calm >= need:
            return n
    raise AssertionError("never calm")


# --- 1. the Laguerre basis -------------------------------------------------------------------
@pytest.mark.parametrize(("pole_hz", "rate_hz", "order"), [(2.0, 1000.0, 6), (5.0, 250.0, 9),
                                                           (0.7, 500.0, 3)])
def test_laguerre_basis_is_the_transform_of_the_cascaded_factors(
        pole_hz: float, rate_hz: float, order: int) -> None:
    a = math.exp(-2 * math.pi * pole_hz / rate_hz)
    horizon = int(60 * rate_hz / (2 * math.pi * pole_hz)) + 200 * order  # a^n * n^k negligible
    impulse = np.zeros(horizon)
    impulse[0] = 1.0
    lk = laguerre_outputs(a, order, impulse)
    assert np.max(np.abs(lk[:, -50:])) < 1e-13  # the horizon covers the tails
    # L_0's impulse response in closed form: sqrt(1 - a^2) a^n
    np.testing.assert_allclose(lk[0], math.sqrt(1 - a * a) * a ** np.arange(horizon),
                               rtol=1e-12, atol=1e-300)
    f = np.concatenate([[0.0], np.geomspace(0.01, 0.49 * rate_hz, 40)])
    basis = laguerre_basis(a, order, np.exp(2j * np.pi * f / rate_hz))
    assert basis.shape == (f.size, order + 1)
    np.testing.assert_array_equal(basis[:, 0], 1.0)
    for k in range(order):
        _, hk = signal.freqz(lk[k], worN=f, fs=rate_hz)
        np.testing.assert_allclose(basis[:, k + 1], hk, rtol=1e-9, atol=1e-9)
    # orthonormal: sum_n l_j[n] l_k[n] = delta_jk
    np.testing.assert_allclose(lk @ lk.T, np.eye(order), atol=1e-9)


def test_laguerre_functions_are_all_pass_chained() -> None:
    """|L_k| = |L_0| on the unit circle and arg L_{k+1} - arg L_k is the all-pass' phase."""
    a = P.pole
    w = np.linspace(0.001, 3.0, 50)
    z = np.exp(1j * w)
    basis = laguerre_basis(a, 5, z)
    l0 = math.sqrt(1 - a * a) / np.abs(1 - a / z)
    for k in range(1, 6):
        np.testing.assert_allclose(np.abs(basis[:, k]), l0, rtol=1e-12)
    ratio = basis[:, 2:] / basis[:, 1:-1]
    np.testing.assert_allclose(ratio, ((1 / z - a) / (1 - a / z))[:, None] * np.ones((1, 4)),
                               rtol=1e-12)


def test_the_designed_predictor_leads_over_the_band() -> None:
    """The recipe gives what the other tests assume: F(1) = 1, about 30 ms lead at 0.5-2 Hz,
    gain within 3 % of 1 in the band, below 3 at any frequency."""
    assert P.dc_gain == pytest.approx(1.0, abs=1e-12)
    f = np.array([0.5, 1.0, 2.0])
    resp = predictor_freqresp(P, f)
    lead_s = np.angle(resp) / (2 * np.pi * f)
    assert np.all((lead_s > 0.02) & (lead_s < 0.04)), lead_s
    np.testing.assert_allclose(np.abs(resp), 1.0, atol=0.03)
    assert np.max(np.abs(predictor_freqresp(P, np.linspace(0, RATE / 2, 2001)))) < 3.0


# --- 2. the step against the transfer function ------------------------------------------------
@pytest.mark.parametrize("f_hz", [0.3, 1.0, 2.0])
def test_steady_sine_gets_the_filters_gain_and_phase(f_hz: float) -> None:
    n = 8000
    x = sine(f_hz, n)
    pred = Prediction([P], MON, RATE)
    out, w, ratio = run(pred, x)
    y = prefilter(P, x)
    # sample by sample from rest: the blend of the reference and F's output with the weight
    np.testing.assert_allclose(out[:, 0], x + w[:, 0] * (y - x), rtol=0, atol=1e-12)
    np.testing.assert_allclose(ratio[:, 0], monitor_ratio(P, x), rtol=1e-9, atol=1e-12)
    # the fade-in completed, then the prediction alone
    assert np.all(w[-4000:, 0] == 1.0) and pred.fallbacks == [0]
    assert pred.predicting() == [True]
    np.testing.assert_allclose(out[-4000:, 0], y[-4000:], rtol=0, atol=1e-12)
    # the steady state is |F| sin(wt + arg F)
    resp = predictor_freqresp(P, [f_hz])[0]
    t = np.arange(n) * H
    np.testing.assert_allclose(out[-2000:, 0], 0.1 * abs(resp) * np.sin(
        2 * np.pi * f_hz * t[-2000:] + np.angle(resp)), rtol=0, atol=1e-11)


def test_the_fade_in_waits_for_calm_and_takes_fade_in_s() -> None:
    """From rest, a sine: the weight starts rising on the sample after the ratio (computed
    independently) has stayed below resume_ratio for resume_after_s, follows the minimum-jerk
    blend and reaches 1 fade_in_s later."""
    x = sine(0.5, 2500)
    pred = Prediction([P], MON, RATE)
    _, w, _ = run(pred, x)
    k = resume_index(monitor_ratio(P, x), 0)
    assert np.all(w[:k, 0] == 0.0)
    m = np.arange(1, round(MON.fade_in_s * RATE) + 1)
    np.testing.assert_allclose(w[k:k + m.size, 0], min_jerk(np.minimum(m * H / MON.fade_in_s,
                                                                       1.0)), atol=1e-9)
    assert np.all(w[k + m.size:, 0] == 1.0)


# --- 3. a constant passes unchanged ------------------------------------------------------------
@pytest.mark.parametrize("r0", [0.0, 0.13, -2.6, 1234.5])
def test_constant_reference_passes_unchanged_from_rest_at_it(r0: float) -> None:
    pred = Prediction([None, None], MON, RATE)
    pred.set_params([P, design(tau_s=0.05)], MON, [r0, r0])  # at rest at r0
    out, w, _ = run(pred, np.full((1500, 2), r0))
    np.testing.assert_allclose(out, r0, rtol=1e-12, atol=1e-15)
    assert np.all(w[-1] == 1.0)  # nothing out of band: it predicts, and still passes r0


def test_constant_zero_from_construction_is_exact() -> None:
    pred = Prediction([P], MON, RATE)
    out, _, ratio = run(pred, np.zeros(1200))
    assert np.all(out == 0.0) and np.all(ratio == 0.0)


# --- 4. validation -----------------------------------------------------------------------------
GOOD: dict[str, Any] = dict(pole_hz=2.0, coeffs=P.coeffs, rate_hz=RATE, band_hz=(0.1, 2.0))


@pytest.mark.parametrize(("over", "key"), [
    (dict(coeffs=(*P.coeffs[:-1], math.nan)), f"coeffs[{P.order}]"),
    (dict(coeffs=(math.inf, *P.coeffs[1:])), "coeffs[0]"),
    (dict(coeffs=(1.0,)), "coeffs"),
    (dict(coeffs=(1.0,) + (0.0,) * (MAX_ORDER + 1)), "coeffs"),
    (dict(pole_hz=500.0), "pole_hz"),
    (dict(pole_hz=700.0), "pole_hz"),
    (dict(pole_hz=0.0), "pole_hz"),
    (dict(pole_hz=-1.0), "pole_hz"),
    (dict(pole_hz=math.nan), "pole_hz"),
    (dict(rate_hz=math.inf), "rate_hz"),
    (dict(rate_hz=0.0), "rate_hz"),
    (dict(coeffs=(P.coeffs[0] + 1e-5, *P.coeffs[1:])), "F(1)"),
    (dict(coeffs=(0.5, 0.1, 0.2)), "F(1)"),
    (dict(band_hz=(0.0, 2.0)), "band_hz"),
    (dict(band_hz=(2.0, 1.0)), "band_hz"),
    (dict(band_hz=(0.1, 125.0)), "band_hz"),  # rate / 8
    (dict(band_hz=(0.1, math.nan)), "band_hz"),
])
def test_predictor_params_refused_naming_the_key(over: dict, key: str) -> None:
    with pytest.raises(ConfigError, match=f"prediction.*{re.escape(key)}"):
        PredictorParams(**{**GOOD, **over})


def test_the_limits_of_the_rules_are_accepted() -> None:
    PredictorParams(**{**GOOD, "band_hz": (0.1, 124.9)})
    PredictorParams(pole_hz=499.0, coeffs=(1.0, 0.0), rate_hz=RATE)
    PredictorParams(pole_hz=2.0, coeffs=(1.0,) + (0.0,) * MAX_ORDER, rate_hz=RATE)
    PredictorParams(**{**GOOD, "coeffs": (P.coeffs[0] + 5e-7, *P.coeffs[1:])})  # within 1e-6


@pytest.mark.parametrize("band", [(2.0,), (0.1, 1.0, 2.0)])
def test_band_of_the_wrong_length_is_refused_naming_the_key(band: tuple) -> None:
    with pytest.raises(ConfigError, match="band_hz"):
        PredictorParams(**{**GOOD, "band_hz": band})


def test_a_pole_at_z_equal_1_is_refused() -> None:
    with pytest.raises(ConfigError, match="prediction"):
        p = PredictorParams(pole_hz=1e-20, coeffs=(0.5, 0.5), rate_hz=RATE)
        Prediction([p], MON, RATE)


@pytest.mark.parametrize(("over", "key"), [
    (dict(resume_ratio=0.3), "resume_ratio"),
    (dict(resume_ratio=0.4), "resume_ratio"),
    (dict(resume_ratio=0.0), "resume_ratio"),
    (dict(fallback_ratio=math.nan), "fallback_ratio"),
    (dict(fallback_ratio=-0.3), "fallback_ratio"),
    (dict(resume_after_s=-1.0), "resume_after_s"),
    (dict(resume_after_s=math.inf), "resume_after_s"),
    (dict(fade_out_s=-0.01), "fade_out_s"),
    (dict(fade_in_s=math.nan), "fade_in_s"),
    (dict(floor=0.0), "floor"),
    (dict(floor=-1e-4), "floor"),
])
def test_monitor_params_refused_naming_the_key(over: dict, key: str) -> None:
    with pytest.raises(ConfigError, match=f"prediction.*{key}"):
        MonitorParams(**over)


def test_prediction_refuses_a_filter_for_another_rate() -> None:
    with pytest.raises(ConfigError, match=r"500 Hz.*1000 Hz"):
        Prediction([design(rate_hz=500.0)], MON, RATE)
    with pytest.raises(ConfigError, match="2 predictors for 1 axes"):
        Prediction([P], MON, RATE).set_params([P, P], MON, [0.0, 0.0])


# --- 5. fallback and resume ----------------------------------------------------------------------
def test_band_limited_sine_keeps_predicting() -> None:
    x = sine(0.3, 6000, 0.2)
    pred = Prediction([P], MON, RATE)
    _, w, ratio = run(pred, x)
    assert np.max(ratio[1500:, 0]) < MON.resume_ratio
    assert np.all(w[1500:, 0] == 1.0) and pred.fallbacks == [0]


@pytest.mark.parametrize("disturbance", ["step", "sine_6hz"])
def test_out_of_band_input_falls_back_and_resumes_bumplessly(disturbance: str) -> None:
    """A 0.3 Hz sine, predicted; at 2 s a 5 cm step (or a 6 Hz sine for 0.5 s): the weight
    leaves 1 on the sample the ratio (computed independently) first exceeds fallback_ratio and
    reaches 0 within fade_out_s (+1 sample); once the ratio has stayed below resume_ratio for
    resume_after_s it fades back in over fade_in_s.  The output is the blend of the reference
    and F's output (computed independently) at every sample, and its first difference stays
    within the blend's bound."""
    n, k0 = 6000, 2000
    if disturbance == "step":
        x = sine(0.3, n)
        x[k0:] += 0.05
    else:  # out of band: 6 Hz at 2.5 times the in-band amplitude
        x = sine(0.3, n, 0.02)
        x[k0:k0 + 500] += 0.05 * np.sin(2 * np.pi * 6.0 * np.arange(500) * H)
    pred = Prediction([P], MON, RATE)
    out, w, ratio = run(pred, x)
    w, out = w[:, 0], out[:, 0]
    ref_ratio = monitor_ratio(P, x)
    np.testing.assert_allclose(ratio[:, 0], ref_ratio, rtol=1e-9, atol=1e-12)
    assert np.all(w[k0 - 500:k0] == 1.0)
    kf = first(ref_ratio > MON.fallback_ratio, k0)
    assert kf - k0 <= (3 if disturbance == "step" else 170)  # a 6 Hz sine: within a period
    assert np.all(w[k0:kf] == 1.0) and w[kf] < 1.0
    fade_out = round(MON.fade_out_s * RATE)
    assert w[kf + fade_out] == 0.0 and w[kf + fade_out - 2] > 0.0
    assert pred.fallbacks == [1]
    kr = resume_index(ref_ratio, kf)
    assert np.all(w[kf + fade_out:kr] == 0.0)
    assert 0.0 < w[kr] < 1.0  # it starts on the sample that completes resume_after_s
    fade_in = round(MON.fade_in_s * RATE)
    assert w[kr + fade_in] == 1.0 and w[kr + fade_in - 2] < 1.0
    assert kr + fade_in + 1 < n and pred.fallbacks == [1]
    # the output is the blend, the weight moves at the minimum-jerk rate, no jump
    y = prefilter(P, x)
    np.testing.assert_allclose(out, x + w * (y - x), rtol=0, atol=1e-12)
    dw = np.abs(np.diff(w))
    assert np.max(dw[kf - 1:kf + fade_out + 1]) <= PEAK_SPEED_FACTOR * H / MON.fade_out_s + 1e-12
    assert np.max(dw[kr:]) <= PEAK_SPEED_FACTOR * H / MON.fade_in_s + 1e-12
    for a, b, fade in ((kf - 1, kf + fade_out + 2, MON.fade_out_s),
                       (kr - 1, kr + fade_in + 2, MON.fade_in_s)):
        d_out = np.abs(np.diff(out[a:b]))
        assert np.all(d_out <= blend_bound(x[a:b], y[a:b] - x[a:b], w[a:b], fade))


# --- 6. live, per axis, and unpredicted axes ----------------------------------------------------
def test_live_false_forces_the_fallback() -> None:
    n, k0 = 3500, 2000
    x = sine(0.3, n)
    pred = Prediction([P], MON, RATE)
    live = np.ones((n, 1), dtype=bool)
    live[k0:] = False
    out, w, _ = run(pred, x, live)
    assert w[k0 - 1, 0] == 1.0 and w[k0, 0] < 1.0
    fade_out = round(MON.fade_out_s * RATE)
    assert w[k0 + fade_out, 0] == 0.0 and np.all(w[k0 + fade_out:, 0] == 0.0)
    assert pred.fallbacks == [0] and pred.predicting() == [False]  # not the monitor's
    np.testing.assert_array_equal(out[k0 + fade_out:, 0], x[k0 + fade_out:])
    y = prefilter(P, x)
    d_out = np.abs(np.diff(out[k0 - 1:k0 + fade_out + 2, 0]))
    sl = slice(k0 - 1, k0 + fade_out + 2)
    assert np.all(d_out <= blend_bound(x[sl], y[sl] - x[sl], w[sl, 0], MON.fade_out_s))


def test_never_live_never_predicts_and_counts_no_fallback() -> None:
    x = sine(0.3, 2000)
    pred = Prediction([P], MON, RATE)
    out, w, _ = run(pred, x, live=False)
    assert np.all(w == 0.0) and pred.fallbacks == [0]
    np.testing.assert_array_equal(out[:, 0], x)


def test_live_acts_per_axis_and_an_unpredicted_axis_passes_bit_exactly() -> None:
    n, k0 = 4000, 2000
    t = np.arange(n) * H
    refs = np.stack([sine(0.3, n), np.sin(t) * math.pi + 1e-17 * t, sine(0.4, n)], axis=1)
    live = np.ones((n, 3), dtype=bool)
    live[:k0, 2] = False
    live[k0:, 0] = False
    p2 = design(tau_s=0.05)
    pred = Prediction([P, None, p2], MON, RATE)
    out, w, _ = run(pred, refs, live)
    assert np.array_equal(out[:, 1], refs[:, 1]) and np.all(w[:, 1] == 0.0)
    assert w[k0 - 1, 0] == 1.0 and np.all(w[:k0, 2] == 0.0)
    fade_out = round(MON.fade_out_s * RATE)
    assert np.all(w[k0 + fade_out:, 0] == 0.0)
    # axis 2 goes live at k0: resume_after_s of calm from then, then fade_in_s
    k_on = k0 + round(MON.resume_after_s * RATE)
    assert np.all(w[:k_on - 1, 2] == 0.0) and w[k_on + 1, 2] > 0.0
    assert np.all(w[k_on + round(MON.fade_in_s * RATE) + 1:, 2] == 1.0)
    assert pred.fallbacks == [0, 0, 0] and pred.predicting() == [False, False, True]
    np.testing.assert_allclose(out[-500:, 2], prefilter(p2, refs[:, 2])[-500:], rtol=0,
                               atol=1e-12)


def test_no_predictor_at_all_returns_the_reference() -> None:
    pred = Prediction([None, None], MON, RATE)
    r = [0.1, math.nan]
    out = pred.step(r)
    assert out[0] == 0.1 and math.isnan(out[1])
    assert pred.predicting() == [False, False] and pred.weight == [0.0, 0.0]


# --- 7. set_params ------------------------------------------------------------------------------
def test_equal_params_keep_the_state() -> None:
    n, k0 = 3000, 1700
    x = np.stack([sine(0.3, n), sine(0.6, n)], axis=1)
    a = Prediction([P, None], MON, RATE)
    b = Prediction([P, None], MON, RATE)
    out_a, _, _ = run(a, x)
    out_b1, _, _ = run(b, x[:k0])
    b.set_params([design(), None], MON, x[k0 - 1].tolist())  # equal, not the same object
    out_b2, _, _ = run(b, x[k0:])
    np.testing.assert_array_equal(out_a, np.concatenate([out_b1, out_b2]))


def test_new_coefficients_mid_motion_do_not_jump() -> None:
    """Swap to a 50 ms predictor while predicting: the new filter starts at rest at the last
    reference, the old output's lead is an offset faded out over fade_in_s, the new prediction
    fades in once calm: the output is that sum exactly, and its first difference within the
    blend's bound across the swap."""
    n, k0 = 5000, 2000
    x = sine(0.3, n)
    p2 = design(tau_s=0.05, order=8)
    pred = Prediction([P], MON, RATE)
    out1, w1, _ = run(pred, x[:k0])
    assert w1[-1, 0] == 1.0
    pred.set_params([p2], MON, [float(x[k0 - 1])])
    out2, w2, _ = run(pred, x[k0:])
    out = np.concatenate([out1[:, 0], out2[:, 0]])
    off = out1[-1, 0] - x[k0 - 1]
    assert abs(off) > 1e-3  # the old lead: a real offset to fade out
    m = np.arange(1, n - k0 + 1)
    offset = off * (1.0 - min_jerk(np.minimum(m * H / MON.fade_in_s, 1.0)))
    y2 = prefilter(p2, x[k0:], rest=float(x[k0 - 1]))
    np.testing.assert_allclose(out2[:, 0], x[k0:] + w2[:, 0] * (y2 - x[k0:]) + offset,
                               rtol=0, atol=1e-12)
    assert w2[-1, 0] == 1.0 and pred.fallbacks == [0]
    # first difference across the swap
    a = k0 - 5
    e = np.concatenate([out1[-5:, 0] - x[k0 - 5:k0], y2 - x[k0:]])
    w = np.concatenate([w1[-5:, 0], w2[:, 0]])
    assert np.all(np.abs(np.diff(out[a:])) <= blend_bound(x[a:], e, w, MON.fade_in_s, off))
    d = np.abs(np.diff(out[k0 - 2:k0 + 2]))
    assert np.max(d) < 2 * np.max(np.abs(np.diff(out[k0 - 200:k0])))  # no step at the swap


def test_changing_one_axis_keeps_the_others_state() -> None:
    n, k0 = 3000, 2000
    x = np.stack([sine(0.3, n), sine(0.5, n)], axis=1)
    a = Prediction([P, P], MON, RATE)
    b = Prediction([P, P], MON, RATE)
    out_a, _, _ = run(a, x)
    out_b1, _, _ = run(b, x[:k0])
    b.set_params([design(tau_s=0.05), P], MON, x[k0 - 1].tolist())
    out_b2, _, _ = run(b, x[k0:])
    np.testing.assert_array_equal(out_a[:, 1], np.concatenate([out_b1, out_b2])[:, 1])


# --- 8. non-finite references -------------------------------------------------------------
def test_non_finite_reference_reaches_neither_state_nor_output() -> None:
    n = 3000
    x = np.stack([sine(0.3, n), sine(0.5, n)], axis=1)
    bad = x.copy()
    bad[1800, 0] = math.nan
    bad[1900:1905, 0] = math.inf
    bad[2000, 0] = -math.inf
    clean = Prediction([P, P], MON, RATE)
    pred = Prediction([P, P], MON, RATE)
    out_c, _, _ = run(clean, x)
    out, w, ratio = run(pred, bad)
    for k in (1800, *range(1900, 1905), 2000):
        given = bad[k, 0]  # the input as given: nan for nan, the same infinity for an infinity
        assert out[k, 0] == given if math.isinf(given) else math.isnan(out[k, 0])
    finite = np.isfinite(bad[:, 0])
    assert np.all(np.isfinite(out[finite, 0]))
    assert np.all(np.isfinite(w)) and np.all(np.isfinite(ratio))
    np.testing.assert_array_equal(out[:, 1], out_c[:, 1])  # the other axis untouched
    # a few held samples of a 0.3 Hz sine: the prediction stays within a hair of the clean one
    assert np.max(np.abs(out[finite, 0] - out_c[finite, 0])) < 2e-3
    assert pred.fallbacks == [0, 0] and w[-1, 0] == 1.0


def test_non_finite_reference_advances_with_the_last_finite_value() -> None:
    """As the docstring says: a NaN sample is returned as given and the filter, monitor and
    blend advance with the last finite value, so the next outputs are those of a run where the
    NaN was that value (weight 1 throughout: the blend plays no part)."""
    x = sine(0.3, 2600)
    a = Prediction([P], MON, RATE)
    b = Prediction([P], MON, RATE)
    held = np.concatenate([x[:2500], [x[2499]], x[2500:]])
    out_a, _, _ = run(a, held)
    with_nan = np.concatenate([x[:2500], [math.nan], x[2500:]])
    out_b, w_b, _ = run(b, with_nan)
    assert np.all(w_b[2000:] == 1.0) and math.isnan(out_b[2500, 0])
    np.testing.assert_allclose(out_b[2501:, 0], out_a[2501:, 0], rtol=0, atol=1e-12)


def test_states_decaying_at_rest_never_become_subnormal() -> None:
    """A prefilter at rest at 0 after a tiny motion: its states decay geometrically and, left
    alone, would pass through subnormal numbers (70 times slower on some CPUs: 2.5 -> 170 us
    for the hexapod's six); they are set to 0 below TINY_STATE first."""
    pred = Prediction([P], MON, RATE)
    tiny = np.finfo(float).tiny
    for _ in range(200):  # a step of 1e-150: the states start near it
        pred.step([1e-150])
    smallest = math.inf
    for k in range(80_000):  # long enough to decay past 1e-308 from 1e-150 (about 60 000)
        pred.step([0.0])
        if k % 97 == 0:
            state = np.abs(pred._x[:, :-1])
            nonzero = state[state != 0.0]
            if nonzero.size:
                smallest = min(smallest, float(nonzero.min()))
    assert smallest >= tiny, smallest  # (TINY_STATE, then 0)
    assert tiny < TINY_STATE
    assert not np.any(pred._x[:, :-1]), "still decaying after 80 000 steps"


def test_a_switch_off_fades_the_prediction_over_fade_in_s() -> None:
    """``wanted`` False (compensation switched off): held off like ``live`` False, no fallback
    counted, but the prediction fades out over ``fade_in_s`` (continuous in position and
    velocity at that pace), not over the fallback's ``fade_out_s``."""
    n, k0 = 3500, 2000
    x = sine(0.3, n)
    pred = Prediction([P], MON, RATE)
    out, w, moving = np.empty(n), np.empty(n), np.empty(n, dtype=int)
    for k in range(n):
        out[k] = pred.step([float(x[k])], True, k < k0)[0]
        w[k] = pred.weight[0]
        moving[k] = pred.moving
    fade = round(MON.fade_in_s * RATE)
    # ``moving`` says the fade, and nothing else (the fade-in at the start included)
    np.testing.assert_array_equal(moving[k0 - 50:], (w[k0 - 50:] != w[k0 - 51:-1]).astype(int))
    assert MON.fade_in_s > 2 * MON.fade_out_s
    assert w[k0 - 1] == 1.0 and 0.4 < w[k0 + fade // 2] < 0.6 and w[k0 + fade] == 0.0
    assert pred.fallbacks == [0] and pred.predicting() == [False]
    np.testing.assert_array_equal(out[k0 + fade:], x[k0 + fade:])
    y = prefilter(P, x)
    sl = slice(k0 - 1, k0 + fade + 2)
    assert np.all(np.abs(np.diff(out[sl])) <= blend_bound(x[sl], y[sl] - x[sl], w[sl],
                                                          MON.fade_in_s))
