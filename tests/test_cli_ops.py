"""The operator's side of the commands, as a new user meets it: help on every option, bad numbers
refused by argparse, unreachable peers named and answered with exit 3 after the wait, progress
and an honest summary from ``source``, ``hil``'s start-up and exit logs, ``status`` as a table,
the shipped example config, ``info`` on a recording.  Processes run as subprocesses on real
zenoh sessions over loopback (multicast scouting off, a free port each)."""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from motcomp.cli import build_parser, main
from motcomp.cli._common import (
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
)
from motcomp.cli.admin import format_status
from motcomp.config import config_hash, load_config, parse_config
from motcomp.core.axes import AXES
from motcomp.io.wire import encode_output
from motcomp.io.zenoh_io import ZenohEndpoints, free_tcp_port, loopback, open_session
from motcomp.replay.synth import SynthOptions, synthesize
from motcomp.resources import config_file
from tests.conftest import motcomp_cmd, subprocess_env
from tests.test_service_process import process


def cli(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                          env=subprocess_env(), timeout=timeout)


def dead_endpoint() -> str:
    """A loopback endpoint nobody listens on."""
    return loopback(free_tcp_port())


def wait_for_text(log: Path, text: str, proc: subprocess.Popen[bytes],
                  timeout: float = 30.0) -> str:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        content = log.read_text(errors="replace")
        if text in content:
            return content
        if proc.poll() is not None:
            break
        time.sleep(0.1)
    raise AssertionError(f"{text!r} not in {log}:\n{log.read_text(errors='replace')}")


# --- the parser ---------------------------------------------------------------------------
def _subparsers(parser: argparse.ArgumentParser, path: str = "motcomp"
                ) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _subparsers(sub, f"{path} {name}")


def test_every_option_of_every_command_has_help() -> None:
    missing = []
    for path, parser in _subparsers(build_parser()):
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            if isinstance(action, argparse._SubParsersAction):
                missing += [f"{path} {c.dest}" for c in action._choices_actions
                            if not (c.help or "").strip()]
                continue
            if not (action.help or "").strip():
                missing.append(f"{path} {'/'.join(action.option_strings) or action.dest}")
    assert not missing, missing


@pytest.mark.parametrize(("helper", "good", "bad"), [
    (positive_float, {"2.5": 2.5, "1e-3": 1e-3}, ["0", "-1", "nan", "inf", "x", ""]),
    (non_negative_float, {"0": 0.0, "3": 3.0}, ["-0.1", "nan", "-inf", "x"]),
    (positive_int, {"1": 1, "12": 12}, ["0", "-3", "1.5", "x"]),
    (non_negative_int, {"0": 0, "7": 7}, ["-1", "2.0", "x"]),
])
def test_number_types_accept_and_refuse(helper: Any, good: dict[str, float],
                                        bad: list[str]) -> None:
    for text, value in good.items():
        assert helper(text) == value
    for text in bad:
        with pytest.raises(argparse.ArgumentTypeError, match=repr(text).replace("'", ".")):
            helper(text)


@pytest.mark.parametrize("argv", [
    ["status", "--timeout", "-1"],
    ["status", "--watch", "0"],
    ["bypass", "on", "--timeout", "nan"],
    ["reload", "--timeout", "0"],
    ["source", "--signal", "slalom", "--rate", "0"],
    ["source", "--signal", "slalom", "--repeat", "0"],
    ["source", "--signal", "slalom", "--wait-peer", "-2"],
    ["source", "--signal", "slalom", "--seq-start", "-1"],
    ["hil", "--duration", "-1"],
    ["hil", "--margin", "-0.1"],
    ["hil", "--seed", "-4"],
    ["record", "-o", "x.mcap", "--flush-s", "inf"],
    ["record", "-o", "x.mcap", "--chunk-kb", "0"],
    ["replay", "x.mcap", "--speed", "0"],
    ["replay", "x.mcap", "--jobs", "0"],
    ["replay", "x.mcap", "--realtime", "--lead-in", "-1"],
    ["excite", "--axis", "rails_x", "--out", "x", "--fade", "-1"],
    ["excite", "--axis", "rails_x", "--out", "x", "--limits", "1", "nan", "2"],
    ["info", "x.mcap", "--gap-s", "0"],
])
def test_bad_numbers_are_usage_errors(argv: list[str], capsys: pytest.CaptureFixture[str]
                                      ) -> None:
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"motcomp {argv[0]}: error: argument" in err, err


@pytest.mark.parametrize("argv", [["design", "--plant", "rails", "--bogus", "1"],
                                  ["status", "--nope"], ["config", "check", "a", "b"]])
