"""``motcomp design`` / ``motcomp evaluate`` as a user runs them."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from tests.conftest import motcomp_cmd, subprocess_env


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True, env=subprocess_env(),
                          timeout=300)


def test_design_json_schema() -> None:
    p = run("design", "--plant", "rails", "--rule", "zn", "--rate", "1000", "--json")
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["model"]["kind"] == "p1d"
    assert set(out["model"]) >= {"K", "Td", "Tp1"}
    assert out["rate_hz"] == 1000.0 and out["rule"] == "zn"
    assert set(out["gains"]) == {"kp", "ki_per_s", "kd_s", "tf_s", "b", "c"}  # the config's keys
    for block in ("uncorrected", "corrected"):
        assert set(out[block]["phase_delay_ms"]) == {"0.2", "0.5", "1", "2"}
    c = out["corrected"]
    for key in ("max_residual_delay_ms", "peak_gain_db", "peak_gain_hz", "ms"):
        assert isinstance(c[key], float)
    assert c["stable"] is True and out["warnings"] == []
    assert c["phase_delay_ms"]["0.2"] < 10
    assert out["recommendation"] == "compensate"


def test_design_gains_paste_into_the_config(tmp_path: Path) -> None:
    """``design --json`` gains are ``[axes.<name>.gains]`` as the config takes them."""
    from motcomp.config import load_config, resolve_axes
    from motcomp.core.pid import PIDGains
    from motcomp.resources import config_file

    p = run("design", "--plant", "rails", "--rule", "zn", "--json")
    assert p.returncode == 0, p.stderr
    gains = json.loads(p.stdout)["gains"]
    body = ", ".join(f"{k} = {v!r}" for k, v in gains.items())
    path = tmp_path / "site.toml"
    path.write_text(f'include = ["{config_file("motcomp.toml")}"]\n'
                    f"[axes.rails_y]\ngains = {{ {body} }}\n")
    axes = resolve_axes(load_config(path))
    assert axes.gains[axes.names.index("rails_y")] == PIDGains.from_config(gains)
    chk = run("config", "check", str(path))
    assert chk.returncode == 0, chk.stderr


def test_design_with_model_spec_and_hexapod_warning() -> None:
    p = run("design", "--model", "p1d:K=1,Td=0.0325,Tp1=0.0025", "--rule", "cc", "--json")
    assert p.returncode == 0
    out = json.loads(p.stdout)
    assert any("lag-dominated" in w for w in out["warnings"])
    assert out["recommendation"] == "bypass"
    assert "WARNING" in p.stderr
    p = run("design", "--plant", "hexapod", "--rule", "zn")
    assert p.returncode == 0 and "WARNING" in p.stderr and "bypass" in p.stderr


@pytest.mark.parametrize(("args", "msg"), [
    (("--model", "p1d:K=1,Td=0.01"), "missing parameter"),
    (("--plant", "nonesuch"), "unknown plant preset 'nonesuch'"),
    (("--plant", "p1d:K=1,Td=0.01,Tp1=0.1"), "a model spec goes with --model: --model p1d:"),
    (("--model", "p1d:K=1,Td=0.01,Tp1=0.1", "--rate", "-5"), "positive"),
    (("--plant", "rails", "--axis", "hex_x"), "preset rails has no axis hex_x"),
    (("--plant", "rails", "--axis", "rails_z"), "--axis: unknown axis 'rails_z'"),
    (("--plant", "nonesuch.toml"), "nonesuch.toml: cannot read"),
    (("--plant", "rails", "--out", "/nonexistent/dir/design.toml"),
     "/nonexistent/dir/design.toml: cannot write"),
])
def test_bad_input_exit_2(args: tuple[str, ...], msg: str) -> None:
    p = run("design", *args)
    assert p.returncode == 2
    assert msg in p.stderr
    assert "Traceback" not in p.stderr


def test_evaluate_writes_report_and_figures(tmp_path: Path) -> None:
    out = tmp_path / "ev"
    p = run("evaluate", "--plant", "rails", "--rule", "zn", "--out", str(out), "--json")
    assert p.returncode == 0, p.stderr
    report = json.loads(p.stdout)
    for name in ("report.json", "report.md", "bode.png", "sweep.png", "slalom.png"):
        assert (out / name).stat().st_size > 1000 or name.endswith(".md")
    assert report["time_domain"]["slalom"]["delay_reduction_ms"] > 150
    assert json.loads((out / "report.json").read_text())["rule"] == "zn"
    assert not list(out.glob(".tmp-*"))


def test_hexapod_design_writes_the_prefilter_alone(tmp_path: Path) -> None:
    """Delay-dominated: ``bypass = true`` plus a ``prediction`` table that round-trips (the
    platform alone: no band limit before it)."""
    import tomllib

    from motcomp.core.predictor import PredictorParams

    out = tmp_path / "design.toml"
    p = run("design", "--plant", "hexapod", "--rule", "optimal", "--peak-db", "6",
            "--hf-gain", "3", "--input-band-hz", "0", "--quiet", "--json", "--out", str(out))
    assert p.returncode == 0, p.stderr
    report = json.loads(p.stdout)
    pred = report["prediction"]
    assert pred["used"] and pred["series"] == "bypass" and report["recommendation"] == "bypass"
    assert pred["with"]["max_delay_ms"] <= 10.0 < pred["without"]["max_delay_ms"]
    assert pred["with"]["hf_command_gain"] <= 3.0 * 1.001
    assert report["corrected"]["max_residual_delay_ms"] == pytest.approx(
        pred["with"]["max_delay_ms"], abs=1e-6)
    table = tomllib.loads(out.read_text())["axes"]["hex_x"]
    assert table["bypass"] is True and "gains" not in table
    t = table["prediction"]
    params = PredictorParams(pole_hz=t["pole_hz"], coeffs=tuple(t["coeffs"]),
                             rate_hz=t["rate_hz"], band_hz=tuple(t["band_hz"]))
    assert params.to_config() == pred["design"]["params"]  # full precision
    assert abs(params.dc_gain - 1.0) < 1e-12


def test_rails_prediction_on_keeps_delay_and_peak_with_a_quieter_command(
        tmp_path: Path) -> None:
    out = tmp_path / "design.toml"
    p = run("design", "--plant", "rails", "--rule", "optimal", "--prediction", "on",
            "--quiet", "--json", "--out", str(out))
    assert p.returncode == 0, p.stderr
    pred = json.loads(p.stdout)["prediction"]
    off, wi = pred["prediction_off"], pred["with"]  # the optimal PID alone, and the chain
    assert wi["max_delay_ms"] <= off["max_delay_ms"] + 1e-3
    assert wi["peak_gain_db"] <= max(off["peak_gain_db"], 8.0) + 0.005
    assert wi["hf_command_gain"] < 0.5 * off["hf_command_gain"]
    assert "prediction = {" in out.read_text() and "gains = {" in out.read_text()
    auto = run("design", "--plant", "rails", "--rule", "optimal", "--quiet", "--json")
    assert auto.returncode == 0, auto.stderr
    assert json.loads(auto.stdout)["prediction"]["used"] is False


def test_rails_chain_hf_gain_states_the_noise_figure_and_buys_delay_with_it() -> None:
    """``--chain-hf-gain G``: the whole chain's command gain above 10 Hz is at most G (as the
    report's noise figure says) and its worst delay is the least within it: a looser G buys
    less delay, and G = 16 already beats the default, which only holds the optimal PID's
    delay (what --prediction off deploys, reported beside the chain)."""
    base = ("design", "--plant", "rails", "--rule", "optimal", "--prediction", "on",
            "--band", "0.03", "2", "--input-lag-ms", "1.1", "--quiet", "--json")
    worst: dict[float, float] = {}
    for g in (16.0, 20.0):
        p = run(*base, "--chain-hf-gain", f"{g:g}")
        assert p.returncode == 0, p.stderr
        out = json.loads(p.stdout)
        pred = out["prediction"]
        assert pred["used"] is True and pred["chain_hf_bound"] == g
        assert pred["with"]["hf_command_gain"] <= g * 1.001
        assert out["corrected"]["hf_command_gain"] <= g * 1.001  # the deployed chain
        assert out["noise"]["with_band_limit"]["hf_gain"] <= g * 1.001  # the stated figure
        assert pred["with"]["peak_gain_db"] <= 8.0 + 0.005
        assert pred["with"]["gain_error_db"] <= 1.0 + 0.005
        worst[g] = pred["with"]["max_delay_ms"]
        held = pred["prediction_off"]["max_delay_ms"]
        assert pred["baseline_delay_ms"] == pytest.approx(held, abs=1e-6)
        assert_one_story(out)
    assert worst[20.0] < worst[16.0] < held, (worst, held)


def assert_one_story(out: dict) -> None:
    """A chain's report never contradicts itself: the metrics table is the deployed chain, the
    optimised PID's block and the prefilter's "without" are the same PID alone, each labelled
    with what it includes and the band it is over."""
    from motcomp.design.report import markdown

    pred, opt = out["prediction"], out["optimal"]
    assert out["chain"] == "the prefilter, then the PID"
    assert out["corrected"]["max_residual_delay_ms"] == pytest.approx(
        pred["with"]["max_delay_ms"], abs=1e-9)
    assert opt["values"]["max_residual_delay_ms"] == pytest.approx(
        pred["without"]["max_delay_ms"], abs=1e-9)
    assert opt["constraints"]["hf_command_gain"] == (
        pred["pid_hf_bound"] or opt["constraints"]["max_command_gain"])
    lo, hi = out["band_hz"]
    text = markdown(out)
    chain = (f"| worst residual phase delay {lo:g}-{hi:g} Hz (input lag, prefilter, PID, "
             f"platform) | {out['corrected']['max_residual_delay_ms']:.2f} ms")
    alone = (f"| worst residual phase delay {lo:g}-{hi:g} Hz, the PID alone | minimised | "
             f"{opt['values']['max_residual_delay_ms']:.2f} ms")
    assert chain in text and alone in text, text
    assert text.count("worst residual phase delay") == 2
    row = next(line for line in text.splitlines() if line.startswith("| worst phase delay in"))
    *_, alone_cell, with_cell, _ = row.split("|")  # the chain's PID alone, the chain
    assert alone_cell.strip() == f"{pred['without']['max_delay_ms']:.2f} ms"
    assert with_cell.strip() == f"{pred['with']['max_delay_ms']:.2f} ms"


def test_chain_hf_gain_needs_prediction_on() -> None:
    p = run("design", "--plant", "rails", "--rule", "optimal", "--chain-hf-gain", "20",
            "--quiet")
    assert p.returncode == 2 and "--prediction on" in p.stderr and "Traceback" not in p.stderr
    p = run("design", "--plant", "rails", "--rule", "optimal", "--prediction", "on",
            "--chain-hf-gain", "-3", "--quiet")
    assert p.returncode == 2 and "-3" in p.stderr and "Traceback" not in p.stderr
    for cmd, says in ((("evaluate", "--rule", "optimal"), "predictive prefilter"),
                      (("pareto", "--prediction", "on"), "option of motcomp design")):
        p = run(*cmd, "--plant", "rails", "--out", "never-written", "--chain-hf-gain", "20")
        assert p.returncode == 2 and says in p.stderr and "Traceback" not in p.stderr, p.stderr


def test_pareto_with_prediction_draws_both_curves(tmp_path: Path) -> None:
    out = tmp_path / "pareto"
    p = run("pareto", "--plant", "hexapod", "--bounds", "6", "--hf-bounds", "3",
            "--prediction", "on", "--input-band-hz", "0", "--out", str(out), "--quiet", "--json")
    assert p.returncode == 0, p.stderr
    assert (out / "pareto_prediction.png").stat().st_size > 10_000
    points = {q["kind"]: q for q in json.loads(p.stdout)["prediction"]}
    assert points["pid"]["series"] == "bypass"  # delay-dominated: the PID is not worth it
    assert points["prediction"]["worst_delay_ms"] < 10.0 < points["pid"]["worst_delay_ms"]
    assert "With and without the predictive prefilter" in (out / "pareto.md").read_text()


def test_a_fragment_identified_through_the_stack_is_designed_with_its_input_lag(
        tmp_path: Path) -> None:
    """The fragment ``identify`` writes for a model identified through the stack names the
    pairing's phase its Td does not hold: without ``--input-lag-ms`` the design takes the
    config's default playback lag (1.7 ms) plus that phase, and says so; an explicit value,
    0 included, is taken as given; a fragment without the comment is designed with none."""
    from motcomp.presets import input_lag_comment, pairing_phase_of

    for phase in (0.43, -0.2, 1.0):
        assert pairing_phase_of("\n".join(["# x", *input_lag_comment(phase), "[axes.y]"])) \
            == pytest.approx(phase, abs=0.005)
    assert input_lag_comment(float("nan")) == [] and pairing_phase_of("# nothing") is None
    model = 'model = "p1d:K=1,Td=0.0215,Tp1=0.293"\n'
    hinted = tmp_path / "rails_y.toml"
    hinted.write_text("\n".join(["# Identified by motcomp identify", *input_lag_comment(0.43),
                                 "[axes.rails_y]", model]))
    bare = tmp_path / "bare.toml"
    bare.write_text("[axes.rails_y]\n" + model)
    lags = {}
    for name, path, extra in (("hinted", hinted, ()), ("explicit", hinted, ("--input-lag-ms", "0")),
                              ("bare", bare, ())):
        p = run("design", "--plant", str(path), "--rule", "zn", "--json", *extra)
        assert p.returncode == 0, p.stderr
        lags[name] = (json.loads(p.stdout)["input_playback_lag_ms"], p.stderr)
    assert lags["hinted"][0] == pytest.approx(1.7 + 0.43)
    assert "input lag 2.13 ms: input.playback_lag_s's default 1.7 ms plus the pairing's phase " \
        "0.43 ms that rails_y.toml names" in lags["hinted"][1]
    assert lags["explicit"][0] == 0.0 and "input lag" not in lags["explicit"][1]
    assert lags["bare"][0] == 0.0 and "input lag" not in lags["bare"][1]
