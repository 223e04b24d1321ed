"""Model supervision end to end, from the outside: a platform written from docs/WIRE.md alone
(``tools/wire_platform.py``) whose rails_y is not the example config's model (a hidden truth,
Td 21.5 ms and Tp1 190 ms against 17.5 and 185.8: about 8 ms late in the band), ordinary driving
(``motcomp source --signal driving``: slaloms and lane changes) through the service.

The lab's path, as docs/SUPERVISION.md gives it: the mismatch is seen (the alarm, within 30 s
of driving plus one window); ``identify --from-status`` writes the estimate as a fragment,
``design`` tunes for it, the site config includes both, ``reload`` -- the alarm clears and the
lag the mismatch added is gone (the residual delay back within 1 ms of zero); then the platform
drifts by +10 ms (SIGUSR1 to the platform) and that is seen within 30 s.  The estimate is
judged against the truth plus the stack's share (docs/SUPERVISION.md).

What depends on the host's timing is judged after the run, where the host probe says the host
held the loop's rate (docs/TESTING.md); the checks that do not (exit codes, the fragment, the
reload) fail as usual.  About 100 s of wall time, four processes."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from motcomp.core.models import parse_model
from motcomp.errors import TransportError
from motcomp.io.zenoh_io import ZenohEndpoints, first_reply, free_tcp_port, loopback, open_session
from motcomp.runtime.estimate import mismatch
from motcomp.runtime.probe import HostProbe, loop_kept_from_cpu
from tests.conftest import ROOT, judge_realtime, motcomp_cmd, site_config, subprocess_env
from tests.test_service_process import process, wait_status

pytestmark = [pytest.mark.slow, pytest.mark.e2e]

MODEL = parse_model("p1d:K=1,Td=0.0175,Tp1=0.1857683128")
"""The example config's rails model."""
TRUTH_MS = (21.5, 190.0)
"""The platform's rails_y: pure delay and time constant (ms)."""
DRIFT_MS = 10.0
WINDOW_S = 15.0
"""The example config's supervision.window_s."""
LAG_MS = 1.7
"""The example config's input.playback_lag_s, which a design for a model identified through
the stack cancels, with the pairing's phase the fragment names (docs/SUPERVISION.md)."""
SETTLED_SE_MS = 0.4
"""The residual delay's standard error of the estimate a retune is taken from."""


def cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                          env=subprocess_env(), timeout=timeout)


def status(session: Any) -> dict[str, Any]:
    """The service's status, asked in process (a ``motcomp status`` a second would load this
    2-core host as much as the service)."""
    out: dict[str, Any] = msgpack.unpackb(first_reply(session, "motcomp/status", None, 5.0))
    return out


def truth(td_ms: float) -> Any:
    return parse_model(f"p1d:K=1,Td={td_ms / 1e3:g},Tp1={TRUTH_MS[1] / 1e3:g}")


def held(ok: bool, host: str | None) -> bool | None:
    """``ok``, or None (not judged) where it failed while the host kept the service's loop or
    its platform's from their CPU over the figure's stretch (``host``: why, from
    :func:`loop_kept_from_cpu` over the statuses at the stretch's start and end); the product's
    own figures then wait for the host: its estimates leave out the stalls."""
    return ok if ok or host is None else None


def log_instant(log: Path, text: str, after: float = 0.0) -> float | None:
    """The epoch instant of the first line of a motcomp log after ``after`` that holds
    ``text``."""
    for line in log.read_text().splitlines():
        if text in line:
            t = time.mktime(time.strptime(line[:19], "%Y-%m-%d %H:%M:%S")) + int(line[20:23]) / 1e3
            if t > after:
                return t
    return None


