"""Deployment files: the systemd unit (verified by systemd-analyze when present)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from motcomp.resources import config_file


def unit_text() -> str:
    return config_file("motcomp.service").read_text()


def test_unit_has_notify_watchdog_reload_restart_and_allows_realtime() -> None:
    lines = {ln.split("=", 1)[0]: ln.split("=", 1)[1] for ln in unit_text().splitlines()
             if "=" in ln and not ln.startswith("#")}
    assert lines["Type"] == "notify"
    assert float(lines["WatchdogSec"]) > 0
    assert lines["ExecReload"] == "/bin/kill -HUP $MAINPID"
    assert lines["Restart"] == "on-failure"
    assert lines["KillSignal"] == "SIGTERM"
    assert "RestrictRealtime" not in lines  # it would forbid SCHED_FIFO
    assert "CAP_SYS_NICE" in lines["AmbientCapabilities"]
    assert lines["NoNewPrivileges"] == "yes" and lines["ProtectSystem"] == "strict"
    assert "motcomp run --config" in lines["ExecStart"]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not here")
def test_systemd_analyze_verify(tmp_path: Path) -> None:
    exe = Path(sys.executable).parent / "motcomp"
    if not exe.exists():
        exe = Path(shutil.which("motcomp") or "/bin/true")
    unit = tmp_path / "motcomp.service"
    unit.write_text(unit_text().replace("/opt/motcomp/venv/bin/motcomp", str(exe)))
    p = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 0, p.stderr
    assert "motcomp.service" not in p.stderr, p.stderr  # no warning about our unit
