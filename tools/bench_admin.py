"""Benchmark: what operator work costs the 1 kHz loop -- a burst of reloads and a burst of admin
requests, each beside a twin service that gets none.

On a shared machine the missed ticks of a quiet service vary several-fold from one run to the
next (other processes), so every run starts two services at once, the same example config (8
axes at 1 kHz, admin on, each config in a directory of its own) on different status, admin and
output keys: the *target* gets the scenario, its *twin* nothing; both take the same input from
one publisher process sending all 8 axes at 1 kHz (the one of tools/bench_service.py; this
process is the zenoh router between them).  Once the frames flow, both services' missed ticks
are read from their status, the scenario is played on the target at the start of a window of
``--seconds``, and the missed ticks are read again at its end.  Scenarios:

- ``quiet``: nothing on either (how far the two differ with nothing to tell them apart);
- ``reloads``: a burst of 20 ``reload --config`` requests at once, alternating between two files
  of the config directory whose gain rules differ (every accepted one swaps new gains in);
- ``admin``: a burst of 1000 requests at once, half status queries and half bypass toggles of
  rails_y (on, off, ...).

Rounds of the three scenarios (``--repeats``, order alternating); the reading per scenario is
the target's missed ticks over its twin's, of the sums over the rounds and the median of the
rounds' ratios (target <= 2 for both: a stall of the host in one round weighs on the sums),
beside the twin's own rate, the replies by kind (ok, busy, other), the time to the last reply,
and the machine's load.  The twin shares the machine with the target: work the scenario puts
on the machine's cores (the reader process, zenoh's threads) slows both; what the table tells
apart is what it costs the target's loop alone (its interpreter, its process).  Writes the
"admin" section of docs/BENCHMARKS.md.

With ``--interpreter`` instead: the loop without transport (``Service.tick`` paced by its clock
in a thread, in-memory ports) in a process of its own while its main thread prepares 20 reloads,
in the same interpreter as before this design or in the reader process as now (the twin cannot
tell work that loads the cores apart from work that holds the interpreter); the
"admin-interpreter" section.

Usage: ``python tools/bench_admin.py [--seconds 20] [--repeats 3] [--quick] [--no-write]
[--save JSON]`` (``--report JSON``: the report of saved runs).
"""

from __future__ import annotations

import argparse
import json
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
import numpy as np
from _bench import machine, write_section
from bench_service import child_env, cpu_times, proc_cpu_rss, publisher, ratio

from motcomp.io.zenoh_io import ZenohEndpoints, first_reply, free_tcp_port, loopback, open_session
from motcomp.resources import config_file

RATIO_MAX = 2.0
"""Target: missed ticks of a scenario / missed ticks of the quiet run of the same length."""
RELOADS = 20
ADMIN_REQUESTS = 1000
SCENARIOS = ("quiet", "reloads", "admin")


def write_configs(tmp: Path, seconds: float, twin: bool) -> tuple[Path, Path, Path]:
    """The start-up file and two reload files (different gain rules) in a directory of their
    own."""
    tmp = tmp / ("twin" if twin else "target")
    tmp.mkdir(exist_ok=True)
    base = (f'include = ["{config_file("motcomp.toml")}"]\n[admin]\nenabled = true\n'
            f"[status]\nwindow_s = {max(seconds - 2, 1):g}\n")
    if twin:
        base = base.replace("[admin]\n", "[admin]\nkey = \"twin/admin\"\n").replace(
            "[status]\n", "[status]\nkey = \"twin/status\"\n") + '[output]\nkey = "twin/setpoint"\n'
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


def status_of(session: Any, key: str) -> dict[str, Any]:
    out: dict[str, Any] = msgpack.unpackb(first_reply(session, key, None, 3.0))
    return out


