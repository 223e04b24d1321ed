"""The issue's reloads against a running service (subprocess): limits of +-1e308 or 1000 m, limits
just outside the envelope, a widened envelope -- each refused naming the key, its value and the
bound; the running config stays, and a setpoint beyond the range afterwards is held at the
envelope."""

from __future__ import annotations

import math
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

from motcomp.io.wire import decode_output, encode_input
from motcomp.io.zenoh_io import ZenohEndpoints, free_tcp_port, loopback, open_session
from motcomp.resources import config_file
from tests._frames import assert_frames_within_limits
from tests.conftest import motcomp_cmd, subprocess_env
from tests.test_reload import status
from tests.test_service_process import process, wait_status

REFUSED = {
    "the issue's 1e308 file": (
        "[axes.rails_y]\npos_min_m = -1e308\npos_max_m = 1e308\nvel_max_m_s = 1e308\n"
        "acc_max_m_s2 = 1e308\n",
        ("axes.rails_y.pos_min_m", "[-10, 10] m", "-1e+308")),
    "1000 m": ("[axes.rails_y]\npos_max_m = 1000.0\n",
               ("axes.rails_y.pos_max_m", "[-10, 10] m", "1000.0")),
    "outside the envelope": (
        "[axes.rails_y]\npos_max_m = 2.7\n",
        ("axes.rails_y.pos_max_m = 2.7 lies outside envelope.rails_y.pos_max_m = 2.6",)),
    "a widened envelope": (
        "[envelope.rails_y]\npos_max_m = 5.0\n[axes.rails_y]\npos_max_m = 5.0\n",
        ("envelope", "cannot change live")),
}


@pytest.mark.slow
def test_reloads_outside_the_envelope_are_refused(tmp_path: Path) -> None:
    import zenoh

    etc = tmp_path / "etc"
    etc.mkdir(mode=0o755)
    shutil.copy(config_file("motcomp.toml"), etc / "motcomp.toml")
    (etc / "motcomp.toml").chmod(0o644)
    base = 'include = ["motcomp.toml"]\n[admin]\nenabled = true\n'
    cfg = etc / "service.toml"
    cfg.write_text(base)
    p_svc = free_tcp_port()
    stop = threading.Event()
    with process(["run", "--config", str(cfg), "-l", loopback(p_svc)], tmp_path / "svc.log") \
            as svc, open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
        out_sub = session.declare_subscriber("platform/setpoint",
                                             zenoh.handlers.FifoChannel(200_000))
        st0 = wait_status(session)
        pub = session.declare_publisher("sim/motion/setpoint")
        target = [0.0]

        def feed() -> None:  # 1 kHz, rails_y towards ``target`` (a step: the limiter's work)
            k = 0
            t0 = time.time()
            while not stop.is_set():
                pub.put(encode_input(k, t0 + k / 1000, {"rails_y": target[0]}))
                k += 1
                time.sleep(max(0.0, t0 + k / 1000 - time.time()))

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        try:
            for name, (text, needles) in REFUSED.items():
                bad = etc / f"reload-{name.replace(' ', '_')}.toml"
                bad.write_text(base + text)
                r = subprocess.run(motcomp_cmd("reload", "-e", loopback(p_svc), "--config",
                                               str(bad)), capture_output=True, text=True,
                                   env=subprocess_env(), timeout=60)
                assert r.returncode == 2, (name, r.stdout, r.stderr)  # a refused request
                for needle in needles:
                    assert needle in r.stderr, (name, needle, r.stderr)
                st = status(session)
                assert st["config"]["hash"] == st0["config"]["hash"], name
            target[0] = 3.5  # beyond the rails' 2.6 m, within the accepted reach (3.9 m)
            time.sleep(4.0)
            target[0] = -3.5
            time.sleep(5.0)
            target[0] = 0.0  # back home within the limits (2 m/s): SIGTERM's parking is short
            time.sleep(2.5)
        finally:
            stop.set()
            feeder.join()
        frames = []
        while (s := out_sub.try_recv()) is not None:
            frames.append(decode_output(s.payload.to_bytes()))
        y = [f["pos"]["rails_y"] for f in frames]
        assert all(math.isfinite(v) and abs(v) <= 2.6 for v in y)
        # the setpoints were applied (towards the ends: a loaded host's stalls of the sender
        # make the input stale now and then, and the reference holds), never beyond
        assert max(y) > 2.0 and min(y) < -2.0
        # the limiter held it there: the envelope guard behind it had nothing to do
        assert not [f for fr in frames for f in fr["flags"] if f.startswith("envelope:")]
        assert_frames_within_limits(frames, "rails_y", 2.0, 6.0, min_checked=3000)
        final = status(session)
        assert final["config"]["version"] == st0["config"]["version"]
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(timeout=30) == 0