def test_an_unknown_argument_is_said_with_the_command_s_usage(
        argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    """Not the top level's ``usage: motcomp [-h] [--version] COMMAND ...``."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    usage = f"usage: motcomp {' '.join(argv[:2] if argv[0] == 'config' else argv[:1])}"
    assert err.startswith(usage) and "error: unrecognized arguments" in err, err


def test_negative_timeout_is_a_usage_error_not_a_traceback() -> None:
    p = cli("status", "--timeout", "-1")
    assert p.returncode == 2
    assert "argument --timeout: expected a positive number, got '-1'" in p.stderr
    assert "Traceback" not in p.stderr


# --- unreachable peers --------------------------------------------------------------------
LATE_S = 0.7
"""How much longer than its --timeout or --wait-peer a command may take: the interpreter's own
start before the command's first line (the timeout counts from there: imports and zenoh's
0.5 s scouting delay at open are part of it), and its exit."""


def test_status_waits_the_full_timeout_and_names_the_endpoint() -> None:
    dead = dead_endpoint()
    for timeout in (1, 2):
        t0 = time.monotonic()
        p = cli("status", "-e", dead, "--timeout", str(timeout))
        took = time.monotonic() - t0
        assert timeout <= took < timeout + LATE_S, took  # what the user asked (it took +2.5 s)
        assert p.returncode == 3, p.stderr
        assert f"no reply from the service at connect {dead} (key motcomp/status) within " \
            f"{timeout} s" in p.stderr
        assert "Traceback" not in p.stderr


def test_a_change_waits_for_the_answer_as_long_as_the_service_may_prepare_it() -> None:
    """A reload or profile switch the service is still preparing is not reported as no
    answer: the commands' default wait exceeds the service's own limit for preparing one."""
    from motcomp.runtime.reload import PREPARE_TIMEOUT_S

    parser = build_parser()
    for argv in (["reload"], ["profile", "fast"]):
        assert parser.parse_args(argv).timeout >= PREPARE_TIMEOUT_S + 1.0, argv
    assert parser.parse_args(["status"]).timeout == 3.0


def test_a_bad_truth_is_named_with_its_option() -> None:
    p = cli("hil", "--truth", "rails_x=p1d:bad", "--duration", "1")
    assert p.returncode == 2, p.stderr
    assert ("--truth 'rails_x=p1d:bad': model spec 'p1d:bad': 'bad' is not KEY=VALUE"
            in p.stderr), p.stderr
    p = cli("hil", "--truth", "rails_y=p1d:K=1,Td=21.5,Tp1=293", "--duration", "1")
    assert p.returncode == 2, p.stderr
    assert ("--truth 'rails_y=p1d:K=1,Td=21.5,Tp1=293': delay 21.5 s beyond 0.25 s" in p.stderr
            ), p.stderr


def test_bad_endpoints_are_named() -> None:
    p = cli("status", "-e", "nonsense", "--timeout", "1")
    assert p.returncode == 2, p.stderr
    assert "zenoh: connect endpoint 'nonsense': Endpoints must be" in p.stderr
    assert ".rs:" not in p.stderr and "Traceback" not in p.stderr
    # zenoh itself takes a port that is no number, and fails as if nobody were there
    p = cli("status", "-e", "tcp/localhost:notaport", "--timeout", "1")
    assert p.returncode == 2, p.stderr
    assert ("zenoh: connect endpoint 'tcp/localhost:notaport': port 'notaport' is not a "
            "number 0-65535") in p.stderr
    p = cli("source", "--signal", "slalom", "-l", "udp/127.0.0.1:70000", "--wait-peer", "1")
    assert p.returncode == 2 and "port '70000' is not a number 0-65535" in p.stderr, p.stderr
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = loopback(busy.getsockname()[1])
        p = cli("source", "--signal", "slalom", "-l", taken, "--wait-peer", "1")
    assert p.returncode == 1, p.stderr
    assert f"cannot open a zenoh session (listen {taken})" in p.stderr
    assert "Address already in use" in p.stderr and ".rs:" not in p.stderr


def test_source_without_a_subscriber_exits_3_naming_the_endpoint() -> None:
    dead = dead_endpoint()
    t0 = time.monotonic()
    p = cli("source", "--signal", "slalom", "-e", dead, "--wait-peer", "2")
    took = time.monotonic() - t0
    assert p.returncode == 3, (p.stdout, p.stderr)
    assert 2 <= took < 2 + LATE_S, took
    assert f"no subscriber of sim/motion/setpoint reachable within 2 s (connect {dead})" \
        in p.stderr
    assert "published" not in p.stdout


def test_a_recording_no_peer_reached_exits_3_naming_the_endpoint(tmp_path: Path) -> None:
    dead = dead_endpoint()
    out = tmp_path / "empty.mcap"
    p = cli("record", "-o", str(out), "-e", dead, "--duration", "1.5", "--status-timeout", "0")
    assert p.returncode == 3, (p.stdout, p.stderr)
    assert (f"no zenoh peer was reachable (connect {dead}) at any time of the recording"
            in p.stdout), p.stdout
    assert "recorded 0 messages" in p.stdout and out.exists()


def test_realtime_replay_without_a_subscriber_exits_3(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    synthesize(path, load_config(config_file("motcomp.toml")),
               SynthOptions(duration_s=1.0, feedback=False, status=False))
    dead = dead_endpoint()
    p = cli("replay", str(path), "--realtime", "-e", dead, "--wait-peer", "1", "--quiet")
    assert p.returncode == 3, (p.stdout, p.stderr)
    assert f"no subscriber of sim/motion/setpoint reachable within 1 s (connect {dead})" \
        in p.stderr
    assert "republished" not in p.stdout


def test_realtime_replay_s_progress_spans_the_frames_it_sends(tmp_path: Path) -> None:
    """A recording whose input stopped before the recorder: the progress runs over the
    input's frames (1 s here), not the recording's whole span (3 s)."""
    from motcomp.io.wire import encode_input
    from motcomp.record.recorder import SessionWriter

    path = tmp_path / "s.mcap"
    keys = ["sim/motion/setpoint", "platform/setpoint"]
    t0 = 1_750_000_000.0
    with SessionWriter(path, keys, {}, b"{}", chunk_bytes=8 << 10) as w:
        for k in range(3001):
            t = t0 + k * 1e-3
            if k <= 1000:
                w.write(keys[0], round(t * 1e9), encode_input(k, t, {"rails_x": 0.0}))
            w.write(keys[1], round(t * 1e9) + 1000,
                    encode_output(k, t, k, [0.0] * len(AXES), []))
    p = cli("replay", str(path), "--realtime", "-e", dead_endpoint(), "--wait-peer", "1")
    assert p.returncode == 3, (p.stdout, p.stderr)
    assert (f"republishing {path} (1.0 s of sim/motion/setpoint frames in the 3.0 s "
            "recorded) at 1x") in p.stderr, p.stderr


@pytest.mark.slow
def test_source_shows_progress_and_says_it_was_stopped(tmp_path: Path) -> None:
    import zenoh

    port = free_tcp_port()
    with open_session(ZenohEndpoints(listen=(loopback(port),))) as session:
        sub = session.declare_subscriber("sim/motion/setpoint", zenoh.handlers.RingChannel(1))
        log = tmp_path / "source.log"
        with process(["source", "--signal", "sweep", "-e", loopback(port), "--lead-in", "0"],
                   log) as src:
            wait_for_text(log, " of 60.0 s (", src, timeout=20)  # a progress line
            assert sub.try_recv() is not None
            src.send_signal(signal.SIGTERM)
            assert src.wait(timeout=10) == 0
        text = log.read_text()
        sub.undeclare()
    assert "0.1-3 Hz swept sine on rails_x: 60000 samples at 1000 Hz (60.0 s)" in text
    assert "stopped by a signal with" in text, text
    assert "published" in text and "Traceback" not in text


# --- hil ----------------------------------------------------------------------------------
def test_hil_logs_its_setup_and_a_summary_at_exit(tmp_path: Path) -> None:
    port = free_tcp_port()
    log = tmp_path / "hil.log"
    with process(["hil", "-l", loopback(port), "--quiet-sensor"], log) as hil:
        text = wait_for_text(log, "accelerometer: ideal", hil)
        assert f"zenoh listen {loopback(port)}" in text and "setpoints from zenoh " \
            "platform/setpoint" in text
        assert "rails_y   truth p1d:K=1,Td=0.0175,Tp1=0.1857683128; hard limits" in text
        assert "hex_yaw   truth p2uzd:" in text
        with open_session(ZenohEndpoints(connect=(loopback(port),))) as session:
            pub = session.declare_publisher("platform/setpoint")
            t_end = time.monotonic() + 10
            while not pub.matching_status.matching and time.monotonic() < t_end:
                time.sleep(0.02)
            for k in range(20):
                pub.put(encode_output(k, time.time(), k, [0.0] * len(AXES), []))
                time.sleep(0.005)
            time.sleep(0.3)
            pub.undeclare()
        hil.send_signal(signal.SIGTERM)
        assert hil.wait(timeout=20) == 0
    text = log.read_text()
    line = next((ln for ln in text.splitlines() if "stopped: " in ln), "")
    assert " ticks, " in line and " missed, " in line and "periods caught up" in line, text
    assert "setpoint frames received 20 (0 bad)" in line, line
    assert line.endswith("hard-limit violations: none"), line


# --- status -------------------------------------------------------------------------------
def test_status_table_from_a_status_map() -> None:
    st = {"mode": "running", "version": "9.9", "rate_hz": 1000.0, "ticks": 1234,
          "missed_ticks": 2, "config": {"hash": "abc123", "version": 3, "path": "/etc/m.toml"},
          "profile": "fast", "loop": {"compute_p50_us": 10.0, "compute_p99_us": 20.0,
                                      "compute_p999_us": 30.0, "compute_max_us": 40.0,
                                      "late_p50_us": 1.0, "late_p99_us": 2.0,
                                      "late_p999_us": 3.0, "late_max_us": 4.0},
          "loop_window_s": 10.0,
          "frames": {"received": 100, "accepted": 97, "rejected": 3, "superseded": 1,
                     "rejected_by_reason": {"range": 2, "decode": 1}, "last_reject": "x"},
          "stale_s": 0.0, "stale_total_s": 1.5, "stale_episodes": 2,
          "saturation": dict.fromkeys(AXES, 0) | {"rails_y": 7},
          "bypass": ["hex_z"], "driven": ["rails_x", "rails_y", "hex_z"],
          "prediction": {"hex_z": {"state": "fallback", "weight": 0.0, "ratio": 0.4,
                                   "fallbacks": 2}},
          "t": 1000.0,
          "deadlines": {"window_s": 10.0, "due": 10000, "missed": 512, "share": 0.0512,
                        "degraded": True, "windows_degraded": 1},
          "platform": {"received_t": 999.5, "setpoint_age_ms": 1.62,
                       "setpoint_age_mean_ms": 1.75, "missed_ticks": 3}}
    text = format_status(st)
    assert ("deadlines   missed 512 of 10000 over the last 10 s (5.1 %)  DEGRADED: the host "
            "does not give the loop its CPU") in text
    assert ("platform    setpoints applied 1.62 ms after their t (median; mean 1.75 ms): the "
            "stack's delay; its loop missed 3 ticks") in text
    assert "{" not in text and "[" not in text  # no Python reprs
    assert "hash abc123  version 3  profile fast" in text
    assert "1000 Hz  ticks 1234  missed 2" in text
    # of the missed deadlines, those the loop waited for a CPU, where the status says
    st["missed_waiting_cpu"] = 1
    st["deadlines"]["missed_waiting_cpu"] = 500
    st["platform"]["missed_waiting_cpu"] = 0
    text = format_status(st)
    assert "1000 Hz  ticks 1234  missed 2 (1 waiting for a CPU)" in text
    assert "\nmode        running\n" in f"\n{text}\n"
    waiting = {**st, "mode": "stale", "frames": {**st["frames"], "received": 0}}
    assert ("mode        stale (no frame received yet: holding the start position)"
            in format_status(waiting))
    assert "deadlines   missed 512 (500 waiting for a CPU) of 10000 over the last 10 s" in text
    # the reference's band limits, each with the axes it holds where they differ
    narrow, wide = {"band_hz": 48.0, "delay_ms": 7.01}, {"band_hz": 64.0, "delay_ms": 5.26}
    st["input"] = {"reconstruction": "smooth", "period_ms": 1.0, "lag_ms": 1.7,
                   "band": {"rails_x": narrow, "rails_y": narrow, "hex_roll": wide}}
    assert ("band limit 48 Hz (7.01 ms) on rails_x, rails_y; 64 Hz (5.26 ms) on hex_roll "
            "(design --input-band-hz") in format_status(st)
    st["input"]["band"] = {"rails_x": narrow, "rails_y": narrow}
    assert "band limit 48 Hz (7.01 ms) (design --input-band-hz" in format_status(st)
    assert "input       smooth  period 1.00 ms  lag 1.70 ms (design --input-lag-ms)" in \
        format_status(st)
    # before a frame is accepted the period and lag are not known yet (they read 0.00 ms)
    st["input"]["playback_lag_ms"] = 1.7
    st["frames"] = {"received": 0, "accepted": 0, "rejected": 0}
    waiting = format_status(st)
    assert ("input       smooth  period and lag from the first frames on (the config's "
            "playback lag 1.70 ms)") in waiting
    assert "band limit 48 Hz (7.01 ms) (design --input-band-hz" in waiting  # the config's own
    assert "its loop missed 3 ticks (0 waiting for a CPU)" in text
    assert "received 100  accepted 97  rejected 3 (decode 1, range 2)  superseded 1" in text
    assert "stale       no  (before: 1.50 s over 2 episode(s))" in text
    # an episode going on is not in the total, which counts the finished ones
    ongoing = format_status({**st, "stale_s": 8.15, "stale_total_s": 0.48, "stale_episodes": 8,
                             "frames": {"received": 100, "accepted": 100, "rejected": 0}})
    assert ("stale       NOW 8.15 s since the last frame (episode 8; the 7 before: 0.48 s)"
            in ongoing), ongoing
    rows = {ln.split()[0]: ln.split()[1:] for ln in text.splitlines()}
    assert rows["compute"] == ["10.0", "20.0", "30.0", "40.0"]
    assert rows["rails_y"] == ["yes", "no", "-", "-", "7"]
    assert rows["hex_z"] == ["yes", "yes", "fallback", "2", "0"]
    assert rows["hex_yaw"] == ["no", "-", "-", "-", "0"]


@pytest.mark.slow
def test_status_of_a_running_service_as_table_json_and_watch(tmp_path: Path) -> None:
    port = free_tcp_port()
    ep = loopback(port)
    with process(["run", "--config", str(config_file("motcomp.toml")), "-l", ep],
               tmp_path / "svc.log"):
        p = cli("status", "-e", ep, "--timeout", "20")  # waits for the service to come up
        assert p.returncode == 0, p.stderr
        lines = p.stdout.splitlines()
        assert lines[0].startswith("mode ")
        header = next(ln for ln in lines if ln.startswith("axis"))
        assert header.split() == ["axis", "driven", "bypass", "prediction", "fallbacks",
                                  "saturation"]
        rows = {ln.split()[0]: ln.split()[1:] for ln in lines[lines.index(header) + 1:]}
        assert set(rows) == set(AXES)
        assert rows["rails_x"][0] == "yes" and rows["rails_x"][4].isdigit()
        assert rows["hex_z"][2] in ("held", "predicting") and rows["hex_z"][3].isdigit()
        assert "loop times (us" in p.stdout and "{" not in p.stdout
        p = cli("status", "-e", ep, "--json")
        assert p.returncode == 0 and json.loads(p.stdout)["ticks"] > 0

        def watch(*extra: str) -> str:
            """``status --watch 0.5`` for 3 s, stopped by Ctrl-C (exit 0): its stdout."""
            w = subprocess.Popen(motcomp_cmd("status", "-e", ep, "--watch", "0.5", *extra),
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                 env=subprocess_env())
            time.sleep(3.0)
            w.send_signal(signal.SIGINT)
            out, err = w.communicate(timeout=10)
            assert w.returncode == 0, err
            return out

        out = watch()
        assert out.count("\naxis ") >= 2 and out.count("--- ") >= 2, out
        # with --json: one object per line, each the whole status
        out = watch("--json")
        polls = [json.loads(line) for line in out.splitlines()]
        assert len(polls) >= 2 and all(q["ticks"] > 0 for q in polls), out[:2000]
        assert polls[-1]["ticks"] > polls[0]["ticks"]


@pytest.mark.slow
def test_a_starved_loop_says_so_and_the_platform_s_stack_delay_is_shown(tmp_path: Path
                                                                         ) -> None:
    """The service stopped for 30 ms of every 100 ms (SIGSTOP/SIGCONT: a host that takes its
    CPU; a CPU hog beside it no longer does, the loop's short slice wins it back): the deadlines
    it misses are logged at WARNING and flagged in the status -- from the first seconds, before
    the first window closes, as that window so far; the platform's own figure of the stack's
    delay (hil's setpoint age) is in the status and its table."""
    p_hil, p_svc = free_tcp_port(), free_tcp_port()
    stop = threading.Event()

    def thief(pid: int) -> None:
        while not stop.is_set():
            os.kill(pid, signal.SIGSTOP)
            time.sleep(0.03)
            os.kill(pid, signal.SIGCONT)
            time.sleep(0.07)

    with process(["hil", "-l", loopback(p_hil), "--log-level", "warning"], tmp_path / "hil.log"), \
            process(["run", "--config", str(config_file("motcomp.toml")), "-l", loopback(p_svc),
                     "-e", loopback(p_hil)], tmp_path / "svc.log") as svc:
        wait_for_text(tmp_path / "svc.log", "running:", svc)
        starve = threading.Thread(target=thief, args=(svc.pid,), daemon=True)
        starve.start()
        t_thief = time.monotonic()
        try:
            time.sleep(2.0)
            first = cli("status", "-e", loopback(p_svc), "--json", "--timeout", "5")
            first_table = cli("status", "-e", loopback(p_svc), "--timeout", "5").stdout
            log = wait_for_text(tmp_path / "svc.log", "deadlines over the last", svc,
                                timeout=40.0)
        finally:
            stop.set()
            starve.join()
            os.kill(svc.pid, signal.SIGCONT)
            stopped_s = 0.3 * (time.monotonic() - t_thief)  # 30 ms of every 100
        p = cli("status", "-e", loopback(p_svc), "--json")
        assert p.returncode == 0, p.stderr
        st = json.loads(p.stdout)
        table = cli("status", "-e", loopback(p_svc)).stdout
    assert "WARNING" in log and "the host does not give the loop its CPU" in log, log
    assert "%: more than 2 %)" in log, log
    assert first.returncode == 0, first.stderr
    early = json.loads(first.stdout)["deadlines"]
    assert early["open"] and early["degraded"] and early["windows_degraded"] == 0, early
    assert early["window_s"] < 10 and early["due"] > 0 and early["share"] > 0.02, early
    assert "s (so far)" in first_table and "DEGRADED" in first_table, first_table
    assert "open" not in st["deadlines"]  # a closed window since
    assert st["deadlines"]["windows_degraded"] >= 1, st["deadlines"]
    assert st["deadlines"]["due"] > 0
    assert st["platform"]["setpoint_age_ms"] > 0, st["platform"]
    assert "platform    setpoints applied" in table, table
    if st["missed_waiting_cpu"] is not None:  # a stopped loop was not waiting for a CPU
        # at least half the deadlines of the stops are not counted as waits, whatever the
        # host's own load adds to both (a busy CI host made half of all the misses waits)
        not_waiting = st["missed_ticks"] - st["missed_waiting_cpu"]
        assert not_waiting >= 0.5 * stopped_s * st["rate_hz"], (stopped_s, st)
        # the platform (motcomp hil) says the same of its own loop
        assert 0 <= st["platform"]["missed_waiting_cpu"] <= st["platform"]["missed_ticks"], st


def test_record_and_identify_live_refuse_a_directory_that_does_not_exist(tmp_path: Path
                                                                        ) -> None:
    where = tmp_path / "no" / "such"
    p = cli("record", "-o", str(where / "x.mcap"), "-e", dead_endpoint())
    assert p.returncode == 2 and f"directory {where} does not exist" in p.stderr, p.stderr
    p = cli("identify", "--live", "--axis", "rails_y", str(where / "live.mcap"), "-e",
            dead_endpoint())
    assert p.returncode == 2 and f"directory {where} does not exist" in p.stderr, p.stderr
    assert not (tmp_path / "no").exists()


# --- config example -----------------------------------------------------------------------
def test_config_example_is_the_documented_config_and_lists_the_others() -> None:
    p = cli("config", "example")
    assert p.returncode == 0, p.stderr
    assert p.stdout == config_file("motcomp.toml").read_text()
    parse_config(tomllib.loads(p.stdout), "motcomp config example")
    p = cli("config", "example", "--list")
    assert p.returncode == 0
    for name in ("motcomp.toml", "plants/rails.toml", "plants/hexapod.toml", "motcomp.dbc",
                 "zenoh-acl.json5", "motcomp.service"):
        assert f"  {name} " in p.stdout, p.stdout
    p = cli("config", "example", "plants/rails.toml")
    assert p.returncode == 0 and p.stdout == config_file("plants", "rails.toml").read_text()
    p = cli("config", "example", "nope.toml")
    assert p.returncode == 2 and "no shipped file 'nope.toml'" in p.stderr


def test_every_profile_the_example_config_names_exists() -> None:
    """A name the example's comments give (``profile = "..."``, ``motcomp profile NAME``) is one
    of its profiles."""
    import re

    text = config_file("motcomp.toml").read_text()
    profiles = set(tomllib.loads(text)["profiles"])
    named = set(re.findall(r'profile\s*=\s*"([^"]+)"', text))
    named |= set(re.findall(r"`motcomp profile (\w+)`", text)) - {"NAME", "none"}
    assert named and named <= profiles, (named, profiles)


# --- info ---------------------------------------------------------------------------------
def test_info_summarises_a_recording(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    cfg = load_config(config_file("motcomp.toml"))
    facts = synthesize(path, cfg, SynthOptions(
        duration_s=3.0, bypass=[(1.0, True, ("rails_x",)), (2.0, False, ("rails_x",))],
        gaps=[(1.5, 0.3)], lose_outputs=[(0.5, 100)]))
    p = cli("info", str(path), "--json")
    assert p.returncode == 0, p.stderr
    info = json.loads(p.stdout)
    keys = {k["key"]: k for k in info["keys"]}
    assert keys["sim/motion/setpoint"]["messages"] == facts["frames"] == 3000 - 300
    assert keys["platform/setpoint"]["messages"] == facts["ticks"] - 100
    assert keys["motcomp/status"]["messages"] == 4
    assert keys["sim/motion/setpoint"]["rate_hz"] == pytest.approx(1000, rel=0.02)
    gaps = keys["sim/motion/setpoint"]["gaps"]
    # the source was silent 1.5-1.8 s of its own time (recorded from 0.2 s on)
    assert gaps["count"] == 1 and gaps["longest_s"] == pytest.approx(0.301, abs=0.002)
    assert gaps["longest_at_s"] == pytest.approx(1.7, abs=0.01)
    out_gaps = keys["platform/setpoint"]["gaps"]
    assert out_gaps["count"] == 1 and out_gaps["longest_s"] == pytest.approx(0.101, abs=0.002)
    assert keys["platform/feedback"]["gaps"]["count"] == 0
    assert info["config_hash"] == config_hash(cfg) and info["recorded_config"]
    (run,) = info["modes"]["bypass"]["rails_x"]
    assert run[0] == pytest.approx(1.2, abs=0.01) and run[1] == pytest.approx(2.2, abs=0.01)
    assert "rails_y" not in info["modes"]["bypass"]
    stale = info["modes"]["stale"]
    assert any(abs(s - 1.75) < 0.01 for s, _ in stale)  # 50 ms into the gap
    # the wait for the first frame is told apart from an input lost (the status counts no
    # stale episode there), and its rejoin is not one "no recorded output shows"
    (start, end), first_input = info["modes"]["first_input_wait"], keys["sim/motion/setpoint"]
    assert start == pytest.approx(info["modes"]["first_output_s"] + cfg.loop.stale_after_s,
                                  abs=0.002)
    assert end == pytest.approx(first_input["first_s"], abs=0.002)
    assert stale[0][0] == pytest.approx(1.75, abs=0.01) and stale[-1][1] is None  # the end
    assert not info["truncated"] and info["modes"]["parking"] == []
    p = cli("info", str(path))
    assert p.returncode == 0
    assert f"  no input   {start:.2f}-{end:.2f} s (the service waiting for its first frame)" \
        in p.stdout, p.stdout
    assert "  stale      2: 1.75-" in p.stdout and "after a stale input" not in p.stdout
    assert "bypass     rails_x: on at 1.20 s, off at 2.20 s" in p.stdout, p.stdout
    assert "sim/motion/setpoint" in p.stdout and "0.301 s at 1.70 s" in p.stdout
    assert ("(lost: the seq numbers missing; rate: the median over runs of 10 intervals, gaps "
            "left out; rates and gaps on the frames' own t)") in p.stdout
    # recorded from inside an input loss: that stale run is an episode, not the first wait
    late = tmp_path / "late.mcap"
    synthesize(late, cfg, SynthOptions(duration_s=3.0, gaps=[(1.5, 0.3)], record_from_s=1.6))
    p = cli("info", str(late), "--json")
    assert p.returncode == 0, p.stderr
    modes = json.loads(p.stdout)["modes"]
    assert modes["first_input_wait"] is None
    assert modes["stale"][0] == [0.0, pytest.approx(0.2, abs=0.01)]  # the gap's end, kept
    assert keys["platform/setpoint"]["lost"] == 100  # the recorder lost them
    assert keys["sim/motion/setpoint"]["lost"] == 300  # (the synthetic source numbers its
    # samples, sent or not: its 0.3 s of silence skips 300)
    assert keys["platform/feedback"]["lost"] is None and keys["motcomp/status"]["lost"] is None


def test_info_says_an_axis_none_of_whose_windows_was_judged_is_not_supervised() -> None:
    """"No alarm" on windows none of which was judged means nothing: info says so, and why the
    last estimate was not judged; a supervised axis gets its judged windows counted."""
    from motcomp.cli.info import _mismatch, _mismatch_text

    def frame(ns: int, axis: dict[str, Any]) -> tuple[int, dict[str, Any]]:
        return ns, {"model_mismatch": {"axes": {"rails_y": axis}}}

    est = {"estimate": {"spec": "p1d:K=1.008,Td=0.0236,Tp1=0.179"}, "alarm": False}
    blind = [frame(k * 10**9, {**est, "informative": False, "windows": k + 1,
                               "informative_windows": 0,
                               "reason": "the residual delay is uncertain (+-2.64 ms > 1 ms)"})
             for k in range(23)]
    text = _mismatch_text(_mismatch(blind, 0)["rails_y"])
    assert text == ("not supervised: none of its 23 windows judged, no alarm possible; last "
                    "estimate p1d:K=1.008,Td=0.0236,Tp1=0.179 (not judged: the residual delay "
                    "is uncertain (+-2.64 ms > 1 ms))"), text
    seen = [*blind, frame(24 * 10**9, {**est, "informative": True, "windows": 24,
                                       "informative_windows": 1})]
    text = _mismatch_text(_mismatch(seen, 0)["rails_y"])
    assert text == ("no mismatch alarm (1 of 24 windows judged); last estimate "
                    "p1d:K=1.008,Td=0.0236,Tp1=0.179"), text
    alarm = [*seen, frame(25 * 10**9, {**est, "alarm": True, "informative": True,
                                       "residual_delay_ms": 10.3, "windows": 25,
                                       "informative_windows": 2})]
    text = _mismatch_text(_mismatch(alarm, 0)["rails_y"])
    assert text.startswith("mismatch alarm 1: 25.00 s-end (residual +10.3 ms); last "), text


def test_info_tells_a_stalled_recorder_from_a_gap_in_the_frames(tmp_path: Path) -> None:
    """A recorder its host stalled for 115 ms receives the frames late and in a burst: not a
    gap in what was sent, nor a faster rate (taken on the receive times, a loaded host's
    recording read 1007.6 Hz and a 0.115 s gap on every key); said apart, as the recorder's."""
    from motcomp.cli.info import format_info, summarise

    path = tmp_path / "s.mcap"
    cfg = load_config(config_file("motcomp.toml"))
    synthesize(path, cfg, SynthOptions(duration_s=3.0, recorder_stalls=[(1.0, 0.115)]))
    info = summarise(path)
    for k in info["keys"]:
        if k["role"] in ("input", "output", "feedback"):
            assert k["clock"] == "frame" and k["gaps"]["count"] == 0, k
            assert k["rate_hz"] == pytest.approx(1000.0, abs=0.05), k
    stall = info["recorder_stall"]
    assert stall["longest_s"] == pytest.approx(0.115, abs=0.002)
    assert stall["at_s"] == pytest.approx(1.2, abs=0.01)  # (the loop's 0 is 0.2 s in)
    text = format_info(info)
    assert "recorder: received nothing for 0.11" in text and "at 1.20 s" in text, text


def test_info_names_a_rejoin_after_a_stale_input_no_output_shows() -> None:
    """A loop stalled for longer than ``stale_after_s``: the input is stale and back within the
    one late tick, no output carries ``stale``, the next ones ``rejoin``."""
    from motcomp.cli.info import rejoins_unseen

    modes = {"stale": [[0.0, 4.53], [64.54, None]], "rejoin": [[4.53, 5.59], [19.59, 22.54]]}
    assert rejoins_unseen(modes) == 1
    assert rejoins_unseen({**modes, "rejoin": [[4.53, 5.59]]}) == 0
    assert rejoins_unseen({"stale": [], "rejoin": []}) == 0
    # recorded from within a rejoin: not one the recording saw begin
    assert rejoins_unseen({"stale": [], "rejoin": [[0.2, 1.0]], "first_output_s": 0.2}) == 0


def test_info_warns_about_an_unfinished_recording(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    synthesize(path, load_config(config_file("motcomp.toml")), SynthOptions(duration_s=2.0))
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[:len(data) * 2 // 3])
    p = cli("info", str(cut))
    assert p.returncode == 0, p.stderr
    assert "warning: unfinished recording" in p.stdout and "Traceback" not in p.stderr
    # cut before its first chunk: nothing recovered is bad input, not a summary of nothing
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(data[:300])
    for command in (["info", str(empty)], ["replay", str(empty), "--quiet"]):
        p = cli(*command)
        assert p.returncode == 2, (command, p.stdout, p.stderr)
        assert f"{empty}: unfinished recording" in p.stderr and "no message to read" in p.stderr
        assert "Traceback" not in p.stderr


def test_each_command_imports_its_own_module_only() -> None:
    """The fast path of ``motcomp <command>`` (:data:`motcomp.cli.MODULE_OF`) names the module
    that registers each command, and a query of the service loads neither the optimiser nor
    scipy."""
    import importlib
    import pkgutil

    import motcomp.cli as cli_pkg

    registered = {}
    for info in pkgutil.iter_modules(cli_pkg.__path__):
        if info.name.startswith("_"):
            continue
        sub = argparse.ArgumentParser().add_subparsers()
        importlib.import_module(f"motcomp.cli.{info.name}").register(sub)
        registered.update(dict.fromkeys(sub.choices, info.name))
    assert registered == cli_pkg.MODULE_OF
    code = ("import sys; from motcomp.cli import MODULE_OF, build_parser; "
            "build_parser(MODULE_OF['status']).parse_args(['status']); "
            "print(sorted(m for m in sys.modules if m.startswith('motcomp.design') "
            "or m.split('.')[0] == 'scipy'))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=subprocess_env(), timeout=60)
    assert p.returncode == 0 and p.stdout.strip() == "[]", (p.stdout, p.stderr)


def test_a_status_the_service_could_not_build_says_so() -> None:
    text = format_status({"t": 1.0, "version": "0.1.0", "mode": "running", "ticks": 5,
                          "error": "status failed: RuntimeError('dictionary changed size')"})
    assert text.splitlines()[1] == ("ERROR       status failed: RuntimeError('dictionary "
                                    "changed size') (the service's status is incomplete)")


def test_info_names_every_config_the_service_ran(tmp_path: Path) -> None:
    """A recording through which the service was reloaded to other configs: info names each,
    in the order they came (the replay's note the same)."""
    from motcomp.cli.info import format_info, summarise
    from motcomp.record.session import read_session

    path = tmp_path / "s.mcap"
    cfg = load_config(config_file("motcomp.toml"))
    synthesize(path, cfg, SynthOptions(duration_s=2.0))
    s = read_session(path)
    first = config_hash(cfg)
    assert s.config_hashes() == [first]
    s.status += [(s.status[-1][0] + k, {"config": {"hash": h}})
                 for k, h in enumerate(["b2", first, "c3", "b2"], start=1)]
    s.status.append((s.status[-1][0] + 1, {"config": "not a table"}))
    assert s.config_hashes() == [first, "b2", "c3"]
    info = summarise(path)
    info["config_hashes"] = s.config_hashes()
    assert f"config hash {first}, then b2, c3 (reloaded during the recording)" in format_info(info)


def test_json_output_is_strict_json_whatever_the_status_holds(
        capsys: pytest.CaptureFixture[str]) -> None:
    """A status whose figures are NaN or infinite (a platform that reports no setpoint age, as
    over CAN) prints as strict JSON with null there; before, ``status --json`` crashed."""
    import math

    import numpy as np

    from motcomp.cli._common import print_json

    print_json({"platform": {"setpoint_age_ms": math.nan, "ages": [1.0, math.inf]},
                "n": np.int64(3), "x": np.float64(-math.inf)})
    assert json.loads(capsys.readouterr().out) == {
        "platform": {"setpoint_age_ms": None, "ages": [1.0, None]}, "n": 3, "x": None}


def test_status_watch_ends_on_sigterm_with_exit_0() -> None:
    """``motcomp status --watch`` stops on SIGTERM as on Ctrl-C: exit 0."""
    p = subprocess.Popen(motcomp_cmd("status", "--watch", "0.2", "--timeout", "0.2", "-e",
                                     loopback(free_tcp_port())),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env=subprocess_env())
    try:
        deadline = time.monotonic() + 30
        assert p.stdout is not None
        line = p.stdout.readline()  # a first (unanswered) poll: the watch runs
        assert line and time.monotonic() < deadline
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=30) == 0, p.stderr.read() if p.stderr else ""
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_status_watch_goes_on_past_a_service_that_does_not_answer(tmp_path: Path) -> None:
    """A service that takes the query but does not answer in time (stalled: zenoh replies
    ``Timeout`` for it) is a poll nobody answered: a line on stderr, the watch goes on; a
    single status or an admin request says so and exits 3, the request sent once."""
    port = free_tcp_port()
    with open_session(ZenohEndpoints(listen=(loopback(port),))) as session:
        mute = session.declare_queryable("motcomp/status")  # takes queries, never replies
        try:
            p = subprocess.Popen(motcomp_cmd("status", "--watch", "0.2", "--timeout", "0.3",
                                             "--json", "-e", loopback(port)),
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                 env=subprocess_env())
            try:
                assert p.stderr is not None
                lines = [p.stderr.readline() for _ in range(3)]  # three unanswered polls
                p.send_signal(signal.SIGTERM)
                assert p.wait(timeout=30) == 0
                rest = p.stderr.read()
            finally:
                if p.poll() is None:
                    p.kill()
                    p.wait()
            late = "it received the query but did not answer in time"
            assert all(late in line for line in lines), (lines, rest)
            assert "Traceback" not in rest and "failed" not in rest, rest
            one = subprocess.run(motcomp_cmd("status", "--timeout", "0.5", "-e", loopback(port)),
                                 capture_output=True, text=True, env=subprocess_env(),
                                 timeout=60)
            assert one.returncode == 3 and late in one.stderr, one.stderr
            # an admin request the service took is not sent again (it may still be served)
            asked = []
            mute.undeclare()
            mute = session.declare_queryable("motcomp/admin/bypass", lambda q: asked.append(q))
            one = subprocess.run(motcomp_cmd("bypass", "on", "--timeout", "1", "-e",
                                             loopback(port)),
                                 capture_output=True, text=True, env=subprocess_env(),
                                 timeout=60)
            assert one.returncode == 3 and late in one.stderr, one.stderr
            assert len(asked) == 1, asked
        finally:
            mute.undeclare()


def test_info_of_a_recording_without_outputs_does_not_claim_no_bypass(tmp_path: Path) -> None:
    """Without output frames (a service whose output went over CAN alone) the mode switches
    cannot be told: info says so instead of "bypass none"."""
    from motcomp.cli.info import format_info, summarise
    from motcomp.record.mcapio import ScanResult, iter_records
    from motcomp.record.recorder import SessionWriter

    full = tmp_path / "full.mcap"
    synthesize(full, load_config(config_file("motcomp.toml")), SynthOptions(duration_s=1.0))
    res = ScanResult(full)
    records = [r for r in iter_records(full, result=res) if r.topic != "platform/setpoint"]
    path = tmp_path / "no_outputs.mcap"
    with SessionWriter(path, sorted({r.topic for r in records}), None, None, flush_s=0,
                       fsync=False) as w:
        for r in records:
            w.write_raw(r.topic, r.log_ns, r.publish_ns, r.sequence, r.data)
    text = format_info(summarise(path))
    assert "mode switches: unknown, no output frames recorded" in text, text
    assert "bypass     none" not in text
    assert "mode switches (output flags):" in format_info(summarise(full))


def test_ctrl_c_while_the_command_s_modules_load_exits_130_without_a_traceback(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    import importlib

    def interrupted(name: str, package: str | None = None) -> Any:
        raise KeyboardInterrupt

    monkeypatch.setattr(importlib, "import_module", interrupted)
    assert main(["design", "--plant", "rails"]) == 130
    assert "Traceback" not in capsys.readouterr().err