class Watch:
    """The status read every second: rows of rails_y's supervision, and the figures the
    estimate is judged on."""

    def __init__(self, session: Any) -> None:
        self.session = session
        self.rows: list[dict[str, Any]] = []
        self.last: dict[str, Any] | None = None

    def now(self) -> dict[str, Any]:
        """The status now, or the last one when the service did not answer in time (a stall
        of this loaded host: the next read tries again)."""
        try:
            self.last = status(self.session)
        except TransportError:
            if self.last is None:
                raise
        return self.last

    def read(self, phase: str) -> dict[str, Any]:
        """:meth:`now`, as a row of ``phase``."""
        last = self.last
        st = self.now()
        if st is last:
            return st
        f = st["model_mismatch"]["axes"]["rails_y"]
        plat = st.get("platform") or {}
        q = st["axes_quality"]["rails_y"]
        self.rows.append({"t": time.time(), "phase": phase, "state": f["state"],
                          "alarm": f["alarm"], "informative": f.get("informative"),
                          "to_t": f.get("to_t"), "at_hz": f.get("at_hz"),
                          "residual_ms": f.get("residual_delay_ms"),
                          "se_ms": f.get("residual_delay_se_ms"), "reason": f.get("reason"),
                          "age_ms": plat.get("setpoint_age_ms"),
                          "phase_ms": f.get("pairing_phase_ms"),
                          "delay_ms": q["apparent_delay_ms"] if q["delay_valid"] else None,
                          "missed": st["missed_ticks"], "ticks": st["ticks"]})
        return st

    def windows(self, phase: str) -> list[dict[str, Any]]:
        """One row per window (the status repeats a window until the next)."""
        seen: dict[float, dict[str, Any]] = {}
        for r in self.rows:
            if r["phase"] == phase and r["to_t"] is not None:
                seen.setdefault(r["to_t"], r)
        return list(seen.values())

    def errors_ms(self, phase: str, td_ms: float, since: float = 0.0, model: Any = None
                  ) -> list[float]:
        """Residual delay of the informative windows ending after ``since`` (epoch s) minus the
        truth's against ``model`` at the window's frequency plus the stack's share
        (docs/SUPERVISION.md): the platform's setpoint age (the median: the stalls that
        stretch the others are cut out of the estimate) less the pairing's phase, plus the one
        cycle the platform's acceleration is centred before its ``t`` (docs/WIRE.md)."""
        out = []
        for r in self.windows(phase):
            if (r["informative"] and r["to_t"] >= since and r["age_ms"] is not None
                    and r["phase_ms"] is not None):
                d, _ = mismatch(truth(td_ms), model or self.model, r["at_hz"])
                share = r["age_ms"] - r["phase_ms"] + 1.0
                out.append(r["residual_ms"] - (d * 1e3 + share))
        return out

    model: Any = MODEL