def run(seconds: float, scenario: str, tmp: Path) -> dict[str, Any]:
    """One run: target and twin at once, the scenario on the target at the start of a window of
    ``seconds``."""
    router = free_tcp_port()
    env = child_env()
    procs = []
    keys = ("motcomp/status", "twin/status")
    files = None
    pub = None
    try:
        with open_session(ZenohEndpoints(listen=(loopback(router),), mode="router")) as session:
            for twin in (False, True):
                site, a, b = write_configs(tmp, seconds, twin)
                files = files or (a, b)
                procs.append(subprocess.Popen(
                    [sys.executable, "-m", "motcomp", "run", "--config", str(site), "-e",
                     loopback(router), "-l", loopback(free_tcp_port()), "--log-level", "error"],
                    env=env))
            t_end = time.monotonic() + 60
            for key in keys:
                while True:
                    try:
                        status_of(session, key)
                        break
                    except Exception:
                        if time.monotonic() > t_end:
                            raise
                        time.sleep(0.2)
            pub = subprocess.Popen([sys.executable, __file__, "--publisher", str(router),
                                    "--seconds", str(seconds + 8)], env=env)
            for key in keys:
                while status_of(session, key)["mode"] != "running":
                    if time.monotonic() > t_end:
                        raise SystemExit(f"{key}: the service never ran on the input")
                    time.sleep(0.1)
            time.sleep(1.0)
            st0 = [status_of(session, key) for key in keys]
            cpu0 = [proc_cpu_rss(p.pid)[0] for p in procs]
            host0 = cpu_times()
            load = os.getloadavg()[0]
            w0 = time.monotonic()
            kinds: Counter[str] = Counter()
            span = 0.0
            if scenario != "quiet":
                assert files is not None
                kinds, span = burst(session, scenario, files)
            time.sleep(max(0.0, w0 + seconds - time.monotonic()))
            st1 = [status_of(session, key) for key in keys]
            wall = time.monotonic() - w0
            cpu1 = [proc_cpu_rss(p.pid)[0] for p in procs]
            host = [y - x for x, y in zip(host0, cpu_times(), strict=True)]
    finally:
        for p in procs:
            p.send_signal(signal.SIGTERM)
        for p in procs:
            p.wait(timeout=30)
        if pub is not None:
            pub.kill()
            pub.wait()
    missed = [b["missed_ticks"] - a["missed_ticks"] for a, b in zip(st0, st1, strict=True)]
    ticks = [b["ticks"] - a["ticks"] for a, b in zip(st0, st1, strict=True)]
    return {"scenario": scenario, "ticks": ticks[0], "missed": missed[0],
            "twin_ticks": ticks[1], "twin_missed": missed[1],
            "versions": st1[0]["config"]["version"] - st0[0]["config"]["version"],
            "kinds": dict(kinds), "span": span, "wall": wall, "load": load,
            "cpu": 100 * (cpu1[0] - cpu0[0]) / wall, "twin_cpu": 100 * (cpu1[1] - cpu0[1]) / wall,
            "steal": 100 * host[7] / max(sum(host), 1),
            "busy_host": 100 * (1 - (host[3] + host[4]) / max(sum(host), 1))}


