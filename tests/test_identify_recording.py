"""``motcomp identify`` on recordings of the stack (issue 15): what the platform received (the
service's output in force) against what it did (the feedback's acceleration), on the stretch
where the axis is bypassed and not limited, with feedback gaps bridged and counted, and files
cut short read up to the cut.

Sessions are synthesized through the service's own tick (:mod:`motcomp.replay.synth`) with the
example config, whose rails plant is P1D ``Td = 17.5 ms, Tp1 = 185.8 ms``; the platform's
feedback is that plant's exact response to the outputs.  Time in a recording counts from its
first output, 0.2 s before the synthesizer's time origin (hence :data:`T0`).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from motcomp.cli import main
from motcomp.config import load_config
from motcomp.errors import DataError
from motcomp.ident.data import load_recording
from motcomp.record import read_session
from motcomp.replay.synth import SynthOptions, synthesize
from motcomp.resources import config_file
from tests.conftest import RAILS, motcomp_cmd, subprocess_env

CFG = load_config(config_file("motcomp.toml"))
T0 = 0.199  # recording time of the synthesizer's t = 0
BYPASS_AT = 10.0
FEEDBACK_GAPS = [(15.0, 0.008), (20.0, 0.015), (25.0, 0.02)]  # 9, 16 and 21 ms without data
LOST_OUTPUTS = (18.0, 5)  # the recorder misses 5 outputs: their feedback is left out (6 ms)


@pytest.fixture(scope="module")
def mixed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """rails_y compensated (the config's choice) and excited for 8 s, then bypassed from 10 s
    and excited again for 24 s, with feedback gaps and outputs the recorder lost."""
    path = tmp_path_factory.mktemp("ident_rec") / "mixed.mcap"
    synthesize(path, CFG, SynthOptions(
        duration_s=36.0, seed=3, bypass=[(BYPASS_AT, True, ("rails_y",))],
        excite=[("rails_y", "noise", 1.0, 8.0), ("rails_y", "noise", 11.0, 24.0)],
        feedback_gaps=FEEDBACK_GAPS, lose_outputs=[LOST_OUTPUTS]))
    return path


@pytest.fixture(scope="module")
def compensated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """rails_y excited, compensated throughout."""
    path = tmp_path_factory.mktemp("ident_rec") / "compensated.mcap"
    synthesize(path, CFG, SynthOptions(duration_s=12.0, seed=4,
                                       excite=[("rails_y", "noise", 1.0, 10.0)]))
    return path


def identify_json(path: Path, out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd("identify", str(path), "--axis", "rails_y", "--out",
                                      str(out), "--no-figures", "--json", "--quiet", *extra),
                          capture_output=True, text=True, env=subprocess_env(), timeout=600)


def test_identifies_the_bypassed_stretch_as_a_user_runs_it(mixed: Path, tmp_path: Path) -> None:
    p = identify_json(mixed, tmp_path / "out")
    assert p.returncode == 0, p.stderr
    rep = json.loads(p.stdout)
    # the longest stretch bypassed and not limited: from the bypass switch to the end
    win = rep["data"]["window"]
    assert win["how"] == "longest stretch bypassed and not limited"
    assert win["start_s"] == pytest.approx(BYPASS_AT + T0, abs=0.05)
    assert win["end_s"] > 36.0 and win["samples"] > 26_000
    # the plant: P1D chosen, Td within 1 ms, Tp1 within 5 %
    assert rep["selected"] == "p1d", rep["reason"]
    params = rep["models"]["p1d"]["params"]
    assert params["Td"] == pytest.approx(RAILS.Td, abs=1e-3)
    assert params["Tp1"] == pytest.approx(RAILS.Tp1, rel=0.05)
    assert rep["phase_delay_0p2hz_ms"] == pytest.approx(200.0, abs=3.0)
    # the pairing's phase over the window: the synthesizer stamps its feedback 0.3 ms after the
    # tick whose output is in force (time stamps quantised to 0.24 us)
    assert rep["data"]["conditions"]["pairing_phase_ms"] == pytest.approx(0.3, abs=1e-3)
    # the gaps: three without feedback and one where the outputs were lost, bridged
    gaps = rep["data"]["gaps"]
    assert gaps["count"] == 4 and gaps["longest_ms"] == pytest.approx(21.0, abs=0.5)
    assert [round(g["start_s"] - T0) for g in gaps["first"]] == [15, 18, 20, 25]
    assert any("left out: the recording lost the outputs in force" in w for w in rep["warnings"])
    fragment = (tmp_path / "out" / "rails_y.toml").read_text()
    assert "--input-lag-ms = the config's input.playback_lag_s + 0.30 ms, the pairing's" in fragment
    md = (tmp_path / "out" / "report.md").read_text()
    assert f"Window {win['start_s']:.2f}-{win['end_s']:.2f} s of the recording" in md
    assert "4 gap(s) without data bridged by linear interpolation (longest 21.0 ms" in md


def test_refuses_an_axis_that_was_compensated(compensated: Path, tmp_path: Path) -> None:
    p = identify_json(compensated, tmp_path / "out")
    assert p.returncode == 2, p.stderr
    err = p.stderr.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert "rails_y: no stretch of 5 s or more with the axis bypassed and not limited" in err
    assert "compensated (no bypass:rails_y flag in the outputs) during 13.0 s of 13.0 s" in err
    assert "--window START END" in err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_a_given_window_with_compensation_is_used_with_a_warning(compensated: Path) -> None:
    rec = load_recording(compensated, axis="rails_y", window=(2.0, 9.0))
    assert rec.window is not None and rec.window.how == "given"
    assert rec.window.start_s == pytest.approx(2.0, abs=2e-3)
    assert rec.window.end_s == pytest.approx(9.0, abs=2e-3)
    assert rec.window.samples == pytest.approx(7000, abs=2)
    assert any(w.startswith("rails_y was compensated (no bypass:rails_y flag in the outputs) on "
                            "7000 of 7000 samples") for w in rec.warnings), rec.warnings


def test_refuses_an_axis_the_limiter_kept_acting_on(tmp_path: Path) -> None:
    # bypassed throughout, but a position step every 4 s that the limiter must absorb
    path = tmp_path / "limited.mcap"
    synthesize(path, CFG, SynthOptions(
        duration_s=14.0, seed=5, bypass=[(-1.0, True, ("rails_y",))],
        steps=[(2.0, "rails_y", 0.4), (6.0, "rails_y", -0.4), (10.0, "rails_y", 0.4)]))
    cols = read_session(path).identification_columns("rails_y")
    assert cols.bypassed.all() and cols.limited.any()
    with pytest.raises(DataError, match=r"rails_y: no stretch of 5 s or more with the axis "
                                        r"bypassed and not limited: limited \(sat:rails_y\) on "
                                        r"\d+ samples; the longest stretch bypassed and not "
                                        r"limited is \d\.\d\d s"):
        load_recording(path, axis="rails_y")
    # chosen anyway: a warning names the limiting
    rec = load_recording(path, axis="rails_y", window=(0.5, 13.0))
    assert any(w.startswith("rails_y was limited (sat:rails_y) on ") for w in rec.warnings)


def test_a_gap_longer_than_max_gap_ends_the_window_or_is_named(mixed: Path) -> None:
    # 10 ms bridged at most: the 16 ms gap at 20 s and the 21 ms one at 25 s split the bypassed
    # stretch; the longest piece is the last
    rec = load_recording(mixed, axis="rails_y", max_gap_s=0.01)
    assert rec.window is not None
    assert rec.window.start_s == pytest.approx(25.02 + T0, abs=2e-3)
    assert rec.gaps.count == 0 and rec.gaps.max_gap_s == 0.01
    with pytest.raises(DataError, match=r"platform/feedback message \d+: column t: gap of "
                                        r"0\.016 s without data at 20\.\d+ s \(median period "
                                        r"0\.001 s; longer than --max-gap 0\.01 s\)"):
        load_recording(mixed, axis="rails_y", max_gap_s=0.01, window=(11.0, 30.0))


def test_the_automatic_window_searched_inside_bounds(mixed: Path) -> None:
    """``within`` (identify --live: the excitation's bounds) keeps the automatic window's rules
    inside it: with 10 ms bridged at most, the longest piece inside 11-33 s runs from the
    bounds' start to the 16 ms gap at 20 s (the whole recording's is the last, 25-36 s);
    compensated samples inside the bounds are never taken."""
    rec = load_recording(mixed, axis="rails_y", max_gap_s=0.01, within=(11.0, 33.0))
    assert rec.window is not None
    assert rec.window.how == "longest stretch bypassed and not limited inside 11.00-33.00 s"
    assert rec.window.start_s == pytest.approx(11.0, abs=2e-3)
    assert rec.window.end_s == pytest.approx(20.0 + T0, abs=2e-3)
    with pytest.raises(DataError, match=r"rails_y: no stretch of 5 s or more with the axis "
                                        r"bypassed and not limited inside 2\.00-12\.00 s: "):
        load_recording(mixed, axis="rails_y", within=(2.0, 12.0))
    with pytest.raises(DataError, match="exclude each other"):
        load_recording(mixed, axis="rails_y", within=(2.0, 12.0), window=(2.0, 12.0))


def test_gaps_of_a_few_milliseconds_are_bridged(mixed: Path) -> None:
    rec = load_recording(mixed, axis="rails_y", window=(14.0, 16.0 + T0))
    # one gap, 9 ms; the grid goes on through it at 1 kHz
    assert rec.gaps.count == 1 and rec.gaps.longest_s == pytest.approx(0.009, abs=1e-6)
    assert rec.resampled and rec.rate_hz == 1000.0
    assert np.allclose(np.diff(rec.t), 1e-3)
    assert rec.period_jitter_s < 1e-6  # the gap is not jitter


def test_a_recording_cut_short_is_identified_with_a_warning(
        mixed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cut = tmp_path / "cut.mcap"
    data = mixed.read_bytes()
    cut.write_bytes(data[:int(len(data) * 0.8)])
    code = main(["identify", str(cut), "--axis", "rails_y", "--models", "p1d", "--out",
                 str(tmp_path / "out"), "--no-figures", "--json", "--quiet"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    rep = json.loads(cap.out)
    warned = [line for line in cap.err.splitlines() if "unfinished recording" in line]
    assert len(warned) == 1 and warned[0].startswith(f"warning: {cut}: unfinished recording")
    assert any("unfinished recording" in w for w in rep["warnings"])
    assert rep["data"]["window"]["end_s"] < 32.0
    assert rep["models"]["p1d"]["params"]["Td"] == pytest.approx(RAILS.Td, abs=1e-3)


def test_the_command_is_the_output_in_force_not_the_input(mixed: Path) -> None:
    # while rails_y is compensated (2-8 s) the service sends another motion than it receives;
    # the command is what it sent, in force at each feedback sample
    s = read_session(mixed)
    cols = s.identification_columns("rails_y")
    t_fb = cols.t - cols.start_s
    rec = load_recording(mixed, axis="rails_y", window=(2.0, 8.0))
    k = int(np.searchsorted(t_fb, rec.start_s))
    assert t_fb[k] == rec.start_s
    # (resampled at 1 kHz from time stamps quantised to 0.24 us)
    assert np.allclose(rec.cmd, cols.cmd[k:k + rec.n], rtol=0, atol=1e-3 * np.ptp(rec.cmd))
    assert s.inputs is not None
    t_in = s.inputs.log_ns / 1e9 - cols.start_s
    received = s.inputs.pos[(t_in > 2.0) & (t_in < 8.0), 1]
    # the compensated command, limited on most samples, spans 3x the input (over 4x before the
    # limiter's wall stopped with a stopping target): another motion than the one received
    assert np.ptp(rec.cmd) > 2 * np.ptp(received[np.isfinite(received)])


def test_all_axes_leaves_out_those_without_usable_data(
        mixed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # rails_x was compensated throughout: left out with the reason; rails_y identified
    code = main(["identify", str(mixed), "--axis", "all", "--models", "p1d", "--out",
                 str(tmp_path / "out"), "--no-figures", "--json", "--quiet"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    rep = json.loads(cap.out)
    assert "rails_x" not in rep["axes"] and "rails_y" in rep["axes"]
    assert rep["axes"]["rails_y"]["pure_delay_ms"] == pytest.approx(RAILS.Td * 1e3, abs=1.0)
    assert any(line.startswith(f"warning: left out: {mixed}: rails_x: no stretch of 5 s or more")
               and "compensated (no bypass:rails_x flag in the outputs)" in line
               for line in cap.err.splitlines()), cap.err


def test_a_fit_that_explains_nothing_writes_no_fragment(tmp_path: Path) -> None:
    """An acceleration unrelated to the command: the report is written, the config fragment
    only with --force, and the exit code says it (2)."""
    rng = np.random.default_rng(5)
    t = np.arange(30_000) / 1000.0
    cmd = sum(0.02 * np.sin(2 * np.pi * f * t + rng.uniform(0, 6))
              for f in (0.3, 0.7, 1.3, 2.1, 3.3))
    acc = rng.normal(0.0, 1.0, t.size)
    data = tmp_path / "unrelated.csv"
    data.write_text("t,cmd,acc\n" + "".join(f"{a:.3f},{b:.9f},{c:.6f}\n"
                                            for a, b, c in zip(t, cmd, acc, strict=True)))
    p = identify_json(data, tmp_path / "out")
    assert p.returncode == 2, p.stderr
    assert "validation fit is" in p.stderr and "below 50 %" in p.stderr, p.stderr
    assert "no config fragment written" in p.stderr
    assert (tmp_path / "out" / "report.md").is_file()
    assert not (tmp_path / "out" / "rails_y.toml").exists()
    p = identify_json(data, tmp_path / "forced", "--force")
    assert p.returncode == 0, p.stderr
    assert "written anyway (--force)" in p.stderr
    assert (tmp_path / "forced" / "rails_y.toml").is_file()


def test_the_run_s_conditions_come_from_the_recorded_status() -> None:
    """Deadlines missed over the window, from the service's status frames around it, and the
    platform's stack delay; a busy run is named in a warning."""
    from types import SimpleNamespace

    from motcomp.ident.data import run_conditions
    from motcomp.runtime.clock import DEGRADED_MISSED_SHARE

    def frame(t: float, ticks: int, missed: int) -> tuple[int, dict[str, object]]:
        return 0, {"t": t, "ticks": ticks, "missed_ticks": missed,
                   "platform": {"setpoint_age_ms": 1.25, "setpoint_age_mean_ms": 1.5}}

    busy = SimpleNamespace(status=[frame(99.0, 0, 0), frame(100.0, 900, 100),
                                   frame(120.0, 18_000, 2_100), frame(121.0, 19_000, 2_100)])
    c = run_conditions(busy, 100.2, 119.8)  # type: ignore[arg-type]
    assert (c["service_ticks"], c["service_missed"]) == (17_100, 2_000)
    assert c["service_missed_share"] == pytest.approx(2_000 / 19_100)
    assert c["platform_setpoint_age_ms"] == 1.25
    # the report: the age, the pairing's phase and their difference inside the fitted Td
    from motcomp.ident.report import _window_text
    text = _window_text({"window": None, "gaps": {"count": 0},
                         "conditions": {**c, "pairing_phase_ms": 0.75}})
    assert ("applied its setpoints 1.25 ms after their t (median), the pairing's phase 0.75 ms "
            "(the model's hold, outside the fitted Td): +0.50 ms of the stack's delay inside the "
            "fitted Td.") in text
    assert len(c["warnings"]) == 1 and "missed 2000 of 19100 deadlines" in c["warnings"][0]
    quiet = SimpleNamespace(status=[frame(100.0, 1000, 0), frame(120.0, 20_990, 10)])
    c = run_conditions(quiet, 100.2, 119.8)  # type: ignore[arg-type]
    assert c["service_missed_share"] == pytest.approx(10 / 20_000)
    assert c["service_missed_share"] < DEGRADED_MISSED_SHARE
    assert c["warnings"] == []
    assert run_conditions(SimpleNamespace(status=[]), 0.0, 1.0) == {}  # type: ignore[arg-type]


def test_a_starved_run_or_a_poor_fit_is_not_a_fragment() -> None:
    from types import SimpleNamespace

    from motcomp.cli.identify import MAX_MISSED_SHARE_FRAGMENT, MIN_FIT_PERCENT, _untrusted

    def ident(fit: float, share: float | None) -> SimpleNamespace:
        cond = {} if share is None else {"service_missed_share": share}
        return SimpleNamespace(best=SimpleNamespace(fit_percent=fit), selected="p1d",
                               prep=SimpleNamespace(recording=SimpleNamespace(conditions=cond)))

    assert _untrusted(ident(95.0, None)) == ""  # type: ignore[arg-type]
    assert _untrusted(ident(95.0, MAX_MISSED_SHARE_FRAGMENT)) == ""  # type: ignore[arg-type]
    why = _untrusted(ident(95.0, 0.077))  # type: ignore[arg-type]
    assert "missed 7.7 % of its deadlines while the data were recorded" in why
    why = _untrusted(ident(MIN_FIT_PERCENT - 1, 0.0))  # type: ignore[arg-type]
    assert "validation fit is 49.0 %" in why
