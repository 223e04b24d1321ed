"""``motcomp design --rule optimal`` and ``motcomp pareto`` as a user runs them."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from tests._designs import assert_same_gains, assert_same_prefilter
from tests.conftest import motcomp_cmd, subprocess_env


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True, env=subprocess_env(),
                          timeout=300)


def test_design_optimal_json_keeps_the_schema_and_adds_its_block() -> None:
    p = run("design", "--plant", "rails", "--rule", "optimal", "--json", "--quiet")
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    # the schema of the other rules
    assert out["rule"] == "optimal" and out["rate_hz"] == 1000.0
    assert set(out["model"]) >= {"kind", "K", "Td", "Tp1"}
    assert set(out["gains"]) == {"kp", "ki_per_s", "kd_s", "tf_s", "b", "c"}
    for block in ("uncorrected", "corrected"):
        assert set(out[block]["phase_delay_ms"]) == {"0.2", "0.5", "1", "2"}
    assert out["warnings"] == [] and out["corrected"]["stable"] is True
    # what optimal adds: the setpoint weights, the bounds and the values reached
    assert (out["gains"]["b"], out["gains"]["c"]) != (1.0, 1.0)
    opt = out["optimal"]
    assert opt["constraints"]["peak_db"] == 8.0 and opt["constraints"]["band_hz"] == [0.1, 2.0]
    assert opt["values"]["max_residual_delay_ms"] == out["corrected"]["max_residual_delay_ms"]
    assert out["corrected"]["max_residual_delay_ms"] <= 3.0
    assert out["corrected"]["peak_gain_db"] <= 8.02
    assert opt["recommendation"] == "compensate" and opt["feasible"] is True
    assert "robust" not in opt


def test_design_optimal_fragment_is_the_example_configs_rails_tuning(
        tmp_path: Path,
        example_rails_design: tuple[subprocess.CompletedProcess[str], Path]) -> None:
    """``--out`` writes the gains and the prefilter in the config's keys, exactly; the example
    config's rails are this design -- the live stack's 2.8 ms (a 1 kHz sender's playback and the
    platform's setpoint age), the default 48 Hz band limit, the PID and the prefilter in series
    over 0.03-2 Hz, the chain's command gain above 10 Hz bounded to 20 -- within the design's
    stated tolerance (the same design on any machine: tests/test_optimal_determinism.py)."""
    import re
    import tomllib

    import pytest

    from motcomp.config import load_config, resolve_axes
    from motcomp.core.pid import PIDGains
    from motcomp.resources import config_file

    p, frag = example_rails_design  # conftest.EXAMPLE_RAILS with --out
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    text = frag.read_text()
    assert re.match(r"# motcomp design: optimal, rails preset, 1000 Hz: residual 0\.\d\d ms, "
                    r"peak \+7\.9 dB \(generated\)\n", text), text
    assert "played back 9.81 ms behind its newest sample (of which 7.01 ms the band limit" in text
    assert out["input_lag_ms"] == pytest.approx(2.8 + 7.009, abs=1e-3)
    assert out["noise"]["with_band_limit"]["hf_gain"] <= 20.0  # the figure the docs quote
    axis = tomllib.loads(text)["axes"]["rails_y"]
    assert set(axis) == {"model", "bypass", "gains", "prediction"} and axis["bypass"] is False
    assert axis["gains"] == out["gains"]
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{config_file("motcomp.toml")}", "{frag}"]\n')
    assert run("config", "check", str(site)).returncode == 0
    axes = resolve_axes(load_config(site))
    y, x = axes.names.index("rails_y"), axes.names.index("rails_x")
    assert axes.gains[y] == PIDGains.from_config(out["gains"])  # the fragment, exactly
    pred_y, pred_x = axes.prediction[y], axes.prediction[x]
    assert pred_y is not None and pred_x is not None
    assert pred_y.to_config() == out["prediction"]["design"]["params"]
    # rails_x: the example's own lines, which this design reproduces
    assert_same_gains(axes.gains[y], axes.gains[x])
    assert_same_prefilter(pred_y, pred_x)


def test_design_optimal_options_reach_the_optimiser() -> None:
    p = run("design", "--plant", "rails", "--rule", "optimal", "--peak-db", "6", "--plain-pid",
            "--band", "0.1", "1.5", "--max-command", "40", "--json", "--quiet")
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    c = out["optimal"]["constraints"]
    assert (c["peak_db"], c["band_hz"], c["max_command_gain"]) == (6.0, [0.1, 1.5], 40.0)
    assert out["optimal"]["setpoint_weights"] is False and out["gains"]["b"] == 1.0
    assert out["corrected"]["peak_gain_db"] <= 6.02
    assert out["corrected"]["peak_command_gain"] <= 40.0 * 1.002


def test_design_optimal_rejects_a_bad_bound() -> None:
    p = run("design", "--plant", "rails", "--rule", "optimal", "--gain-db", "-1")
    assert p.returncode == 2 and "gain_error_db" in p.stderr and "Traceback" not in p.stderr


def test_pareto_writes_figure_and_table(tmp_path: Path) -> None:
    out = tmp_path / "pareto"
    p = run("pareto", "--plant", "rails", "--bounds", "8", "--out", str(out), "--quiet")
    assert p.returncode == 0, p.stderr
    assert (out / "pareto.png").stat().st_size > 10_000
    table = (out / "pareto.md").read_text()
    for name in ("Ziegler-Nichols", "Cohen-Coon", "AMIGO", "SIMC", "optimal, peak <= 8 dB",
                 "optimal, plain PID, peak <= 8 dB"):
        assert name in table
    data = json.loads((out / "pareto.json").read_text())
    points = data["points"]
    assert {p["kind"] for p in points} == {"optimal", "optimal-plain", "rule"}
    assert not list(out.glob(".tmp-*"))
    # the frontier's 8 dB point is motcomp design's optimum: the same plant as the compensator
    # sees it, the input's band limit included by default in both
    p = run("design", "--plant", "rails", "--rule", "optimal", "--prediction", "off", "--json",
            "--quiet")
    assert p.returncode == 0, p.stderr
    design = json.loads(p.stdout)
    assert data["input_lag_ms"] == design["input_lag_ms"] > 5.0  # the band limit's delay
    eight = next(q for q in points if q["label"] == "optimal, peak <= 8 dB")
    assert eight["max_residual_delay_ms"] == pytest.approx(
        design["corrected"]["max_residual_delay_ms"], abs=0.01)
