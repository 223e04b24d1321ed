"""``motcomp status``, ``motcomp bypass``, ``motcomp reload``: talk to a running service."""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import msgpack

from motcomp.cli._common import positive_float, print_json, remaining
from motcomp.core.axes import AXES, ROTATIONAL
from motcomp.errors import NoAnswerError, ServiceError
from motcomp.io.zenoh_io import (
    NoPeerError,
    ZenohEndpoints,
    add_zenoh_args,
    connected_peers,
    endpoints_from_args,
    open_session,
    query,
)

ORDER = 2

CHANGE_TIMEOUT_S = 12.0
"""How long a reload or profile switch waits for the service's answer by default: longer than
the service may take to prepare one (``motcomp.runtime.reload.PREPARE_TIMEOUT_S``, 10 s, not
imported here: a command loads its own module only) and swap it in."""


def _service_args(p: argparse.ArgumentParser, key: str, timeout: float) -> None:
    """The key of the service endpoint, a timeout and zenoh's flags."""
    p.add_argument("--key", default=key, help=f"endpoint key (default: {key})")
    p.add_argument("--timeout", type=positive_float, default=timeout, metavar="S",
                   help=f"wait this long for the service's reply (default {timeout:g} s); "
                        "exit 3 if none came")
    add_zenoh_args(p)


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("status", help="query a running service's status",
                       description="Query the service's status endpoint and print it as a "
                                   "table (mode, config, loop timing, frames, per-axis state). "
                                   "Exit 3 if the service does not answer within --timeout.")
    s.add_argument("--json", action="store_true", help="print the raw status map as JSON")
    s.add_argument("--watch", nargs="?", type=positive_float, const=1.0, default=None,
                   metavar="SECONDS",
                   help="refresh every SECONDS (default 1) until Ctrl-C; with --json, one "
                        "JSON object per line (a poll nobody answered: a line on stderr)")
    _service_args(s, "motcomp/status", 3.0)
    s.set_defaults(func=run_status)

    b = sub.add_parser("bypass", help="turn compensation off (on) or back on (off), bumplessly",
                       description="Admin command (needs [admin] enabled = true). Exits 2 if "
                                   "the service rejects the request (an axis it does not "
                                   "drive), 1 if it could not serve it (busy, stopping).")
    b.add_argument("state", choices=["on", "off"],
                   help="on: compensation off (the reference passes through); off: back on")
    b.add_argument("--axes", nargs="+", metavar="AXIS",
                   help="default: 'on' every driven axis; 'off' the driven axes the running "
                        "config compensates (an axis it bypasses stays bypassed; one it "
                        "predicts gets its prediction back, its PID staying bypassed)")
    _service_args(b, "motcomp/admin", 3.0)
    b.set_defaults(func=run_bypass)

    pr = sub.add_parser("profile", help="switch the running service's scenario profile",
                        description="Make a profile of the service's config active (its gains "
                                    "replace the current ones, bumplessly). Needs [admin] "
                                    "enabled = true. Exits 2 if the service rejects it (a "
                                    "profile its config does not define), 1 if it could not "
                                    "serve the request (busy, stopping).")
    pr.add_argument("name", help="profile name, or 'none' for the config's base tuning")
    _service_args(pr, "motcomp/admin", CHANGE_TIMEOUT_S)
    pr.set_defaults(func=run_profile)

    r = sub.add_parser("reload", help="reload a running service's config",
                       description="Ask the running service to re-read its config file (or "
                                   "FILE); prints the outcome; exits 2 if the service rejects the "
                                   "file (every reason, the first one first), 1 if it could not "
                                   "serve the request (busy, stopping). "
                                   "Needs [admin] enabled = true.")
    r.add_argument("--config", type=Path, metavar="FILE",
                   help="file to load instead of the config in force; it must lie in the "
                        "service's config directory (the directory of the file it was started "
                        "with), and once accepted it is the config in force (SIGHUP and "
                        "`reload` re-read it)")
    _service_args(r, "motcomp/admin", CHANGE_TIMEOUT_S)
    r.set_defaults(func=run_reload)


