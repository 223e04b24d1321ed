"""The predictive prefilter in the tick (:mod:`motcomp.core.tick`) and the config: the hexapod
axes of the example config given a prediction table (designed in :mod:`tests.test_predictor`,
tau = 30 ms), driven through :func:`motcomp.core.tick.step` with encoded frames."""

from __future__ import annotations

import copy
import dataclasses
import math
from functools import cache
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from motcomp.config import ServiceConfig, new_tick, parse_config, read_toml, resolve_axes
from motcomp.core.axes import AXES
from motcomp.core.tick import (
    TickOutput,
    TickParams,
    TickState,
    prediction_status,
    set_bypass,
    step,
)
from motcomp.errors import ConfigError
from motcomp.io.wire import encode_input
from tests.test_predictor import P, design
from tests.test_tick import EXAMPLE, HEX, MS, H, assert_within_limits

Z = AXES.index("hex_z")
HEX_I = [AXES.index(a) for a in HEX]


def config_data(**axis_over: Any) -> dict[str, Any]:
    """The example config's document, every hexapod axis with :data:`P` as its prediction and
    the others without one (the rails' own prefilter is the subject of other tests);
    ``axis_over`` sets keys of ``axes.hex_z``."""
    data = read_toml(EXAMPLE)
    for a, table in data["axes"].items():
        if a in HEX:
            table["prediction"] = P.to_config()
        else:
            table.pop("prediction", None)
    data["axes"]["hex_z"].update(axis_over)
    return data


@cache
def config(predict_z: bool = True) -> ServiceConfig:
    return parse_config(config_data() if predict_z else config_data(predict=False))


def drive(params: TickParams, state: TickState, pos: dict[str, np.ndarray], k0: int = 0,
          ) -> list[TickOutput]:
    """One frame a tick (seq = tick = k0 ...), ``pos`` axis -> samples."""
    n = len(next(iter(pos.values())))
    outs = []
    for j in range(n):
        k = k0 + j
        frame = encode_input(k, k * H, {a: float(v[j]) for a, v in pos.items()})
        outs.append(step(state, params, k * MS, frame))
    return outs


def heave(n: int, amp: float = 0.1, f_hz: float = 0.5, ramp_s: float = 1.0) -> np.ndarray:
    """A sine on hex_z whose amplitude rises along a minimum-jerk ramp over ``ramp_s``."""
    t = np.arange(n) * H
    x = np.minimum(t / ramp_s, 1.0)
    return amp * x**3 * (10 - 15 * x + 6 * x * x) * np.sin(2 * np.pi * f_hz * t)


def lag_s(u: np.ndarray, x: np.ndarray, max_lag: int = 80) -> float:
    """The lag of ``u`` behind ``x`` maximising their cross-correlation (negative: it leads)."""
    lags = np.arange(-max_lag, max_lag + 1)
    m = max_lag
    corr = [np.dot(u[m:-m], x[m - L:x.size - m - L]) for L in lags]
    return float(lags[int(np.argmax(corr))] * H)


# --- 1. the config --------------------------------------------------------------------------
def test_a_config_with_predictions_resolves() -> None:
    axes = resolve_axes(config())
    for i, a in enumerate(AXES):
        if a in HEX:
            assert axes.prediction[i] == P and axes.predict[i]
        else:
            assert axes.prediction[i] is None and not axes.predict[i]
    off = resolve_axes(config(predict_z=False))
    assert off.prediction[Z] == P and not off.predict[Z]
    params, _ = new_tick(config())
    assert params.prediction == axes.prediction and params.predict == axes.predict


def test_predict_is_settable_in_a_profile() -> None:
    data = config_data()
    data["profiles"]["fast"]["predict"] = False
    data["profiles"]["paper"]["axes"] = {"hex_z": {"predict": False}}
    cfg = parse_config(data)
    assert not any(resolve_axes(cfg, "fast").predict)
    paper = resolve_axes(cfg, "paper").predict
    assert not paper[Z] and all(paper[i] for i in HEX_I if i != Z)


def test_a_prediction_for_another_rate_is_refused_naming_the_key() -> None:
    data = config_data(prediction=design(rate_hz=500.0).to_config())
    with pytest.raises(ConfigError, match=r"axes\.hex_z\.prediction\.rate_hz.*500 Hz"):
        parse_config(data)
    data = config_data()
    data["loop"]["rate_hz"] = 500
    with pytest.raises(ConfigError, match=r"axes\.hex_\w+\.prediction\.rate_hz.*1000 Hz"):
        parse_config(data)


