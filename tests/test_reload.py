"""Live reload against a running service (subprocess): ``motcomp reload`` and SIGHUP."""

from __future__ import annotations

import math
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import msgpack
import pytest

from motcomp.io.wire import decode_output, encode_input
from motcomp.io.zenoh_io import ZenohEndpoints, first_reply, free_tcp_port, loopback, open_session
from motcomp.resources import config_file
from tests._frames import assert_frames_within_limits
from tests._notify import NotifyListener
from tests.conftest import motcomp_cmd, subprocess_env
from tests.test_service_process import process, wait_status

pytestmark = pytest.mark.slow

BASE = f'include = ["{config_file("motcomp.toml")}"]\n[admin]\nenabled = true\n'


def reload_cmd(port: int, path: Path | None = None) -> subprocess.CompletedProcess[str]:
    args = ["reload", "-e", loopback(port)] + (["--config", str(path)] if path else [])
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                          env=subprocess_env(), timeout=60)


def status(session: Any) -> dict[str, Any]:
    out: dict[str, Any] = msgpack.unpackb(first_reply(session, "motcomp/status", None, 3.0))
    return out


INVALID = {
    "not TOML": ("[loop\nrate_hz = 1000\n", "not valid TOML"),
    "unknown key": (BASE + "[loop]\nratehz = 1000\n", "loop.ratehz"),
    "inverted limits": (BASE + "[axes.rails_y]\npos_min_m = 1.0\npos_max_m = -1.0\n",
                        "pos_min_m=1.0 must be < pos_max_m=-1.0"),
    "non-finite": (BASE + "[axes.rails_x]\nvel_max_m_s = nan\n", "finite"),
    "unstable gains": (BASE + "[axes.rails_y]\ngains = { kp = 500.0, ki_per_s = 10.0 }\n",
                       "unstable"),
    "restart key": (BASE + "[loop]\nrate_hz = 500\n", "loop.rate_hz cannot change live"),
    "axes set": (BASE.replace("enabled = true", "enabled = true") + "", None),
}


def test_reload_valid_and_invalid_and_sighup(tmp_path: Path) -> None:
    import zenoh

    cfg = tmp_path / "motcomp.toml"
    cfg.write_text(BASE)
    p_svc = free_tcp_port()
    notify = tmp_path / "notify.sock"
    listener = NotifyListener(notify)
    env = subprocess_env()
    env["NOTIFY_SOCKET"] = str(notify)
    stop = threading.Event()
    with process(["run", "--config", str(cfg), "-l", loopback(p_svc)], tmp_path / "svc.log",
                 env) as svc, open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
        out_sub = session.declare_subscriber("platform/setpoint",
                                             zenoh.handlers.FifoChannel(200_000))
        st0 = wait_status(session)
        pub = session.declare_publisher("sim/motion/setpoint")

        def feed() -> None:  # a feasible slalom-like motion on rails_y, 1 kHz
            k = 0
            t0 = time.time()
            while not stop.is_set():
                t = k / 1000
                pub.put(encode_input(k, t0 + t,
                                     {"rails_y": 0.3 * math.sin(2 * math.pi * 0.3 * t)}))
                k += 1
                time.sleep(max(0.0, t0 + (k / 1000) - time.time()))

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        try:
            time.sleep(2.0)
            # 1. valid: ZN -> AMIGO on the rails, live
            cfg.write_text(BASE + "[defaults]\nrule = \"amigo\"\n")
            r = reload_cmd(p_svc)
            assert r.returncode == 0, r.stderr
            assert "reloaded" in r.stdout
            st1 = status(session)
            assert st1["config"]["version"] == 2
            assert st1["config"]["hash"] != st0["config"]["hash"]
            assert st1["reloads"][-1]["ok"] is True
            time.sleep(1.0)
            # 2. every kind of invalid config is refused; the running config stays
            for name, (text, reason) in INVALID.items():
                if reason is None:
                    continue
                bad = tmp_path / f"bad-{name.replace(' ', '_')}.toml"
                bad.write_text(text)
                r = reload_cmd(p_svc, bad)
                assert r.returncode == 1, (name, r.stdout, r.stderr)
                assert reason in r.stderr, (name, r.stderr)
                st = status(session)
                assert st["config"]["version"] == 2 and st["mode"] == "running", name
                assert st["reloads"][-1]["ok"] is False
            # 3. SIGHUP re-reads the file the service was started with
            cfg.write_text(BASE + "[defaults]\nrule = \"zn\"\nfilter_n = 8\n")
            svc.send_signal(signal.SIGHUP)
            t_end = time.monotonic() + 10
            while status(session)["config"]["version"] != 3 and time.monotonic() < t_end:
                time.sleep(0.1)
            assert status(session)["config"]["version"] == 3
            time.sleep(1.0)
        finally:
            stop.set()
            feeder.join()
        # the output never stepped beyond the limits through the reloads
        frames = []
        while (s := out_sub.try_recv()) is not None:
            frames.append(decode_output(s.payload.to_bytes()))
        assert_frames_within_limits(frames, "rails_y", 2.0, 6.0, min_checked=3000)
        out_sub.undeclare()
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(timeout=20) == 0
    text = listener.close()
    assert text.count("RELOADING=1") >= 2 + sum(1 for v in INVALID.values() if v[1])
    assert "MONOTONIC_USEC=" in text
    log = (tmp_path / "svc.log").read_text()
    assert "reload ok" in log and "reload rejected" in log
    assert log.count("hash") >= 2


def test_reload_refused_when_admin_is_off(tmp_path: Path) -> None:
    cfg = tmp_path / "motcomp.toml"
    cfg.write_text(f'include = ["{config_file("motcomp.toml")}"]\n')
    p_svc = free_tcp_port()
    with process(["run", "--config", str(cfg), "-l", loopback(p_svc)], tmp_path / "svc.log"), \
            open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
        wait_status(session)
        r = reload_cmd(p_svc)
        assert r.returncode == 1
        assert "no reply" in r.stderr
