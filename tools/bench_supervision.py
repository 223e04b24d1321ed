"""The model supervision on the real processes: estimate against truth over time, the time to
detect a drift, false alarms, and what it costs (docs/SUPERVISION.md).

Scenarios (``--scenario``, each a fresh ``motcomp hil`` + ``motcomp run`` + ``motcomp source``
on loopback, the example config with its supervision defaults unless said):

``drift``
    ordinary driving on one axis, the platform's pure delay stepping by ``--drift-ms`` at
    ``--drift-at``: when the alarm comes, and the estimate's Td against the drawn truth plus
    the stack's own share (the platform's median setpoint age, which it reports).
``steady``
    the demo's motions (slalom, sweep, hexapod sines) for ``--seconds`` on an unchanged
    platform: alarms (there must be none), informative share, CPU.
``cost``
    the same motion with supervision on and off, alternately (``--repeats`` pairs): the loop's
    missed ticks with it against without, beside the bare clock's (a probe process).
``twins``
    two stacks at once, one service with supervision and one without (``--repeats`` runs):
    the loop's missed ticks of one against the other under the same host conditions.
``outside``
    the platform written from docs/WIRE.md (``tools/wire_platform.py``) with a hidden truth on
    ``--axis`` (``--truth TD_MS,TP1_MS``, default 21.5,190: about 8 ms late in the band against
    the example config's model, or ``--model SPEC`` in force), ``--signal driving``, a drift of
    ``--drift-ms`` at ``--drift-at`` (0: none): per window, informative or why, the residual
    delay against the truth plus the stack's share (docs/SUPERVISION.md); the
    alarm after the driving starts and after the drift; alarms; the estimator's CPU share.

Writes ``--out`` (JSON, one row per status read) and, for ``drift``, a figure of the estimate
against the truth (``--figure``).  ``--doc`` writes the summary into docs/SUPERVISION.md.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from motcomp.core.models import parse_model  # noqa: E402
from motcomp.io.zenoh_io import (  # noqa: E402
    ZenohEndpoints,
    first_reply,
    free_tcp_port,
    loopback,
    open_session,
)
from motcomp.resources import config_file  # noqa: E402
from motcomp.runtime.probe import HostProbe  # noqa: E402
from tools._bench import machine  # noqa: E402

DOC = ROOT / "docs" / "SUPERVISION.md"
RAILS = "p1d:K=1,Td={td},Tp1=0.1857683128"


def _spawn(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    with log.open("wb") as fh:
        return subprocess.Popen([sys.executable, "-m", "motcomp", *args], stdout=fh,
                                stderr=subprocess.STDOUT, env=env)


def _stop(*procs: subprocess.Popen[bytes]) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()


def run_once(work: Path, seconds: float, signal_name: str, axis: str, supervision: str = "",
             drift: str = "", poll_s: float = 1.0) -> dict[str, Any]:
    """One run: hil (+drift), the service (example config + ``supervision`` TOML lines), the
    source; the status read every ``poll_s``.  Returns the rows and the logs' summaries."""
    p_svc, p_hil = free_tcp_port(), free_tcp_port()
    svc_ep, hil_ep = loopback(p_svc), loopback(p_hil)
    site = work / "site.toml"
    site.write_text(f'include = ["{config_file("motcomp.toml")}"]\n{supervision}\n')
    hil_args = ["hil", "-l", hil_ep, "--log-level", "info"] + (["--drift", drift] if drift
                                                               else [])
    hil = _spawn(hil_args, work / "hil.log")
    t0, wall0 = time.monotonic(), time.time()
    svc = _spawn(["run", "--config", str(site), "-l", svc_ep, "-e", hil_ep], work / "svc.log")
    rows: list[dict[str, Any]] = []
    src = None
    try:
        with open_session(ZenohEndpoints(connect=(svc_ep,))) as session:
            time.sleep(2.0)
            repeat = max(1, math.ceil(seconds / 8.0))
            src = _spawn(["source", "--signal", signal_name, "--repeat", str(repeat),
                          "--quiet", "-e", svc_ep], work / "src.log")
            t_src = time.monotonic()
            while time.monotonic() - t_src < seconds:
                time.sleep(poll_s)
                try:
                    st = msgpack.unpackb(first_reply(session, "motcomp/status", None, 2.0))
                except Exception:
                    continue
                mm = st.get("model_mismatch", {})
                fig = mm.get("axes", {}).get(axis, {})
                plat = st.get("platform") or {}
                rows.append({"t": time.monotonic() - t0, "state": fig.get("state"),
                             "informative": bool(fig.get("informative")),
                             "alarm": fig.get("alarm"), "alarms": fig.get("alarms"),
                             "reason": fig.get("reason"), "at_hz": fig.get("at_hz"),
                             "residual_delay_ms": fig.get("residual_delay_ms"),
                             "residual_delay_se_ms": fig.get("residual_delay_se_ms"),
                             "gain_error": fig.get("gain_error"),
                             "estimate": fig.get("estimate"),
                             "window_to_t": fig.get("to_t"),
                             "pairing_phase_ms": fig.get("pairing_phase_ms"),
                             "any_alarm": mm.get("alarm"),
                             "all_alarms": sum(int(a.get("alarms") or 0)
                                               for a in mm.get("axes", {}).values()),
                             "estimates": mm.get("estimates"), "cpu_s": mm.get("cpu_s"),
                             "ticks": st.get("ticks"), "missed": st.get("missed_ticks"),
                             "setpoint_age_ms": plat.get("setpoint_age_ms"),
                             "delay_ms": (st.get("axes_quality", {}).get(axis, {})
                                          .get("apparent_delay_ms"))})
    finally:
        _stop(*(p for p in (src, svc, hil) if p is not None))
    hil_log = (work / "hil.log").read_text()
    m = re.search(r"truth now .* \(([\d.]+) s after the start\)", hil_log)
    svc_log = (work / "svc.log").read_text()
    alarm_lines = [ln for ln in svc_log.splitlines() if "model mismatch starts" in ln]
    truth_lines = [ln for ln in hil_log.splitlines() if "truth now" in ln]
    return {"rows": rows, "drift_at_hil_s": float(m.group(1)) if m else None,
            "alarm_lines": alarm_lines, "wall0": wall0,
            "drift_wall": _log_time(truth_lines[0]) if truth_lines else None,
            "alarm_wall": _log_time(alarm_lines[0]) if alarm_lines else None}