def _ask(session: Any, ep: ZenohEndpoints, key: str, payload: bytes | None,
         timeout_s: float, asked_s: float | None = None) -> dict[str, Any]:
    """The service's reply on ``key``, asked until one comes or ``timeout_s`` has passed
    (``asked_s``: the timeout the user gave, for the message; default ``timeout_s``).

    A query that no queryable matches returns at once with no reply (nobody connected yet, or
    an endpoint that is down): it is asked again until the timeout, so that a service still
    starting is waited for and the message below is said after the full wait.  A query the
    service took and did not answer in time is not asked again (a request may still be served).

    Raises
    ------
    NoPeerError
        No reply within ``timeout_s`` (naming the endpoints, the key and whether any zenoh
        peer was connected, or that the service took the query and did not answer).
    """
    t_end = time.monotonic() + timeout_s
    late = False
    while True:
        remaining = t_end - time.monotonic()
        if remaining <= 0:
            break
        try:
            replies = query(session, key, payload, remaining)
        except NoAnswerError:  # taken and not answered in time: not sent again (a request
            late = True        # may still be served: sent twice, it could be served twice)
            break
        if replies:
            out = msgpack.unpackb(replies[0])
            if not isinstance(out, dict):
                raise ServiceError(f"unexpected reply from {key}")
            return out
        time.sleep(min(0.1, max(0.0, t_end - time.monotonic())))
    peers = connected_peers(session)
    within = f"within {timeout_s if asked_s is None else asked_s:g} s"
    if late:
        raise NoPeerError(
            f"no reply from the service at {ep.describe()} (key {key}) {within}: it received "
            "the query but did not answer in time (busy or stalled); a request may still be "
            "served: check `motcomp status`")
    raise NoPeerError(
        f"no reply from the service at {ep.describe()} (key {key}) {within}; "
        + (f"{peers} zenoh peer(s) connected, but none answers on this key (another service's "
           "key, or an access-control rule that drops the query?)" if peers
           else "no zenoh peer was reachable"))


def _request(args: argparse.Namespace, key: str, body: dict[str, Any] | None) -> dict[str, Any]:
    """One request; ``--timeout`` counts from the command's start (opening the session, about
    0.5 s of zenoh's scouting delay, is part of it)."""
    ep = endpoints_from_args(args)
    with open_session(ep) as session:
        payload = msgpack.packb(body) if body is not None else None
        return _ask(session, ep, key, payload, remaining(args.timeout), args.timeout)


NOT_NOW = {
    "busy": "busy (the service is serving other admin requests: try again shortly)",
    "stopping": "stopping (the service is parking the platform before it exits)",
    "admin off": ("admin off (the service's config has [admin] enabled = false, read at its "
                  "start: set it to true and restart the service; docs/DEPLOYMENT.md)"),
}
"""Rejections that say nothing of the request (exit 1, a failure): the service could not
serve it now.  Any other rejection names what is wrong with the request (exit 2, bad input)."""


def _command(args: argparse.Namespace, name: str, body: dict[str, Any]) -> dict[str, Any] | int:
    """Call the admin endpoint ``name``: its reply, or the exit code of a rejection (the reason
    on stderr): 2 for a request the service refuses (unknown axis or profile, a config it does
    not accept), 1 when it could not serve it (busy, stopping, an internal error)."""
    out = _request(args, f"{args.key}/{name}", body)
    if not out.get("ok"):
        error = str(out.get("error"))
        failure = error in NOT_NOW or error.startswith("internal error")
        print(f"motcomp {name}: {'failed' if failure else 'rejected'}: "
              f"{NOT_NOW.get(error, error)}", file=sys.stderr)
        return 1 if failure else 2
    return out