@pytest.mark.parametrize(("table", "key"), [
    (dict(coeffs=[P.coeffs[0] + 1e-3, *P.coeffs[1:]]), "F(1)"),
    (dict(pole_hz=600.0), "pole_hz"),
    (dict(band_hz=[0.1, 200.0]), "band_hz"),
    (dict(coeffs=[1.0]), "coeffs"),
])
def test_a_bad_prediction_table_is_refused_naming_axis_and_key(table: dict, key: str) -> None:
    data = config_data(prediction={**P.to_config(), **table})
    with pytest.raises(ConfigError, match=r"axes\.hex_z\.prediction: .*" + key.replace(
            "(", r"\(").replace(")", r"\)")):
        parse_config(data)


def test_a_prediction_table_rejects_unknown_keys() -> None:
    with pytest.raises(ConfigError, match=r"axes\.hex_z\.prediction\.tau_s"):
        parse_config(config_data(prediction={**P.to_config(), "tau_s": 0.03}))


# --- 2. the command leads --------------------------------------------------------------------
@pytest.mark.parametrize("predict_z", [True, False])
def test_the_predicted_heave_leads_the_reference(predict_z: bool) -> None:
    """A 0.5 Hz heave of 10 cm: with prediction the command leads the input by about the
    predictor's 30 ms (more than 10 ms, less than 40 ms, net of the reconstruction's lag);
    without, it lags by the band limit's delay (and no more than 5 ms beyond)."""
    n = 7000
    x = heave(n)
    params, state = new_tick(config(predict_z))
    outs = drive(params, state, {"hex_z": x})
    u = np.array([o.u[Z] for o in outs])
    lag = lag_s(u[3000:], x[3000:])
    status = prediction_status(state)
    assert set(status) == set(HEX)
    if predict_z:
        assert -0.04 < lag < -0.01, lag
        assert status["hex_z"]["state"] == "predicting" and status["hex_z"]["weight"] == 1.0
        assert status["hex_z"]["fallbacks"] == 0
    else:
        band = params.shaper.band[Z]
        assert band is not None
        assert -1e-3 <= lag - band.delay_s < 0.005, lag
        assert status["hex_z"]["state"] == "off" and status["hex_z"]["weight"] == 0.0
        np.testing.assert_array_equal(u, state_free_reference(x))
    assert status["hex_x"]["state"] == "predicting"  # at rest: nothing out of band
    assert not any(f.startswith("fallback:") for o in outs[2500:] for f in o.flags)


def state_free_reference(x: np.ndarray) -> np.ndarray:
    """hex_z's command without prediction: the same config's tick without any prediction."""
    data = config_data()
    for a in HEX:
        del data["axes"][a]["prediction"]
    params, state = new_tick(parse_config(data))
    return np.array([o.u[Z] for o in drive(params, state, {"hex_z": x})])


# --- 3. flags and bypass ------------------------------------------------------------------------
def test_a_step_flags_fallback_and_bypass_turns_prediction_off_and_back() -> None:
    params, state = new_tick(config())
    x = np.concatenate([np.zeros(2500), np.full(3000, 0.05)])  # a 5 cm step at 2.5 s
    outs = drive(params, state, {"hex_z": x})
    assert prediction_status(state)["hex_z"]["state"] == "predicting"
    # start-up: held (the shaper's mode, then the calm time), not a fallback: no flag
    assert not any("fallback:hex_z" in o.flags for o in outs[:2500])
    flagged = [k for k, o in enumerate(outs) if "fallback:hex_z" in o.flags and k >= 2500]
    assert flagged and 2500 <= flagged[0] <= 2503  # within a few ticks of the step
    assert flagged == list(range(flagged[0], flagged[-1] + 1))  # one fallback, then back
    assert 0.5 < (flagged[-1] - flagged[0]) * H < 2.0
    assert not any(f.startswith("fallback:") and f != "fallback:hex_z"
                   for o in outs[2500:] for f in o.flags)
    st_z = prediction_status(state)["hex_z"]
    assert st_z["fallbacks"] == 1 and st_z["state"] == "predicting"
    # the order of flags: sat, bypass, fallback last
    o = outs[flagged[0]]
    assert o.flags[-1] == "fallback:hex_z"
    assert o.flags[:-1] == [f for f in o.flags if f.startswith(("sat:", "bypass:"))]
    # compensation turned off on the hexapod: its prediction is off, no fallback flag
    pid_mask = list(state.comp.bypass)
    assert [AXES[i] for i, b in enumerate(pid_mask) if b] == HEX
    set_bypass(state, pid_mask)
    assert state.prediction_off == pid_mask
    k0 = len(x)
    outs = drive(params, state, {"hex_z": x[-1] + heave(800, amp=0.02)}, k0)
    assert all(s["state"] == "off" for s in prediction_status(state).values())
    assert not any(f.startswith("fallback:") for o in outs for f in o.flags)
    assert prediction_status(state)["hex_z"]["weight"] == 0.0
    # given back while the PID stays bypassed: held until calm (no flag), then predicting
    set_bypass(state, pid_mask, prediction_off=[False] * len(AXES))
    assert list(state.comp.bypass) == pid_mask
    assert prediction_status(state)["hex_z"]["state"] == "held"
    outs = drive(params, state, {"hex_z": np.full(1500, x[-1])}, k0 + 800)
    assert "fallback:hex_z" not in outs[0].flags and "bypass:hex_z" in outs[0].flags
    st_z = prediction_status(state)["hex_z"]
    assert st_z["state"] == "predicting" and st_z["weight"] == 1.0
    assert all("bypass:hex_z" in o.flags for o in outs)
    assert "fallback:hex_z" not in outs[-1].flags


