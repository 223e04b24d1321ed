"""The lab's workflow end to end on the real processes, each step one command, no number edited
by hand: an unknown (simulated) platform -> ``identify --live`` through the running service ->
``design --plant <fragment> --out`` -> ``config check`` -> ``reload`` -> the slalom's apparent
delay measured on the platform's feedback.

In the suite (about 60 s, five processes on the machine's cores; ``pytest -m e2e`` runs it
alone).  Figures of real runs: docs/IDENTIFICATION.md."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from motcomp.config import load_config
from motcomp.core.models import parse_model
from motcomp.core.quality import estimate_delay
from motcomp.io.zenoh_io import free_tcp_port, loopback
from motcomp.record.session import read_session
from motcomp.resources import config_file
from motcomp.runtime.probe import HostProbe
from tests.conftest import judge_realtime, motcomp_cmd, site_config, skip_if_starved, subprocess_env
from tests.test_service_process import process

pytestmark = [pytest.mark.slow, pytest.mark.e2e]

PRESET_TD, PRESET_TP1 = 0.0175, 0.1858
SLALOM_HZ = 40.0 / 3.6 / (2 * 18.0)
"""The built-in slalom's weave: 40 km/h past cones 18 m apart (motcomp.design.timedomain)."""
MAX_TD_ERROR_S = 1e-3
"""The identified delay against the drawn one plus the stack's share (docs/IDENTIFICATION.md):
the fit's scatter between runs (up to 0.38 ms seen) and up to half a cycle where the hop to the
platform sometimes outlasts the tick phase and sometimes not (the medians read 0 or 1 cycle)."""
MAX_PHASE_STDERR_MS = 1.0
"""The slalom is judged against its 3 ms bound where the identification states its phase delay
(at 0.2 Hz) to within this standard error: a third of the bound."""


def p1d_lag_s(td_s: float, tp1_s: float, hz: float = SLALOM_HZ) -> float:
    """A unit-gain first order with delay's phase delay at ``hz`` (s): Td + atan(w Tp1) / w."""
    w = 2 * np.pi * hz
    return td_s + float(np.arctan(w * tp1_s)) / w


def draw_plant(seed: int = 20261124) -> tuple[float, float]:
    """A rails platform unlike the preset: Td 10-22 ms, Tp1 100-300 ms, at least 3 ms and 15 %
    away from the preset's.  (A PID around the model cannot cancel pure delay: with Td = 29 ms
    the optimal design's own residual is 7.4 ms at +8 dB, above the 5 ms asked of the slalom.)"""
    rng = np.random.default_rng(seed)
    while True:
        td = round(float(rng.uniform(0.010, 0.022)), 4)
        tp1 = round(float(rng.uniform(0.10, 0.30)), 3)
        if abs(td - PRESET_TD) >= 0.003 and abs(tp1 / PRESET_TP1 - 1) >= 0.15:
            return td, tp1


def cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                          env=subprocess_env(), timeout=timeout)