def _unreachable(command: str, exc: NoPeerError) -> int:
    print(f"motcomp {command}: {exc}", file=sys.stderr)
    return 3


def run_status(args: argparse.Namespace) -> int:
    if args.watch is None:
        ep = endpoints_from_args(args)
        try:
            with open_session(ep) as session:
                st = _ask(session, ep, args.key, None, remaining(args.timeout), args.timeout)
                # a status the service could not build (its fallback names the error): asked
                # again while the timeout lasts, else shown as it is
                while st.get("error") and remaining(args.timeout, 0.0) > 0.2:
                    time.sleep(0.1)
                    st = _ask(session, ep, args.key, None, remaining(args.timeout),
                              args.timeout)
        except NoPeerError as exc:
            return _unreachable("status", exc)
        _show(args, st)
        return 0
    ep = endpoints_from_args(args)
    clear = sys.stdout.isatty() and not args.json
    # Ctrl-C (SIGINT) or SIGTERM ends the watch after the poll in progress (exit 0): raised as
    # KeyboardInterrupt inside zenoh's calls, it could leave the session to a close that never
    # returned
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda _sig, _frame: stop.set())
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with open_session(ep) as session:
            while not stop.is_set():
                t_next = time.monotonic() + args.watch
                try:
                    st = _ask(session, ep, args.key, None, args.timeout)
                except NoPeerError as exc:  # stdout stays JSON lines with --json
                    print(f"{time.strftime('%H:%M:%S')} {exc}", flush=True,
                          file=sys.stderr if args.json else sys.stdout)
                else:
                    if clear:
                        sys.stdout.write("\x1b[H\x1b[2J")
                    elif not args.json:
                        print(f"--- {time.strftime('%H:%M:%S')}")
                    _show(args, st)
                    sys.stdout.flush()
                stop.wait(max(0.0, t_next - time.monotonic()))
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0


def _show(args: argparse.Namespace, st: dict[str, Any]) -> None:
    if args.json:
        print_json(st, None if args.watch is not None else 2)
    else:
        print(format_status(st))


def _yes(flag: bool) -> str:
    return "yes" if flag else "no"


def platform_line(plat: dict[str, Any], now_t: float) -> str:
    """The platform's own figures of the stack, from its status (docs/WIRE.md)."""
    age = plat.get("setpoint_age_ms")
    text = "platform    " + (
        f"setpoints applied {float(age):.2f} ms after their t (median; mean "
        f"{float(plat.get('setpoint_age_mean_ms', float('nan'))):.2f} ms): the stack's delay"
        if isinstance(age, int | float) and math.isfinite(age)
        else "reports no setpoint age")
    if isinstance(plat.get("missed_ticks"), int):
        text += f"; its loop missed {plat['missed_ticks']} ticks" + waiting_text(plat)
    seen = plat.get("received_t")
    if isinstance(seen, int | float) and now_t - seen > 5.0:
        text += f" ({now_t - seen:.0f} s ago)"
    return text


def waiting_text(counts: dict[str, Any], missed: str = "missed_ticks") -> str:
    """`` (N waiting for a CPU)``: of a loop's missed deadlines (``counts[missed]``), those it
    waited for a CPU (docs/DEPLOYMENT.md, "Missed deadlines"); empty if none were missed or the
    loop does not say."""
    waiting = counts.get("missed_waiting_cpu")
    if not isinstance(waiting, int) or not counts.get(missed):
        return ""
    return f" ({waiting} waiting for a CPU)"


