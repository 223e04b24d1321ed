"""Identification data: CSV and MCAP loaders, resampling, and every bad-input case of
``motcomp identify`` (one-line message naming the place, exit code 2, nothing written)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import msgpack
import numpy as np
import pytest

from motcomp.cli import main
from motcomp.core.models import P1D
from motcomp.errors import DataError
from motcomp.ident.data import (
    FEEDBACK_KEY,
    OUTPUT_KEY,
    SETPOINT_KEY,
    load_recording,
    write_recording_csv,
)
from motcomp.ident.excitation import AxisRange, excitation
from motcomp.sim.platform import Accelerometer, record_identification
from tests.conftest import motcomp_cmd, subprocess_env

TRUTH = P1D(K=1.0, Td=0.02, Tp1=0.12)


@pytest.fixture(scope="module")
def base() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    exc = excitation("sweep", "rails_y", AxisRange(-2.6, 2.6, 2.0, 6.0), duration_s=20.0,
                     f_max_hz=4.0)
    return record_identification(TRUTH, exc.cmd, 1000.0, Accelerometer(noise_std=0.01), seed=9)


def write_csv(path: Path, rows: list[str], header: str = "t,cmd,acc") -> Path:
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


def rows_of(t: np.ndarray, cmd: np.ndarray, acc: np.ndarray) -> list[str]:
    return [f"{a:.9f},{b:.12g},{c:.12g}" for a, b, c in zip(t, cmd, acc, strict=True)]


def identify_cli(capsys: pytest.CaptureFixture[str], path: Path, out: Path, *extra: str
                 ) -> tuple[int, str]:
    code = main(["identify", str(path), "--out", str(out), "--no-figures", "--quiet", *extra])
    return code, capsys.readouterr().err


def test_csv_round_trip_and_axis_comment(tmp_path: Path,
                                         base: tuple[np.ndarray, ...]) -> None:
    t, cmd, acc = base
    write_recording_csv(tmp_path / "d.csv", t, cmd, acc, axis="rails_x")
    rec = load_recording(tmp_path / "d.csv")
    assert rec.axis == "rails_x" and rec.rate_hz == 1000.0 and not rec.resampled
    assert np.allclose(rec.cmd, cmd, rtol=1e-11, atol=1e-15)
    assert np.allclose(rec.acc, acc, rtol=1e-11, atol=1e-12)
    assert load_recording(tmp_path / "d.csv", axis="hex_x").axis == "hex_x"


def test_irregular_time_is_resampled_onto_a_uniform_grid(tmp_path: Path) -> None:
    # a signal known in closed form, sampled at jittered instants
    rng = np.random.default_rng(1)
    t = np.arange(5000) / 1000.0 + rng.uniform(-3e-4, 3e-4, 5000)
    t.sort()
    f = lambda x: np.sin(2 * np.pi * 1.3 * x)  # noqa: E731
    path = write_csv(tmp_path / "j.csv", rows_of(t, f(t), 2 * f(t)))
    rec = load_recording(path)
    assert rec.resampled and rec.rate_hz == 1000.0 and rec.period_jitter_s > 1e-4
    assert np.allclose(np.diff(rec.t), 1e-3)
    grid = rec.t + t[0]
    # linear interpolation of a 1.3 Hz sine at 1 kHz: error below (w h)^2 / 8
    assert np.max(np.abs(rec.cmd - f(grid))) < (2 * np.pi * 1.3 * 1.6e-3) ** 2 / 8


def test_short_gaps_are_bridged_and_counted_a_long_one_named(tmp_path: Path,
                                                             base: tuple[np.ndarray, ...]) -> None:
    t, cmd, acc = base
    keep = np.ones(t.size, bool)
    keep[5000:5010] = False  # 11 ms between two samples
    keep[12000:12020] = False  # 21 ms
    path = write_csv(tmp_path / "g.csv", rows_of(t[keep], cmd[keep], acc[keep]))
    rec = load_recording(path)
    assert rec.gaps.count == 2 and rec.gaps.longest_s == pytest.approx(0.021, abs=1e-9)
    assert rec.gaps.total_s == pytest.approx(0.032, abs=1e-9)
    assert [round(a, 3) for a, _ in rec.gaps.first] == [4.999, 11.999]
    # the grid goes on through the gaps at the rate outside them; no jitter from the gaps
    assert rec.resampled and rec.rate_hz == 1000.0 and rec.n == t.size
    assert rec.period_jitter_s < 1e-9
    assert rec.window is not None and rec.window.how == "whole recording"
    # linear interpolation across the 21 ms: the command's error is below (w d)^2 / 8 of it
    assert np.allclose(rec.cmd, cmd, atol=0.021 ** 2 * np.max(np.abs(np.diff(cmd, 2))) / 8e-6)
    with pytest.raises(DataError, match=r"g\.csv: line 11992: column t: gap of 0\.021 s without "
                                        r"data at 11\.999 s \(median period 0\.001 s; longer "
                                        r"than --max-gap 0\.015 s\)"):
        load_recording(path, max_gap_s=0.015)
    # a window of the data, in seconds from its start, leaving the long gap out
    rec = load_recording(path, max_gap_s=0.015, window=(1.0, 11.0))
    assert rec.window is not None and rec.window.how == "given"
    assert rec.window.samples == 10001 - 10 and rec.gaps.count == 1
    assert rec.start_s == 1.0 and rec.n == 10001


def write_mcap(path: Path, t: np.ndarray, cmd: np.ndarray, acc: np.ndarray,
               latency_s: float = 0.0, inputs: np.ndarray | None = None) -> None:
    """A session as the stack records it: the service's outputs (rails_y bypassed) and the
    platform's feedback; ``inputs``, if given, on the input key (what identify must not take
    as the command)."""
    from mcap.writer import Writer

    from motcomp.core.axes import AXES
    from motcomp.io.wire import encode_output

    t0 = 1_700_000_000.0
    j = AXES.index("rails_y")
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sp = w.register_channel(SETPOINT_KEY, "msgpack", 0)
        out = w.register_channel(OUTPUT_KEY, "msgpack", 0)
        fb = w.register_channel(FEEDBACK_KEY, "msgpack", 0)
        for k in range(t.size):
            ts = int((t0 + t[k]) * 1e9)
            if inputs is not None:
                w.add_message(sp, log_time=ts, publish_time=ts, data=msgpack.packb(
                    {"seq": k, "t": t0 + float(t[k]), "pos": {"rails_y": float(inputs[k])}}))
            pos = [0.0] * len(AXES)
            pos[j] = float(cmd[k])
            w.add_message(out, log_time=ts, publish_time=ts, data=encode_output(
                k, t0 + float(t[k]), k, pos, ["bypass:rails_y"]))
            tf = int((t0 + t[k] + latency_s) * 1e9)
            w.add_message(fb, log_time=tf, publish_time=tf, data=msgpack.packb(
                {"t": t0 + float(t[k]), "pos": {"rails_y": 0.0},
                 "acc": {"rails_y": float(acc[k]), "hex_z": 0.0}}))
        w.finish()


def test_mcap_session_recording(tmp_path: Path, base: tuple[np.ndarray, ...]) -> None:
    t, cmd, acc = base
    # the inputs are not what the platform received: a compensator scaled them
    write_mcap(tmp_path / "s.mcap", t, cmd, acc, latency_s=0.3e-3, inputs=cmd / 3)
    rec = load_recording(tmp_path / "s.mcap")
    # the axis whose output moves is found; the frames' t are one clock; the command is the
    # output in force at each feedback sample
    # (resampled: the time stamps since the epoch vary by their resolution, 0.24 us)
    assert rec.axis == "rails_y" and rec.rate_hz == 1000.0 and rec.n == t.size
    assert np.allclose(rec.cmd, cmd, rtol=0, atol=1e-3 * np.ptp(cmd))
    assert np.allclose(rec.acc, acc, rtol=0, atol=1e-3 * np.ptp(acc))
    assert rec.window is not None and rec.window.samples == t.size
    assert rec.gaps.count == 0 and not rec.warnings
    from motcomp.ident.fit import FitOptions, identify

    fit_frame = identify(rec, FitOptions(models=("p1d",))).fits["p1d"].model
    assert fit_frame.pure_delay_s == pytest.approx(0.020, abs=2e-4)
    # the recorder's clock: each feedback sample, received 0.3 ms late, still pairs with the
    # output in force (received less than a period before it)
    rec_log = load_recording(tmp_path / "s.mcap", clock="log")
    assert np.allclose(rec_log.cmd, cmd, rtol=0, atol=1e-3 * np.ptp(cmd))
    fit_log = identify(rec_log, FitOptions(models=("p1d",))).fits["p1d"].model
    assert fit_log.pure_delay_s == pytest.approx(fit_frame.pure_delay_s, abs=1.5e-4)
    with pytest.raises(DataError, match=r"platform/feedback: no message carries acc\.hex_y"):
        load_recording(tmp_path / "s.mcap", axis="hex_y")


def test_mcap_missing_channel(tmp_path: Path) -> None:
    from mcap.writer import Writer

    with open(tmp_path / "e.mcap", "wb") as fh:
        w = Writer(fh)
        w.start()
        ch = w.register_channel(SETPOINT_KEY, "msgpack", 0)
        w.add_message(ch, log_time=1, publish_time=1,
                      data=msgpack.packb({"seq": 0, "t": 0.0, "pos": {"rails_y": 0.0}}))
        w.finish()
    # the inputs alone do not say what the platform received
    with pytest.raises(DataError, match="no messages on channel platform/setpoint: the command "
                                        "identified against is the service's output in force"):
        load_recording(tmp_path / "e.mcap")
    (tmp_path / "bad.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(DataError, match=r"bad\.mcap"):
        load_recording(tmp_path / "bad.mcap")


# --- every bad input, through the command --------------------------------------------------------

def _case(name: str, t: np.ndarray, cmd: np.ndarray, acc: np.ndarray, tmp: Path
          ) -> tuple[Path, tuple[str, ...], str]:
    rows = rows_of(t, cmd, acc)
    if name == "missing column":
        return write_csv(tmp / "d.csv", rows, "t,cmd"), (), \
            "missing column(s) 'acc'; the header must name t, cmd and acc; found: t, cmd"
    if name == "misnamed column":
        return write_csv(tmp / "d.csv", rows, "t,cmd,Acc"), (), "missing column(s) 'acc' " \
            "(found 'Acc')"
    if name == "nan":
        rows[41] = rows[41].rsplit(",", 1)[0] + ",nan"
        return write_csv(tmp / "d.csv", rows), (), "d.csv: line 43: column acc: value nan is " \
            "not a finite number"
    if name == "not a number":
        parts = rows[7].split(",")
        rows[7] = f"{parts[0]},abc,{parts[2]}"
        return write_csv(tmp / "d.csv", rows), (), "d.csv:9: column cmd: 'abc' is not a number"
    if name == "time backwards":
        t2 = t.copy()
        t2[100] = t2[98]
        return write_csv(tmp / "d.csv", rows_of(t2, cmd, acc)), (), \
            "line 102: column t: time goes backwards (0.098 s after 0.099 s)"
    if name == "repeated time":
        t2 = t.copy()
        t2[100] = t2[99]
        return write_csv(tmp / "d.csv", rows_of(t2, cmd, acc)), (), \
            "line 102: column t: repeated time 0.099 s"
    if name == "too few samples":
        return write_csv(tmp / "d.csv", rows[:600]), (), "only 600 samples; at least 1000"
    if name == "gap":
        t2 = t.copy()
        t2[3000:] += 0.5
        return write_csv(tmp / "d.csv", rows_of(t2, cmd, acc)), (), \
            "line 3002: column t: gap of 0.501 s without data"
    if name == "constant command":
        return write_csv(tmp / "d.csv", rows_of(t, np.full_like(cmd, 0.25), acc)), (), \
            "column cmd: the command is constant (0.25 on every sample): nothing was excited"
    if name == "clipped":
        hi = np.quantile(acc, 0.995)
        return write_csv(tmp / "d.csv", rows_of(t, cmd, np.minimum(acc, hi))), (), \
            "column acc: measurement clipped or saturated"
    if name == "delay above range":
        return write_csv(tmp / "d.csv", rows), ("--delay-range", "0", "12", "--models", "p1d"), \
            "pure delay outside the searched range: the best delay is at the upper end " \
            "(12.0 ms) of [0.0, 12.0] ms; widen the delay range (--delay-range)"
    if name == "delay below range":
        return write_csv(tmp / "d.csv", rows), ("--delay-range", "30", "100", "--models", "p1d"), \
            "the best delay is at the lower end (30.0 ms) of [30.0, 100.0] ms; lower the delay " \
            "range's minimum, or the measurement may lead the command"
    if name == "empty file":
        (tmp / "d.csv").write_text("# axis: rails_y\n")
        return tmp / "d.csv", (), "empty file: expected a header line 't,cmd,acc'"
    if name == "unknown format":
        (tmp / "d.parquet").write_text("x")
        return tmp / "d.parquet", (), "unknown data format '.parquet'; readable: .csv, .mcap"
    if name == "unknown axis":
        return write_csv(tmp / "d.csv", rows), ("--axis", "rails_w"), "unknown axis 'rails_w'"
    raise AssertionError(name)


BAD = ["missing column", "misnamed column", "nan", "not a number", "time backwards",
       "repeated time", "too few samples", "gap", "constant command", "clipped",
       "delay above range", "delay below range", "empty file", "unknown format", "unknown axis"]


@pytest.mark.parametrize("name", BAD)
def test_bad_input_one_line_exit_2_nothing_written(name: str, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str],
                                                   base: tuple[np.ndarray, ...]) -> None:
    t, cmd, acc = base
    path, extra, msg = _case(name, t, cmd, acc, tmp_path)
    out = tmp_path / "out"
    code, err = identify_cli(capsys, path, out, *extra)
    assert code == 2, err
    assert msg in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not out.exists() or not any(out.iterdir())


def test_bad_input_exit_code_in_a_real_process(tmp_path: Path) -> None:
    write_csv(tmp_path / "d.csv", ["0,0,0"], "time,cmd,acc")
    p = subprocess.run(motcomp_cmd("identify", str(tmp_path / "d.csv"), "--quiet"),
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert p.returncode == 2
    assert p.stderr.strip() == (f"motcomp identify: error: {tmp_path / 'd.csv'}:1: missing "
                                "column(s) 't' (found 'time'); the header must name t, cmd and "
                                "acc; found: time, cmd, acc")


@pytest.mark.slow
def test_mcap_with_two_axes_identified_together(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    import json
    import tomllib

    from mcap.writer import Writer

    truths = {"rails_x": P1D(K=1.0, Td=0.018, Tp1=0.16), "hex_z": P1D(K=1.0, Td=0.033, Tp1=0.01)}
    lims = {"rails_x": AxisRange(-2.6, 2.6, 2.0, 6.0), "hex_z": AxisRange(-0.18, 0.18, 0.5, 7.0)}
    data = {}
    for i, (axis, truth) in enumerate(truths.items()):
        exc = excitation("sweep" if axis == "rails_x" else "noise", axis, lims[axis],
                         duration_s=30.0, seed=i + 1)
        data[axis] = record_identification(truth, exc.cmd, 1000.0,
                                           Accelerometer(noise_std=0.01), seed=i + 50)
    t = data["rails_x"][0]
    from motcomp.core.axes import AXES
    from motcomp.io.wire import encode_output

    with open(tmp_path / "two.mcap", "wb") as fh:
        w = Writer(fh)
        w.start()
        out = w.register_channel(OUTPUT_KEY, "msgpack", 0)
        fb = w.register_channel(FEEDBACK_KEY, "msgpack", 0)
        for k in range(t.size):
            ts = int((100.0 + t[k]) * 1e9)
            pos = [float(data[a][1][k]) if a in data else 0.0 for a in AXES]
            w.add_message(out, log_time=ts, publish_time=ts, data=encode_output(
                k, 100.0 + float(t[k]), k, pos, [f"bypass:{a}" for a in data]))
            w.add_message(fb, log_time=ts, publish_time=ts, data=msgpack.packb(
                {"t": 100.0 + float(t[k]), "pos": {},
                 "acc": {a: float(d[2][k]) for a, d in data.items()}}))
        w.finish()
    code = main(["identify", str(tmp_path / "two.mcap"), "--axis", "all", "--models", "p1d",
                 "--out", str(tmp_path / "out"), "--no-figures", "--json"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    rep = json.loads(cap.out)
    assert [r["axis"] for r in rep["table1"]] == ["rails_x", "hex_z"]
    for row in rep["table1"]:
        truth = truths[row["axis"]]
        assert row["pure_delay_ms"] == pytest.approx(truth.Td * 1e3, abs=0.5)
        assert row["phase_delay_0p2hz_ms"] == pytest.approx(
            float(truth.phase_delay(0.2)[0]) * 1e3, abs=3.0)
    doc = tomllib.loads((tmp_path / "out" / "axes.toml").read_text())
    assert set(doc["axes"]) == {"rails_x", "hex_z"}
    assert (tmp_path / "out" / "hex_z" / "report.json").is_file()
    assert "| hex_z | p1d |" in (tmp_path / "out" / "table1.md").read_text()
