"""Recording and replay with the real components: ``motcomp hil``, ``motcomp run``,
``motcomp record`` and ``motcomp source`` as subprocesses on loopback zenoh (multicast
scouting off, free ports).  The recording is then replayed offline -- the service's own tick
reproduces every recorded output bit for bit, the offline engine to 1e-6 m -- cut short like a
power loss would, and republished in real time into the still running service."""

from __future__ import annotations

import contextlib
import json
import math
import re
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from motcomp.config import config_hash, parse_config, resolve_axes
from motcomp.io.zenoh_io import ZenohEndpoints, first_reply, free_tcp_port, loopback, open_session
from motcomp.record import read_session
from motcomp.replay.engine import run_ticks
from motcomp.replay.offline import plan_for
from motcomp.resources import config_file
from motcomp.runtime.probe import HostProbe
from tests.conftest import judge_realtime, motcomp_cmd, subprocess_env
from tests.test_record import mcap_messages

pytestmark = pytest.mark.slow

MOTION_S = 5.0


def _status(ep: ZenohEndpoints, timeout: float = 25.0) -> dict[str, Any]:
    t_end = time.monotonic() + timeout
    with open_session(ep) as session:
        while time.monotonic() < t_end:
            with contextlib.suppress(Exception):
                st: dict[str, Any] = msgpack.unpackb(first_reply(session, "motcomp/status",
                                                                 None, 1.0))
                if st["ticks"] > 0 and st.get("clock"):
                    return st
            time.sleep(0.2)
    raise AssertionError("the service did not answer its status query")


def _wait_for(path: Path, text: str, proc: subprocess.Popen[bytes], timeout: float = 20.0
              ) -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if path.exists() and text in path.read_text(errors="replace"):
            return
        assert proc.poll() is None, path.read_text(errors="replace")
        time.sleep(0.1)
    raise AssertionError(f"{text!r} not in {path}")


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    tmp = tmp_path_factory.mktemp("live")
    p_hil, p_svc, p_rec = free_tcp_port(), free_tcp_port(), free_tcp_port()
    t = np.arange(0.0, MOTION_S, 1e-3)
    # minimum-jerk fade in and out over 1.5 s: the compensated command stays within the rails'
    # limits (a kink in the envelope, or a shorter fade, saturates them: no delay to gain there)
    ramp_in, ramp_out = np.clip(t / 1.5, 0, 1), np.clip((MOTION_S - t) / 1.5, 0, 1)
    env = (ramp_in**3 * (10 - 15 * ramp_in + 6 * ramp_in**2)
           * ramp_out**3 * (10 - 15 * ramp_out + 6 * ramp_out**2))
    rows = ["t,rails_y,rails_x,hex_z"] + [
        f"{a:.4f},{0.25 * e * math.sin(2 * math.pi * 0.3 * a):.9f},"
        f"{0.1 * e * math.sin(2 * math.pi * 0.4 * a):.9f},"
        f"{0.02 * e * math.sin(2 * math.pi * 0.5 * a):.9f}" for a, e in zip(t, env, strict=True)]
    (tmp / "motion.csv").write_text("\n".join(rows) + "\n")
    procs: dict[str, subprocess.Popen[bytes]] = {}
    logs = {name: (tmp / f"{name}.log").open("wb") for name in ("hil", "svc", "rec", "src")}

    def spawn(name: str, *args: str) -> subprocess.Popen[bytes]:
        procs[name] = subprocess.Popen(motcomp_cmd(*args), stdout=logs[name],
                                       stderr=subprocess.STDOUT, env=subprocess_env())
        return procs[name]

    try:
        spawn("hil", "hil", "-l", loopback(p_hil), "--log-level", "warning")
        spawn("svc", "run", "--config", str(config_file("motcomp.toml")), "-l", loopback(p_svc),
              "-e", loopback(p_hil))
        status = _status(ZenohEndpoints(connect=(loopback(p_svc),)))
        rec = spawn("rec", "record", "-o", str(tmp / "live.mcap"), "-l", loopback(p_rec),
                    "-e", loopback(p_svc), "-e", loopback(p_hil), "--flush-s", "0.2",
                    "--status-timeout", "3")
        _wait_for(tmp / "rec.log", "recording", rec)
        time.sleep(1.0)  # subscriptions propagate
        with HostProbe() as probe:
            src = spawn("src", "source", "--file", str(tmp / "motion.csv"), "-e",
                        loopback(p_svc), "-e", loopback(p_rec), "--lead-in", "2.0")
            assert src.wait(timeout=60) == 0
            time.sleep(0.5)
            rec.send_signal(signal.SIGTERM)
            assert rec.wait(timeout=20) == 0
        # what the service itself received: its publisher may drop a frame on the way to it
        # (congestion control DROP) that the recorder still got
        end = _status(ZenohEndpoints(connect=(loopback(p_svc),)))
        yield {"path": tmp / "live.mcap", "tmp": tmp, "svc": loopback(p_svc), "status": status,
               "received": end["frames"]["received"], "end": end, "host": probe.result,
               "rec_log": (tmp / "rec.log").read_text(),
               "src_log": (tmp / "src.log").read_text()}
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs.values():
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for fh in logs.values():
            fh.close()


