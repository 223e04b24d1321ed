"""``motcomp excite`` -> simulated platform -> ``motcomp identify``, as a user runs them: the
rails row of the paper's Table 1, the JSON schema, the report files and the config fragment."""

from __future__ import annotations

import json
import math
import subprocess
import tomllib
from pathlib import Path

import pytest

from motcomp.core.models import P1D, parse_model
from tests.conftest import motcomp_cmd, subprocess_env

# one excite + identify of 60 s at 1 kHz with the four models, shared by every test here
pytestmark = pytest.mark.slow


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                          env=subprocess_env(), timeout=600)


@pytest.fixture(scope="module")
def rails_report(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    d = tmp_path_factory.mktemp("rails")
    # the paper's procedure: low-pass pseudo-white noise (4 Hz) on the rails, 60 s at 1 kHz,
    # a platform with the rails preset's dynamics, an accelerometer at 10 dB SNR with tremor
    p = run("excite", "--axis", "rails_y", "--kind", "noise", "--seed", "11",
            "--out", str(d / "rails"), "--simulate", "rails", "--snr", "10")
    assert p.returncode == 0, p.stderr
    p = run("identify", str(d / "rails.sim.csv"), "--out", str(d / "out"), "--json", "--quiet")
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout), d / "out"


def test_rails_row_of_table1(rails_report: tuple[dict, Path]) -> None:
    rep, _ = rails_report
    # paper, Table 1, rails: pure delay 15-20 ms, phase delay at 0.2 Hz 200 ms
    assert rep["selected"] == "p1d", rep["reason"]
    assert 15.0 <= rep["pure_delay_ms"] <= 20.0
    assert rep["phase_delay_0p2hz_ms"] == pytest.approx(200.0, abs=5.0)
    # -6 dB bandwidth of the preset: sqrt(3) / (2 pi 0.1858 s) = 1.48 Hz (the paper: 1.25 Hz)
    assert rep["bandwidth_hz"]["-6dB"] == pytest.approx(1.484, rel=0.03)


def test_json_schema(rails_report: tuple[dict, Path]) -> None:
    rep, out = rails_report
    assert set(rep["models"]) == {"p1d", "p2d", "p2uzd", "oe"}
    for kind, m in rep["models"].items():
        assert isinstance(m["fit_percent"], float) and isinstance(m["vaf_percent"], float)
        assert 50 < m["fit_percent"] <= 100 and 90 < m["vaf_percent"] <= 100, kind
        assert isinstance(m["aic"], float) and parse_model(m["spec"]).kind == kind
        assert set(m["stderr"]) >= {"Td"}
    p1d = rep["models"]["p1d"]
    assert set(p1d["params"]) == {"K", "Td", "Tp1"}
    assert set(p1d["stderr"]) == {"K", "Td", "Tp1"}
    assert all(isinstance(v, float) and v > 0 for v in p1d["stderr"].values())
    assert set(rep["models"]["p2d"]["params"]) == {"K", "Td", "Tp1", "Tp2"}
    for key in ("selected", "reason", "model_spec", "pure_delay_ms", "phase_delay_0p2hz_ms",
                "pure_delay_ms_stderr", "phase_delay_0p2hz_ms_stderr", "table1", "data"):
        assert key in rep
    assert set(rep["bandwidth_hz"]) == {"-3dB", "-6dB"}
    assert rep["axis"] == "rails_y"
    assert rep["data"]["samples"] == 60000 and rep["data"]["rate_hz"] == 1000.0
    # a CSV: the whole data, no gaps
    assert rep["data"]["window"] == {"start_s": 0.0, "end_s": pytest.approx(59.999),
                                     "samples": 60000, "how": "whole recording"}
    assert rep["data"]["gaps"] == {"count": 0, "longest_ms": 0.0, "total_ms": 0.0,
                                   "max_gap_s": 0.05, "first": []}
    assert any(abs(f - 14.0) < 0.3 for f in rep["data"]["notches_hz"]) or \
        rep["data"]["prefilter_cutoff_hz"] < 7.0
    assert sorted(Path(f).name for f in rep["files"]) == sorted(
        ["report.json", "report.md", "rails_y.toml", "identification.png", "bode.png",
         "delay_profile.png"])
    assert json.loads((out / "report.json").read_text())["selected"] == rep["selected"]


def test_table1_numbers_follow_the_closed_forms(rails_report: tuple[dict, Path]) -> None:
    rep, _ = rails_report
    p = rep["models"]["p1d"]["params"]
    Td, Tp1 = p["Td"], p["Tp1"]
    w = 2 * math.pi * 0.2
    assert rep["pure_delay_ms"] == pytest.approx(Td * 1e3, rel=1e-12)
    assert rep["phase_delay_0p2hz_ms"] == pytest.approx((Td + math.atan(w * Tp1) / w) * 1e3,
                                                        rel=1e-9)
    assert rep["bandwidth_hz"]["-3dB"] == pytest.approx(1 / (2 * math.pi * Tp1), rel=1e-6)
    assert rep["bandwidth_hz"]["-6dB"] == pytest.approx(math.sqrt(3) / (2 * math.pi * Tp1),
                                                        rel=1e-6)


def test_config_fragment_is_what_the_compensator_reads(rails_report: tuple[dict, Path]) -> None:
    rep, out = rails_report
    text = (out / "rails_y.toml").read_text()
    doc = tomllib.loads(text)
    assert doc == {"axes": {"rails_y": {"model": rep["model_spec"]}}}
    model = parse_model(doc["axes"]["rails_y"]["model"])
    assert isinstance(model, P1D) and model == parse_model(rep["models"]["p1d"]["spec"])
    assert "# Selected p1d: validation fit" in text and "phase delay at 0.2 Hz" in text


def test_markdown_and_figures(rails_report: tuple[dict, Path]) -> None:
    _, out = rails_report
    md = (out / "report.md").read_text()
    assert ("| axis | model | pure delay (held / smooth command) | phase delay at 0.2 Hz | "
            "bandwidth (-3 dB) | bandwidth (-6 dB) |") in md
    assert "| rails_y | p1d | 17." in md
    # the convention stated, and the smooth command's delay half a sample (0.5 ms) later
    assert "zero-order hold, the convention of the fit" in md
    row = rep_row = next(ln for ln in md.splitlines() if ln.startswith("| rails_y | p1d |"))
    held, smooth = (float(x.split()[0]) for x in rep_row.split("|")[3].split("/"))
    assert smooth == pytest.approx(held + 0.5, abs=0.051), row
    assert "| p1d (selected) |" in md and "Selected **p1d**" in md
    assert ("Window 0.00-60.00 s of the recording (60000 samples; whole recording). No gaps in "
            "the data.") in md
    for name in ("identification.png", "bode.png", "delay_profile.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert (out / name).stat().st_size > 20000
    assert not list(out.glob(".tmp-*"))
