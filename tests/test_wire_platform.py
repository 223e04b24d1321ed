"""The README's identification workflow by hand, against a platform written from docs/WIRE.md's
platform side alone (``tools/wire_platform.py``: a pure delay and a first-order lag per axis,
simulated exactly at 1 kHz).

The service reads the platform's feedback (none bad) and shows its setpoint age; then, as the
README has it, the axis is bypassed, ``motcomp excite`` writes a multisine, ``motcomp record``
records while ``motcomp source --file`` plays it, and ``motcomp identify session.mcap`` (no
options) selects P1D and recovers the platform's model -- which needs the feedback's ``t``,
``pos`` and ``acc`` as the contract defines them.  (The live path, ``identify --live``, is the
workflow test's, against ``motcomp hil``.)

Real processes on loopback: ``motcomp run`` (the example config, admin on), the platform and
the recorder as subprocesses, the other commands as the README gives them."""

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
CYCLE_MS = 1.0
"""The platform's cycle (tools/wire_platform.py's default rate, 1 kHz)."""


def cli(*args: str, timeout: float = 300.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                          env=subprocess_env(), timeout=timeout)


def test_the_workflow_by_hand_identifies_a_platform_written_from_the_contract(
        tmp_path: Path) -> None:
    site = tmp_path / "site.toml"
    site.write_text(f'include = ["{config_file("motcomp.toml")}"]\n[admin]\nenabled = true\n')
    p_plat, p_svc = free_tcp_port(), free_tcp_port()
    svc_ep, plat_ep = loopback(p_svc), loopback(p_plat)
    plat_log = tmp_path / "platform.log"
    session = tmp_path / "session.mcap"
    with HostProbe() as probe, plat_log.open("wb") as fh:
        plat = subprocess.Popen([sys.executable, str(ROOT / "tools" / "wire_platform.py"),
                                 "-l", plat_ep, "--truth", f"rails_y={TD_MS:g},{TP1_MS:g}"],
                                stdout=fh, stderr=subprocess.STDOUT, env=subprocess_env())
        try:
            with process(["run", "--config", str(site), "-l", svc_ep, "-e", plat_ep],
                         tmp_path / "svc.log") as svc:
                p = cli("bypass", "on", "--axes", "rails_y", "-e", svc_ep, "--timeout", "20")
                assert p.returncode == 0, p.stderr
                p = cli("excite", "--axis", "rails_y", "--kind", "multisine", "--duration", "20",
                        "--out", str(tmp_path / "exc"))
                assert p.returncode == 0, p.stderr
                with process(["record", "-o", str(session), "-e", svc_ep, "-e", plat_ep],
                             tmp_path / "rec.log") as rec:
                    time.sleep(1.5)
                    p = cli("source", "--file", str(tmp_path / "exc.msgpack"), "--quiet", "-e",
                            svc_ep)
                    assert p.returncode == 0, p.stderr
                    time.sleep(1.0)
                    rec.send_signal(signal.SIGTERM)
                    assert rec.wait(timeout=30) == 0, (tmp_path / "rec.log").read_text()
                st = json.loads(cli("status", "-e", svc_ep, "--json").stdout)
                svc.send_signal(signal.SIGTERM)
                assert svc.wait(timeout=30) == 0
        finally:
            plat.send_signal(signal.SIGTERM)
            plat.wait(timeout=20)
    assert plat.returncode == 0, plat_log.read_text()[-2000:]
    # the platform's frames as the service read them, and its own figure of the stack
    assert st["feedback"]["received"] > 15_000 and st["feedback"]["bad"] == 0, st["feedback"]
    age_ms = st["platform"]["setpoint_age_ms"]
    assert 0.0 < age_ms < 5.0, st["platform"]
    p = cli("identify", str(session), "--axis", "rails_y", "--out", str(tmp_path / "ident"),
            "--json", "--quiet", "--no-figures")
    skip_if_starved(p, "identification on a host that starved the service")
    assert p.returncode == 0, p.stderr[-3000:]
    judge_realtime(probe.result, "the model identified from the contract's platform", st, p)
    rep = json.loads(p.stdout)
    assert rep["selected"] == "p1d", rep["reason"]
    fit = rep["models"]["p1d"]["params"]
    # the platform's delay as the service's stamps see it: its own plus the stack's -- the
    # setpoint age in the recording's window less the pairing's phase, which the fit reads as
    # the model's hold -- plus the cycle by which the second difference it sends as acc is
    # centred before its t (docs/WIRE.md, docs/SUPERVISION.md "The stack's share")
    c = rep["data"]["conditions"]
    assert "platform_setpoint_age_ms" in c and "pairing_phase_ms" in c, c
    share_ms = c["platform_setpoint_age_ms"] - c["pairing_phase_ms"] + CYCLE_MS
    print(f"identified Td {fit['Td'] * 1e3:.2f} ms, Tp1 {fit['Tp1'] * 1e3:.1f} ms; drawn "
          f"{TD_MS:g} + the stack's {share_ms:.2f} ms, {TP1_MS:g} ms")
    assert fit["Td"] * 1e3 == pytest.approx(TD_MS + share_ms, abs=1.0), (fit, c)
    assert fit["Tp1"] * 1e3 == pytest.approx(TP1_MS, rel=0.05), fit
    assert fit["K"] == pytest.approx(1.0, abs=0.02), fit
    assert (tmp_path / "ident" / "rails_y.toml").is_file()


def test_the_contract_s_platform_runs_zenoh_on_one_thread_as_the_commands_do() -> None:
    """The platform cannot import motcomp (it is written from the contract alone): its zenoh
    runtime setting is a copy of the commands', held equal here."""
    from motcomp.io.zenoh_io import ONE_THREAD
    from tests.test_supervise_retune import _wire_platform

    assert _wire_platform().ONE_THREAD == ONE_THREAD