def format_status(st: dict[str, Any]) -> str:
    """The service's status map (``motcomp/status``) as a table for people."""
    cfg = st.get("config") or {}
    first = st.get("mode") == "stale" and (st.get("frames") or {}).get("received", 1) == 0
    lines = [
        f"mode        {st.get('mode', '?')}"
        + (" (no frame received yet: holding the start position)" if first else ""),
        *([f"ERROR       {st['error']} (the service's status is incomplete)"]
          if st.get("error") else []),
        f"config      hash {cfg.get('hash', '?')}  version {cfg.get('version', '?')}  profile "
        f"{st.get('profile') or 'none'}" + (f"  ({cfg['path']})" if cfg.get("path") else ""),
        f"service     motcomp {st.get('version', '?')}",
        f"loop        {st.get('rate_hz', 0):g} Hz  ticks {st.get('ticks', 0)}  missed "
        f"{st.get('missed_ticks', 0)}" + waiting_text(st)
        + ("  (ticks on input)" if st.get("sync_to_input") else ""),
    ]
    dl = st.get("deadlines") or {}
    if dl.get("due"):
        share = 100 * float(dl.get("share", 0))
        over = (f"over the first {float(dl.get('window_s', 0)):.1f} s (so far)" if dl.get("open")
                else f"over the last {float(dl.get('window_s', 0)):.0f} s")
        lines.append(f"deadlines   missed {dl.get('missed', 0)}{waiting_text(dl, 'missed')} of "
                     f"{dl['due']} {over} ({share:.1f} %)"
                     + ("  DEGRADED: the host does not give the loop its CPU"
                        if dl.get("degraded") else ""))
    plat = st.get("platform")
    if isinstance(plat, dict):
        lines.append(platform_line(plat, float(st.get("t", 0.0))))
    loop = st.get("loop") or {}
    series = [k[:-len("_p50_us")] for k in loop if k.endswith("_p50_us")]
    if series:
        window = st.get("loop_window_s")
        head = f"loop times (us{f', last {window:g} s' if window else ''})"
        lines.append(f"  {head:<24}" + "".join(f"{q:>9}" for q in ("p50", "p99", "p99.9",
                                                                   "max")))
        for name in series:
            vals = [float(loop.get(f"{name}_{q}_us", float("nan")))
                    for q in ("p50", "p99", "p999", "max")]
            lines.append(f"    {name:<22}" + "".join(f"{v:9.1f}" for v in vals))
    fr = st.get("frames") or {}
    reasons = fr.get("rejected_by_reason") or {}
    why = ", ".join(f"{k} {v}" for k, v in sorted(reasons.items()) if v)
    lines.append(f"frames      received {fr.get('received', 0)}  accepted {fr.get('accepted', 0)}"
                 f"  rejected {fr.get('rejected', 0)}" + (f" ({why})" if why else "")
                 + f"  superseded {fr.get('superseded', 0)}")
    if fr.get("last_reject"):
        lines.append(f"            last rejection: {fr['last_reject']}")
    inp = st.get("input") or {}
    if inp:
        lead = f"  lead {float(inp['lead_ms']):.2f} ms" if inp.get("lead_ms") else ""
        if not fr.get("accepted"):  # the period and the lag are the frames' own
            lines.append(f"input       {inp.get('reconstruction', '?')}  period and lag from "
                         "the first frames on (the config's playback lag "
                         f"{float(inp.get('playback_lag_ms', 0.0)):.2f} ms){lead}")
        else:
            lines.append(f"input       {inp.get('reconstruction', '?')}  period "
                         f"{float(inp.get('period_ms', 0.0)):.2f} ms  lag "
                         f"{float(inp.get('lag_ms', 0.0)):.2f} ms (design --input-lag-ms)"
                         + lead)
        bands: dict[tuple[float, float], list[str]] = {}
        for axis, b in (inp.get("band") or {}).items():
            bands.setdefault((float(b["band_hz"]), float(b["delay_ms"])), []).append(axis)
        if bands:
            lines.append("            band limit " + "; ".join(
                f"{hz:g} Hz ({ms:.2f} ms)" + (f" on {', '.join(axes)}" if len(bands) > 1 else "")
                for (hz, ms), axes in sorted(bands.items()))
                + " (design --input-band-hz; its delay is cancelled with the lag)")
    if (st.get("frames") or {}).get("received", 1) == 0:
        lines.append(f"stale       waiting for a first frame ({st.get('stale_s', 0.0):.2f} s)")
    else:
        now_s, n = st.get("stale_s", 0.0), st.get("stale_episodes", 0)
        before = f"{st.get('stale_total_s', 0.0):.2f} s"  # the finished episodes only
        lines.append(f"stale       NOW {now_s:.2f} s since the last frame (episode {n}; the "
                     f"{n - 1} before: {before})" if now_s > 0 and n > 0 else
                     f"stale       no  (before: {before} over {n} episode(s))")
    env = st.get("envelope") or {}
    if env.get("clamps"):
        acted = ", ".join(f"{a} {n}" for a, n in (env.get("acted") or {}).items() if n)
        lines.append(f"ENVELOPE    the guard changed {env['clamps']} command(s) ({acted}): "
                     "a bug upstream of it (docs/DEPLOYMENT.md)")
    can = st.get("can")
    if can:
        lines.append(f"can         sent {can.get('sent', 0)}  errors {can.get('errors', 0)}")
    if st.get("realtime"):
        lines.append(f"scheduling  {st['realtime']}")
    if st.get("tick"):
        lines.append(f"tick        {st['tick']}")
    lines += _quality_lines(st)
    lines += _mismatch_lines(st)
    driven = set(st.get("driven") or [])
    bypass = set(st.get("bypass") or [])
    sat = st.get("saturation") or {}
    pred = st.get("prediction") or {}
    lines.append(f"{'axis':<12}{'driven':<8}{'bypass':<8}{'prediction':<12}{'fallbacks':<11}"
                 "saturation")
    for axis in [a for a in AXES if a in driven or a in sat] + sorted(
            set(sat) - set(AXES)):
        on = axis in driven
        p = pred.get(axis)
        state, falls = ((str(p.get("state", "?")), str(p.get("fallbacks", 0)))
                        if isinstance(p, dict) else ("-", "-"))
        lines.append(f"{axis:<12}{_yes(on):<8}{(_yes(axis in bypass) if on else '-'):<8}"
                     f"{state:<12}{falls:<11}{sat.get(axis, 0)}")
    return "\n".join(lines)