def test_unknown_platform_to_compensated_in_one_command_per_step(tmp_path: Path) -> None:
    td, tp1 = draw_plant()
    truth = f"p1d:K=1,Td={td},Tp1={tp1}"
    p_svc, p_hil = free_tcp_port(), free_tcp_port()
    svc_ep, hil_ep = loopback(p_svc), loopback(p_hil)
    site = site_config(tmp_path / "site.toml")
    with HostProbe() as probe, \
            process(["hil", "-l", hil_ep, "--truth", f"rails_y={truth}", "--log-level", "info"],
                    tmp_path / "hil.log") as hil, \
            process(["run", "--config", str(site), "-l", svc_ep, "-e", hil_ep],
                    tmp_path / "svc.log") as svc:
        time.sleep(2.0)
        # 1. identification through the stack
        ident = tmp_path / "ident"
        p = cli("identify", "--live", "--axis", "rails_y", str(tmp_path / "live.mcap"),
                "--excite-s", "20", "--out", str(ident), "--json", "--no-figures",
                "-e", svc_ep, "-e", hil_ep)
        skip_if_starved(p, "identification on a host that starved the service")
        if p.returncode == 2 and "so nothing was excited" in p.stderr:
            # its probe found the service starved before the run: said, nothing moved
            pytest.skip(f"not judged (identification on a host that starved the service): "
                        f"{p.stderr.strip().splitlines()[-1]}")
        assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
        m = re.search(r"limiter acted on (\d+) of (\d+) feedback samples, compensation on at "
                      r"(\d+)", p.stderr)
        # the axis was bypassed over the whole window and compensated again after it; the
        # report says how often the limiter acted (the fit uses the command the platform
        # received, limited or not)
        assert m and int(m.group(2)) > 15000 and int(m.group(3)) == 0, p.stderr
        print(p.stderr.strip().splitlines()[0])
        assert "compensated again" in p.stderr
        # each step says so as it starts: the probe, the bypass and recording, then the summary
        steps = [ln for ln in p.stderr.splitlines() if ln.startswith("live: ")]
        assert len(steps) >= 3, p.stderr
        assert steps[0].startswith("live: watching the service for 3 s before anything moves")
        assert steps[1].startswith("live: rails_y bypassed (compensation off); recording to ")
        assert "a 20 s multisine at 0.5 of its limits" in steps[1], steps[1]
        assert "excitation frames on rails_y" in steps[-1], steps
        fragment = ident / "rails_y.toml"
        model = parse_model(re.search(r'model = "([^"]+)"', fragment.read_text()).group(1))
        ident_run = p
        rep = json.loads(p.stdout)
        p1d = rep["models"]["p1d"]["params"]
        c = rep["data"]["conditions"]
        age, phase = c.get("platform_setpoint_age_ms"), c.get("pairing_phase_ms")
        assert age is not None and phase is not None, f"identify reports no age or phase: {c}"
        # the same file identified offline, without options, gives the same answer: the
        # recording holds the excitation's window and the reference's band
        q = cli("identify", str(tmp_path / "live.mcap"), "--axis", "rails_y", "--out",
                str(tmp_path / "offline"), "--json", "--quiet", "--no-figures")
        assert q.returncode == 0, q.stderr[-3000:]
        assert json.loads(q.stdout)["models"]["p1d"]["params"] == p1d
        # 2. design from the fragment, written as a fragment of the config
        design = tmp_path / "design.toml"
        # identified through the stack: the design cancels the input's playback lag on top, and
        # the pairing's phase, which the fitted Td does not hold (docs/TUNING.md)
        lag_ms = load_config(config_file("motcomp.toml")).input.playback_lag_s * 1e3 + phase
        p = cli("design", "--plant", str(fragment), "--rule", "optimal", "--out", str(design),
                "--input-lag-ms", f"{lag_ms:g}", "--quiet")
        assert p.returncode == 0, p.stderr
        # 3. the site config includes both; config check accepts it
        site_config(site, fragment, design)
        p = cli("config", "check", str(site))
        assert p.returncode == 0, p.stderr
        assert "  rails_y    model from design.toml, gains from design.toml" in p.stdout
        eff = load_config(site).axes["rails_y"]
        assert parse_model(eff.model) == model and eff.gains is not None
        # 4. reload into the running service
        p = cli("reload", "-e", svc_ep)
        assert p.returncode == 0, p.stdout + p.stderr
        # 5. the slalom, measured on the platform's feedback
        rec = tmp_path / "slalom.mcap"
        with process(["record", "-o", str(rec), "-e", svc_ep, "-e", hil_ep],
                     tmp_path / "rec.log") as recorder:
            time.sleep(1.5)
            p = cli("source", "--signal", "slalom", "--quiet", "-e", svc_ep)
            assert p.returncode == 0, p.stderr
            time.sleep(1.0)
            st = json.loads(cli("status", "-e", svc_ep, "--json").stdout)
            recorder.send_signal(signal.SIGTERM)
            assert recorder.wait(timeout=30) == 0
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(timeout=30) == 0
        hil.send_signal(signal.SIGTERM)
        assert hil.wait(timeout=30) == 0
    judge_realtime(probe.result, "the identified delay and the compensated slalom", st,
                   ident_run)
    # the P1D fit against the drawn truth, and P1D selected for it
    assert rep["selected"] == "p1d", (rep["reason"], truth)
    assert abs(p1d["Tp1"] / tp1 - 1) <= 0.05, (p1d, truth, fragment.read_text())
    # the platform as the service's stamps see it: the drawn delay plus each setpoint's age when
    # the simulator applied it (the transport and its tick phase); the fit reads the pairing's
    # phase as the model's hold, the rest of the age as delay (docs/SUPERVISION.md)
    assert 0.0 <= phase <= 1.0 and 0.0 < age < 5.0, c
    seen_td = td + age / 1e3
    fitted_td = seen_td - phase / 1e3
    print(f"identified Td {p1d['Td'] * 1e3:.2f} ms; drawn {td * 1e3:.2f} ms + the stack's "
          f"{age:.2f} - {phase:.2f} ms")
    assert abs(p1d["Td"] - fitted_td) <= MAX_TD_ERROR_S, (p1d, truth, c)
    s = read_session(rec)
    assert s.inputs is not None and s.feedback is not None
    y_axis = 1  # rails_y
    ti, ri = s.inputs.t, s.inputs.pos[:, y_axis]
    tf, yf = s.feedback.t, s.feedback.pos[:, y_axis]
    ok = np.isfinite(ri)
    ti, ri = ti[ok], ri[ok]
    grid = np.arange(max(ti[0], tf[0]) + 0.5, min(ti[-1], tf[-1]) - 0.5, 1e-3)
    delay = estimate_delay(np.interp(grid, ti, ri), np.interp(grid, tf, yf), 1000.0,
                           min_lag_s=-0.1, max_lag_s=0.5)
    # the compensator cancels its model's lag and the input lag it was designed for: what is
    # left is the platform's (as the stamps see it) less the identified model's and the
    # pairing's phase, at the slalom's frequency -- the identification's error, whatever the
    # host did to it; the compensation itself adds nothing (within 1 ms)
    left = p1d_lag_s(seen_td, tp1) - p1d_lag_s(p1d["Td"], p1d["Tp1"]) - phase / 1e3
    print(f"slalom apparent delay {delay * 1e3:.2f} ms with {truth}; the model's error leaves "
          f"{left * 1e3:.2f} ms (its phase delay at 0.2 Hz +- "
          f"{rep['phase_delay_0p2hz_ms_stderr']:.2f} ms)")
    assert abs(delay - left) <= 1e-3, (delay, left, p1d, truth)
    fig = st["axes_quality"]["rails_y"]
    # the status says the same delay (from the sender's samples at their t)
    assert fig["delay_valid"] and abs(fig["apparent_delay_ms"] - delay * 1e3) <= 1.0, (
        fig, delay)
    # the drawn platform lags about 300 ms; compensated, the slalom is within 3 ms of the
    # sender's motion -- judged where the identification states its phase delay precisely
    # enough for that (a host that took 1-2 % of the service's ticks while it recorded, under
    # identify's warning, left it +-3.6 ms, and the slalom 3.6 ms late: docs/TESTING.md)
    phase_se = rep["phase_delay_0p2hz_ms_stderr"]
    if phase_se > MAX_PHASE_STDERR_MS:
        pytest.skip(f"not judged (the compensated slalom against 3 ms): the identification "
                    f"states its phase delay at 0.2 Hz to +-{phase_se:.2f} ms (judged within "
                    f"{MAX_PHASE_STDERR_MS:g} ms); the slalom read {delay * 1e3:.2f} ms, the "
                    f"model's error {left * 1e3:.2f} ms")
    assert abs(delay) < 3e-3, f"apparent slalom delay {delay * 1e3:.1f} ms with {truth}"
