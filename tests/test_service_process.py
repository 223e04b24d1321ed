"""The service as a user runs it: ``motcomp run`` and ``motcomp hil`` as subprocesses, a client
in this process on real zenoh sessions over loopback (multicast scouting off, free ports), CAN
frames on a real ``udp_multicast`` bus, systemd notifications on a real datagram socket."""

from __future__ import annotations

import contextlib
import math
import os
import platform
import re
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import msgpack
import numpy as np
import pytest

from motcomp.io.can_io import CanSetpointReceiver
from motcomp.io.wire import decode_output, encode_input
from motcomp.io.zenoh_io import ZenohEndpoints, first_reply, free_tcp_port, loopback, open_session
from motcomp.resources import config_file
from motcomp.runtime.probe import loop_kept_from_cpu
from motcomp.runtime.rt import CPU_LATENCY_DEVICE
from tests._notify import NotifyListener
from tests.conftest import motcomp_cmd, subprocess_env

pytestmark = pytest.mark.slow


def write_config(tmp: Path, extra: str = "") -> Path:
    path = tmp / "service.toml"
    path.write_text(f'include = ["{config_file("motcomp.toml")}"]\n{extra}\n')
    return path


@contextlib.contextmanager
def process(args: list[str], log: Path, env: dict[str, str] | None = None
            ) -> Iterator[subprocess.Popen[bytes]]:
    with log.open("wb") as fh:
        p = subprocess.Popen(motcomp_cmd(*args), stdout=fh, stderr=subprocess.STDOUT,
                             env=env or subprocess_env())
        try:
            yield p
        finally:
            if p.poll() is None:
                p.kill()
                p.wait()


def wait_status(session: Any, timeout: float = 20.0) -> dict[str, Any]:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        with contextlib.suppress(Exception):
            st: dict[str, Any] = msgpack.unpackb(first_reply(session, "motcomp/status", None, 1.0))
            if st["ticks"] > 0:
                return st
        time.sleep(0.2)
    raise AssertionError("service did not answer its status query")


