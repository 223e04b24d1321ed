"""The service against a platform written from docs/WIRE.md's platform side alone
(``tools/wire_platform.py``: a pure delay and a first-order lag per axis, simulated exactly at
1 kHz): its feedback is read (none bad), its status' setpoint age reaches the service's status,
and ``identify --live`` recovers its model -- which needs the feedback's ``t``, ``pos`` and
``acc`` as the contract defines them.

Real processes on loopback: ``motcomp run`` (the example config, admin on) and the platform as
subprocesses, ``motcomp identify --live`` and ``motcomp status`` as commands."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from motcomp.io.zenoh_io import free_tcp_port, loopback
from motcomp.resources import config_file
from motcomp.runtime.probe import HostProbe
from tests.conftest import ROOT, judge_realtime, motcomp_cmd, skip_if_starved, subprocess_env
from tests.test_service_process import process

pytestmark = pytest.mark.slow

TD_MS, TP1_MS = 24.0, 130.0
"""The platform's rails_y, unlike the example config's model (17.5 ms, 186 ms)."""


def cli(*args: str, timeout: float = 300.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                          env=subprocess_env(), timeout=timeout)


def test_identify_live_recovers_a_platform_written_from_the_contract(tmp_path: Path) -> None:
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{config_file("motcomp.toml")}"]\n[admin]\nenabled = true\n')
    p_plat, p_svc = free_tcp_port(), free_tcp_port()
    plat_log = tmp_path / "platform.log"
    with HostProbe() as probe, plat_log.open("wb") as fh:
        plat = subprocess.Popen([sys.executable, str(ROOT / "tools" / "wire_platform.py"),
                                 "-l", loopback(p_plat), "--truth",
                                 f"rails_y={TD_MS:g},{TP1_MS:g}"],
                                stdout=fh, stderr=subprocess.STDOUT, env=subprocess_env())
        try:
            with process(["run", "--config", str(site), "-l", loopback(p_svc), "-e",
                          loopback(p_plat)], tmp_path / "svc.log") as svc:
                time.sleep(2.0)
                p = cli("identify", "--live", "--axis", "rails_y", str(tmp_path / "live.mcap"),
                        "--excite-s", "30", "--out", str(tmp_path / "ident"), "--json",
                        "--quiet", "--no-figures", "-e", loopback(p_svc), "-e",
                        loopback(p_plat))
                st = json.loads(cli("status", "-e", loopback(p_svc), "--json").stdout)
                svc.send_signal(signal.SIGTERM)
                assert svc.wait(timeout=30) == 0
        finally:
            plat.send_signal(signal.SIGTERM)
            plat.wait(timeout=20)
    assert plat.returncode == 0, plat_log.read_text()[-2000:]
    skip_if_starved(p, "identification on a host that starved the service")
    assert p.returncode == 0, p.stderr[-3000:]
    # the platform's frames as the service read them, and its own figure of the stack
    assert st["feedback"]["received"] > 20_000 and st["feedback"]["bad"] == 0, st["feedback"]
    age_ms = st["platform"]["setpoint_age_ms"]
    assert 0.0 < age_ms < 5.0, st["platform"]
    judge_realtime(probe.result, "the model identified from the contract's platform")
    rep = json.loads(p.stdout)
    assert rep["selected"] == "p1d", rep["reason"]
    fit = rep["models"]["p1d"]["params"]
    print(f"identified Td {fit['Td'] * 1e3:.2f} ms, Tp1 {fit['Tp1'] * 1e3:.1f} ms; drawn "
          f"{TD_MS:g} + the stack's {age_ms:.2f} ms, {TP1_MS:g} ms")
    # the platform's delay as the service's stamps see it: its own plus the stack's (the
    # second difference it sends as acc is centred one cycle before t: docs/WIRE.md)
    assert fit["Td"] * 1e3 == pytest.approx(TD_MS + age_ms, abs=1.5), (fit, age_ms)
    assert fit["Tp1"] * 1e3 == pytest.approx(TP1_MS, rel=0.05), fit
    assert fit["K"] == pytest.approx(1.0, abs=0.02), fit