def test_an_outside_platform_off_its_model_is_seen_retuned_and_its_drift_seen(
        tmp_path: Path) -> None:
    p_svc, p_plat = free_tcp_port(), free_tcp_port()
    svc_ep, plat_ep = loopback(p_svc), loopback(p_plat)
    site = site_config(tmp_path / "site.toml")
    # what depends on the host's timing, judged last: (what, ok, figures); ok None where the
    # host did not hold the loops' rate over that figure's own stretch (not judged)
    late: list[tuple[str, bool | None, Any]] = []
    plat_log = tmp_path / "platform.log"
    with HostProbe() as probe, plat_log.open("wb") as fh:
        plat = subprocess.Popen(
            [sys.executable, str(ROOT / "tools" / "wire_platform.py"), "-l", plat_ep,
             "--truth", f"rails_y={TRUTH_MS[0]:g},{TRUTH_MS[1]:g}",
             "--drift", f"rails_y={TRUTH_MS[0] + DRIFT_MS:g},{TRUTH_MS[1]:g}@usr1"],
            stdout=fh, stderr=subprocess.STDOUT, env=subprocess_env())
        try:
            with process(["run", "--config", str(site), "-l", svc_ep, "-e", plat_ep],
                         tmp_path / "svc.log") as svc, \
                    open_session(ZenohEndpoints(connect=(svc_ep,))) as session:
                wait_status(session)
                watch = Watch(session)
                with process(["source", "--signal", "driving", "--repeat", "3", "--quiet",
                              "-e", svc_ep], tmp_path / "src.log") as src:
                    t_src = time.time()
                    at_src = watch.now()
                    # 1. the platform 8 ms off its model: the alarm
                    while time.time() - t_src < 30.0 + WINDOW_S + 15.0:
                        time.sleep(1.0)
                        if watch.read("off")["model_mismatch"]["axes"]["rails_y"]["alarm"]:
                            break
                    alarm = log_instant(tmp_path / "svc.log", "rails_y: model mismatch starts")
                    host = loop_kept_from_cpu(watch.last or {}, at_src)
                    late.append(("the alarm within 30 s of driving plus one window",
                                 held(alarm is not None and alarm - t_src <= 30.0 + WINDOW_S,
                                      host),
                                 (alarm and alarm - t_src, watch.windows("off"), host)))
                    # 2. the retune, from a settled estimate as an operator would take it
                    t_end = time.time() + 30.0
                    while True:
                        seen = watch.read("off")
                        f = seen["model_mismatch"]["axes"]["rails_y"]
                        if f.get("informative") and f["residual_delay_se_ms"] <= SETTLED_SE_MS:
                            break
                        if time.time() > t_end:
                            break
                        time.sleep(1.0)
                    saved = tmp_path / "status.json"
                    saved.write_text(json.dumps(seen))
                    before = [r["delay_ms"] for r in watch.rows[-10:] if r["delay_ms"]]
                    p = cli("identify", str(saved), "--from-status", "--axis", "rails_y",
                            "--out", str(tmp_path / "retune"))
                    settled = f.get("informative") and f["residual_delay_se_ms"] <= SETTLED_SE_MS
                    if not settled:  # judged with the host (below); no retune from it
                        host = loop_kept_from_cpu(watch.last or {}, at_src)
                        late.append(("a settled estimate to retune from in 30 s",
                                     held(False, host), (f, host)))
                        if f.get("informative"):  # taken, but too uncertain for this test's retune
                            assert p.returncode == 0, p.stdout + p.stderr
                        else:  # the product refuses what it cannot tell, and says so
                            assert p.returncode == 2 and "not informative" in p.stderr, \
                                p.stderr
                    else:
                        assert p.returncode == 0, p.stdout + p.stderr
                        fragment = tmp_path / "retune" / "rails_y.toml"
                        assert "forced" not in fragment.read_text()
                        design = tmp_path / "design.toml"
                        # the playback lag and the pairing's phase, as the fragment says
                        # (docs/SUPERVISION.md, "Retune from the estimate")
                        phase = re.search(r"input\.playback_lag_s \+ ([0-9.]+) ms",
                                          fragment.read_text())
                        lag_ms = LAG_MS + (float(phase.group(1)) if phase else 0.0)
                        p = cli("design", "--plant", str(fragment), "--rule", "optimal",
                                "--input-lag-ms", f"{lag_ms:g}", "--out", str(design),
                                "--quiet")
                        assert p.returncode == 0, p.stderr
                        site_config(site, fragment, design)
                        p = cli("config", "check", str(site))
                        assert p.returncode == 0, p.stderr
                        p = cli("reload", "-e", svc_ep)
                        assert p.returncode == 0, p.stdout + p.stderr
                        t_reload = time.time()
                        watch.model = parse_model(re.search(
                            r'model = "([^"]+)"', fragment.read_text()).group(1))
                        # the alarm clears; the driving's delay comes back (the status' 10 s
                        # delay window filled after the reload)
                        while time.time() - t_reload < 16.0:
                            time.sleep(1.0)
                            watch.read("retuned")
                        cleared = [r for r in watch.rows if r["phase"] == "retuned"
                                   and not r["alarm"]]
                        late.append(("the alarm cleared after the reload", bool(cleared),
                                     watch.windows("retuned")))
                        # the lag the mismatch added to the delivered motion is gone: the
                        # residual delay within 1 ms of zero.  (The driving's apparent delay is
                        # the design's: a design with prediction leads by some ms, which the
                        # 8 ms mismatch had hidden -- printed, not judged.)
                        back = [r["residual_ms"] for r in watch.windows("retuned")
                                if r["informative"]]
                        late.append(("the delay back: the residual within 1 ms of zero once "
                                     "retuned", bool(back)
                                     and abs(float(np.median(back))) <= 1.0, back))
                        after = [r["delay_ms"] for r in watch.rows[-4:] if r["delay_ms"]]
                        print(f"apparent delay before the retune {before}, after {after}")
                        # 3. the drift
                        plat.send_signal(signal.SIGUSR1)
                        t_drift = time.time()
                        at_drift = watch.now()
                        # until the alarm and a window of the drifted truth alone (ending a
                        # window's length after it): on one core the alarm came 0.6 s before
                        # the first, and the estimate after the drift had nothing to judge
                        while time.time() - t_drift < 40.0 and src.poll() is None:
                            time.sleep(1.0)
                            if watch.read("drifted")["model_mismatch"]["axes"]["rails_y"][
                                    "alarm"] and any(r["to_t"] >= t_drift + WINDOW_S + 1.0
                                                     for r in watch.windows("drifted")):
                                break
                        drift_line = next((ln for ln in plat_log.read_text().splitlines()
                                           if "truth now" in ln), "")
                        m = re.search(r"at epoch ([\d.]+) s", drift_line)
                        assert m, plat_log.read_text()[-2000:]
                        t_truth = float(m.group(1))
                        seen_at = log_instant(tmp_path / "svc.log",
                                              "rails_y: model mismatch starts", t_truth)
                        host = loop_kept_from_cpu(watch.last or {}, at_drift)
                        late.append(("the +10 ms drift seen within 30 s",
                                     held(seen_at is not None and seen_at - t_truth <= 30.0,
                                          host),
                                     (seen_at and seen_at - t_truth, watch.windows("drifted"),
                                      host)))
                        errs = watch.errors_ms("drifted", TRUTH_MS[0] + DRIFT_MS,
                                               t_truth + WINDOW_S)
                        late.append(("after the drift, the estimate within 1 ms of the truth "
                                     "plus the stack's share", bool(errs)
                                     and float(np.median(np.abs(errs))) <= 1.0, errs))
                    errs = watch.errors_ms("off", TRUTH_MS[0], model=MODEL)  # before the retune
                    late.append(("the estimate within 1 ms of the truth plus the stack's share",
                                 bool(errs) and float(np.median(np.abs(errs))) <= 1.0, errs))
                    # the windows once the first holds its data (those filling up at the start
                    # say so: "... paired with outputs (needs ...)")
                    off = watch.windows("off")
                    full = off[next((k for k, r in enumerate(off)
                                     if "paired with outputs (needs" not in r["reason"]),
                                    len(off)):]
                    judged = [r for r in full if r["informative"]]
                    late.append(("at least half the windows informative",
                                 2 * len(judged) >= len(full) > 0,
                                 [(r["informative"], r["reason"]) for r in off]))
                svc.terminate()
                assert svc.wait(timeout=30) == 0
        finally:
            plat.terminate()
            assert plat.wait(timeout=30) == 0
    for r in watch.rows:
        print({k: (round(v, 2) if isinstance(v, float) else v) for k, v in r.items()})
    judge_realtime(probe.result, "the supervision's figures on the outside platform",
                   watch.last)
    failed = [(what, data) for what, ok, data in late if ok is False]
    assert not failed, failed
    unjudged = [f"{what}: {data[-1]}" for what, ok, data in late if ok is None]
    if unjudged:
        pytest.skip(f"not judged ({'; '.join(unjudged)})")
