"""The retune path never dead-ends: what ``motcomp design`` writes for a retuned model -- a
bypass recommendation included -- is a config ``config check`` accepts; ``identify
--from-status`` refuses an estimate of no plausible platform, and ``--force`` marks what it
writes so that ``config check`` and the service warn; the identify report's model comparison
says what it found; the simulated platforms say when they drift."""

from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from motcomp.config import BYPASS_STAND_IN_RULE, load_config, new_tick, resolve_axes
from motcomp.core.loop import stability
from motcomp.core.models import P1D, parse_model
from motcomp.core.tuning import tune
from motcomp.design.report import config_fragment as design_fragment
from motcomp.ident.fit import ModelFit, select_model
from motcomp.ident.live import probe_host
from motcomp.ident.report import model_fragment
from motcomp.resources import config_file
from tests.conftest import ROOT, motcomp_cmd, subprocess_env

RETUNED = "p1d:K=1,Td=0.141,Tp1=0.05"
"""A retune's model far from the example config's rails (Td 17.5 ms): the example's gains make
the internal loop unstable with it."""


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                          env=subprocess_env(), timeout=120)


def _bypass_design(model: str) -> str:
    """What ``motcomp design --rule optimal --out`` writes when it recommends bypass."""
    report = {"rule": "optimal", "rate_hz": 1000.0, "model_spec": model, "plant_spec": model,
              "corrected": {"max_residual_delay_ms": 160.0, "peak_gain_db": 0.0,
                            "hf_from_hz": 10.0},
              "recommendation": "bypass", "prediction": {"used": False}}
    return design_fragment(report, "rails_y")


def test_a_bypass_recommendation_for_a_retuned_model_gives_a_config_that_runs(
        tmp_path: Path) -> None:
    (tmp_path / "retune.toml").write_text(model_fragment("rails_y", RETUNED, ["# retune"]))
    (tmp_path / "design.toml").write_text(_bypass_design(RETUNED))
    assert "bypass = true" in (tmp_path / "design.toml").read_text()
    assert "gains" not in (tmp_path / "design.toml").read_text().split("[axes.rails_y]")[1]
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{config_file("motcomp.toml")}", "retune.toml", '
                    '"design.toml"]\n')
    p = cli("config", "check", str(site))
    assert p.returncode == 0, p.stderr
    kp = load_config(config_file("motcomp.toml")).axes["rails_y"].gains.kp  # the example's
    assert f"rails_y: bypassed, and its gains (kp={kp:.4g}" in p.stderr
    assert f"the {BYPASS_STAND_IN_RULE} rule's gains for this model stand in" in p.stderr
    # the service's own check: the tick builds with the stand-in, which is stable
    cfg = load_config(site)
    axes = resolve_axes(cfg)
    y = axes.names.index("rails_y")
    model = parse_model(RETUNED).to_p1d()
    assert axes.bypass[y] and axes.gains[y] == tune(BYPASS_STAND_IN_RULE, model).gains
    assert stability(axes.gains[y], model, 1000.0)[0]
    new_tick(cfg, axes)
    # the example's own bypassed hexapod keeps its gains, without a word
    assert not [w for w in axes.warnings if w.startswith("hex_")]
    # not bypassed, the same gains are refused as before: a compensated axis is never run
    # with gains its model makes unstable
    (tmp_path / "design.toml").write_text("[axes.rails_y]\nbypass = false\n")
    p = cli("config", "check", str(site))
    assert p.returncode == 2 and "make the internal loop unstable" in p.stderr, p.stderr


def _status(informative: bool, td_ms: float, td_se_ms: float) -> dict[str, Any]:
    est = {"spec": f"p1d:K=1.02,Td={td_ms / 1e3:.6g},Tp1=0.05", "K": 1.02, "K_se": 0.01,
           "Td_ms": td_ms, "Td_se_ms": td_se_ms, "Tp1_ms": 50.0, "Tp1_se_ms": 4.0,
           "identified": "K, Td, Tp1", "explained": 0.93}
    fig = {"informative": informative, "alarm": True, "from_t": 100.0, "to_t": 115.0,
           "at_hz": 0.4, "model": "p1d:K=1,Td=0.0175,Tp1=0.1857683128", "estimate": est,
           "reason": "" if informative else "the residual delay is uncertain (+-8.90 ms > 1 ms)",
           "residual_delay_ms": 60.0, "residual_delay_se_ms": 8.9, "gain_error": 0.02,
           "gain_error_se": 0.01, "pairing_phase_ms": 0.42}
    return {"t": 1.0e9, "model_mismatch": {"axes": {"rails_y": fig}}}