def _num(x: Any, fmt: str) -> str:
    return "-" if not isinstance(x, int | float) or isinstance(x, bool) else format(x, fmt)


def _mismatch_lines(st: dict[str, Any]) -> list[str]:
    """The model supervision's table (docs/SUPERVISION.md)."""
    mm = st.get("model_mismatch")
    if not isinstance(mm, dict) or not mm.get("enabled") or not mm.get("axes"):
        return []
    lines = [f"model       estimate over the last {mm.get('window_s', 0):g} s against the model "
             f"in force; alarm beyond {mm.get('delay_bound_ms', 0):g} ms or "
             f"{100 * float(mm.get('gain_bound', 0)):g} % held {mm.get('hold_s', 0):g} s"
             + (f"; ERRORS {mm['errors']}: {mm.get('last_error')}" if mm.get("errors") else ""),
             f"  {'':<10}{'state':<17}{'resid ms':>9}{'+-':>6}{'gain %':>8}{'at Hz':>7}"
             f"{'Td ms':>8}{'Tp1 ms':>8}"]
    for axis, f in mm["axes"].items():
        e = f.get("estimate") or {}
        gain = f.get("gain_error")
        state = "DRIFT" if f.get("alarm") else str(f.get("state", "?"))
        why = "" if f.get("informative") or not f.get("reason") else f"  {f['reason']}"
        lines.append(f"  {axis:<10}{state:<17}{_num(f.get('residual_delay_ms'), '+.2f'):>9}"
                     f"{_num(f.get('residual_delay_se_ms'), '.2f'):>6}"
                     f"{_num(gain * 100 if isinstance(gain, int | float) else None, '+.1f'):>8}"
                     f"{_num(f.get('at_hz'), '.2f'):>7}{_num(e.get('Td_ms'), '.2f'):>8}"
                     f"{_num(e.get('Tp1_ms'), '.1f'):>8}{why}".rstrip())
    return lines