def test_the_shaper_not_live_forces_the_fallback() -> None:
    """The input stops: stale, then the hold and the ramp to neutral; the prediction is held
    off (status ``held``; the mode flag says why, no ``fallback:`` flag), and resumes once the
    input is back and the rejoin blend over."""
    params, state = new_tick(config())
    x = heave(3000, amp=0.03)
    drive(params, state, {"hex_z": x})
    assert prediction_status(state)["hex_z"]["state"] == "predicting"
    outs = [step(state, params, k * MS) for k in range(3000, 3200)]
    stale = [k for k, o in enumerate(outs) if o.mode]
    assert stale and not any("fallback:hex_z" in outs[k].flags for k in stale)
    assert prediction_status(state)["hex_z"]["weight"] == 0.0
    assert prediction_status(state)["hex_z"]["state"] == "held"
    outs = drive(params, state, {"hex_z": np.full(2500, x[-1])}, 3200)
    assert prediction_status(state)["hex_z"]["state"] == "predicting"
    assert not outs[-1].flags[-1].startswith("fallback:")


# --- 4. the limits whatever the reference -----------------------------------------------------
WARM = 2200  # past the start-up blend, resume_after_s and fade_in_s: predicting


@cache
def _warm() -> tuple[TickParams, TickState, tuple[tuple[float, ...], ...]]:
    params, state = new_tick(config())
    outs = drive(params, state, {"hex_z": heave(WARM, amp=0.02)})
    assert prediction_status(state)["hex_z"]["state"] == "predicting"
    return params, state, tuple(tuple(o.u) for o in outs)


sines = st.lists(st.tuples(st.floats(0.1, 2.0), st.floats(0.0, 0.12), st.floats(0, 2 * math.pi)),
                 min_size=1, max_size=3)
steps = st.lists(st.tuples(st.floats(-0.27, 0.27), st.integers(1, 300)), min_size=1, max_size=8)
bad_values = st.dictionaries(st.integers(0, 999), st.sampled_from([math.nan, math.inf,
                                                                   -math.inf]), max_size=20)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(kind=st.sampled_from(["band", "steps", "both"]), components=sines, levels=steps,
       axes=st.lists(st.sampled_from(HEX), min_size=1, max_size=3, unique=True),
       bad=bad_values)