def report(args: argparse.Namespace, rows: list[dict[str, Any]], elapsed_s: float,
           host: str) -> str:
    lines = [
        f"Machine: {host}.",
        "",
        f"`python tools/bench_admin.py --seconds {args.seconds:g} --repeats {args.repeats}` "
        f"({elapsed_s / 60:.1f} min): two `motcomp run` at once with the example config (8 "
        "axes, 1 kHz, admin on, no real-time privileges), the target and its twin, on one "
        "publisher process sending all 8 axes at 1 kHz; per round one run of each scenario, "
        f"{args.seconds:g} s each, missed ticks counted over that window from each service's "
        "status: *quiet* nothing; *reloads* a burst of "
        f"{RELOADS} `reload --config` requests at once to the target (alternating two files "
        "with different gain rules: every accepted one swaps new gains in); *admin* a burst of "
        f"{ADMIN_REQUESTS} requests at once to the target (half status queries, half bypass "
        "toggles of rails_y).  Load: the 1-minute load average at the window's start; host "
        "busy: the share of the machine's CPU time in use over the window.",
        "",
        "| scenario | runs | target: missed of ticks (per run) | twin: missed of ticks (per run) "
        f"| target / twin: of the sums, median of the runs (target <= {RATIO_MAX:g}) | replies "
        "| last reply after (s) | config swaps | CPU % target / twin | load | host busy % |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    verdict = []
    for name in SCENARIOS:
        runs = [r for r in rows if r["scenario"] == name]
        if not runs:
            continue
        kinds: Counter[str] = Counter()
        for r in runs:
            kinds.update(r["kinds"])
        missed, twin = sum(r["missed"] for r in runs), sum(r["twin_missed"] for r in runs)
        rt = ratio(missed, twin)
        med = float(np.median([ratio(r["missed"], r["twin_missed"]) for r in runs]))
        met = "meets" if max(rt, med) <= RATIO_MAX else "misses"
        verdict.append(f"{name} {rt:.2f}x its twin (median of the runs {med:.2f}x)" + (
            f", {met} the target" if name != "quiet" else ""))
        lines.append(
            f"| {name} | {len(runs)} | {missed} of {sum(r['ticks'] for r in runs)} "
            f"({', '.join(str(r['missed']) for r in runs)}) | {twin} of "
            f"{sum(r['twin_ticks'] for r in runs)} "
            f"({', '.join(str(r['twin_missed']) for r in runs)}) | {rt:.2f}, {med:.2f} | "
            f"{', '.join(f'{k} {v}' for k, v in sorted(kinds.items())) or '-'} | "
            f"{max(r['span'] for r in runs):.2f} | {sum(r['versions'] for r in runs)} | "
            f"{max(r['cpu'] for r in runs):.0f} / {max(r['twin_cpu'] for r in runs):.0f} | "
            f"{min(r['load'] for r in runs):.2f}-{max(r['load'] for r in runs):.2f} | "
            f"{min(r['busy_host'] for r in runs):.0f}-{max(r['busy_host'] for r in runs):.0f} |")
    twins = sum(r["twin_missed"] for r in rows)
    twin_ticks = sum(r["twin_ticks"] for r in rows)
    lines += ["", f"The twins' own rate (all runs): {twins} missed of {twin_ticks} ticks "
              f"({100 * twins / max(twin_ticks, 1):.2f} %).  Reading: {'; '.join(verdict)}."]
    return "\n".join(lines)


INTERP_MODES = ("quiet", "inline", "child")


def interpreter_child(site: str, mode: str, seconds: float) -> dict[str, Any]:
    """Child process: ``Service.tick`` paced by the loop's clock in a thread (in-memory ports,
    a valid 8-axis frame each tick, GC frozen: the loop without transport) for ``seconds``,
    while the main thread prepares 20 reloads 1 s in: ``inline`` in this interpreter, the way
    reloads were prepared before (switch interval 5 ms), ``child`` by :class:`Preparer` (the
    service's way, switch interval 0.2 ms); nothing is swapped in.  The loop's missed ticks."""
    import gc
    import math
    import threading

    from motcomp.config import load_config
    from motcomp.core.axes import AXES
    from motcomp.io.memory import MemorySink, MemorySource
    from motcomp.io.wire import encode_input
    from motcomp.runtime.clock import DeadlineClock
    from motcomp.runtime.reload import prepare_config
    from motcomp.runtime.service import SWITCH_INTERVAL_S, Service

    path = Path(site)
    svc = Service(load_config(path), ZenohEndpoints(), config_path=path)
    if mode == "child":
        svc.preparer.start(wait=True)
        sys.setswitchinterval(SWITCH_INTERVAL_S)
    src = MemorySource(burst=True)
    svc.attach(src, [MemorySink(keep=1)])
    loop = svc.cfg.loop
    done = threading.Event()
    missed = []

    def run_loop() -> None:
        gc.collect()
        gc.freeze()
        clock = DeadlineClock(loop.rate_hz, loop.spin_us, sleep_max_us=loop.sleep_max_us)
        k = 0
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            deadline, _ = clock.wait()
            src.push(encode_input(k, k / 1e3, {a: 0.05 * math.sin(k / 300 + i)
                                               for i, a in enumerate(AXES)}))
            svc.tick(deadline, clock.skipped)
            k += 1
        missed.append(clock.missed)
        done.set()

    thread = threading.Thread(target=run_loop)
    thread.start()
    time.sleep(1.0)
    t0 = time.monotonic()
    files = [path.with_name("site-a.toml"), path.with_name("site-b.toml")]
    for k in range(RELOADS if mode != "quiet" else 0):
        if mode == "inline":
            prepare_config(svc.cfg, svc.axes, files[k % 2], svc.confinement)
        else:
            svc.preparer.prepare_config(svc.cfg, svc.axes, files[k % 2], svc.confinement)
    span = time.monotonic() - t0 if mode != "quiet" else 0.0
    thread.join()
    svc.preparer.close()
    return {"mode": mode, "missed": missed[0], "span": span,
            "load": os.getloadavg()[0]}


def interpreter_report(rows: list[dict[str, Any]], seconds: float) -> str:
    lines = [
        f"Machine: {machine()}.",
        "",
        f"`python tools/bench_admin.py --interpreter --seconds {seconds:g} --repeats "
        f"{len(rows) // len(INTERP_MODES)}`: the loop without transport (`Service.tick` paced by "
        "its clock in a thread, in-memory ports, GC frozen) in a process of its own for "
        f"{seconds:g} s, the main thread preparing {RELOADS} reloads 1 s in, nothing swapped: "
        "*inline* in the same interpreter, as before (switch interval 5 ms), *child* in the "
        "reader process, as now (switch interval 0.2 ms), *quiet* none; modes interleaved.",
        "",
        "| mode | runs | missed ticks (per run) | preparing 20 took (s, max) | load |",
        "|---|---|---|---|---|",
    ]
    for mode in INTERP_MODES:
        runs = [r for r in rows if r["mode"] == mode]
        lines.append(f"| {mode} | {len(runs)} | {sum(r['missed'] for r in runs)} "
                     f"({', '.join(str(r['missed']) for r in runs)}) | "
                     f"{max(r['span'] for r in runs):.2f} | "
                     f"{min(r['load'] for r in runs):.2f}-{max(r['load'] for r in runs):.2f} |")
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
    ap.add_argument("--save", type=Path, metavar="JSON", help="also save the runs' numbers")
    ap.add_argument("--report", type=Path, metavar="JSON",
                    help="no runs: the report of runs saved with --save")
    ap.add_argument("--interpreter", action="store_true",
                    help="instead: what preparing reloads costs a loop in the same process, "
                         "inline (as before) or in the reader process (as now)")
    ap.add_argument("--publisher", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--interp-child", nargs=2, metavar=("SITE", "MODE"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.publisher:
        publisher(args.publisher, args.seconds)
        return
    if args.interp_child:
        site, mode = args.interp_child
        print(json.dumps(interpreter_child(site, mode, args.seconds)))
        return
    if args.interpreter:
        rows = []
        with tempfile.TemporaryDirectory() as tmp:
            site, _, _ = write_configs(Path(tmp), args.seconds, False)
            for rep in range(args.repeats):
                for mode in INTERP_MODES if rep % 2 == 0 else INTERP_MODES[::-1]:
                    out = subprocess.run([sys.executable, __file__, "--interp-child", str(site),
                                          mode, "--seconds", str(args.seconds)],
                                         env=child_env(), capture_output=True, text=True,
                                         check=True)
                    rows.append(json.loads(out.stdout))
                    print(f"round {rep + 1} {mode}: {rows[-1]}", file=sys.stderr)
        text = interpreter_report(rows, args.seconds)
        print(text)
        if not args.no_write:
            write_section("admin-interpreter", text)
        return
    if args.quick:
        args.seconds, args.repeats = 10.0, 1
    if args.report is not None:
        saved = json.loads(args.report.read_text())
        args.seconds, args.repeats = saved["seconds"], saved["repeats"]
        text = report(args, saved["rows"], saved["elapsed_s"], saved["machine"])
        print(text)
        if not args.no_write:
            write_section("admin", text)
        return
    scenarios = [s for s in SCENARIOS if s == "quiet" or not args.only or s in args.only]
    print(f"{args.repeats * len(scenarios)} runs of {args.seconds:g} s: about "
          f"{args.repeats * len(scenarios) * (args.seconds + 15) / 60:.0f} min", file=sys.stderr)
    t0 = time.monotonic()
    host = machine()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeats):
            order = scenarios if rep % 2 == 0 else scenarios[::-1]
            for name in order:
                row = run(args.seconds, name, Path(tmp))
                print(f"round {rep + 1} {name}: missed {row['missed']} of {row['ticks']}, twin "
                      f"{row['twin_missed']} of {row['twin_ticks']}; {row['kinds']}",
                      file=sys.stderr)
                rows.append(row)
    elapsed = time.monotonic() - t0
    if args.save is not None:
        args.save.write_text(json.dumps({"seconds": args.seconds, "repeats": args.repeats,
                                         "elapsed_s": elapsed, "machine": host, "rows": rows}))
    text = report(args, rows, elapsed, host)
    print(text)
    if not args.no_write:
        write_section("admin", text)


if __name__ == "__main__":
    main()