def test_recording_holds_the_session(live: dict[str, Any]) -> None:
    s = read_session(live["path"])
    assert not s.warnings and not s.truncated
    assert "recorded" in live["rec_log"] and "Traceback" not in live["rec_log"]
    assert s.inputs is not None and s.outputs is not None and s.feedback is not None
    # the frames the source sent (it skips the samples of its own stalls, and says how many):
    # the recorder dropped none of what reached it; the data path's publishers drop rather than
    # block when the machine starves them, which on a busy shared host cost up to 5 %
    m = re.search(r"published (\d+) frames \(seq 0-(\d+)\) of (\d+) samples", live["src_log"])
    assert m, live["src_log"]
    sent = int(m.group(1))
    assert int(m.group(3)) == round(MOTION_S * 1000) and sent > 0.5 * round(MOTION_S * 1000)
    assert "dropped (queue full): 0" in live["rec_log"]
    assert len(s.inputs) >= 0.9 * sent and s.inputs.decoded.all()
    assert len(s.outputs) > 0.9 * len(s.inputs) and len(s.feedback) > 0.9 * len(s.inputs)
    # the service's config, checked against the hash it reported
    assert s.metadata["config_hash"] == live["status"]["config"]["hash"]
    cfg = s.config()
    assert config_hash(cfg) == s.metadata["config_hash"]
    assert any(st.get("clock") for _, st in s.status)
    # (nearly) every input an output tick used is in the recording: as above, up to the loss in
    # transit to the recorder on a starved host
    used = set(s.outputs.src_seq.tolist()) - {-1}
    assert len(used - set(s.inputs.seq.tolist())) <= 0.1 * len(used)
    # the stack's delay as the platform measured it, from the recorded service status
    p = subprocess.run(motcomp_cmd("info", str(live["path"])), capture_output=True, text=True,
                       env=subprocess_env(), timeout=60)
    assert p.returncode == 0, p.stderr
    assert "platform    setpoints applied" in p.stdout and "no config recorded" not in p.stdout