def _log_time(line: str) -> float:
    """The wall-clock instant of a log line of motcomp (``YYYY-MM-DD HH:MM:SS,mmm ...``)."""
    stamp = line[:23]
    return time.mktime(time.strptime(stamp[:19], "%Y-%m-%d %H:%M:%S")) + int(stamp[20:23]) / 1e3


def scenario_drift(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    td0, td1 = 0.0175, 0.0175 + args.drift_ms / 1e3
    drift = f"{args.axis}={RAILS.format(td=td1)}@{args.drift_at:g}"
    sup = f"[supervision]\nwindow_s = {args.window:g}\n" if args.window else ""
    res = run_once(work, args.seconds, args.signal, args.axis, sup, drift)
    rows = res["rows"]
    # the drift's and the alarm's instants from the two processes' logs (one host clock)
    if res["drift_wall"] is None:
        raise SystemExit("the simulated platform did not log its drift: the run was too short")
    t_drift = res["drift_wall"] - res["wall0"]
    alarm_after = None if res["alarm_wall"] is None else res["alarm_wall"] - res["drift_wall"]
    ages = [r["setpoint_age_ms"] for r in rows if r["setpoint_age_ms"] is not None]
    stack = float(np.median(ages)) if ages else math.nan
    # of that, the time the motion held too little in the band to tell anything (a sweep's
    # low end): status reads about a second apart
    quiet = 0.0
    if alarm_after is not None:
        for a, b in itertools.pairwise(rows):
            if t_drift < b["t"] <= t_drift + alarm_after and (
                    b["reason"] or "").startswith("too little motion"):
                quiet += b["t"] - a["t"]
    errs_before, errs_after, pd_before, pd_after = [], [], [], []
    for r in rows:
        e = r["estimate"]
        if not e or not r["informative"]:
            continue
        if r["t"] < t_drift:
            td, errs, pds = td0, errs_before, pd_before
        elif r["t"] > t_drift + args.window_settle:
            td, errs, pds = td1, errs_after, pd_after
        else:
            continue
        # the stack's share as the pairing counts it: the platform's setpoint age less the
        # part of it the output in force was already held before the feedback sample
        share = stack - r["pairing_phase_ms"]
        errs.append(e["Td_ms"] - (td * 1e3 + share))
        # the phase delay at the motion's centre frequency, which the band's figures use
        truth = parse_model(RAILS.format(td=td))
        pds.append(e["phase_delay_ms"] - (float(truth.phase_delay([r["at_hz"]])[0]) * 1e3
                                          + share))
    out = {"scenario": "drift", "signal": args.signal, "axis": args.axis,
           "drift_ms": args.drift_ms, "drift_at_s": t_drift, "window_s": args.window or 15.0,
           "alarm_after_s": alarm_after,
           "alarm_after_motion_s": None if alarm_after is None else alarm_after - quiet,
           "stack_ms": stack,
           "td_error_before_ms": _summary(errs_before), "td_error_after_ms": _summary(errs_after),
           "phase_delay_error_before_ms": _summary(pd_before),
           "phase_delay_error_after_ms": _summary(pd_after),
           "false_alarm_before_drift": any(r["alarm"] for r in rows if r["t"] < t_drift),
           "alarm_lines": res["alarm_lines"],
           "rows": rows}
    if args.figure:
        _figure(out, td0, td1, Path(args.figure))
    return out


def _summary(x: list[float]) -> dict[str, float] | None:
    if not x:
        return None
    a = np.abs(np.asarray(x))
    return {"n": len(x), "median_abs": float(np.median(a)), "max_abs": float(a.max()),
            "mean": float(np.mean(x))}


def _figure(res: dict[str, Any], td0: float, td1: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = res["rows"]
    t = np.array([r["t"] for r in rows])
    td = np.array([r["estimate"]["Td_ms"] if r["estimate"] else np.nan for r in rows])
    se = np.array([r["estimate"]["Td_se_ms"] if r["estimate"] else np.nan for r in rows])
    ok = np.array([r["informative"] for r in rows])
    resid = np.array([r["residual_delay_ms"] if r["residual_delay_ms"] is not None else np.nan
                      for r in rows])
    rse = np.array([r["residual_delay_se_ms"] if r["residual_delay_se_ms"] is not None
                    else np.nan for r in rows])
    stack = res["stack_ms"]
    phase = np.nanmedian([r["pairing_phase_ms"] for r in rows
                          if r["pairing_phase_ms"] is not None] or [0.0])
    truth = np.where(t < res["drift_at_s"], td0 * 1e3, td1 * 1e3) + stack - phase
    fig, ax = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    ax[0].plot(t, truth, "k-", label="truth + stack share (the platform's setpoint age less "
                                     "the pairing's hold)")
    ax[0].errorbar(t[ok], td[ok], yerr=2 * se[ok], fmt="o", ms=3, label="estimate Td (+-2 SE)")
    ax[0].plot(t[~ok], td[~ok], "x", color="0.6", label="not informative")
    ax[0].set_ylabel("pure delay Td (ms)")
    ax[0].legend(loc="upper left", fontsize=8)
    ax[0].set_title(f"{res['axis']}: {res['signal']}, pure delay +{res['drift_ms']:g} ms at "
                    f"{res['drift_at_s']:.1f} s; {res['window_s']:g} s window")
    ax[1].errorbar(t[ok], resid[ok], yerr=2 * rse[ok], fmt="o", ms=3,
                   label="residual delay in the band (+-2 SE)")
    alarm = np.array([bool(r["alarm"]) for r in rows])
    if alarm.any():
        ax[1].fill_between(t, -5, 15, where=alarm, color="tab:red", alpha=0.15, label="alarm")
    ax[1].axhline(2.5, color="tab:red", ls="--", lw=0.8, label="bound 2.5 ms")
    ax[1].axvline(res["drift_at_s"], color="k", ls=":", lw=0.8)
    ax[0].axvline(res["drift_at_s"], color="k", ls=":", lw=0.8)
    ax[1].set_ylabel("residual delay (ms)")
    ax[1].set_xlabel("time since the platform started (s)")
    ax[1].legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def scenario_steady(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    res = run_once(work, args.seconds, args.signal, args.axis)
    rows = res["rows"]
    last = rows[-1] if rows else {}
    informative = [r for r in rows if r["informative"]]
    resid = [r["residual_delay_ms"] for r in informative]
    return {"scenario": "steady", "signal": args.signal, "axis": args.axis,
            "seconds": args.seconds, "reads": len(rows), "alarms": last.get("all_alarms"),
            "alarm_lines": res["alarm_lines"],
            "informative_share": len(informative) / len(rows) if rows else None,
            "residual_delay_ms": _summary(resid),
            "estimates": last.get("estimates"), "cpu_s": last.get("cpu_s"),
            "cpu_per_estimate_ms": (1e3 * last["cpu_s"] / last["estimates"]
                                    if last.get("estimates") else None),
            "ticks": last.get("ticks"), "missed": last.get("missed"), "rows": rows}


def scenario_cost(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    runs = []
    for k in range(args.repeats):
        for on in (True, False) if k % 2 == 0 else (False, True):
            with HostProbe() as probe:
                res = run_once(work, args.seconds, args.signal, args.axis,
                               f"[supervision]\nenabled = {'true' if on else 'false'}\n")
            last = res["rows"][-1]
            clock = probe.result
            runs.append({"supervision": on, "ticks": last["ticks"], "missed": last["missed"],
                         "bare_missed": clock.missed if clock else None,
                         "bare_ticks": clock.ticks if clock else None,
                         "cpu_s": last["cpu_s"], "estimates": last["estimates"]})
            print(runs[-1], flush=True)
    on = [r for r in runs if r["supervision"]]
    off = [r for r in runs if not r["supervision"]]

    def share(rs: list[dict[str, Any]], key: str, ticks: str) -> float:
        m = sum(r[key] for r in rs)
        return m / (m + sum(r[ticks] for r in rs))
    return {"scenario": "cost", "signal": args.signal, "seconds": args.seconds, "runs": runs,
            "missed_share_on": share(on, "missed", "ticks"),
            "missed_share_off": share(off, "missed", "ticks"),
            "bare_share_on": share(on, "bare_missed", "bare_ticks"),
            "bare_share_off": share(off, "bare_missed", "bare_ticks")}


def scenario_twins(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    import threading

    runs = []
    for k in range(args.repeats):
        out: dict[bool, dict[str, Any]] = {}

        def one(on: bool, k: int = k, out: dict[bool, dict[str, Any]] = out) -> None:
            d = work / f"{k}-{'on' if on else 'off'}"
            d.mkdir()
            out[on] = run_once(d, args.seconds, args.signal, args.axis,
                               f"[supervision]\nenabled = {'true' if on else 'false'}\n")
        threads = [threading.Thread(target=one, args=(on,)) for on in (True, False)]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        row = {}
        for on, res in out.items():
            last = res["rows"][-1]
            row["on" if on else "off"] = {"ticks": last["ticks"], "missed": last["missed"],
                                          "cpu_s": last["cpu_s"],
                                          "estimates": last["estimates"]}
        runs.append(row)
        print(row, flush=True)
    on = sum(r["on"]["missed"] for r in runs)
    off = sum(r["off"]["missed"] for r in runs)
    return {"scenario": "twins", "signal": args.signal, "seconds": args.seconds, "runs": runs,
            "missed_on": on, "missed_off": off,
            "ratio": on / off if off else math.inf}


def _windows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per estimate window (the status repeats a window until the next)."""
    seen: dict[float, dict[str, Any]] = {}
    for r in rows:
        if r.get("window_to_t") is not None:
            seen.setdefault(r["window_to_t"], r)
    return list(seen.values())


def scenario_outside(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    td, tp1 = (float(x) for x in args.truth.split(","))
    p_svc, p_plat = free_tcp_port(), free_tcp_port()
    svc_ep, plat_ep = loopback(p_svc), loopback(p_plat)
    site = work / "site.toml"
    model = f'[axes.{args.axis}]\nmodel = "{args.model}"\n' if args.model else ""
    site.write_text(f'include = ["{config_file("motcomp.toml")}"]\n{model}')
    plat_args = [sys.executable, str(ROOT / "tools" / "wire_platform.py"), "-l", plat_ep,
                 "--truth", f"{args.axis}={td:g},{tp1:g}"]
    if args.drift_at:
        plat_args += ["--drift", f"{args.axis}={td + args.drift_ms:g},{tp1:g}@{args.drift_at:g}"]
    with (work / "platform.log").open("wb") as fh:
        plat = subprocess.Popen(plat_args, stdout=fh, stderr=subprocess.STDOUT)
    svc = _spawn(["run", "--config", str(site), "-l", svc_ep, "-e", plat_ep], work / "svc.log")
    rows: list[dict[str, Any]] = []
    src = None
    loads = []
    try:
        with open_session(ZenohEndpoints(connect=(svc_ep,))) as session:
            time.sleep(3.0)
            src = _spawn(["source", "--signal", "driving", "--repeat",
                          str(max(1, math.ceil(args.seconds / 120.0))), "--quiet", "-e",
                          svc_ep], work / "src.log")
            t_src = time.time()
            while time.time() - t_src < args.seconds:
                time.sleep(1.0)
                loads.append(os.getloadavg()[0])
                try:
                    st = msgpack.unpackb(first_reply(session, "motcomp/status", None, 2.0))
                except Exception:
                    continue
                mm = st.get("model_mismatch", {})
                fig = mm.get("axes", {}).get(args.axis, {})
                plat_st = st.get("platform") or {}
                rows.append({"t": time.time() - t_src, "state": fig.get("state"),
                             "informative": bool(fig.get("informative")),
                             "alarm": fig.get("alarm"), "reason": fig.get("reason"),
                             "at_hz": fig.get("at_hz"), "model": fig.get("model"),
                             "residual_delay_ms": fig.get("residual_delay_ms"),
                             "residual_delay_se_ms": fig.get("residual_delay_se_ms"),
                             "window_to_t": fig.get("to_t"), "cut_s": fig.get("cut_s"),
                             "age_ms": plat_st.get("setpoint_age_mean_ms"),
                             "phase_ms": fig.get("pairing_phase_ms"),
                             "age_median_ms": plat_st.get("setpoint_age_ms"),
                             "estimates": mm.get("estimates"), "cpu_s": mm.get("cpu_s"),
                             "cpu_share": mm.get("cpu_share"),
                             "all_alarms": sum(int(a.get("alarms") or 0)
                                               for a in mm.get("axes", {}).values()),
                             "ticks": st.get("ticks"), "missed": st.get("missed_ticks"),
                             "plat_ticks": plat_st.get("ticks"),
                             "plat_missed": plat_st.get("missed_ticks")})
    finally:
        _stop(*(p for p in (src, svc) if p is not None))
        plat.terminate()
        plat.wait(timeout=30)
    svc_log = (work / "svc.log").read_text()
    alarms = [_log_time(ln) - t_src for ln in svc_log.splitlines()
              if f"{args.axis}: model mismatch starts" in ln]
    drift_line = next((ln for ln in (work / "platform.log").read_text().splitlines()
                       if "truth now" in ln), "")
    m = re.search(r"at epoch ([\d.]+) s", drift_line)
    t_drift = float(m.group(1)) - t_src if m else None
    wins = _windows(rows)
    errors = []
    for w in wins:
        if not w["informative"] or w["age_median_ms"] is None or w["phase_ms"] is None:
            continue
        t_win = w["window_to_t"] - t_src
        if t_drift is not None and t_drift < t_win < t_drift + 15.0:
            continue  # a window that straddles the drift holds two platforms
        now = td + (args.drift_ms if t_drift is not None and t_win >= t_drift else 0.0)
        truth = parse_model(f"p1d:K=1,Td={now / 1e3:g},Tp1={tp1 / 1e3:g}")
        against = parse_model(w["model"])
        d = (float(truth.phase_delay([w["at_hz"]])[0]) - float(against.phase_delay(
            [w["at_hz"]])[0])) * 1e3
        # the stack's share (docs/SUPERVISION.md): the (median) setpoint age less the
        # pairing's phase, plus the one cycle the platform's acceleration is centred before t
        errors.append(w["residual_delay_ms"] - (d + w["age_median_ms"] - w["phase_ms"] + 1.0))
    # the drift seen: the first window wholly after it whose residual exceeds the median of
    # those before it by half the drift
    seen_after = None
    if t_drift is not None:
        pre = [w["residual_delay_ms"] for w in wins if w["informative"]
               and w["window_to_t"] - t_src < t_drift]
        ref = float(np.median(pre)) if pre else 0.0
        seen_after = next((w["window_to_t"] - t_src - t_drift for w in wins
                           if w["informative"] and w["window_to_t"] - t_src > t_drift
                           and w["residual_delay_ms"] > ref + 0.5 * args.drift_ms), None)
    reasons: dict[str, int] = {}
    for w in wins:
        if not w["informative"]:
            key = re.sub(r"[\d.+-]+", "#", w["reason"] or "")[:60]
            reasons[key] = reasons.get(key, 0) + 1
    last = rows[-1] if rows else {}

    def share(a: str, b: str) -> float | None:
        if not rows or rows[0].get(a) is None or last.get(a) is None:
            return None
        m_ = last[a] - rows[0][a]
        return m_ / (m_ + last[b] - rows[0][b])
    return {"scenario": "outside", "truth_ms": [td, tp1], "model": args.model or "example",
            "seconds": args.seconds, "drift_ms": args.drift_ms if t_drift else None,
            "drift_at_s": t_drift, "windows": len(wins),
            "informative_share": (sum(w["informative"] for w in wins) / len(wins)
                                  if wins else None),
            "not_informative": reasons, "error_ms": _summary(errors),
            "alarms_after_driving_start_s": alarms,
            "drift_seen_after_s": seen_after,
            "first_alarm_after_drift_s": next((a - t_drift for a in alarms
                                               if t_drift is not None and a > t_drift), None),
            "all_alarms": last.get("all_alarms"), "cpu_share": last.get("cpu_share"),
            "cpu_per_estimate_ms": (1e3 * last["cpu_s"] / last["estimates"]
                                    if last.get("estimates") else None),
            "missed_share": share("missed", "ticks"),
            "platform_missed_share": share("plat_missed", "plat_ticks"),
            "load": [min(loads), max(loads)] if loads else None, "rows": rows}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", choices=("drift", "steady", "cost", "twins", "outside"),
                   default="drift")
    p.add_argument("--truth", default="21.5,190",
                   help="outside: the platform's TD_MS,TP1_MS on --axis")
    p.add_argument("--model", default="", help="outside: the model in force on --axis")
    p.add_argument("--signal", default="slalom")
    p.add_argument("--axis", default="rails_y")
    p.add_argument("--seconds", type=float, default=120.0)
    p.add_argument("--drift-ms", type=float, default=10.0)
    p.add_argument("--drift-at", type=float, default=60.0)
    p.add_argument("--window", type=float, default=0.0,
                   help="supervision.window_s (default: the config's)")
    p.add_argument("--window-settle", type=float, default=0.0,
                   help="estimates this long after the drift (default: the window plus 5 s) "
                        "are compared with the new truth")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--figure", default="")
    args = p.parse_args()
    if not args.window_settle:
        args.window_settle = (args.window or 15.0) + 5.0
    print(machine(), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        res = {"drift": scenario_drift, "steady": scenario_steady, "cost": scenario_cost,
               "twins": scenario_twins, "outside": scenario_outside}[args.scenario](args, work)
    res["machine"] = machine()
    res["load_end"] = os.getloadavg()[0]
    summary = {k: v for k, v in res.items() if k != "rows"}
    print(json.dumps(summary, indent=1))
    if args.out:
        args.out.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
