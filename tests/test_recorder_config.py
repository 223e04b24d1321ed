"""The recorder keeps the service's config whatever the host's load: when the service's status
query does not answer in time, the config comes from the status the service publishes every
second; when no status comes at all, the recording, ``info`` and the log say so (WARNING).

Real processes: ``motcomp record`` as a subprocess, and a zenoh session in this process standing
in for the service (it publishes its status frames on ``motcomp/status`` and answers no query,
as a service too busy to answer would look)."""

from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

import msgpack
import pytest

from motcomp.config import config_hash, load_config
from motcomp.io.wire import encode_input
from motcomp.io.zenoh_io import ZenohEndpoints, free_tcp_port, loopback, open_session
from motcomp.record import read_session
from motcomp.resources import config_file
from tests.conftest import motcomp_cmd, subprocess_env
from tests.test_service_process import process

pytestmark = pytest.mark.slow


def _record_beside(tmp_path: Path, publish_status: bool) -> tuple[Path, str]:
    """Run the recorder for about 3 s beside a session that publishes inputs (and, if asked, the
    service's status frames); returns the recording and the recorder's log."""
    cfg_path = config_file("motcomp.toml")
    status = msgpack.packb({"ticks": 100, "config": {
        "path": str(cfg_path), "hash": config_hash(load_config(cfg_path)), "version": 1}})
    port = free_tcp_port()
    out, log = tmp_path / "rec.mcap", tmp_path / "rec.log"
    with open_session(ZenohEndpoints(listen=(loopback(port),))) as session:
        pub_in = session.declare_publisher("sim/motion/setpoint")
        pub_st = session.declare_publisher("motcomp/status")
        with process(["record", "-o", str(out), "-e", loopback(port), "--status-timeout",
                      "0.05"], log) as rec:
            t_end = time.monotonic() + 30  # started (a busy host takes seconds to import)
            while "recording" not in log.read_text():
                assert time.monotonic() < t_end and rec.poll() is None, log.read_text()
                time.sleep(0.05)
            t_end = time.monotonic() + 3.5
            k = 0
            while time.monotonic() < t_end:
                pub_in.put(encode_input(k, time.time(), {"rails_y": 0.0}))
                if publish_status and k % 50 == 0:
                    pub_st.put(status)
                k += 1
                time.sleep(0.01)
            rec.send_signal(signal.SIGTERM)
            assert rec.wait(timeout=20) == 0, log.read_text()
    return out, log.read_text()


def test_config_comes_from_the_published_status_when_the_query_is_late(tmp_path: Path
                                                                        ) -> None:
    out, log = _record_beside(tmp_path, publish_status=True)
    s = read_session(out)
    assert s.config_json is not None, log
    cfg = load_config(config_file("motcomp.toml"))
    assert s.metadata["config_hash"] == config_hash(cfg)
    assert config_hash(s.config()) == config_hash(cfg)
    assert "config_missing" not in s.metadata
    assert "WARNING" not in log and "config attached" in log


def test_a_recording_without_status_says_so_everywhere(tmp_path: Path) -> None:
    out, log = _record_beside(tmp_path, publish_status=False)
    assert "WARNING" in log and "without the service's config" in log, log
    s = read_session(out)
    assert s.config_json is None
    assert "no status" in s.metadata["config_missing"]
    p = subprocess.run(motcomp_cmd("info", str(out)), capture_output=True, text=True,
                       env=subprocess_env(), timeout=60)
    assert p.returncode == 0, p.stderr
    assert "no config recorded: no status" in p.stdout, p.stdout
