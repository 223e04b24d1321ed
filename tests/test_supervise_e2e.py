"""Model supervision end to end on the real processes: a simulated platform whose pure delay
drifts by +10 ms mid-run (``hil --drift``), the service driving it with ordinary driving
(``source --signal slalom``): the drift is detected, ``identify --from-status`` writes the
estimate as a fragment, ``design`` tunes for it, the site config includes both, ``reload`` --
and the slalom's apparent delay returns to its figure before the drift.

The estimate's accuracy is judged on the settled estimate a retune is taken from (standard
error <= 0.4 ms), not on the one that raised the alarm: that one is known only to its standard
error (0.16-0.2 ms on a quiet host; 0.5-1 ms beside a CPU hog, where windows read 11-12.5 ms for
the 10 ms drift).  What depends on the host's timing is judged after the run, where the host
probe says the host held the loop's rate (docs/TESTING.md).

In the suite (about two minutes, four processes; ``pytest -m e2e`` runs it alone).  Figures
of real runs: docs/SUPERVISION.md."""

from __future__ import annotations

import json
import re
import subprocess
import time
from collections import Counter
from pathlib import Path
from typing import Any

import msgpack
import pytest

from motcomp.core.models import parse_model
from motcomp.io.zenoh_io import ZenohEndpoints, first_reply, free_tcp_port, loopback, open_session
from motcomp.runtime.probe import HostProbe
from tests.conftest import judge_realtime, motcomp_cmd, site_config, subprocess_env
from tests.test_service_process import process, wait_status

pytestmark = [pytest.mark.slow, pytest.mark.e2e]

TRUTH = "p1d:K=1,Td=0.0175,Tp1=0.1857683128"
"""The example config's rails model: the platform matches it until the drift."""
DRIFTED = "p1d:K=1,Td=0.0275,Tp1=0.1857683128"
DRIFT_AT_S = 50.0
SETTLED_SE_MS = 0.4
"""The residual delay's standard error of the estimate the retune is taken from."""


def cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                          env=subprocess_env(), timeout=timeout)


def status(session: Any) -> dict[str, Any]:
    """The service's status, asked in process (a ``motcomp status`` a second would load this
    2-core host as much as the service)."""
    out: dict[str, Any] = msgpack.unpackb(first_reply(session, "motcomp/status", None, 5.0))
    return out


def log_instant(log: Path, text: str) -> float:
    """The wall-clock instant of the first line of a motcomp log that holds ``text``."""
    line = next(ln for ln in log.read_text().splitlines() if text in ln)
    return time.mktime(time.strptime(line[:19], "%Y-%m-%d %H:%M:%S")) + int(line[20:23]) / 1e3


def delay_ms(st: dict[str, Any]) -> float | None:
    q = st["axes_quality"]["rails_y"]
    return q["apparent_delay_ms"] if q["delay_valid"] else None


