"""Benchmark: what operator work costs the 1 kHz loop -- a burst of reloads and a burst of admin
requests beside a quiet run of the same length.

Each run starts ``motcomp run`` (the example config, 8 axes at 1 kHz, admin on, the config in a
directory of its own) with a publisher process sending all 8 axes at 1 kHz (the one of
tools/bench_service.py).  Once the publisher's frames flow, the service's missed ticks are read
from its status, the scenario is played at the start of a window of ``--seconds``, and the
missed ticks are read again at the window's end:

- ``quiet``: nothing (the machine's and the service's own rate of missed ticks);
- ``reloads``: a burst of 20 ``reload --config`` requests at once, alternating between two files
  of the config directory whose gain rules differ (every accepted one swaps new gains in);
- ``admin``: a burst of 1000 requests at once, half status queries and half bypass toggles of
  rails_y (on, off, ...).

Scenario runs alternate with quiet runs (``--repeats`` rounds); the reading is the missed ticks
of each scenario over the sum of its rounds divided by the quiet runs' (target <= 2), with the
quiet runs' own rate, the replies by kind (ok, busy, other), the time to the last reply, and
the machine's load and steal.  Writes the "admin" section of docs/BENCHMARKS.md.

Usage: ``python tools/bench_admin.py [--seconds 20] [--repeats 3] [--quick] [--no-write]``
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import msgpack
from _bench import machine, write_section
from bench_service import child_env, cpu_times, proc_cpu_rss, publisher, ratio

from motcomp.io.zenoh_io import ZenohEndpoints, first_reply, free_tcp_port, loopback, open_session
from motcomp.resources import config_file

RATIO_MAX = 2.0
"""Target: missed ticks of a scenario / missed ticks of the quiet run of the same length."""
RELOADS = 20
ADMIN_REQUESTS = 1000
SCENARIOS = ("quiet", "reloads", "admin")


def write_configs(tmp: Path, seconds: float) -> tuple[Path, Path, Path]:
    """The start-up file and two reload files (different gain rules) in one directory."""
    base = (f'include = ["{config_file("motcomp.toml")}"]\n[admin]\nenabled = true\n'
            f"[status]\nwindow_s = {max(seconds - 2, 1):g}\n")
    site, a, b = tmp / "site.toml", tmp / "site-a.toml", tmp / "site-b.toml"
    site.write_text(base)
    a.write_text(base + '[defaults]\nrule = "amigo"\n')
    b.write_text(base + '[defaults]\nrule = "zn"\n')
    return site, a, b


def reply_kind(replies: list[Any]) -> str:
    """ok, busy, error (any other refusal) or none (no reply in time)."""
    for r in replies:
        if r.ok is None:
            return "error"
        out = msgpack.unpackb(r.ok.payload.to_bytes())
        if "ok" not in out:  # a status map
            return "ok"
        return "ok" if out["ok"] else ("busy" if out.get("error") == "busy" else "error")
    return "none"


def burst(session: Any, scenario: str, files: tuple[Path, Path]) -> tuple[Counter[str], float]:
    """Send the scenario's requests all at once; their replies by kind and the time from the
    first request to the last reply (s)."""
    reqs: list[tuple[str, bytes | None]]
    if scenario == "reloads":
        reqs = [("motcomp/admin/reload", msgpack.packb({"path": str(files[k % 2])}))
                for k in range(RELOADS)]
    else:
        reqs = [("motcomp/status", None) if k % 2 == 0 else
                ("motcomp/admin/bypass", msgpack.packb({"on": k % 4 == 1, "axes": ["rails_y"]}))
                for k in range(ADMIN_REQUESTS)]
    t0 = time.monotonic()
    pending = [session.get(key, payload=body, timeout=30.0) if body is not None
               else session.get(key, timeout=30.0) for key, body in reqs]
    kinds: Counter[str] = Counter()
    for (key, _), handler in zip(reqs, pending, strict=True):
        kinds[f"{key.rsplit('/', 1)[-1]} {reply_kind(list(handler))}"] += 1
    return kinds, time.monotonic() - t0


def run(seconds: float, scenario: str, tmp: Path) -> dict[str, Any]:
    """One service run: the scenario at the start of a window of ``seconds``."""
    site, a, b = write_configs(tmp, seconds)
    p_svc = free_tcp_port()
    env = child_env()
    svc = subprocess.Popen([sys.executable, "-m", "motcomp", "run", "--config", str(site), "-l",
                            loopback(p_svc), "--log-level", "warning"], env=env)
    pub = None
    try:
        with open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
            t_end = time.monotonic() + 30
            while True:
                try:
                    first_reply(session, "motcomp/status", None, 1.0)
                    break
                except Exception:
                    if time.monotonic() > t_end:
                        raise
                    time.sleep(0.2)
            pub = subprocess.Popen([sys.executable, __file__, "--publisher", str(p_svc),
                                    "--seconds", str(seconds + 6)], env=env)
            while msgpack.unpackb(first_reply(session, "motcomp/status", None, 3.0))[
                    "mode"] != "running":
                time.sleep(0.1)
            time.sleep(1.0)
            st0 = msgpack.unpackb(first_reply(session, "motcomp/status", None, 3.0))
            cpu0, _ = proc_cpu_rss(svc.pid)
            host0 = cpu_times()
            load = os.getloadavg()[0]
            w0 = time.monotonic()
            kinds: Counter[str] = Counter()
            span = 0.0
            if scenario != "quiet":
                kinds, span = burst(session, scenario, (a, b))
            time.sleep(max(0.0, w0 + seconds - time.monotonic()))
            st1 = msgpack.unpackb(first_reply(session, "motcomp/status", None, 3.0))
            wall = time.monotonic() - w0
            cpu1, rss = proc_cpu_rss(svc.pid)
            host = [y - x for x, y in zip(host0, cpu_times(), strict=True)]
    finally:
        svc.send_signal(signal.SIGTERM)
        svc.wait(timeout=30)
        if pub is not None:
            pub.kill()
            pub.wait()
    return {"scenario": scenario, "ticks": st1["ticks"] - st0["ticks"],
            "missed": st1["missed_ticks"] - st0["missed_ticks"],
            "versions": st1["config"]["version"] - st0["config"]["version"],
            "kinds": dict(kinds), "span": span, "wall": wall, "load": load,
            "cpu": 100 * (cpu1 - cpu0) / wall, "rss": rss,
            "steal": 100 * host[7] / max(sum(host), 1),
            "busy_host": 100 * (1 - (host[3] + host[4]) / max(sum(host), 1))}


def report(args: argparse.Namespace, rows: list[dict[str, Any]], elapsed_s: float) -> str:
    quiet = [r for r in rows if r["scenario"] == "quiet"]
    q_missed = sum(r["missed"] for r in quiet)
    q_ticks = sum(r["ticks"] for r in quiet)
    lines = [
        f"Machine: {machine()}.",
        "",
        f"`python tools/bench_admin.py --seconds {args.seconds:g} --repeats {args.repeats}` "
        f"({elapsed_s / 60:.1f} min): `motcomp run` with the example config (8 axes, 1 kHz, "
        "admin on, no real-time privileges) and a publisher process sending all 8 axes at "
        f"1 kHz; per round one run of each scenario, {args.seconds:g} s each, missed ticks "
        "counted over that window from the service's status: *quiet* nothing else; "
        f"*reloads* a burst of {RELOADS} `reload --config` requests at once (alternating two "
        "files with different gain rules: every accepted one swaps new gains in); *admin* a "
        f"burst of {ADMIN_REQUESTS} requests at once (half status queries, half bypass toggles "
        "of rails_y).  Load: the 1-minute load average at the window's start; host busy and "
        "steal: the machine's CPU time over the window.",
        "",
        "| scenario | runs | ticks | missed | missed / quiet (target <= "
        f"{RATIO_MAX:g}) | replies | last reply after (s) | config swaps | CPU % | load | "
        "host busy % | steal % |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in SCENARIOS:
        runs = [r for r in rows if r["scenario"] == name]
        if not runs:
            continue
        kinds: Counter[str] = Counter()
        for r in runs:
            kinds.update(r["kinds"])
        missed = sum(r["missed"] for r in runs)
        lines.append(
            f"| {name} | {len(runs)} | {sum(r['ticks'] for r in runs)} | {missed} "
            f"({', '.join(str(r['missed']) for r in runs)}) | "
            f"{'-' if name == 'quiet' else f'{ratio(missed, q_missed):.2f}'} | "
            f"{', '.join(f'{k} {v}' for k, v in sorted(kinds.items())) or '-'} | "
            f"{max(r['span'] for r in runs):.2f} | {sum(r['versions'] for r in runs)} | "
            f"{max(r['cpu'] for r in runs):.0f} | "
            f"{min(r['load'] for r in runs):.2f}-{max(r['load'] for r in runs):.2f} | "
            f"{min(r['busy_host'] for r in runs):.0f}-{max(r['busy_host'] for r in runs):.0f} | "
            f"{max(r['steal'] for r in runs):.1f} |")
    verdict = []
    for name in SCENARIOS[1:]:
        missed = sum(r["missed"] for r in rows if r["scenario"] == name)
        if any(r["scenario"] == name for r in rows):
            rq = ratio(missed, q_missed)
            verdict.append(f"{name} {rq:.2f}x quiet ({'meets' if rq <= RATIO_MAX else 'misses'} "
                           f"the target)")
    lines += ["", f"Quiet rate: {q_missed} missed of {q_ticks} ticks "
              f"({100 * q_missed / max(q_ticks, 1):.3f} %).  Reading: {'; '.join(verdict)}."]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each window")
    ap.add_argument("--repeats", type=int, default=3, help="rounds of the three scenarios")
    ap.add_argument("--quick", action="store_true", help="a smoke test: 10 s windows, 1 round")
    ap.add_argument("--only", choices=SCENARIOS, action="append",
                    help="run only these scenarios (with quiet; repeatable)")
    ap.add_argument("--no-write", action="store_true", help="print only")
    ap.add_argument("--publisher", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.publisher:
        publisher(args.publisher, args.seconds)
        return
    if args.quick:
        args.seconds, args.repeats = 10.0, 1
    scenarios = [s for s in SCENARIOS if s == "quiet" or not args.only or s in args.only]
    print(f"{args.repeats * len(scenarios)} runs of {args.seconds:g} s: about "
          f"{args.repeats * len(scenarios) * (args.seconds + 12) / 60:.0f} min", file=sys.stderr)
    t0 = time.monotonic()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeats):
            order = scenarios if rep % 2 == 0 else scenarios[::-1]
            for name in order:
                row = run(args.seconds, name, Path(tmp))
                print(f"round {rep + 1} {name}: {row['missed']} missed of {row['ticks']} "
                      f"{row['kinds']}", file=sys.stderr)
                rows.append(row)
    text = report(args, rows, time.monotonic() - t0)
    print(text)
    if not args.no_write:
        write_section("admin", text)


if __name__ == "__main__":
    main()