def test_run_hil_client_bad_frames_fade_can_and_sigterm(tmp_path: Path) -> None:
    import zenoh

    p_svc, p_hil, p_me = free_tcp_port(), free_tcp_port(), free_tcp_port()
    group = f"239.74.{os.getpid() % 250}.{int(time.time()) % 250 + 1}"
    cfg = write_config(tmp_path, f"""
[admin]
enabled = true
[output]
transport = "both"
[output.can]
interface = "udp_multicast"
channel = "{group}"
send_every = 4
""")
    notify = tmp_path / "notify.sock"
    listener = NotifyListener(notify)
    env = subprocess_env()
    env.update(NOTIFY_SOCKET=str(notify), WATCHDOG_USEC="2000000")
    rx = can.Bus(interface="udp_multicast", channel=group)
    recv = CanSetpointReceiver(rx, config_file("motcomp.dbc"))
    with process(["hil", "-l", loopback(p_hil), "--log-level", "warning"], tmp_path / "hil.log"), \
            process(["run", "--config", str(cfg), "-l", loopback(p_svc), "-e", loopback(p_hil)],
                    tmp_path / "svc.log", env) as svc:
        ep = ZenohEndpoints(connect=(loopback(p_svc), loopback(p_hil)), listen=(loopback(p_me),))
        with open_session(ep) as session:
            out_sub = session.declare_subscriber("platform/setpoint",
                                                 zenoh.handlers.FifoChannel(100_000))
            fb_sub = session.declare_subscriber("platform/feedback",
                                                zenoh.handlers.RingChannel(1))
            pub = session.declare_publisher("sim/motion/setpoint")
            wait_status(session)
            # 3 s of a smooth motion at 500 Hz, with every kind of bad frame mixed in
            bad = [b"\xc1junk", msgpack.packb({"seq": 10**9, "pos": {"rails_y": float("nan")}}),
                   msgpack.packb({"seq": 10**9, "pos": {"rails_q": 0.1}}),
                   msgpack.packb({"seq": 10**9, "pos": {"rails_y": 99.0}}),
                   msgpack.packb({"seq": "x", "pos": {"rails_y": 0.1}}),
                   msgpack.packb({"seq": 3, "pos": {"rails_y": 0.1}})]  # old by then
            n = 1500
            sent = 0
            t0 = time.time()
            for k in range(n):  # on real time, as docs/WIRE.md asks: late samples are skipped
                t = k / 500
                if k % 50 == 25:  # each kind 5 times; a tick apart from the good frames, so
                    time.sleep(0.002)  # that the loop's newest-frame input takes it
                    pub.put(bad[(k // 50) % len(bad)])
                    time.sleep(0.002)
                wait = t0 + t - time.time()
                if wait > 0:
                    time.sleep(wait)
                elif wait < -0.002:
                    continue
                pub.put(encode_input(100 + k, t0 + t,  # feasible: 2.2 m/s^2 at most
                                     {"rails_y": 0.25 * math.sin(2 * math.pi * 0.3 * t) ** 3}))
                sent += 1
            st = msgpack.unpackb(first_reply(session, "motcomp/status", None, 2.0))
            rej = st["frames"]["rejected_by_reason"]
            for reason in ("decode", "nonfinite", "axis", "range", "type", "old"):
                assert rej[reason] >= 1, rej
            # (a frame that a newer one supersedes before the loop's tick is not taken)
            assert sent > 0.5 * n and st["frames"]["accepted"] > 0.5 * sent
            assert st["mode"] == "running"
            assert "slice" in st["realtime"], st["realtime"]  # the loop thread's scheduling
            if platform.machine() in ("x86_64", "aarch64"):  # and its floating-point mode
                assert st["realtime"].endswith("; subnormals flushed to zero"), st["realtime"]
            if os.access(CPU_LATENCY_DEVICE, os.W_OK):  # its request, held while it runs
                assert "CPU wake-up latency at most 0 us" in st["realtime"], st["realtime"]
                fds = Path(f"/proc/{svc.pid}/fd")
                assert CPU_LATENCY_DEVICE in {os.path.realpath(f) for f in fds.iterdir()}
            else:
                assert "CPU wake-up latency not held" in st["realtime"], st["realtime"]
            assert st["loop"]["tick_p50_us"] >= st["loop"]["compute_p50_us"] > 0
            # outputs: every axis, finite, within the limits; the input reached them
            frames = []
            while (s := out_sub.try_recv()) is not None:
                frames.append(decode_output(s.payload.to_bytes()))
            # every tick the loop ran over the motion sent its frame, and none was lost on the
            # way (the output seq counts ticks run; deadlines a starved host made the loop miss
            # send nothing: on one core of a busy host about 10 % of the 3 s)
            seqs = [f["seq"] for f in frames]
            assert len(frames) > 1000 and seqs == sorted(seqs)
            # (judged at the end, where the host let the loop have its CPU: a starved host's
            # data path drops rather than blocks, about 2 % of the outputs once at 6x slower)
            outputs = (len(frames), seqs[0], seqs[-1])
            st_run = st
            y = np.array([f["pos"]["rails_y"] for f in frames])
            # the compensated command leads and exceeds the 0.25 m reference a little (ideal:
            # 0.30; the stalls of a busy shared host, hundreds of missed ticks in these 3 s, add
            # a few centimetres)
            assert np.all(np.isfinite(y)) and np.max(np.abs(y)) < 0.4 and np.ptp(y) > 0.2
            assert max(f["src_seq"] for f in frames) >= 100 + n - 50
            # the platform feedback follows
            fb = fb_sub.try_recv()
            assert fb is not None
            # CAN frames carried the same setpoints (checked CRC and alive counter)
            got = recv.poll()
            assert recv.received > 100 and recv.crc_errors == 0
            assert abs(got["rails_y"] - frames[-1]["pos"]["rails_y"]) < 0.05
            # input stops: stale after 50 ms, hold 0.5 s, then ramp to neutral
            time.sleep(2.5)
            st = msgpack.unpackb(first_reply(session, "motcomp/status", None, 2.0))
            assert st["mode"] == "stale" and st["stale_s"] > 2.0
            frames = []
            while (s := out_sub.try_recv()) is not None:
                frames.append(decode_output(s.payload.to_bytes()))
            assert "stale" in frames[-1]["flags"]
            assert abs(frames[-1]["pos"]["rails_y"]) < 1e-6  # back at neutral
            # SIGTERM: park and exit 0, in bounded time
            t_stop = time.monotonic()
            svc.send_signal(signal.SIGTERM)
            assert svc.wait(timeout=20) == 0
            assert time.monotonic() - t_stop < 10
            out_sub.undeclare()
            fb_sub.undeclare()
    recv.close()
    text = listener.close()
    assert "READY=1" in text and "WATCHDOG=1" in text and "STOPPING=1" in text
    log = (tmp_path / "svc.log").read_text()
    assert "stopped after" in log and "Traceback" not in log
    got, first, last = outputs
    if got < 0.98 * (last - first + 1) and (why := loop_kept_from_cpu(st_run)) is not None:
        pytest.skip(f"not judged (outputs lost on the way, {got} of {last - first + 1}): {why}")
    assert got >= 0.98 * (last - first + 1), outputs


def _nested(depth: int) -> bytes:
    """An input frame of about ``depth`` bytes whose position is nested ``depth`` levels deep."""
    return b"\x82\xa3seq\x01\xa3pos\x81\xa7rails_y" + b"\x91" * depth + b"\x00"


def test_hostile_burst_never_stops_the_service(tmp_path: Path) -> None:
    """Every kind of bad frame, in bursts, and hostile admin requests: the loop goes on at its
    rate, counts each frame under its reason, and parks on SIGTERM (exit 0)."""
    import zenoh

    p_svc = free_tcp_port()
    cfg = write_config(tmp_path, "[admin]\nenabled = true\n")
    rng = np.random.default_rng(7)
    t_ulp = 1_700_000_000.0
    hostile = [_nested(1000), _nested(5000), b"\xc1" * 2_000_000,
               msgpack.packb({"seq": 1, "pos": {"rails_y": [0.1] * 300_000}}),
               msgpack.packb({"seq": 10**30 % 2**64, "pos": {"x" * 100_000: 0.1}}),
               msgpack.packb({"seq": 2**64 - 1, "t": float("inf"), "pos": {"rails_y": 0.1}}),
               *[bytes(rng.integers(0, 256, int(n), dtype=np.uint8))
                 for n in rng.integers(1, 2000, 40)]]
    with process(["run", "--config", str(cfg), "-l", loopback(p_svc)], tmp_path / "svc.log") as svc:
        with open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
            out_sub = session.declare_subscriber("platform/setpoint",
                                                 zenoh.handlers.FifoChannel(100_000))
            first = wait_status(session)
            pub = session.declare_publisher("sim/motion/setpoint")
            seq = 0
            for rep in range(3):
                for frame in hostile:
                    pub.put(frame)
                    time.sleep(0.002)  # a tick apart: the newest-frame input takes each
                # two valid frames one ulp apart in t, far apart in value
                for value, t in ((-0.4, t_ulp + rep), (0.4, math.nextafter(t_ulp + rep, 1e300))):
                    seq += 1
                    pub.put(encode_input(seq, t, {"rails_y": value}))
                    time.sleep(0.002)
            for name, body in (("bypass", msgpack.packb({"on": True, "axes": 5})),
                               ("bypass", _nested(3000)), ("reload", msgpack.packb({"path": 1})),
                               ("profile", b"\xc1"), ("nothing", b"")):
                reply = msgpack.unpackb(first_reply(session, f"motcomp/admin/{name}", body, 3.0))
                assert reply["ok"] is False and reply["error"], (name, reply)
            time.sleep(1.0)
            st = wait_status(session)
            rej = st["frames"]["rejected_by_reason"]
            assert rej["oversize"] >= 3 and rej["decode"] >= 3, rej
            assert rej["internal"] == 0, st["frames"]["last_reject"]
            assert len(st["frames"]["last_reject"]) <= 200
            # the loop kept its schedule: every deadline since the first status was a tick or
            # is counted as missed (the host's stalls), and it ticks on
            elapsed = st["t"] - first["t"]
            done = st["ticks"] + st["missed_ticks"] - first["ticks"] - first["missed_ticks"]
            assert done >= 0.95 * elapsed * 1000, (done, elapsed)
            assert st["mode"] in ("running", "stale", "rejoin")
            frames = []
            while (s := out_sub.try_recv()) is not None:
                frames.append(decode_output(s.payload.to_bytes()))
            y = np.array([[f["pos"][a] for a in ("rails_x", "rails_y")] for f in frames])
            assert len(frames) > 500 and np.all(np.isfinite(y)) and np.all(np.abs(y) <= 2.6)
            out_sub.undeclare()
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(timeout=30) == 0, (tmp_path / "svc.log").read_text()[-2000:]


def test_sigint_parks_from_motion_and_exits_zero(tmp_path: Path) -> None:
    p_svc = free_tcp_port()
    cfg = write_config(tmp_path)
    with process(["run", "--config", str(cfg), "-l", loopback(p_svc)], tmp_path / "svc.log") as svc:
        ep = ZenohEndpoints(connect=(loopback(p_svc),))
        with open_session(ep) as session:
            import zenoh

            out_sub = session.declare_subscriber("platform/setpoint",
                                                 zenoh.handlers.RingChannel(1))
            wait_status(session)
            pub = session.declare_publisher("sim/motion/setpoint")
            for k in range(1500):  # hold rails_x at 0.5 m
                pub.put(encode_input(k, time.time(), {"rails_x": 0.5}))
                time.sleep(0.001)
            s = out_sub.try_recv()
            assert s is not None and decode_output(s.payload.to_bytes())["pos"]["rails_x"] > 0.4
            svc.send_signal(signal.SIGINT)
            last = None
            t_end = time.monotonic() + 15
            while svc.poll() is None and time.monotonic() < t_end:
                s = out_sub.try_recv()
                if s is not None:
                    last = decode_output(s.payload.to_bytes())
                time.sleep(0.01)
            assert svc.wait(timeout=5) == 0
            assert last is not None and abs(last["pos"]["rails_x"]) < 1e-3
            assert "parking" in last["flags"]
            out_sub.undeclare()


def test_bad_config_exits_2_with_the_key(tmp_path: Path) -> None:
    cfg = write_config(tmp_path, "[loop]\nrate_hz = 5000\n")
    p = subprocess.run(motcomp_cmd("run", "--config", str(cfg)), capture_output=True, text=True,
                       env=subprocess_env(), timeout=60)
    assert p.returncode == 2
    assert "loop.rate_hz" in p.stderr and "5000" in p.stderr


def test_hil_consumes_can_frames_from_the_service(tmp_path: Path) -> None:
    """Service -> CAN (udp_multicast, DBC frames) -> ``motcomp hil --transport can`` ->
    feedback on zenoh: the simulated platform follows the setpoints it decoded."""
    import zenoh

    p_svc, p_hil = free_tcp_port(), free_tcp_port()
    group = f"239.75.{os.getpid() % 250}.{int(time.time()) % 250 + 1}"
    cfg = write_config(tmp_path, f"""
[output]
transport = "can"
[output.can]
interface = "udp_multicast"
channel = "{group}"
send_every = 1
""")
    with process(["hil", "-l", loopback(p_hil), "--transport", "can", "--can-channel", group,
                  "--quiet-sensor", "--log-level", "warning"], tmp_path / "hil.log"), \
            process(["run", "--config", str(cfg), "-l", loopback(p_svc)], tmp_path / "svc.log"):
        ep = ZenohEndpoints(connect=(loopback(p_svc), loopback(p_hil)))
        with open_session(ep) as session:
            fb = session.declare_subscriber("platform/feedback", zenoh.handlers.RingChannel(1))
            hs = session.declare_subscriber("platform/status", zenoh.handlers.RingChannel(1))
            wait_status(session)
            pub = session.declare_publisher("sim/motion/setpoint")
            for k in range(2500):  # 2.5 s at 0.3 m on rails_y
                pub.put(encode_input(k, time.time(), {"rails_y": 0.3}))
                time.sleep(0.001)
            time.sleep(0.5)
            s = fb.try_recv()
            assert s is not None
            y = msgpack.unpackb(s.payload.to_bytes())["pos"]["rails_y"]
            assert y == pytest.approx(0.3, abs=0.01)
            time.sleep(1.2)
            st = msgpack.unpackb(hs.try_recv().payload.to_bytes())
            assert st["can"]["received"] > 1000 and st["can"]["crc_errors"] == 0
            assert sum(st["violations"].values()) == 0
            fb.undeclare()
            hs.undeclare()


def zenoh_threads(pid: int) -> list[str]:
    """The names of a process' zenoh threads: those of its task runtimes (app, rx, tx, acc,
    net; ``<runtime>-<n>``)."""
    names = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(OSError):
            names.append(Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip())
    return sorted(n for n in names if re.fullmatch(r"(app|rx|tx|acc|net)-\d+", n))


@pytest.mark.parametrize("setting", [None, "(rx: (worker_threads: 1))"])
def test_the_service_runs_zenoh_on_one_thread_unless_the_environment_says_otherwise(
        tmp_path: Path, setting: str | None) -> None:
    """The command sets ``ZENOH_RUNTIME`` to one thread where the environment leaves it unset,
    and keeps the environment's where it is set: zenoh's own runtimes then run as it says (rx
    with one worker, not zenoh's default of two)."""
    env = subprocess_env()
    env.pop("ZENOH_RUNTIME", None)
    if setting is not None:
        env["ZENOH_RUNTIME"] = setting
    p_svc = free_tcp_port()
    with process(["run", "--config", str(write_config(tmp_path)), "-l", loopback(p_svc)],
                 tmp_path / "svc.log", env) as svc, \
            open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
        wait_status(session)  # a link accepted, a query received and its reply sent
        threads = zenoh_threads(svc.pid)
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(timeout=30) == 0
    if setting is None:
        # app-0, the one worker, and the blocking threads tokio adds to it, named alike
        assert "app-0" in threads and all(n.startswith("app-") for n in threads), threads
    else:
        assert {"rx-0", "tx-0", "acc-0"} <= set(threads) and "rx-1" not in threads, threads