def test_a_drift_is_detected_retuned_from_the_status_and_the_delay_returns(
        tmp_path: Path) -> None:
    p_svc, p_hil = free_tcp_port(), free_tcp_port()
    svc_ep, hil_ep = loopback(p_svc), loopback(p_hil)
    site = site_config(tmp_path / "site.toml")
    late: list[tuple[str, bool, Any]] = []  # what depends on the host's timing: judged last
    after: list[float] = []
    drifted = None
    with HostProbe() as probe, \
            process(["hil", "-l", hil_ep, "--truth", f"rails_y={TRUTH}", "--drift",
                     f"rails_y={DRIFTED}@{DRIFT_AT_S:g}", "--log-level", "info"],
                    tmp_path / "hil.log") as hil, \
            process(["run", "--config", str(site), "-l", svc_ep, "-e", hil_ep],
                    tmp_path / "svc.log") as svc, \
            open_session(ZenohEndpoints(connect=(svc_ep,))) as session:
        t_hil = time.monotonic()
        wait_status(session)
        time.sleep(2.0)
        with process(["source", "--signal", "slalom", "--repeat", "10", "--quiet", "-e",
                      svc_ep], tmp_path / "src.log") as src:
            # before the drift: the compensated slalom's delay, and no alarm
            before = []
            while time.monotonic() - t_hil < DRIFT_AT_S - 2.0:
                time.sleep(2.0)
                st = status(session)
                assert not st["model_mismatch"]["alarm"], st["model_mismatch"]
                if (d := delay_ms(st)) is not None:
                    before.append(d)
            assert before, "no valid apparent delay before the drift"
            # the drift, detected within 30 s of it
            detected = None
            trace = []
            while time.monotonic() - t_hil < DRIFT_AT_S + 45.0:
                time.sleep(1.0)
                st = status(session)
                f = st["model_mismatch"]["axes"]["rails_y"]
                plat = st.get("platform") or {}
                trace.append((round(time.monotonic() - t_hil, 1), f["state"],
                              f.get("residual_delay_ms"), f.get("residual_delay_se_ms"),
                              f.get("reason"), st["missed_ticks"], plat.get("missed_ticks"),
                              plat.get("setpoint_age_mean_ms")))
                if f["alarm"]:
                    detected = time.monotonic() - t_hil - DRIFT_AT_S
                    break
            mm = st["model_mismatch"]["axes"]["rails_y"]
            print("(s, state, residual ms, +- ms, reason, service's missed ticks, platform's "
                  "missed ticks, platform's mean setpoint age ms)")
            for row in trace:
                print(row)
            if detected is None and not any(row[1] == "ok" for row in trace):
                # no window after the drift was judged, for the reasons the product gives
                # (the loop degraded: the host's stalls in the data; the estimator starved)
                reasons = Counter(row[4] or row[1] for row in trace)
                pytest.skip(f"not judged: no window after the drift was informative "
                            f"({dict(reasons)})")
            if detected is not None:
                assert "model mismatch starts" in (tmp_path / "svc.log").read_text()
                # from the platform's log line of the drift to the service's WARNING (one clock)
                after_s = log_instant(tmp_path / "svc.log", "model mismatch starts") - \
                    log_instant(tmp_path / "hil.log", "truth now")
                print(f"drift detected {after_s:.1f} s after it; residual "
                      f"{mm['residual_delay_ms']:.2f} +- {mm['residual_delay_se_ms']:.2f} ms, "
                      f"estimate {mm['estimate']['spec']}")
                late.append(("detected within 30 s", after_s <= 30.0, trace))
                drifted = delay_ms(st)
                # the retune, from a settled estimate as an operator would take it (the
                # status shows its uncertainty): the estimate as a fragment, designed,
                # included, reloaded
                t_end = time.monotonic() + 60.0
                while True:
                    seen = status(session)
                    f = seen["model_mismatch"]["axes"]["rails_y"]
                    if f["informative"] and f["residual_delay_se_ms"] <= SETTLED_SE_MS:
                        break
                    if time.monotonic() > t_end:  # the product says it cannot tell
                        pytest.skip("not judged: no settled estimate in 60 s on this host "
                                    f"({f.get('reason') or f.get('residual_delay_se_ms')})")
                    time.sleep(1.0)
                print(f"settled: residual {f['residual_delay_ms']:.2f} +- "
                      f"{f['residual_delay_se_ms']:.2f} ms, estimate {f['estimate']['spec']}")
                late.append(("the settled estimate's residual delay: the drift's 10 ms within "
                             "2 ms", abs(f["residual_delay_ms"] - 10.0) <= 2.0, f))
                # that status, saved (the next estimate may be less certain again)
                saved = tmp_path / "status.json"
                saved.write_text(json.dumps(seen))
                p = cli("identify", str(saved), "--from-status", "--axis", "rails_y", "--out",
                        str(tmp_path / "retune"))
                assert p.returncode == 0, p.stdout + p.stderr
                fragment = tmp_path / "retune" / "rails_y.toml"
                model = parse_model(re.search(r'model = "([^"]+)"',
                                              fragment.read_text()).group(1))
                # the band's phase delay is what the estimate knows (a slalom alone trades Td
                # against Tp1): the drifted truth's, give or take the stack's share
                at = mm["at_hz"]
                off = float(model.phase_delay([at])[0]) - float(
                    parse_model(DRIFTED).phase_delay([at])[0])
                late.append(("the settled estimate's phase delay in the band: the drifted "
                             "truth's within 2 ms", abs(off) <= 2.0e-3, (model, at, off)))
                design = tmp_path / "design.toml"
                p = cli("design", "--plant", str(fragment), "--rule", "optimal", "--out",
                        str(design), "--quiet")
                assert p.returncode == 0, p.stderr
                site_config(site, fragment, design)
                p = cli("reload", "-e", svc_ep)
                assert p.returncode == 0, p.stdout + p.stderr
                t_reload = time.monotonic()
                # after: the status' delay window (10 s) filled with the retuned motion
                while time.monotonic() - t_reload < 30.0 and src.poll() is None:
                    time.sleep(2.0)
                    st = status(session)
                    if time.monotonic() - t_reload > 14.0 and (d := delay_ms(st)) is not None:
                        after.append(d)
                assert after, "no valid apparent delay after the reload"
            else:
                late.append(("detected within 45 s", False, trace))
        for p_ in (svc, hil):
            p_.terminate()
            assert p_.wait(timeout=30) == 0
    # what depends on the host's timing (the estimate, the delays), judged only where the host
    # held the loop's rate (docs/TESTING.md)
    judge_realtime(probe.result, "the drift's detection and the retuned slalom")
    failed = [(what, data) for what, ok, data in late if not ok]
    assert not failed, failed
    ref = float(sorted(before)[len(before) // 2])
    now = float(sorted(after)[len(after) // 2])
    print(f"apparent delay: {ref:.2f} ms before the drift, {drifted} ms drifted, {now:.2f} ms "
          "retuned")
    assert abs(now - ref) <= 3.0, (before, drifted, after)