def _quality_lines(st: dict[str, Any]) -> list[str]:
    """The feedback counters and the motion-quality table (before the axis table, whose rows
    end the output)."""
    fb = st.get("feedback")
    quality = st.get("axes_quality")
    if fb is None and not quality:
        return []  # a service from before these figures
    lines = []
    if fb is not None:
        age = fb.get("age_s")
        lines.append(f"feedback    {fb.get('key', '?')}: received {fb.get('received', 0)}  bad "
                     f"{fb.get('bad', 0)}  dropped {fb.get('dropped', 0)}  "
                     + ("none yet" if age is None else f"newest {age:.2f} s ago"))
        if fb.get("last_bad"):
            lines.append(f"            last bad frame: {fb['last_bad']}")
    if not quality:
        return lines
    q = st.get("quality") or {}
    lines.append(f"quality     delay and limiter over the last {q.get('window_s', 0):g} s, "
                 f"command over the last {q.get('command_window_s', 0):g} s"
                 + (" (rotations: rad/s^2, rad/s^3)" if set(quality) & ROTATIONAL else ""))
    lines.append(f"  {'':<10}{'delay ms':>10}{'valid':>7}{'corr':>8}{'limited %':>11}"
                 f"{'hf acc m/s^2':>14}{'jerk m/s^3':>12}")
    for axis in sorted(quality, key=lambda a: (AXES.index(a) if a in AXES else len(AXES), a)):
        f = quality[axis] or {}
        share = f.get("limited_share")
        share_pct = share * 100 if isinstance(share, int | float) else None
        reason = "" if f.get("delay_valid") else f"  {f.get('delay_reason') or ''}"
        lines.append(f"  {axis:<10}{_num(f.get('apparent_delay_ms'), '.2f'):>10}"
                     f"{_yes(bool(f.get('delay_valid'))):>7}{_num(f.get('delay_corr'), '.3f'):>8}"
                     f"{_num(share_pct, '.2f'):>11}{_num(f.get('hf_acc_rms'), '.3f'):>14}"
                     f"{_num(f.get('jerk_rms'), '.1f'):>12}{reason}".rstrip())
    return lines


def run_bypass(args: argparse.Namespace) -> int:
    try:
        out = _command(args, "bypass", {"on": args.state == "on", "axes": args.axes})
    except NoPeerError as exc:
        return _unreachable("bypass", exc)
    if isinstance(out, int):
        return out
    print(f"bypassed axes (PID): {', '.join(out['bypass']) or 'none'}")
    alone = [a for a in out.get("predicted", []) if a in out["bypass"]]
    if alone:  # compensation on, by prediction alone
        print(f"  of them compensated by prediction: {', '.join(alone)}")
    return 0


def run_reload(args: argparse.Namespace) -> int:
    # absolute, not resolved: the service resolves it and judges where it leads
    body = {"path": str(args.config.absolute())} if args.config else {}
    try:
        out = _command(args, "reload", body)
    except NoPeerError as exc:
        return _unreachable("reload", exc)
    if isinstance(out, int):
        return out
    print(f"reloaded: {out.get('path')} (hash {out.get('hash')}, version {out.get('version')})"
          + (": the same values as before (to run another file: reload --config FILE)"
             if out.get("unchanged") else ""))
    return 0


def run_profile(args: argparse.Namespace) -> int:
    name = None if args.name == "none" else args.name
    try:
        out = _command(args, "profile", {"name": name})
    except NoPeerError as exc:
        return _unreachable("profile", exc)
    if isinstance(out, int):
        return out
    active = out.get("profile")
    print((f"profile {active} active" if active is not None
           else "no profile active (the config's base tuning)")
          + f" (config hash {out.get('hash')}, version {out.get('version')})")
    return 0
