"""Excitation signals: limits verified on the samples, neutral ends, exact lines, writers, CLI."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motcomp.errors import ConfigError
from motcomp.ident.excitation import (
    KINDS,
    AxisRange,
    excitation,
    read_setpoint_stream,
    schroeder_phases,
    write_csv,
    write_setpoint_stream,
)
from tests.conftest import motcomp_cmd, subprocess_env

RAILS = AxisRange(-2.6, 2.6, 2.0, 6.0)
HEX = AxisRange(-0.25, 0.25, 0.6, 7.0)


def peaks(u: np.ndarray, rate: float) -> tuple[float, float, float, float]:
    """Independent check: neutral before and after, backward differences."""
    x = np.concatenate([[0.0, 0.0], u, [0.0, 0.0]])
    v = np.diff(x) * rate
    a = np.diff(v) * rate
    return float(u.min()), float(u.max()), float(np.abs(v).max()), float(np.abs(a).max())


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize(("axis", "lim"), [("rails_y", RAILS), ("hex_z", HEX)])
def test_limits_neutral_ends_and_duration(kind: str, axis: str, lim: AxisRange) -> None:
    exc = excitation(kind, axis, lim, duration_s=30.0, rate_hz=500.0, seed=4)
    assert exc.t.size == 15000 and exc.t[1] == pytest.approx(1 / 500)
    lo, hi, v, a = peaks(exc.cmd, 500.0)
    assert lim.p_min <= lo and hi <= lim.p_max
    assert v <= lim.v_max * (1 + 1e-12) and a <= lim.a_max * (1 + 1e-12)
    # the tightest limit is used at 90 %, no more
    assert max(hi / lim.p_max, lo / lim.p_min, v / lim.v_max, a / lim.a_max) == pytest.approx(0.9)
    # neutral hold at both ends (0.5 s), reached smoothly
    assert np.all(exc.cmd[:250] == 0.0) and np.all(exc.cmd[-250:] == 0.0)
    assert exc.usage["acceleration"] <= 0.9 + 1e-9


def test_noise_is_seeded_and_band_limited() -> None:
    a = excitation("noise", "rails_x", RAILS, duration_s=40, seed=1)
    b = excitation("noise", "rails_x", RAILS, duration_s=40, seed=1)
    c = excitation("noise", "rails_x", RAILS, duration_s=40, seed=2)
    assert np.array_equal(a.cmd, b.cmd) and not np.array_equal(a.cmd, c.cmd)
    spec = np.abs(np.fft.rfft(a.cmd)) ** 2
    f = np.fft.rfftfreq(a.cmd.size, 1e-3)
    in_band = spec[(f > 0.5) & (f < 3.0)].mean()
    assert spec[(f > 12.0) & (f < 50.0)].mean() < 1e-4 * in_band  # 4th order at 4 Hz: -40 dB


def test_sweep_frequency_follows_the_log_law() -> None:
    exc = excitation("sweep", "rails_y", RAILS, duration_s=60, f_min_hz=0.1, f_max_hz=5.0,
                     fade_s=2.0, hold_s=0.5)
    # zero crossings of the active part: half periods of 1 / (2 f(t)), f(t) = f0 (f1/f0)^(t/T)
    u = exc.cmd[500:-500]
    t = np.arange(u.size) / 1000.0
    s = np.signbit(u)
    idx = np.nonzero(s[1:] != s[:-1])[0]
    tc = t[idx]
    mid = (tc[1:] + tc[:-1]) / 2
    f_meas = 1.0 / (2 * np.diff(tc))
    f_law = 0.1 * 50.0 ** (mid / 59.0)
    sel = (mid > 5) & (mid < 54)
    assert np.allclose(f_meas[sel], f_law[sel], rtol=0.02)


def test_schroeder_phases_closed_form_and_crest_factor() -> None:
    K = 40
    phi = schroeder_phases(np.ones(K))
    k = np.arange(1, K + 1)
    assert np.allclose(phi, -np.pi * k * (k - 1) / K)  # Schroeder 1970, equal powers
    t = np.linspace(0, 1, 20000, endpoint=False)
    x = sum(np.cos(2 * np.pi * (kk) * t + p) for kk, p in zip(k, phi, strict=True))
    zero = sum(np.cos(2 * np.pi * kk * t) for kk in k)
    crest = lambda s: np.max(np.abs(s)) / np.sqrt(np.mean(s**2))  # noqa: E731
    assert crest(x) < 1.9 < crest(zero) / 4  # zero phases: sqrt(2K) ~ 8.9


def test_multisine_has_exact_lines_in_every_full_period() -> None:
    exc = excitation("multisine", "hex_y", HEX, duration_s=60, f_min_hz=0.2, f_max_hz=8.0,
                     fade_s=2.0, hold_s=0.5)
    period = exc.params["period_s"]
    assert period == pytest.approx(5.0)
    lines = np.array(exc.params["lines_hz"])
    assert lines[0] == pytest.approx(0.2) and lines[-1] == pytest.approx(8.0)
    # one whole period well inside the fades: the active part starts at 0.5 s
    n0 = int((0.5 + 3 * period) * 1000)
    seg = exc.cmd[n0:n0 + int(period * 1000)]
    spec = np.abs(np.fft.rfft(seg))
    f = np.fft.rfftfreq(seg.size, 1e-3)
    on = np.isin(np.round(f, 6), np.round(lines, 6))
    assert on.sum() == lines.size
    assert spec[~on].max() < 1e-9 * spec[on].min()


def test_bad_parameters_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="unknown excitation kind 'chirp'"):
        excitation("chirp", "rails_y", RAILS)
    with pytest.raises(ConfigError, match="too short"):
        excitation("noise", "rails_y", RAILS, duration_s=4.0)
    with pytest.raises(ConfigError, match="Nyquist"):
        excitation("noise", "rails_y", RAILS, rate_hz=8.0)
    with pytest.raises(ConfigError, match="unknown axis"):
        excitation("noise", "rails_z", RAILS)
    with pytest.raises(ConfigError, match="neutral"):
        AxisRange(0.1, 1.0, 1.0, 1.0)


@settings(max_examples=25, deadline=None)
@given(kind=st.sampled_from(KINDS), p=st.floats(0.01, 3.0), v=st.floats(0.05, 3.0),
       a=st.floats(0.5, 20.0), band=st.floats(1.0, 15.0), seed=st.integers(0, 2**31 - 1),
       usage=st.floats(0.1, 1.0))
def test_any_limits_are_respected(kind: str, p: float, v: float, a: float, band: float,
                                  seed: int, usage: float) -> None:
    lim = AxisRange(-p, 0.7 * p, v, a)
    exc = excitation(kind, "hex_x", lim, duration_s=12.0, rate_hz=200.0, band_hz=band,
                     f_min_hz=0.5, seed=seed, usage=usage, fade_s=1.0, hold_s=0.2)
    lo, hi, vv, aa = peaks(exc.cmd, 200.0)
    tol = 1 + 1e-9
    assert lo >= lim.p_min * tol and hi <= lim.p_max * tol
    assert vv <= lim.v_max * tol and aa <= lim.a_max * tol
    assert exc.cmd[0] == 0.0 and exc.cmd[-1] == 0.0


def test_writers_round_trip(tmp_path: Path) -> None:
    exc = excitation("sweep", "rails_x", RAILS, duration_s=10, rate_hz=100.0, fade_s=1.0)
    write_csv(tmp_path / "e.csv", exc)
    write_setpoint_stream(tmp_path / "e.msgpack", exc)
    lines = (tmp_path / "e.csv").read_text().splitlines()
    assert lines[0] == "t,cmd" and len(lines) == 1001
    data = np.loadtxt(tmp_path / "e.csv", delimiter=",", skiprows=1)
    assert np.allclose(data[:, 0], exc.t) and np.allclose(data[:, 1], exc.cmd, rtol=1e-11,
                                                          atol=1e-15)
    frames = read_setpoint_stream(tmp_path / "e.msgpack")
    assert len(frames) == 1000
    assert frames[0] == {"seq": 0, "t": 0.0, "pos": {"rails_x": 0.0}}
    assert [f["seq"] for f in frames] == list(range(1000))
    assert all(set(f) == {"seq", "t", "pos"} for f in frames)
    assert np.allclose([f["pos"]["rails_x"] for f in frames], exc.cmd, rtol=0, atol=0)
    assert isinstance(frames[5]["t"], float) and frames[5]["t"] == pytest.approx(0.05)
    # a plain streaming unpacker (what a sender uses) reads the same
    with open(tmp_path / "e.msgpack", "rb") as fh:
        unpacker = msgpack.Unpacker(fh, raw=False)
        assert next(iter(unpacker))["seq"] == 0
    assert not list(tmp_path.glob(".*tmp"))


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                          env=subprocess_env(), timeout=300)


def test_cli_excite_writes_csv_stream_and_simulated_recording(tmp_path: Path) -> None:
    stem = tmp_path / "hex"
    p = run("excite", "--axis", "hex_z", "--kind", "multisine", "--duration", "20",
            "--out", str(stem), "--simulate", "hexapod", "--json")
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["axis"] == "hex_z" and out["kind"] == "multisine" and out["samples"] == 20000
    assert out["limits"] == {"p_min": -0.18, "p_max": 0.18, "v_max": 0.5, "a_max": 7.0}
    assert max(out["usage"].values()) == pytest.approx(0.9)
    assert out["limits_from"] == "hexapod"
    for suffix in (".csv", ".msgpack", ".sim.csv"):
        assert (tmp_path / f"hex{suffix}").stat().st_size > 10000
    sim = (tmp_path / "hex.sim.csv").read_text().splitlines()
    assert sim[0] == "# axis: hex_z" and sim[1] == "t,cmd,acc"


@pytest.mark.parametrize(("args", "msg"), [
    (("--axis", "rails_q"), "unknown axis 'rails_q'"),
    (("--axis", "rails_y", "--duration", "3"), "too short"),
    (("--axis", "rails_y", "--limits", "1", "-1", "2"), "must be > 0"),
    (("--axis", "rails_y", "--simulate", "p1d:K=1,Td=0.01"), "missing parameter"),
])
def test_cli_excite_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                              args: tuple[str, ...], msg: str) -> None:
    from motcomp.cli import main

    code = main(["excite", *args, "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert code == 2
    assert msg in err and len(err.strip().splitlines()) == 1
    assert not list(tmp_path.iterdir())