def test_any_reference_keeps_the_command_within_the_limits(
        kind: str, components: list[tuple[float, float, float]],
        levels: list[tuple[float, int]], axes: list[str], bad: dict[int, float]) -> None:
    """Band-limited sums of sines (the reach's extent), piecewise-constant jumps anywhere in the
    reach, or both, on up to three predicted hexapod axes, with non-finite values in some
    frames (rejected): the tick never raises and every command stays within its axis' position,
    velocity and acceleration limits (from rest at neutral, the warm-up included)."""
    params, state, head = _warm()
    state = copy.deepcopy(state)
    n = 1000
    t = (WARM + np.arange(n)) * H
    band = sum(a * np.sin(2 * np.pi * f * t + ph) for f, a, ph in components)
    jumps = np.repeat([v for v, _ in levels], [d for _, d in levels])
    jumps = np.concatenate([jumps, np.full(max(0, n - jumps.size), jumps[-1])])[:n]
    x = {"band": band, "steps": jumps, "both": 0.5 * (band + jumps)}[kind]
    lo, hi = params.shaper.reach_lo, params.shaper.reach_hi
    outputs = [list(u) for u in head]
    rejected = state.rejected
    for j in range(n):
        k = WARM + j
        pos = {}
        for m, a in enumerate(axes):
            i = AXES.index(a)
            pos[a] = float(np.clip(x[j] * (1 - 0.3 * m), lo[i], hi[i]))
        if j in bad:
            pos[axes[0]] = bad[j]
        outputs.append(step(state, params, k * MS, encode_input(k, k * H, pos)).u)
    assert state.rejected - rejected == len(bad)
    assert state.rejected_by_reason["internal"] == 0
    assert_within_limits(outputs, state)


# --- 5. a reload swaps the prediction -------------------------------------------------------------
@pytest.mark.parametrize("change", [True, False])
def test_a_reload_with_new_coefficients_does_not_jump(change: bool) -> None:
    """Mid-heave, TickParams replaced by one whose prediction differs (a 50 ms predictor of
    another order) or is an equal copy: the limiter has nothing to do across the swap (the
    command's acceleration within its bound, no tick where it acted); an equal copy changes
    nothing at all."""
    n, k0 = 6000, 3000
    x = heave(n, amp=0.05)
    params, state = new_tick(config())
    twin = copy.deepcopy(state)
    new_pred = design(tau_s=0.05, order=8) if change else design()
    swapped = dataclasses.replace(params, prediction=tuple(
        new_pred if p is not None else None for p in params.prediction))
    assert (swapped.prediction != params.prediction) == change
    before = drive(params, state, {"hex_z": x[:k0]})
    acted = list(state.acted)
    after = drive(swapped, state, {"hex_z": x[k0:]}, k0)
    u = np.array([o.u[Z] for o in before + after])
    a_max = state.comp.limits.a_max[Z]
    assert np.max(np.abs(np.diff(u, 2))) <= a_max * H * H * (1 + 1e-9)
    assert state.acted == acted  # the limiter never acted after the swap
    d = np.abs(np.diff(u))
    assert np.max(d[k0 - 3:k0 + 3]) < 1.5 * np.max(d[k0 - 600:k0 - 3])  # no step at the swap
    ref = np.array([o.u[Z] for o in drive(params, twin, {"hex_z": x})])
    if change:
        assert prediction_status(state)["hex_z"]["state"] == "predicting"
        assert np.max(np.abs(u[-500:] - ref[-500:])) > 1e-4  # the new filter is in use
    else:
        np.testing.assert_array_equal(u, ref)


@pytest.mark.parametrize("switch_s", [6.0, 6.4, 6.8, 7.2, 7.6])
def test_switching_compensation_while_moving_leaves_the_limiter_idle(switch_s: float) -> None:
    """The example config's rails (prefilter and PID in series) on a 0.4 m slalom at full
    speed: ``set_bypass`` on at ``switch_s``, off 3 s later.  Both switches blend the prediction
    and the command over half a second or more: the command's acceleration never meets the
    6 m/s^2 limit and changes by less than 0.2 m/s^2 a tick (switched off, the prediction used
    to fade out in 20 ms: 93-292 ticks at the limit, steps of 12 m/s^2)."""
    cfg = parse_config(read_toml(EXAMPLE))
    params, state = new_tick(cfg, resolve_axes(cfg))
    y = AXES.index("rails_y")
    on, off = round(switch_s / H), round((switch_s + 3.0) / H)
    u = []
    for k in range(off + 2500):
        t = k * H
        if k == on:
            set_bypass(state, [a == y for a in range(len(AXES))])
        if k == off:
            set_bypass(state, [False] * len(AXES))
        value = 0.4 * math.sin(2 * math.pi * 0.3 * t) * min(t / 2.0, 1.0)
        out = step(state, params, 10**9 + k * MS, encode_input(k, t, {"rails_y": value}))
        u.append(out.u[y])
    acc = np.diff(np.array(u[on - 5:]), 2) / H**2
    assert np.abs(acc).max() < 0.9 * 6.0
    assert np.abs(np.diff(acc)).max() < 0.2