def test_an_implausible_estimate_is_refused_and_forced_only_with_a_mark(tmp_path: Path) -> None:
    saved = tmp_path / "status.json"
    saved.write_text(json.dumps(_status(False, 141.0, 40.0)))
    p = cli("identify", str(saved), "--from-status", "--out", str(tmp_path / "a"))
    assert p.returncode == 2, p.stderr
    assert "not informative (the residual delay is uncertain" in p.stderr
    assert "implausible: Td is undetermined (+-40.0 ms, more than 10 ms)" in p.stderr
    assert not (tmp_path / "a").exists()
    # informative, but on the fit's bound: still no platform
    saved.write_text(json.dumps(_status(True, 250.0, 0.5)))
    p = cli("identify", str(saved), "--from-status", "--out", str(tmp_path / "a"))
    assert p.returncode == 2 and "Td 250.00 ms is on the fit's bound" in p.stderr, p.stderr
    # --force writes it, marked
    saved.write_text(json.dumps(_status(False, 141.0, 40.0)))
    p = cli("identify", str(saved), "--from-status", "--force", "--out", str(tmp_path / "a"))
    assert p.returncode == 0, p.stderr
    text = (tmp_path / "a" / "rails_y.toml").read_text()
    assert "# FORCED (--force) although: not informative" in text
    # the input lag to design it with: the playback lag plus the pairing's phase
    assert ("# Design it with --input-lag-ms = the config's input.playback_lag_s + 0.42 ms, the "
            "pairing's phase (outside this Td: docs/TUNING.md).") in text
    assert 'forced = { model = "p1d:K=1.02,Td=0.141,Tp1=0.05", why = "not informative' in text
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{config_file("motcomp.toml")}", "a/rails_y.toml"]\n'
                    "[axes.rails_y]\nbypass = true\n")
    p = cli("config", "check", str(site))
    assert p.returncode == 0, p.stderr
    assert ("rails_y: its model p1d:K=1.02,Td=0.141,Tp1=0.05 was written by `motcomp identify "
            "--force` against identify's refusal (not informative") in p.stderr
    # a later model replaces it: the mark no longer applies
    site.write_text(f'include = ["{config_file("motcomp.toml")}", "a/rails_y.toml"]\n'
                    '[axes.rails_y]\nmodel = "p1d:K=1,Td=0.0215,Tp1=0.19"\n')
    p = cli("config", "check", str(site))
    assert p.returncode == 0 and "--force" not in p.stderr, p.stderr


def test_a_fragment_identify_writes_with_force_is_marked(tmp_path: Path) -> None:
    # a recording whose measurement the command does not explain: refused, then forced
    rng = np.random.default_rng(0)
    t = np.arange(20000) / 1000.0
    cmd = 0.05 * np.sin(2 * math.pi * 0.5 * t) + 0.02 * np.sin(2 * math.pi * 2.1 * t)
    acc = rng.normal(0.0, 1.0, t.size)
    data = tmp_path / "d.csv"
    data.write_text("# axis: rails_y\nt,cmd,acc\n" + "".join(
        f"{a:.6f},{b:.9g},{c:.6g}\n" for a, b, c in zip(t, cmd, acc, strict=True)))
    p = cli("identify", str(data), "--models", "p1d", "--no-figures", "--quiet",
            "--out", str(tmp_path / "refused"))
    assert p.returncode == 2 and "no config fragment written" in p.stderr, p.stderr
    p = cli("identify", str(data), "--models", "p1d", "--no-figures", "--quiet", "--force",
            "--out", str(tmp_path / "forced"))
    assert p.returncode == 0, p.stderr
    text = (tmp_path / "forced" / "rails_y.toml").read_text()
    assert "# FORCED (--force) although: the selected p1d's validation fit is" in text
    assert "forced = { model = " in text
    # a live run the host starved: the mark says how many deadlines were missed
    why = ("the service missed 7.7 % of its deadlines while the data were recorded (more than "
           "5 %): the fit carries the host's stalls; identify again on a quiet host")
    (tmp_path / "live.toml").write_text(model_fragment("rails_y", "p1d:K=1,Td=0.02,Tp1=0.2",
                                                       [], why))
    (tmp_path / "site.toml").write_text(f'include = ["{config_file("motcomp.toml")}", '
                                        '"live.toml"]\n[axes.rails_y]\nbypass = true\n')
    axes = resolve_axes(load_config(tmp_path / "site.toml"))
    assert any("the service missed 7.7 % of its deadlines" in w and "--force" in w
               for w in axes.warnings), axes.warnings


def _fit(kind: str, aic: float, pure: float, phase: float, se: float) -> ModelFit:
    z = np.zeros(1)
    return ModelFit(kind=kind, model=P1D(K=1.0, Td=pure / 1e3, Tp1=0.1), params={},
                    stderr={}, fit_percent=95.0, vaf_percent=99.0, fit_percent_raw=90.0,
                    vaf_percent_raw=98.0, aic=aic, n_params=3 if kind == "p1d" else 6,
                    rmse=0.1, bias=0.0, seconds=0.1,
                    table1={"pure_delay_ms": pure, "pure_delay_ms_stderr": se,
                            "phase_delay_0p2hz_ms": phase, "phase_delay_0p2hz_ms_stderr": se},
                    at_bounds=[], profile_coarse=(z, z), profile_fine=(z, z), prediction=z,
                    prediction_raw=z)


