"""The model supervision: the estimate against platforms simulated independently (exact ZOH
discretisation, :class:`~motcomp.sim.platform.PlatformSimulator`), the mismatch against its
closed form, the judge's alarm rules, the drifting simulated platform, and ``identify
--from-status``."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from motcomp.config import SupervisionConfig
from motcomp.core.axes import AXIS_INDEX as AXES_INDEX
from motcomp.core.models import OE, P1D, P2D, ProcessModel, parse_model
from motcomp.errors import ConfigError
from motcomp.resources import config_file
from motcomp.runtime.estimate import EstimateSettings, LiveWindow, estimate_axis, mismatch
from motcomp.runtime.supervise import CONFIDENCE_Z, DriftJudge
from motcomp.sim.hil import HilConfig, HilPlatform, default_truth, parse_drift
from motcomp.sim.platform import Accelerometer, PlatformSimulator
from motcomp.sim.source import builtin
from tests.conftest import motcomp_cmd, subprocess_env

RATE = 1000.0
MODEL = P1D(K=1.0, Td=0.0175, Tp1=0.1857683128)
NOISY = Accelerometer(noise_std=0.05, bias=0.02, tremor_hz=14.0, tremor_amp=0.03, lsb=0.001)
"""The sensor ``motcomp hil`` simulates."""
QUIET = Accelerometer()


def drive(truth: ProcessModel, u: np.ndarray, sensor: Accelerometer = QUIET, seed: int = 1
          ) -> tuple[np.ndarray, np.ndarray]:
    """Times and measured accelerations of a simulated platform driven by ``u`` at 1 kHz."""
    sim = PlatformSimulator([truth], RATE, [-5.0], [5.0], None, sensor, seed=seed)
    acc = np.array([sim.step([x])[1][0] for x in u])
    return np.arange(u.size) / RATE, acc


def driving(n_s: float, lead_s: float = 0.18) -> np.ndarray:
    """Ordinary driving on rails_y: slaloms and lane changes, with the lead a compensator
    adds (the command moves above the slalom's frequency too)."""
    r = np.concatenate([builtin("slalom").pos["rails_y"], builtin("lanechange").pos["rails_y"]])
    r = np.tile(r, math.ceil(n_s * RATE / r.size))[: round(n_s * RATE)]
    return np.asarray(r + lead_s * np.gradient(r, 1.0 / RATE))


def test_mismatch_is_the_phase_delay_and_gain_of_the_ratio() -> None:
    est = P1D(K=1.05, Td=0.0275, Tp1=0.21)
    for f in (0.1, 0.31, 1.7):
        w = 2 * math.pi * f
        delay = (0.0275 - 0.0175) + (math.atan(w * 0.21) - math.atan(w * MODEL.Tp1)) / w
        gain = 1.05 * math.hypot(1, w * MODEL.Tp1) / math.hypot(1, w * 0.21) - 1
        d, g = mismatch(est, MODEL, f)
        assert d == pytest.approx(delay, abs=1e-12) and g == pytest.approx(gain, abs=1e-12)


@pytest.mark.parametrize("truth", [MODEL, P1D(K=0.95, Td=0.0275, Tp1=0.24),
                                   P1D(K=1.0, Td=0.005, Tp1=0.12)])
def test_estimate_recovers_the_platform_from_ordinary_driving(truth: P1D) -> None:
    u = driving(20.0)
    t, acc = drive(truth, u)
    fig = estimate_axis(t, u, t, acc, MODEL, EstimateSettings(window_s=20.0))
    assert fig["informative"], fig["reason"]
    e = fig["estimate"]
    assert e["identified"] == "K, Td, Tp1"
    # a quiet sensor: the estimate is the truth to the fit's precision
    assert e["Td_ms"] == pytest.approx(truth.Td * 1e3, abs=0.05)
    assert e["Tp1_ms"] == pytest.approx(truth.Tp1 * 1e3, rel=1e-3)
    assert e["K"] == pytest.approx(truth.K, rel=1e-3)
    d, g = mismatch(truth, MODEL, fig["at_hz"])
    assert fig["residual_delay_ms"] == pytest.approx(d * 1e3, abs=0.05)
    assert fig["gain_error"] == pytest.approx(g, abs=1e-3)
    assert 0.1 <= fig["at_hz"] <= 2.0


def test_a_noisy_sensor_gives_an_honest_standard_error() -> None:
    truth = P1D(K=1.0, Td=0.0275, Tp1=MODEL.Tp1)
    errors = []
    for seed in range(6):
        u = driving(20.0)
        t, acc = drive(truth, u, NOISY, seed=seed)
        fig = estimate_axis(t, u, t, acc, MODEL)
        assert fig["informative"], fig["reason"]
        d, _ = mismatch(truth, MODEL, fig["at_hz"])
        errors.append((fig["residual_delay_ms"] - d * 1e3) / fig["residual_delay_se_ms"])
        assert fig["residual_delay_se_ms"] < 0.5
    # errors in standard errors: none beyond 3, and not all far inside (the figure is not
    # inflated tenfold either)
    assert max(abs(z) for z in errors) < 3.0, errors
    assert max(abs(z) for z in errors) > 0.05, errors


@pytest.mark.parametrize("drift_ms", [0.0, 10.0])
def test_a_platform_of_another_kind_is_judged_in_its_own_form(drift_ms: float) -> None:
    # the hexapod's P2UZD: a P1D read through it is off in the band and uncertain (its phase
    # cannot bend like the P2UZD's); its dynamics held, K and Td fitted, the drift reads as is
    model = parse_model("p2uzd:K=1,Td=0.0325,Tw=0.06399186527,Zeta=0.7,Tz=0.08764049978")
    truth = dataclasses.replace(model, Td=model.Td + drift_ms / 1e3)
    u = 0.2 * driving(20.0, lead_s=0.04)
    t, acc = drive(truth, u, NOISY)
    fig = estimate_axis(t, u, t, acc, model)
    assert fig["informative"], fig["reason"]
    e = fig["estimate"]
    assert e["identified"] == "K, Td (the model's dynamics held)" and e["Tp1_ms"] is None
    assert parse_model(e["spec"]).kind == "p2uzd"
    se = fig["residual_delay_se_ms"]
    assert se < 1.0
    # the same shape: the residual delay is the drift of Td, the gain error K's
    assert fig["residual_delay_ms"] == pytest.approx(drift_ms, abs=3 * se)
    assert e["Td_ms"] - model.Td * 1e3 == pytest.approx(fig["residual_delay_ms"], abs=1e-6)
    assert abs(fig["gain_error"]) <= 3 * fig["gain_error_se"] + 1e-3


def test_an_oe_model_is_judged_through_its_p1d_reduction() -> None:
    model = OE(num=(1.0,), den=(MODEL.Tp1, 1.0), Td=MODEL.Td, pade_order=1)
    u = driving(20.0)
    t, acc = drive(MODEL, u)
    fig = estimate_axis(t, u, t, acc, model)
    assert fig["model"] == model.to_p1d().spec() and fig["informative"], fig


def test_one_frequency_holds_tp1_at_the_model_and_still_tells_the_band() -> None:
    t = np.arange(round(20 * RATE)) / RATE
    u = 0.4 * np.sin(2 * math.pi * 0.31 * t)
    truth = P1D(K=1.0, Td=0.0225, Tp1=MODEL.Tp1)
    _, acc = drive(truth, u, NOISY, seed=3)
    fig = estimate_axis(t, u, t, acc, MODEL)
    assert fig["informative"], fig["reason"]
    assert fig["estimate"]["identified"] == "K, Td (Tp1 held at the model's)"
    assert fig["at_hz"] == pytest.approx(0.31, abs=0.02)
    assert fig["residual_delay_ms"] == pytest.approx(5.0, abs=0.5)
    assert fig["estimate"]["Td_ms"] == pytest.approx(22.5, abs=0.5)


@pytest.mark.parametrize(("u", "reason"), [
    (np.zeros(20000), "the command is constant"),
    (0.001 * np.sin(2 * math.pi * 0.3 * np.arange(20000) / RATE), "too little motion"),
    (0.4 * np.sin(2 * math.pi * 0.3 * np.arange(8000) / RATE), "of feedback paired"),
])
def test_a_window_that_cannot_tell_says_why(u: np.ndarray, reason: str) -> None:
    t, acc = drive(MODEL, u, NOISY)
    fig = estimate_axis(t, u, t, acc, MODEL)
    assert not fig["informative"] and reason in fig["reason"], fig["reason"]
    assert "residual_delay_ms" not in fig


def test_a_platform_the_p1d_does_not_describe_is_not_judged() -> None:
    u = driving(20.0)
    t = np.arange(u.size) / RATE
    rng = np.random.default_rng(0)
    fig = estimate_axis(t, u, t, rng.normal(0, 3.0, u.size), MODEL)
    assert not fig["informative"]
    assert "explains" in fig["reason"] or "uncertain" in fig["reason"], fig["reason"]


def test_live_window_keeps_the_last_seconds_in_time_order() -> None:
    w = LiveWindow(keep_s=5.0, axes=["rails_y"])
    for k in range(10):
        t = k + np.arange(1000) / 1000.0
        fb = t.copy()
        if k == 3:  # a sender's clock steps back a little: kept in order, and trimmed
            fb[500:] -= 0.0005
        w.add(t, np.zeros(1000), fb, np.zeros(1000))
    assert w.t_out[0] >= 10.0 - 5.0 - 1e-9 and w.t_out[-1] == pytest.approx(9.999)
    assert 5000 <= w.t_fb.size <= 5001 and np.all(np.diff(w.t_fb) >= 0)
    assert w.acc.shape == (w.t_fb.size, 1)
    t = np.arange(100) / 1000.0  # a restarted service: its clock starts again
    w.add(t, np.zeros(100), t, np.zeros(100))
    assert w.t_out.size == 100 and w.t_fb.size == 100


def _fig(delay: float, se: float = 0.2, gain: float = 0.0, informative: bool = True
         ) -> dict[str, object]:
    return {"informative": informative, "reason": "" if informative else "no motion",
            "residual_delay_ms": delay, "residual_delay_se_ms": se, "gain_error": gain,
            "gain_error_se": 0.001, "at_hz": 0.4, "model": MODEL.spec(),
            "estimate": {"spec": "p1d:K=1,Td=0.03,Tp1=0.19", "Td_ms": 30.0, "Td_se_ms": 0.3,
                         "identified": "K, Td, Tp1"}}


def test_the_status_keeps_the_last_informative_window() -> None:
    """An informative window then one that tells nothing: the axis' block holds the latest
    and, apart, the last informative one (what ``identify --from-status`` retunes from)."""
    j = DriftJudge(SupervisionConfig())
    told = _fig(10.0)
    j.update("rails_y", told, 1.0, 1.0)
    assert j.block("rails_y")["last_informative"] is None  # the latest is that one
    j.update("rails_y", {**_fig(0.0, informative=False), "reason": "stalls"}, 3.0, 3.0)
    block = j.block("rails_y")
    assert block["reason"] == "stalls" and block["last_informative"] == told


def test_a_window_without_its_end_adds_no_time_to_the_blind_motion() -> None:
    """A first estimate whose window has no end (``to_t`` None: the window not filled yet)
    followed by uninformative ones 2 s apart on the epoch clock: the axis was blind for their
    spacing, not for the epoch's seconds (it read "no window was judged in 1796001837 s of
    motion" 3 s after a start)."""
    j = DriftJudge(SupervisionConfig())
    blind = {**_fig(0.0, informative=False), "reason": "1.1 s of feedback paired with outputs"}
    assert j.update("rails_y", blind, None, 0.0) is None
    t0 = 1.796e9
    for k in range(5):
        assert j.update("rails_y", blind, t0 + 2.0 * k, 2.0 * k) is None
    assert j.axes["rails_y"].blind_s == pytest.approx(8.0)


def test_an_alarm_needs_the_whole_hold_beyond_the_bound_with_confidence() -> None:
    cfg = SupervisionConfig(delay_bound_ms=2.5, hold_s=8.0)
    j = DriftJudge(cfg)
    t = 0.0
    for _ in range(4):  # 6 s beyond: not yet, but the state says it is beyond
        assert j.update("rails_y", _fig(5.0), t, t) is None
        t += 2.0
    assert not j.block("rails_y")["alarm"] and j.block("rails_y")["state"] == "exceeds"
    text = j.update("rails_y", _fig(5.0), t, t)  # 8 s: the alarm, with its numbers
    assert text and "+5.00 +- 0.20 ms" in text and "identify --from-status" in text
    assert j.block("rails_y")["state"] == "drift" and j.block("rails_y")["alarms"] == 1
    # a window that is not informative keeps the alarm; within the bound for the hold clears it
    j.update("rails_y", _fig(0.0, informative=False), t + 2, t + 2)
    block = j.block("rails_y")
    assert block["alarm"] and not block["informative"]  # the last window's flag...
    assert block["windows"] == 6 and block["informative_windows"] == 5  # ...and the counts
    for k in range(5):
        j.update("rails_y", _fig(0.3), t + 4 + 2 * k, t + 4 + 2 * k)
    assert not j.block("rails_y")["alarm"]


def test_no_alarm_when_the_interval_reaches_the_bound_or_a_window_is_not_informative() -> None:
    cfg = SupervisionConfig(delay_bound_ms=2.5, hold_s=4.0)
    j = DriftJudge(cfg)
    se = 1.0
    for k in range(20):  # beyond the bound, but not by CONFIDENCE_Z standard errors
        j.update("rails_y", _fig(2.5 + CONFIDENCE_Z * se - 0.01, se=se), 2.0 * k, 2.0 * k)
    assert not j.block("rails_y")["alarm"] and j.block("rails_y")["state"] == "at the bound"
    for k in range(20):  # beyond, but every other window within: never held
        j.update("rails_y", _fig(9.0 if k % 2 else 0.0), 40 + 2.0 * k, 40 + 2.0 * k)
    assert not j.block("rails_y")["alarm"] and j.block("rails_y")["alarms"] == 0
    # windows that are not informative tell nothing: they neither reset nor count
    j.update("rails_y", _fig(0.0), 99.0, 99.0)
    j.update("rails_y", _fig(9.0), 100.0, 100.0)
    for k in range(5):
        j.update("rails_y", _fig(0.0, informative=False), 101.0 + k, 101.0 + k)
    j.update("rails_y", _fig(9.0), 106.0, 106.0)
    assert not j.block("rails_y")["alarm"]  # a long hold, but two estimates only
    j.update("rails_y", _fig(9.0), 107.0, 107.0)
    assert j.block("rails_y")["alarm"]
    for k in range(4):  # the gain alone
        j.update("rails_x", _fig(0.0, gain=-0.3), 2.0 * k, 2.0 * k)
    assert j.block("rails_x")["alarm"]


def test_parse_drift() -> None:
    d = parse_drift("rails_y=p1d:K=1,Td=0.0275,Tp1=0.1858@60+30")
    assert (d.axis, d.at_s, d.ramp_s) == ("rails_y", 60.0, 30.0)
    assert d.model == parse_model("p1d:K=1,Td=0.0275,Tp1=0.1858")
    assert parse_drift("hex_z=p1d:K=1,Td=0.01,Tp1=0.02@5").ramp_s == 0.0
    for bad, what in (("rails_q=p1d:K=1,Td=0,Tp1=0.1@5", "AXIS=SPEC"),
                      ("rails_y=p1d:K=1,Td=0,Tp1=0.1", "AXIS=SPEC"),
                      ("rails_y=p1d:K=1,Td=0,Tp1=0.1@soon", "seconds"),
                      ("rails_y=p1d:K=1,Td=0,Tp1=0.1@-1", ">= 0"),
                      ("rails_y=p1d:bad@5",
                       r"^--drift 'rails_y=p1d:bad@5': model spec .*KEY=VALUE")):
        with pytest.raises(ConfigError, match=what):
            parse_drift(bad)


def _hil(drifts: list[str]) -> HilPlatform:
    models, p_min, p_max, _ = default_truth()
    return HilPlatform(HilConfig(models=models, p_min=p_min, p_max=p_max, v_max=None,
                                 drifts=[parse_drift(d) for d in drifts]))


def test_hil_truth_steps_and_ramps_at_the_given_times() -> None:
    plat = _hil(["rails_y=p1d:K=1,Td=0.0275,Tp1=0.1857683128@10",
                 "rails_x=p1d:K=1,Td=0.0175,Tp1=0.2857683128@5+10"])
    y, x = 1, 0
    plat.drift_to(4.99)
    assert plat.sim.models[y].Td == 0.0175 and plat.sim.models[x].Tp1 == MODEL.Tp1
    plat.drift_to(10.0)
    assert plat.sim.models[y] == parse_model("p1d:K=1,Td=0.0275,Tp1=0.1857683128")
    assert plat.sim.models[x].Tp1 == pytest.approx(MODEL.Tp1 + 0.05)  # half way
    plat.drift_to(15.0)
    assert plat.sim.models[x].Tp1 == pytest.approx(0.2857683128)
    with pytest.raises(ConfigError, match="kind"):
        _hil(["rails_y=p2d:K=1,Td=0.0275,Tp1=0.1,Tp2=0.01@10"])
    with pytest.raises(ConfigError, match=r"beyond 0\.25 s"):  # at start, not mid-run
        _hil(["rails_y=p1d:K=1,Td=0.3,Tp1=0.1857683128@10"])


def test_a_drifted_simulator_continues_as_the_new_model() -> None:
    a, b = MODEL, P1D(K=1.1, Td=0.0275, Tp1=0.25)
    u = 0.3 * np.sin(2 * math.pi * 0.5 * np.arange(8000) / RATE)
    drifted = PlatformSimulator([a], RATE, [-5], [5])
    only_b = PlatformSimulator([b], RATE, [-5], [5])
    y = []
    for k, x in enumerate(u):
        if k == 3000:
            drifted.set_model(0, b)
        y.append(drifted.step([x])[0][0])
        yb = only_b.step([x])[0][0]
    assert abs(y[3000] - y[2999]) < 1e-3  # the position carries over
    assert abs(y[-1] - yb) < 1e-6  # and forgets the old model
    with pytest.raises(ConfigError, match="same first-order"):
        PlatformSimulator([P2D(K=1, Td=0.01, Tp1=0.1, Tp2=0.02)], RATE, [-5], [5]).set_model(
            0, P2D(K=1, Td=0.01, Tp1=0.2, Tp2=0.02))


def _status(informative: bool) -> dict[str, object]:
    fig = {**_fig(10.0, informative=informative), "alarm": informative, "from_t": 100.0,
           "to_t": 120.0}
    fig["estimate"] = {"spec": "p1d:K=1.001,Td=0.0276,Tp1=0.186", "K": 1.001, "K_se": 0.001,
                       "Td_ms": 27.6, "Td_se_ms": 0.3, "Tp1_ms": 186.0, "Tp1_se_ms": 0.4,
                       "identified": "K, Td, Tp1", "explained": 0.9998}
    return {"t": 1.0e9, "model_mismatch": {"axes": {"rails_y": fig, "rails_x": _fig(0.0)}}}


def test_identify_from_a_saved_status_writes_the_fragment(tmp_path: Path) -> None:
    saved = tmp_path / "status.json"

    def from_status(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(motcomp_cmd("identify", str(saved), "--from-status", *args),
                              capture_output=True, text=True, env=subprocess_env(), timeout=60)

    saved.write_text(json.dumps(_status(True)))
    p = from_status("--out", str(tmp_path / "retune"))
    assert p.returncode == 0, p.stderr
    text = (tmp_path / "retune" / "rails_y.toml").read_text()
    assert '[axes.rails_y]\nmodel = "p1d:K=1.001,Td=0.0276,Tp1=0.186"' in text
    assert "residual delay +10.00 +- 0.20 ms" in text
    # not informative: no fragment, exit 2, the reason said
    saved.write_text(json.dumps(_status(False)))
    p = from_status("--axis", "rails_y", "--out", str(tmp_path / "again"))
    assert p.returncode == 2 and "not informative (no motion)" in p.stderr, p.stderr
    assert not (tmp_path / "again").exists()
    # no axis in alarm and none given: the axes supervision watches, each with its state
    st = _status(False)
    st["model_mismatch"]["axes"]["rails_y"]["state"] = "unsupervised"  # type: ignore[index]
    saved.write_text(json.dumps(st))
    p = from_status("--out", str(tmp_path / "again"))
    assert p.returncode == 2 and ("none is in alarm; the axes supervision watches, with their "
                                  "state: rails_y (unsupervised), rails_x (state unknown)"
                                  ) in p.stderr, p.stderr
    # the latest window told nothing, an earlier one did: that one is taken, and said
    st = _status(True)
    alarmed = st["model_mismatch"]["axes"]["rails_y"]  # type: ignore[index]
    st["model_mismatch"]["axes"]["rails_y"] = {  # type: ignore[index]
        **_fig(0.0, informative=False), "alarm": True, "last_informative": alarmed,
        "reason": "5 stalls of the host cut out 13.8 s of the window", "state": "unsupervised",
        "blind_s": 655.0}
    del st["model_mismatch"]["axes"]["rails_y"]["estimate"]  # type: ignore[index]
    st["t"] = 800.0  # 680 s after that window ended
    saved.write_text(json.dumps(st))
    p = from_status("--out", str(tmp_path / "earlier"))
    assert p.returncode == 0, p.stderr
    text = (tmp_path / "earlier" / "rails_y.toml").read_text()
    assert 'model = "p1d:K=1.001,Td=0.0276,Tp1=0.186"' in text
    flat = " ".join(ln.lstrip("# ") for ln in text.splitlines())
    assert "the last informative window (the latest is not: 5 stalls" in flat, text
    # ...and how old it is, and what the axis is now, in the fragment and on stderr
    note = ("rails_y: the estimate is from a window that ended 680 s before the status; the "
            "axis is unsupervised now (no window judged for 655 s): the platform may have "
            "changed since")
    assert f"warning: {note}" in p.stderr, p.stderr
    assert f"Note: {note}." in flat, text
    saved.write_text(json.dumps({"t": 1.0}))
    p = from_status()
    assert p.returncode != 0 and "no model_mismatch block" in p.stderr, p.stderr


def test_the_status_table_and_a_recording_summary_show_the_alarms() -> None:
    from motcomp.cli.admin import format_status
    from motcomp.cli.info import _mismatch

    block = {"enabled": True, "window_s": 15.0, "delay_bound_ms": 2.5, "gain_bound": 0.1,
             "hold_s": 6.0, "errors": 0, "axes": {}}
    frames = []
    for k, alarm in enumerate([False, False, True, True, False, True]):
        fig = {**_status(True)["model_mismatch"]["axes"]["rails_y"], "alarm": alarm}  # type: ignore[index]
        frames.append((int(1e9) * (k + 1), {"model_mismatch": {**block,
                                                               "axes": {"rails_y": fig}}}))
    mm = _mismatch(frames, 0)["rails_y"]
    assert mm["alarms"] == [[3.0, 5.0], [6.0, None]]
    assert mm["residual_delay_ms_at_alarm"] == [10.0, 10.0]
    assert mm["last_estimate"]["spec"] == "p1d:K=1.001,Td=0.0276,Tp1=0.186"
    text = format_status(frames[-1][1])
    row = next(ln for ln in text.splitlines() if ln.strip().startswith("rails_y") and
               "DRIFT" in ln)
    assert "+10.00" in row and "27.60" in row, text


def test_the_supervisor_judges_a_window_without_its_end_as_adding_no_time() -> None:
    """The same through the supervisor's own judging of its estimator's results: a result
    without ``to_t`` (the window not filled yet) is judged with no end, not at 0 s nor at
    the epoch, and the results after it add their spacing on the frame clock."""
    from motcomp.config import load_config, resolve_axes
    from motcomp.runtime.supervise import Supervisor

    sup = Supervisor(SupervisionConfig(), resolve_axes(load_config(config_file("motcomp.toml"))))
    try:
        model = sup.models["rails_y"].spec()
        blind = {**_fig(0.0, informative=False), "model": model,
                 "reason": "1.1 s of feedback paired with outputs"}
        assert sup._judge({"rails_y": dict(blind)}, 0.0) == []
        state = sup.judge.axes["rails_y"]
        assert state.judged == 1 and state.last_t is None and state.blind_s == 0.0
        t0 = 1.796e9
        for k in range(5):
            assert sup._judge({"rails_y": {**blind, "to_t": t0 + 2.0 * k}}, 2.0 * k) == []
        assert state.judged == 6 and state.blind_s == pytest.approx(8.0)
        assert state.last_t == t0 + 8.0
    finally:
        sup.close()


@pytest.mark.parametrize("missed", [0.1, 0.3])
def test_a_window_the_host_starved_is_not_informative(missed: float) -> None:
    """A window in which the loop missed more than MAX_JUDGED_MISSED_SHARE of its deadlines is not
    judged, its reason says so (an unchanged hexapod read 5.5 ms late at 45-55 % missed); at
    10 % the estimate is judged."""
    from motcomp.config import load_config, resolve_axes
    from motcomp.runtime.monitor import MAX_JUDGED_MISSED_SHARE
    from motcomp.runtime.supervise import Supervisor

    sup = Supervisor(SupervisionConfig(), resolve_axes(load_config(config_file("motcomp.toml"))))
    try:
        model = sup.models["rails_y"].spec()
        # the window's counters: 15 s, ticks and missed deadlines in the given share
        ticks = 15_000
        lost = round(missed * ticks / (1.0 - missed))
        sup._shares.extend([(0.0, 0, (0,) * 8, 0), (15.0, ticks, (0,) * 8, lost)])
        fig = {**_fig(10.0), "model": model}
        sup._judge({"rails_y": fig}, 15.0)
        assert fig["missed_share"] == pytest.approx(missed, abs=1e-4)
        assert fig["informative"] is (missed <= MAX_JUDGED_MISSED_SHARE), fig
        if missed > MAX_JUDGED_MISSED_SHARE:
            assert fig["reason"].startswith("the loop missed 30 % of its deadlines"), fig
        # an estimate the estimator itself found uncertain: the host's stalls are named first
        # (the likely cause), the estimator's reason after them; an axis that did not move
        # keeps its own reason (not a blind window)
        for own in ("the residual delay is uncertain (+-2.64 ms > 1 ms)",
                    "too little motion in the band (0.02 m/s^2 rms)"):
            fig = {**_fig(10.0), "model": model, "informative": False, "reason": own}
            sup._judge({"rails_y": fig}, 15.0)
            assert fig["informative"] is False
            if missed > MAX_JUDGED_MISSED_SHARE and not own.startswith("too little"):
                assert fig["reason"] == ("the loop missed 30 % of its deadlines over the window "
                                         "(more than 20 %): the figures carry its stalls "
                                         f"(and {own})"), fig
            else:
                assert fig["reason"] == own, fig
    finally:
        sup.close()


def test_a_reload_that_replaces_the_model_ends_its_alarm_in_the_log(
        caplog: pytest.LogCaptureFixture) -> None:
    """An axis in alarm whose model a reload replaces is judged anew: the log says that its
    alarm ends with the model it was raised on (before, the state went back to ok unsaid)."""
    from motcomp.config import load_config, resolve_axes
    from motcomp.runtime.supervise import Supervisor, _AxisState

    cfg = load_config(config_file("motcomp.toml"))
    sup = Supervisor(SupervisionConfig(), resolve_axes(cfg))
    try:
        sup.judge.axes["rails_y"] = _AxisState(alarm=True)
        other = cfg.model_copy(update={"axes": {**cfg.axes, "rails_y": cfg.axes[
            "rails_y"].model_copy(update={"model": "p1d:K=1,Td=0.0275,Tp1=0.19"})}})
        with caplog.at_level("INFO", logger="motcomp.supervise"):
            sup.set_axes(resolve_axes(other))
        assert "rails_y" not in sup.judge.axes
        text = caplog.text
        assert "rails_y: the model is now p1d:K=1,Td=0.0275,Tp1=0.19" in text
        assert "its model mismatch alarm ends with the model it was raised on" in text
    finally:
        sup.close()


def test_the_supervisor_estimates_in_its_own_process_from_the_monitor() -> None:
    import time

    from motcomp.config import load_config, resolve_axes
    from motcomp.io.wire import encode_feedback
    from motcomp.runtime.monitor import MotionMonitor
    from motcomp.runtime.supervise import Supervisor

    cfg = load_config(config_file("motcomp.toml"))
    axes = resolve_axes(cfg)
    truth = P1D(K=1.0, Td=0.0275, Tp1=MODEL.Tp1)  # 10 ms more than the example's rails model
    u = driving(14.0)
    t, acc = drive(truth, u, NOISY)
    monitor = MotionMonitor(RATE, 10.0)
    sup = Supervisor(SupervisionConfig(period_s=1.0), axes)
    y = AXES_INDEX["rails_y"]
    try:
        for second in range(14):
            for k in range(second * 1000, (second + 1) * 1000):
                row = [0.0] * 8
                row[y] = float(u[k])
                monitor.record(k * 1_000_000, row, row)
                monitor.on_feedback(k * 1_000_000, encode_feedback(
                    float(t[k]), {"rails_y": float(u[k])}, {"rails_y": float(acc[k])}))
            monitor.drain()
            t_end = time.monotonic() + 60.0
            sup.poll(monitor, lambda ns: ns / 1e9, float(second), (second + 1) * 1000,
                     [0] * 8, 0)
            while sup._busy_since is not None and time.monotonic() < t_end:
                time.sleep(0.02)  # the test waits for each answer; the service does not
                sup.poll(monitor, lambda ns: ns / 1e9, float(second), (second + 1) * 1000,
                         [0] * 8, 0)
        sup.poll(monitor, lambda ns: ns / 1e9, 100.0, 14000, [0] * 8, 0)
        block = sup.status()
    finally:
        sup.close()
    fig = block["axes"]["rails_y"]
    assert block["estimates"] >= 10 and block["errors"] == 0 and block["cpu_s"] > 0
    assert fig["informative"], fig["reason"]
    assert fig["residual_delay_ms"] == pytest.approx(10.0, abs=1.0)
    # a driven axis whose feedback lacks its acceleration says so
    assert block["axes"]["hex_z"]["reason"] == "no feedback acceleration of hex_z in the window"


def _children(pid: int) -> list[tuple[int, str]]:
    """The child processes of ``pid`` with their command lines."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            out.append((int(entry.name), cmd))
    return out


def test_the_estimator_process_ends_with_a_service_that_dies(tmp_path: Path) -> None:
    import signal
    import time

    from motcomp.io.zenoh_io import free_tcp_port, loopback
    from tests.test_service_process import process

    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{config_file("motcomp.toml")}"]\n'
                    "[supervision]\nperiod_s = 0.5\n")
    with process(["run", "--config", str(site), "-l", loopback(free_tcp_port())],
                 tmp_path / "svc.log") as svc:
        t_end = time.monotonic() + 30.0
        helper = []
        while time.monotonic() < t_end and not helper:
            time.sleep(0.5)
            helper = [p for p, cmd in _children(svc.pid) if "runtime.supervise" in cmd]
        assert helper, (tmp_path / "svc.log").read_text()[-2000:]
        svc.send_signal(signal.SIGKILL)  # no goodbye: the estimator must notice by itself
        svc.wait(timeout=10)
        t_end = time.monotonic() + 10.0
        while time.monotonic() < t_end and Path(f"/proc/{helper[0]}").exists():
            time.sleep(0.2)
        state = (Path(f"/proc/{helper[0]}/stat").read_text().split()[2]
                 if Path(f"/proc/{helper[0]}").exists() else "gone")
        assert state in ("gone", "Z"), f"the estimator process {helper[0]} outlived the service"


def test_an_estimate_whose_interval_holds_the_bound_moves_neither_way() -> None:
    j = DriftJudge(SupervisionConfig(delay_bound_ms=2.5, hold_s=4.0))
    for k in range(4):
        j.update("rails_y", _fig(6.0), 2.0 * k, 2.0 * k)
    assert j.block("rails_y")["alarm"]
    # 2.0 +- 2 x 0.4 ms: within the bound, but its interval is not: the alarm stays
    for k in range(10):
        j.update("rails_y", _fig(2.0, se=0.4), 10 + 2.0 * k, 10 + 2.0 * k)
    assert j.block("rails_y")["alarm"] and j.block("rails_y")["state"] == "drift"
    for k in range(4):
        j.update("rails_y", _fig(1.0, se=0.4), 40 + 2.0 * k, 40 + 2.0 * k)
    assert not j.block("rails_y")["alarm"] and j.block("rails_y")["state"] == "within"


def test_the_service_process_does_not_load_what_only_the_estimator_needs() -> None:
    # scipy would add some 70 MB to the service's memory; only the estimator process uses it
    p = subprocess.run([sys.executable, "-c", "import sys, motcomp.runtime.service, "
                        "motcomp.runtime.supervise; print(sorted(m for m in sys.modules "
                        "if m.split('.')[0] == 'scipy'))"],
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "[]", p.stdout


def test_a_reversed_accelerometer_is_estimated_with_its_sign() -> None:
    u = driving(20.0)
    truth = P1D(K=-1.0, Td=0.0175, Tp1=MODEL.Tp1)
    t, acc = drive(truth, u)
    fig = estimate_axis(t, u, t, acc, P1D(K=-1.0, Td=0.0175, Tp1=MODEL.Tp1))
    assert fig["informative"], fig["reason"]
    assert fig["estimate"]["K"] == pytest.approx(-1.0, rel=1e-3)
    assert abs(fig["residual_delay_ms"]) < 0.05 and abs(fig["gain_error"]) < 1e-3


def _stalled(truth: ProcessModel, u: np.ndarray, at_s: float, stall_s: float,
             sensor: Accelerometer = QUIET) -> tuple[np.ndarray, np.ndarray]:
    """A platform that stalls ``stall_s`` at ``at_s``: it applies no new setpoint meanwhile
    (its input stays the one before) and sends no feedback; then it goes on with the newest."""
    sim = PlatformSimulator([truth], RATE, [-5.0], [5.0], None, sensor, seed=1)
    a, b = round(at_s * RATE), round((at_s + stall_s) * RATE)
    acc = np.array([sim.step([float(u[min(k, a - 1)] if a <= k < b else u[k])])[1][0]
                    for k in range(u.size)])
    keep = np.ones(u.size, bool)
    keep[a:b] = False
    t = np.arange(u.size) / RATE
    return t[keep], acc[keep]


def test_a_stall_costs_the_samples_it_touched_not_the_window() -> None:
    truth = P1D(K=1.0, Td=0.0255, Tp1=0.2)
    u = driving(20.0)
    t = np.arange(u.size) / RATE
    # the platform stalls 50 ms at 9 s, during the lane change's motion; the loop misses 50 ms
    # of outputs at 14 s (the platform holds the last one, as the pairing does)
    t_fb, acc = _stalled(truth, u, 9.0, 0.05)
    keep_out = (t < 14.0) | (t >= 14.05)
    v = float(np.max(np.abs(np.diff(u[9000:9050])))) * RATE
    assert v > 0.1  # the platform missed motion there: 0.5 v (50 ms)^2 > stall_area
    fig = estimate_axis(t[keep_out], u[keep_out], t_fb, acc, MODEL,
                        EstimateSettings(window_s=20.0))
    assert fig["informative"], fig["reason"]
    assert fig["stalls"] == 2
    settle = EstimateSettings().settle_s
    assert fig["cut_s"] == pytest.approx(2 * (0.05 + settle), abs=0.01)
    d, _ = mismatch(truth, MODEL, fig["at_hz"])
    assert fig["residual_delay_ms"] == pytest.approx(d * 1e3, abs=0.05)
    assert fig["estimate"]["Td_ms"] == pytest.approx(25.5, abs=0.05)
    # the same window with the stall judged: the stale input's error is in the fit
    whole = estimate_axis(t[keep_out], u[keep_out], t_fb, acc, MODEL,
                          EstimateSettings(window_s=20.0, stall_s=1.0, stall_area=1.0))
    assert whole["stalls"] == 0
    off = abs(whole["residual_delay_ms"] - d * 1e3)
    assert off > 10 * abs(fig["residual_delay_ms"] - d * 1e3) and off > 0.1, (off, whole)


def test_stalls_that_leave_too_little_to_judge_are_said() -> None:
    u = driving(20.0)
    t = np.arange(u.size) / RATE
    keep = np.ones(u.size, bool)
    for at in np.arange(3.0, 19.0, 0.5):  # a 30 ms stall of the outputs every 0.5 s
        keep[round(at * RATE):round((at + 0.03) * RATE)] = False
    _, acc = drive(MODEL, u)
    fig = estimate_axis(t[keep], u[keep], t, acc, MODEL, EstimateSettings(window_s=20.0))
    assert not fig["informative"]
    assert fig["reason"].startswith("32 stretch(es) of stalls of the host or the platform's "
                                    "link (stalls less than 0.4 s apart run together) cut out")
    assert "left to judge (needs 6.1 s)" in fig["reason"], fig["reason"]


def test_a_window_all_cut_out_by_stalls_is_said_without_a_warning() -> None:
    """Stalls less than ``settle_s`` apart from the first sample to the last: nothing is left
    to judge, and nothing is computed over the empty rest (the estimator's warnings go to the
    service's log)."""
    import warnings

    u = driving(20.0)
    t = np.arange(u.size) / RATE
    keep = np.ones(u.size, bool)
    for at in np.arange(0.0, 20.0, 0.3):
        keep[round(at * RATE):round((at + 0.03) * RATE)] = False
    keep[0] = keep[-1] = True
    _, acc = drive(MODEL, u)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fig = estimate_axis(t[keep], u[keep], t, acc, MODEL, EstimateSettings(window_s=20.0))
    assert not fig["informative"]
    assert fig["cut_s"] == pytest.approx(20.0, abs=0.01), fig
    assert "0.0 s left to judge" in fig["reason"], fig["reason"]


def test_the_residual_is_judged_where_the_driving_determines_it_best() -> None:
    # a platform whose lag differs from the model's: the residual delay depends on the
    # frequency; it is reported at the driven frequency of least standard error, and equals
    # the closed form there
    truth = P1D(K=1.0, Td=0.0215, Tp1=0.19)
    u = driving(15.0)
    t, acc = drive(truth, u, NOISY)
    fig = estimate_axis(t, u, t, acc, MODEL)
    assert fig["informative"], fig["reason"]
    d, _ = mismatch(truth, MODEL, fig["at_hz"])
    se = fig["residual_delay_se_ms"]
    assert fig["residual_delay_ms"] == pytest.approx(d * 1e3, abs=3 * se)
    # at the motion's power centre (the slalom's 0.3 Hz) the delay is less certain: the
    # chosen frequency's standard error is the smallest of those the driving moves
    e = fig["estimate"]
    assert e["identified"] == "K, Td, Tp1"
    assert 0.1 <= fig["at_hz"] <= 2.0


def _uncertain(se: float = 3.0) -> dict[str, object]:
    return {**_fig(5.0, se=se, informative=False),
            "reason": f"the residual delay is uncertain (+-{se:.2f} ms > 1 ms)"}


def test_an_axis_blind_for_two_minutes_of_motion_is_said_unsupervised(
        caplog: pytest.LogCaptureFixture) -> None:
    from motcomp.runtime.supervise import BLIND_AFTER_S

    j = DriftJudge(SupervisionConfig())
    texts = []
    t = 0.0
    # standing still tells nothing and is not blindness
    for _ in range(100):
        texts.append(j.update("rails_y", {**_fig(0.0, informative=False),
                                          "reason": "too little motion in 0.1-2 Hz"}, t, t))
        t += 2.0
    assert j.block("rails_y")["blind_s"] == 0.0 and not any(texts)
    for k in range(int(BLIND_AFTER_S / 2.0) + 5):
        fig = _uncertain() if k % 4 else {**_fig(0.0, informative=False),
                                          "reason": "3 stalls of the host or the platform's "
                                                    "link cut out 8.1 s of the window"}
        texts.append(j.update("rails_y", fig, t, t))
        t += 2.0
    said = [x for x in texts if x]
    assert len(said) == 1, said  # once
    assert said[0].startswith("rails_y: unsupervised: no window was judged in 120 s of motion")
    assert "uncertain" in said[0] and "stalls" in said[0] and "It needs" in said[0]
    assert "driving that moves the axis" in said[0] and "a host that keeps" in said[0]
    block = j.block("rails_y")
    assert block["state"] == "unsupervised" and block["unsupervised"]
    with caplog.at_level("INFO", logger="motcomp.supervise"):
        j.update("rails_y", _fig(0.3), t, t)
    assert j.block("rails_y")["state"] == "within" and j.block("rails_y")["blind_s"] == 0.0
    assert "supervised again" in caplog.text


class _StubEstimator:
    """In place of the estimator process: answers each request at once with ``cpu_s``."""

    def __init__(self, cpu_s: float) -> None:
        self.cpu_s = cpu_s
        self.asked: list[float] = []
        self.now = 0.0
        self._reply: tuple[str, object] | None = None

    def ask(self, request: object) -> None:
        self.asked.append(self.now)
        self._reply = ("ok", ({}, self.cpu_s))

    def answer(self) -> tuple[str, object] | None:
        reply, self._reply = self._reply, None
        return reply

    def close(self) -> None:
        pass


class _StubMonitor:
    def chunk(self, since: tuple[int, int]) -> tuple[tuple[int, int], dict[str, object]]:
        return since, {"t_ns": np.zeros(0, np.int64), "u": np.zeros((0, 8)),
                       "fb_sent": np.zeros(0), "fb_ns": np.zeros(0, np.int64),
                       "acc": np.zeros((0, 8)), "lost": False}


def test_the_estimator_is_held_to_its_cpu_budget() -> None:
    from motcomp.config import load_config, resolve_axes
    from motcomp.runtime.supervise import CPU_SHARE_MAX, Supervisor

    axes = resolve_axes(load_config(config_file("motcomp.toml")))
    sup = Supervisor(SupervisionConfig(period_s=2.0), axes)
    stub = _StubEstimator(cpu_s=0.5)  # an estimate of 0.5 s CPU: one per 5 s at most
    sup._estimator = stub  # type: ignore[assignment]
    for k in range(200):  # 20 s, polled every 0.1 s
        stub.now = 0.1 * k
        sup.poll(_StubMonitor(), lambda ns: ns / 1e9, stub.now, 0, [0] * 8, 0)
    gaps = np.diff(stub.asked)
    assert len(stub.asked) >= 4 and np.all(gaps >= 0.5 / CPU_SHARE_MAX - 1e-9), stub.asked
    # each estimate's CPU time over the time to the next request
    assert (len(gaps) * 0.5) / (stub.asked[-1] - stub.asked[0]) <= CPU_SHARE_MAX + 1e-9
    assert sup.status()["cpu_share"] == pytest.approx(len(stub.asked) * 0.5 / 19.9)
    # a cheap estimate: one per period, as configured
    stub.cpu_s, stub.asked = 0.01, []
    for k in range(200, 400):
        stub.now = 0.1 * k
        sup.poll(_StubMonitor(), lambda ns: ns / 1e9, stub.now, 0, [0] * 8, 0)
    assert np.allclose(np.diff(stub.asked[1:]), 2.0, atol=0.11), stub.asked


def test_an_estimator_that_gets_no_cpu_is_said(caplog: pytest.LogCaptureFixture) -> None:
    from motcomp.config import load_config, resolve_axes
    from motcomp.runtime.supervise import BLIND_AFTER_S, Supervisor

    class Silent(_StubEstimator):
        def answer(self) -> tuple[str, object] | None:
            return None  # starved: never answers

        def kill(self) -> None:
            pass

    axes = resolve_axes(load_config(config_file("motcomp.toml")))
    sup = Supervisor(SupervisionConfig(period_s=2.0), axes)
    stub = Silent(cpu_s=0.0)
    sup._estimator = stub  # type: ignore[assignment]
    said = []
    for k in range(round((BLIND_AFTER_S + 10.0) / 0.5)):
        said += sup.poll(_StubMonitor(), lambda ns: ns / 1e9, 0.5 * k, 0, [0] * 8, 0)
    assert len(said) == 1 and said[0].startswith(
        "model supervision: unsupervised: no estimate in 120 s"), said
    assert "gets no CPU time on this host" in said[0]
    block = sup.status()
    assert block["starved"] and block["axes"]["rails_y"]["state"] == "unsupervised"