def test_replay_reproduces_the_live_service(live: dict[str, Any]) -> None:
    s = read_session(live["path"])
    cfg = parse_config(s.config_json or {})
    axes = resolve_axes(cfg)
    plan = plan_for(s, cfg, axes)
    assert plan.method == "outputs+clock"
    rows = np.flatnonzero(plan.output >= 0)
    assert s.outputs is not None and s.inputs is not None
    rec = s.outputs.pos[plan.output[rows]]
    exact = run_ticks(plan, s.inputs, cfg)
    # with every input and output recorded, the replay is the service, bit for bit: the same
    # function (motcomp.core.tick.step) on the same bytes at the same instants; an output lost
    # in transit hides which tick took a frame, and the replay may take it a tick later; an
    # input frame the recorder lost (a hole in the source's seq) shortens the replay's history;
    # one the service did not receive (the recorder did) is found and left out (plan.absent)
    complete = (plan.missing_frames == 0 and plan.seq_holes == 0
                and rows.size == plan.emit.sum()
                and live["received"] + len(plan.absent) == len(s.inputs))
    if complete:
        assert np.array_equal(exact.u[rows], rec)
    again = run_ticks(plan, s.inputs, cfg)
    assert np.array_equal(exact.u, again.u, equal_nan=True)
    p = subprocess.run(motcomp_cmd("replay", str(live["path"]), "--json", "--quiet"),
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    axes_out = {a["axis"]: a for a in out["runs"][0]["axes"]}
    rails_y = axes_out["rails_y"]
    if complete:
        assert rails_y["max_diff"] < 1e-6
    assert rails_y["delay_off_ms"] - rails_y["delay_on_ms"] > 150  # through the model
    # the platform model and the recorded feedback agree on the delay achieved: the feedback's
    # is the live run's, which only a host that held the rate can deliver
    judge_realtime(live["host"], "the delay of the recorded feedback", live["end"])
    assert abs(rails_y["delay_on_ms"] - rails_y["recorded_on_ms"]) < 5.0


def _inside_the_input(path: Path) -> int:
    """A byte offset in the middle of the chunk that holds the middle of the recording's input
    frames: the complete chunks before it hold the first half of them, wherever the input
    began (a starved host's source starts late)."""
    from mcap.reader import make_reader

    times = [m[1] for m in mcap_messages(path) if m[0] == "sim/motion/setpoint"]
    mid = times[len(times) // 2]
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunk = next(c for c in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
                 if c.message_end_time >= mid)
    return int(chunk.chunk_start_offset + chunk.chunk_length // 2)


def test_cut_recording_is_read_up_to_the_cut(live: dict[str, Any]) -> None:
    data = live["path"].read_bytes()
    cut = live["tmp"] / "cut.mcap"
    cut.write_bytes(data[:_inside_the_input(live["path"])])
    expect = mcap_messages(cut)
    s = read_session(cut)
    assert s.truncated and s.messages == len(expect) > 1000
    p = subprocess.run(motcomp_cmd("replay", str(cut), "--json", "--quiet"),
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert p.returncode == 0, p.stderr
    assert "unfinished recording" in p.stderr and str(cut) in p.stderr
    assert f"recovered {len(expect)} messages" in p.stderr and "Traceback" not in p.stderr
    assert json.loads(p.stdout)["ticks"] > 500


def test_realtime_replay_drives_the_running_service(live: dict[str, Any]) -> None:
    ep = ZenohEndpoints(connect=(live["svc"],))
    before = _status(ep)
    s = read_session(live["path"])
    assert s.inputs is not None
    copy = live["tmp"] / "again.mcap"
    shutil.copy(live["path"], copy)
    p = subprocess.run(motcomp_cmd("replay", str(copy), "--realtime", "-e", live["svc"],
                                   "--json", "--quiet", "--lead-in", "1.0"),
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert p.returncode == 0, p.stderr
    stats = json.loads(p.stdout)
    assert stats["sent"] == len(s.inputs)
    assert abs(stats["duration_s"] - (MOTION_S + 1.0)) < 2.0  # the recorded timing
    after = _status(ep)
    got = after["frames"]["accepted"] - before["frames"]["accepted"]
    skipped = after["frames"]["superseded"] - before["frames"]["superseded"]
    # the loop takes the newest frame per tick: a frame it did not take is a gap in seq, except
    # for frames superseded before the first one taken (a burst while the sender warms up)
    span = int(s.inputs.seq[-1] - s.inputs.seq[0]) + 1
    # (on a starved host the loop may take only every other frame: the rest are superseded)
    assert got > 0.25 * len(s.inputs), (after["frames"], before["frames"])
    assert span - 50 <= got + skipped <= span, (got, skipped, span)
    # the last frames taken are the recording's last (the data path may drop a few on a busy host)
    assert int(s.inputs.seq[-1]) - 50 <= after["src_seq"] <= int(s.inputs.seq[-1])