def test_the_model_comparison_says_which_numbers_are_alike() -> None:
    # the report once read "oe lowers the AIC by -11.1 but gives the same pure delay and phase
    # delay at 0.2 Hz (15.3 vs 61.2 ms, 228.2 vs 279.9 ms)"
    kind, why = select_model({"p1d": _fit("p1d", -100.0, 15.3, 228.2, 0.1),
                              "oe": _fit("oe", -111.1, 61.2, 279.9, 30.0)}, 1.0)
    assert kind == "p1d"
    assert ("oe lowers the AIC by 11.1, but its pure delay and phase delay at 0.2 Hz are too "
            "uncertain to differ from p1d's (15.3 vs 61.2 +- 30.0 ms, 228.2 vs 279.9 +- 30.0 "
            "ms: within two standard errors)") in why
    kind, why = select_model({"p1d": _fit("p1d", -100.0, 15.3, 228.2, 0.1),
                              "oe": _fit("oe", -111.1, 15.5, 229.0, 0.2)}, 1.0)
    assert kind == "p1d" and ("oe lowers the AIC by 11.1, but gives the same pure delay and "
                              "phase delay at 0.2 Hz (15.3 vs 15.5 +- 0.2 ms") in why


def test_the_host_probe_reads_the_deadlines_missed_between_two_status_frames() -> None:
    a = {"ticks": 1000, "missed_ticks": 10, "platform": {"ticks": 990, "missed_ticks": 20}}
    b = {"ticks": 3850, "missed_ticks": 160, "platform": {"ticks": 3940, "missed_ticks": 70}}
    shares = probe_host(a, b)
    assert shares["service"] == pytest.approx(150 / 3000)
    assert shares["platform"] == pytest.approx(50 / 3000)
    assert probe_host(a, {"ticks": 1000, "missed_ticks": 10}) == {"service": None,
                                                                   "platform": None}


def test_the_simulated_platform_says_when_it_drifts() -> None:
    p = subprocess.run(motcomp_cmd("hil", "-l", "tcp/127.0.0.1:0", "--duration", "2.5",
                                   "--log-level", "warning", "--drift",
                                   "rails_y=p1d:K=1,Td=0.0275,Tp1=0.1857683128@1"),
                       capture_output=True, text=True, env=subprocess_env(), timeout=60)
    assert p.returncode == 0, p.stderr
    assert ("rails_y: the simulated platform drifted (--drift): truth now "
            "p1d:K=1,Td=0.0275,Tp1=0.1857683128, was p1d:K=1,Td=0.0175,Tp1=0.1857683128 (1.0 s "
            "after the start)") in p.stderr, p.stderr


def _wire_platform() -> Any:
    spec = importlib.util.spec_from_file_location("wire_platform",
                                                  ROOT / "tools" / "wire_platform.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["wire_platform"] = mod
    spec.loader.exec_module(mod)
    return mod


def test_the_contract_platform_drifts_into_its_new_truth() -> None:
    wp = _wire_platform()
    assert wp.parse_drift("rails_y=31.5,190@70") == ("rails_y", 31.5, 190.0, 70.0)
    for bad in ("rails_y=31.5,190", "rails_q=1,2@3", "rails_y=1,2@-1"):
        with pytest.raises(ValueError, match="--drift"):
            wp.parse_drift(bad)
    truth = {a: (20.0, 50.0) for a in wp.AXES}
    drifting = wp.Plant(truth, 1000.0, max_delay_ms=31.5)
    new = wp.Plant({**truth, "rails_y": (31.5, 190.0)}, 1000.0)
    y = wp.AXES.index("rails_y")
    u = 0.3 * np.sin(2 * math.pi * 0.5 * np.arange(6000) / 1000.0)
    for k, x in enumerate(u):
        if k == 2000:
            drifting.set_truth(y, 31.5, 190.0)
        drifting.step(k, np.full(len(wp.AXES), x))
        new.step(k, np.full(len(wp.AXES), x))
    # the old motion is forgotten (190 ms time constant, 4 s later): the new platform's
    assert abs(drifting.y[y] - new.y[y]) < 1e-6
    # and a pure delay of 31.5 ms, exactly: the new plant against the closed form of a
    # first-order lag of the delayed sine (steady state; the held samples lag half a sample)
    w, tau, t_end = 2 * math.pi * 0.5, 0.19, 6000 / 1000.0
    expect = 0.3 * math.sin(w * (t_end - 0.0315 - 0.0005) - math.atan(w * tau)) / math.hypot(
        1, w * tau)
    assert new.y[y] == pytest.approx(expect, abs=2e-5)
