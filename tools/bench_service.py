"""Benchmark: the service with 8 axes at 1 kHz, three processes on loopback.

A publisher process sends setpoints for all 8 axes at 1 kHz (absolute deadlines, ``t`` stamped
just before ``put``); ``motcomp run`` compensates them; this process receives the outputs and,
matching each output's ``src_seq`` with the input's publish time, measures the in->out latency.
The service's own status gives tick compute time and lateness (over the steady part: its status
window is set 2 s shorter than the run, which leaves the start-ups out) and missed ticks (counted
from the publisher's first frame; those of the start-ups apart); /proc gives its CPU time and
RSS.  Run once on the service's clock and once with
``loop.sync_to_input`` (ticking on input arrival).  Writes the "service" section of
docs/BENCHMARKS.md.

Scheduling modes: the example config as it is (normal scheduling, the loop thread's short
slice ``loop.slice_us`` and naps of at most ``loop.sleep_max_us``); with ``--plain`` also the
kernel's default slice and one sleep per tick (what the two buy); with ``--rt`` also SCHED_FIFO
50 on a pinned core (needs the privilege).  Every run is followed by nothing; then the loop's
clock alone is timed in each mode (the stalls the machine itself imposes).

Usage: ``python tools/bench_service.py [--seconds 60] [--repeats 3] [--plain] [--rt]``
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from _bench import machine, write_section

from motcomp.core.axes import AXES
from motcomp.io.zenoh_io import ZenohEndpoints, first_reply, free_tcp_port, loopback, open_session
from motcomp.resources import config_file

SPIN_US: float | None = None
SCHEDS = {  # scheduling mode -> [loop] settings
    "config": "",
    "plain": "slice_us = 0\nsleep_max_us = 0\n",
    "rt": "realtime_priority = 50\ncpu = 1\n",
    "pykernel": "",  # the config as it is, with the tick's Python code (MOTCOMP_KERNEL=python)
    "nowarm": "warm_up = false\n",
}


def publisher(port: int, seconds: float) -> None:
    """Child process: 8 axes at 1 kHz on absolute deadlines."""
    from motcomp.runtime.clock import DeadlineClock

    with open_session(ZenohEndpoints(connect=(loopback(port),))) as session:
        pub = session.declare_publisher("sim/motion/setpoint", express=True)
        time.sleep(1.0)
        clock = DeadlineClock(1000.0, 200.0, sleep_max_us=100.0)
        pack = msgpack.Packer().pack
        for k in range(int(seconds * 1000)):
            clock.wait()
            t = k / 1000.0
            pos = {a: (0.3 if a.startswith("rails") else 0.05) * math.sin(
                2 * math.pi * 0.3 * t + i) for i, a in enumerate(AXES)}
            pub.put(pack({"seq": k, "t": time.time(), "pos": pos}))
        pub.undeclare()


def tick_in_process(ticks: int = 20000, gap_s: float = 0.0, kernel: str = "c",
                    warm: bool = False) -> tuple[float, float]:
    """(p50, p99) us of ``Service.tick`` with in-memory adapters: the work of a tick without
    transport or other processes, with the given compensator kernel; in a tight loop, or
    ``gap_s`` after the last tick, waited as the service's loop waits (naps of 100 us, then a
    spin of 200 us, the shadow tick first if ``warm``), which shows what waking from a sleep
    costs and what the warm-up buys back."""
    from motcomp.config import load_config
    from motcomp.io import wire
    from motcomp.runtime import shaper
    from motcomp.runtime.service import Service

    old = os.environ.get("MOTCOMP_KERNEL")
    saved = wire._cwire, shaper._cshaper
    os.environ["MOTCOMP_KERNEL"] = kernel
    if kernel == "python":  # all of the tick's code in Python, as MOTCOMP_KERNEL=python at start
        wire._cwire = shaper._cshaper = None
    try:
        svc = Service(load_config(config_file("motcomp.toml")), ZenohEndpoints())
        return _time_ticks(svc, ticks, gap_s, warm)
    finally:
        os.environ.pop("MOTCOMP_KERNEL") if old is None else os.environ.update(
            MOTCOMP_KERNEL=old)
        wire._cwire, shaper._cshaper = saved


def _time_ticks(svc: Any, ticks: int, gap_s: float, warm: bool) -> tuple[float, float]:
    from motcomp.io.memory import MemorySink, MemorySource
    from motcomp.io.wire import encode_input

    src = MemorySource(latest_only=True)
    svc.attach(src, [MemorySink(keep=1)])
    frames = [encode_input(k, k / 1000, {a: 0.05 * math.sin(k / 300 + i)
                                         for i, a in enumerate(AXES)}) for k in range(ticks)]
    times = np.empty(ticks)
    if warm:
        svc._shadow = svc.make_shadow()
    perf = time.perf_counter_ns
    for k, f in enumerate(frames):
        src.push(f)
        if gap_s:
            deadline = perf() + int(gap_s * 1e9)
            while deadline - perf() > 200_000:
                time.sleep(0.0001)
            if warm:
                svc.warm_up()
            while perf() < deadline:
                pass
        t0 = time.perf_counter_ns()
        svc.tick(k * 1_000_000)
        times[k] = time.perf_counter_ns() - t0
    t = times[ticks // 10:] / 1e3
    return float(np.percentile(t, 50)), float(np.percentile(t, 99))


BARE_MODES = (  # (slice_us, sleep_max_us, SCHED_FIFO) of the clock-alone probe
    (0.0, 0.0, False), (100.0, 0.0, False), (0.0, 100.0, False), (100.0, 100.0, False),
    (0.0, 0.0, True))


def bare_clock(seconds: float, mode: int) -> dict[str, Any]:
    """Child process: the loop's clock alone (sleep, then spin to each 1 kHz deadline, no work,
    no I/O) in :data:`BARE_MODES` ``[mode]``: the stalls the machine itself imposes on a thread
    that sleeps between ticks."""
    from motcomp.runtime.clock import DeadlineClock
    from motcomp.runtime.rt import set_realtime, set_slice

    slice_us, nap_us, rt = BARE_MODES[mode]
    report = set_realtime(50) if rt else set_slice(slice_us)
    report += f"; naps of {nap_us:g} us" if nap_us else "; one sleep"
    n = int(seconds * 1000)
    late = np.empty(n)
    clock = DeadlineClock(1000.0, 200.0, sleep_max_us=nap_us)
    for k in range(n):
        deadline, now = clock.wait()
        late[k] = (now - deadline) / 1e3
    return {"slice": report, "missed": clock.missed, "late_p999": float(np.percentile(late, 99.9)),
            "late_max": float(late.max())}


def bare_runs(seconds: float, repeats: int, rt: bool) -> list[dict[str, Any]]:
    """:func:`bare_clock` in subprocesses, each mode (SCHED_FIFO only if ``rt``), interleaved;
    one row per mode: the median over the runs of missed ticks per minute and of lateness p99.9,
    and the largest lateness of all runs."""
    import json

    runs = []
    for _ in range(repeats):
        for mode, m in enumerate(BARE_MODES):
            if m[2] and not rt:
                continue
            p = subprocess.run([sys.executable, __file__, "--bare", str(mode), "--seconds",
                                str(seconds)], env=child_env(), capture_output=True, text=True,
                               check=True)
            runs.append(json.loads(p.stdout))
    out = []
    for name in dict.fromkeys(r["slice"] for r in runs):
        mine = [r for r in runs if r["slice"] == name]
        out.append({"slice": name, "runs": len(mine),
                    "missed_min": float(np.median([r["missed"] for r in mine])) * 60 / seconds,
                    "missed_worst": max(r["missed"] for r in mine) * 60 / seconds,
                    "late_p999": float(np.median([r["late_p999"] for r in mine])),
                    "late_max": max(r["late_max"] for r in mine)})
    return out


def proc_cpu_rss(pid: int) -> tuple[float, float]:
    """(user+system CPU seconds, RSS MB) of a process."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    cpu = (int(fields[11]) + int(fields[12])) / ticks
    rss = 0.0
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            rss = int(line.split()[1]) / 1024
    return cpu, rss


def cpu_times() -> list[int]:
    """The machine's aggregate CPU times (user, nice, system, idle, iowait, irq, softirq, steal)."""
    return [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:9]]


def child_env() -> dict[str, str]:
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    return env


def run_once(seconds: float, sync: bool, sched: str, tmp: Path) -> dict[str, Any]:
    import zenoh

    p_svc, p_me = free_tcp_port(), free_tcp_port()
    cfg = tmp / f"bench-{sync}-{sched}.toml"
    spin = (f"spin_us = {SPIN_US:g}\n" if SPIN_US is not None else "") + SCHEDS[sched]
    cfg.write_text(f'include = ["{config_file("motcomp.toml")}"]\n[loop]\nsync_to_input = '
                   f'{"true" if sync else "false"}\n{spin}[status]\nwindow_s = '
                   f'{max(seconds - 2, 1):g}\n')  # the steady part: the start-up out
    env = child_env()
    if sched == "pykernel":
        env["MOTCOMP_KERNEL"] = "python"
    svc = subprocess.Popen([sys.executable, "-m", "motcomp", "run", "--config", str(cfg), "-l",
                            loopback(p_svc), "--log-level", "warning"], env=env)
    try:
        ep = ZenohEndpoints(connect=(loopback(p_svc),), listen=(loopback(p_me),))
        with open_session(ep) as session:
            sub_in = session.declare_subscriber("sim/motion/setpoint",
                                                zenoh.handlers.FifoChannel(500_000))
            sub_out = session.declare_subscriber("platform/setpoint",
                                                 zenoh.handlers.FifoChannel(500_000))
            t_end = time.monotonic() + 30
            while time.monotonic() < t_end:
                try:
                    first_reply(session, "motcomp/status", None, 1.0)
                    break
                except Exception:
                    time.sleep(0.2)
            cpu0, _ = proc_cpu_rss(svc.pid)
            host0 = cpu_times()
            w0 = time.monotonic()
            pub = subprocess.Popen([sys.executable, __file__, "--publisher", str(p_svc),
                                    "--seconds", str(seconds)], env=env)
            sent: dict[int, float] = {}
            lat: list[float] = []
            seen: set[int] = set()
            drain_until = math.inf
            start: dict[str, Any] | None = None
            while time.monotonic() < drain_until:
                if drain_until == math.inf and pub.poll() is not None:
                    drain_until = time.monotonic() + 0.5  # the last outputs are in flight
                while (s := sub_in.try_recv()) is not None:
                    f = msgpack.unpackb(s.payload.to_bytes())
                    sent[f["seq"]] = f["t"]
                    if start is None:  # the publisher is up: its start-up ends here
                        start = msgpack.unpackb(first_reply(session, "motcomp/status", None, 3.0))
                while (s := sub_out.try_recv()) is not None:
                    now = time.time()
                    f = msgpack.unpackb(s.payload.to_bytes())
                    src = f["src_seq"]
                    if src >= 0 and src not in seen and src in sent:
                        seen.add(src)
                        lat.append(now - sent[src])
                time.sleep(0.0002)
            wall = time.monotonic() - w0
            cpu1, rss = proc_cpu_rss(svc.pid)
            host = [b - a for a, b in zip(host0, cpu_times(), strict=True)]
            st = msgpack.unpackb(first_reply(session, "motcomp/status", None, 3.0))
            sub_in.undeclare()
            sub_out.undeclare()
    finally:
        svc.send_signal(signal.SIGTERM)
        svc.wait(timeout=30)
    if start is None:
        raise SystemExit("the publisher's frames never arrived")
    lat_ms = np.array(lat) * 1e3
    loop = st["loop"]
    return {
        "sync": sync, "ticks": st["ticks"] - start["ticks"],
        "missed": st["missed_ticks"] - start["missed_ticks"], "missed_start": start["missed_ticks"],
        "compute_p50": loop["compute_p50_us"], "compute_p99": loop["compute_p99_us"],
        "tick_p50": loop["tick_p50_us"], "tick_p99": loop["tick_p99_us"],
        "io_p50": loop["io_p50_us"], "io_p99": loop["io_p99_us"], "kernel": st["kernel"],
        "late_p50": loop["late_p50_us"], "late_p99": loop["late_p99_us"],
        "late_p999": loop["late_p999_us"], "late_max": loop["late_max_us"],
        "lat_p50": float(np.percentile(lat_ms, 50)), "lat_p99": float(np.percentile(lat_ms, 99)),
        "lat_n": lat_ms.size, "cpu": 100 * (cpu1 - cpu0) / wall, "rss": rss,
        "accepted": st["frames"]["accepted"], "steal": 100 * host[7] / max(sum(host), 1),
        "sched": sched, "realtime": st.get("realtime", ""),
    }


TARGETS = (  # (label, row key, bound): a row meets a target when its value <= bound
    ("compute p99 <= 50 us", "compute_p99", 50.0),
    ("lateness p99.9 <= 500 us", "late_p999", 500.0),
    ("0 missed ticks", "missed", 0.0),
    ("in->out p99 <= 1.5 ms", "lat_p99", 1.5),
    ("RSS <= 150 MB", "rss", 150.0),
)


def mode_medians(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per mode (real-time, sync), the median of each number over that mode's runs."""
    out = []
    for mode in dict.fromkeys((r["sched"], r["sync"]) for r in rows):
        runs = [r for r in rows if (r["sched"], r["sync"]) == mode]
        out.append({k: float(np.median([r[k] for r in runs]))
                    if isinstance(v, int | float) and not isinstance(v, bool) else v
                    for k, v in runs[0].items()})
    return out


def sched_name(r: dict[str, Any]) -> str:
    """How the loop thread was scheduled, from the service's own report."""
    parts = [p for p in r["realtime"].split("; ") if p and p != "not pinned"
             and not p.startswith(("normal scheduling", "slice not set"))]
    return "; ".join(parts)


def mode_name(r: dict[str, Any]) -> str:
    kernel = ", Python code" if r["kernel"] == "python" else ""
    warm = ", no warm-up" if r["sched"] == "nowarm" else ""
    return ("sync to input" if r["sync"] else "own clock") + f", {sched_name(r)}{kernel}{warm}"


def verdict(rows: list[dict[str, Any]]) -> str:
    """Which targets each mode meets and misses, from its numbers."""
    out = []
    for r in rows:
        met = [f"{label} ({r[key]:.4g})" for label, key, bound in TARGETS if r[key] <= bound]
        unmet = [f"{label} ({r[key]:.4g})" for label, key, bound in TARGETS if r[key] > bound]
        out.append(f"{mode_name(r)} meets {', '.join(met) or 'none'}; misses "
                   f"{', '.join(unmet) or 'none'}.")
    return " ".join(out)


def missed_reading(rows: list[dict[str, Any]]) -> str:
    """What the scheduling modes say about the missed ticks (medians per mode, own clock and
    sync to input)."""
    by = {sched: [r["missed"] for r in rows if r["sched"] == sched] for sched in SCHEDS}

    def fmt(ms: list[float]) -> str:
        return " / ".join(f"{m:g}" for m in ms)

    out = []
    if by["plain"] and by["config"]:
        out.append(f"Missed ticks (own clock / sync to input) with the config's short slice and "
                   f"naps: {fmt(by['config'])}; with the kernel's default slice and one sleep "
                   f"per tick: {fmt(by['plain'])}.")
    if by["rt"]:
        out.append(f"With SCHED_FIFO on a pinned core: {fmt(by['rt'])} against "
                   f"{fmt(by['config'])}.")
    if not by["rt"]:
        out.append("Run with --rt to see what SCHED_FIFO on a pinned core changes.")
    return " ".join(out)


def bare_reading(bare: list[dict[str, Any]]) -> str:
    """What the clock-alone probe says (its rows in :data:`BARE_MODES` order)."""
    by = {b["slice"]: b for b in bare}
    plain, config = bare[0], bare[3]
    out = (f"The clock alone missed a median {plain['missed_min']:.0f} ticks per minute with the "
           f"kernel's defaults and one sleep, {config['missed_min']:.0f} with the config's "
           f"slice and naps (slice alone {bare[1]['missed_min']:.0f}, naps alone "
           f"{bare[2]['missed_min']:.0f}): stalls that no work of the service causes; the "
           "slice lets the loop preempt other normal-priority work on its core when it wakes, "
           "the naps keep an idle virtual CPU from being handed back to the host "
           "(docs/DEPLOYMENT.md).")
    rt = [b for name, b in by.items() if name.startswith("SCHED_FIFO")]
    if rt:
        out += (f"  Under SCHED_FIFO it missed a median {rt[0]['missed_min']:.0f} per minute "
                f"(worst run {rt[0]['missed_worst']:.0f}): what the host takes, which no "
                "priority inside the machine removes.")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--publisher", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--bare", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--repeats", type=int, default=1,
                    help="runs of each mode, interleaved; the reading uses their medians")
    ap.add_argument("--spin-us", type=float, help="loop.spin_us of the service (default: config)")
    ap.add_argument("--plain", action="store_true",
                    help="also run with the kernel's default slice and one sleep per tick "
                         "(loop.slice_us = 0, loop.sleep_max_us = 0)")
    ap.add_argument("--pykernel", action="store_true",
                    help="also run the config with the compensator's Python kernel "
                         "(MOTCOMP_KERNEL=python): what the compiled one buys")
    ap.add_argument("--nowarm", action="store_true",
                    help="also run the config without the shadow tick (loop.warm_up = false)")
    ap.add_argument("--rt", action="store_true",
                    help="also run with SCHED_FIFO 50 and the loop pinned to CPU 1 (needs the "
                         "privilege; the service reports whether it got it)")
    args = ap.parse_args()
    global SPIN_US
    SPIN_US = args.spin_us
    if args.publisher:
        publisher(args.publisher, args.seconds)
        return
    if args.bare is not None:
        import json

        print(json.dumps(bare_clock(args.seconds, args.bare)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        scheds = (["plain"] * args.plain + ["config"] + ["nowarm"] * args.nowarm
                  + ["pykernel"] * args.pykernel + ["rt"] * args.rt)
        rows = []
        for rep in range(args.repeats):  # interleaved, so slow spells of the host spread out
            for sched in scheds:
                for sync in (False, True):
                    rows.append(dict(run_once(args.seconds, sync, sched, Path(tmp)),
                                     run=rep + 1))
    rows.sort(key=lambda r: (scheds.index(r["sched"]), r["sync"], r["run"]))
    med = mode_medians(rows)
    lines = [
        f"Machine: {machine()}.",
        "",
        f"`python tools/bench_service.py --seconds {args.seconds:g} --repeats {args.repeats}"
        f"{' --plain' if args.plain else ''}{' --nowarm' if args.nowarm else ''}"
        f"{' --pykernel' if args.pykernel else ''}"
        f"{' --rt' if args.rt else ''}`: "
        "`motcomp run` with the example config (8 axes, 1 kHz; no real-time privileges unless "
        "the mode names SCHED_FIFO; slice and naps are the loop thread's, see "
        "docs/DEPLOYMENT.md), a publisher process (naps of 100 us) sending "
        "all 8 axes at 1 kHz, this process receiving the outputs.  Ticks and missed ticks count "
        "from the publisher's first frame (start-up: the ticks missed before it, while the "
        "service and the publisher started); tick times are the service's own, over the last "
        f"{max(args.seconds - 2, 1):g} s (the maxima since the service started); latency = "
        "output received - input published (same clock); steal = the share of this virtual "
        "machine's CPU time taken by the host during the run.  Tick times: *compute* is the "
        "tick's own work (validation, reference, compensator, saturation verdicts, encoding), "
        "*io* its calls into zenoh (taking the newest input, sending the output), *whole* the "
        "two together (percentiles of each series apart: they do not add up).",
        "",
        "| mode | ticks | missed (start-up) | compute p50 / p99 (us) | io p50 / p99 (us) "
        "| whole tick p50 / p99 (us) "
        "| lateness p50 / p99 / p99.9 / max (us) | in->out p50 / p99 (ms) | CPU % | RSS (MB) "
        "| steal % |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        mode = mode_name(r)
        if args.repeats > 1:
            mode += f", run {r['run']}"
        lines.append(
            f"| {mode} | {r['ticks']} | {r['missed']} ({r['missed_start']}) | "
            f"{r['compute_p50']:.0f} / "
            f"{r['compute_p99']:.0f} | {r['io_p50']:.0f} / {r['io_p99']:.0f} | "
            f"{r['tick_p50']:.0f} / {r['tick_p99']:.0f} | "
            f"{r['late_p50']:.0f} / {r['late_p99']:.0f} / "
            f"{r['late_p999']:.0f} / {r['late_max']:.0f} | {r['lat_p50']:.2f} / "
            f"{r['lat_p99']:.2f} | {r['cpu']:.0f} | {r['rss']:.0f} | {r['steal']:.1f} |")
    bare = bare_runs(6.0, 4 * args.repeats, args.rt)
    lines += [
        "",
        f"The loop's clock alone, in a process of its own while nothing else of the benchmark "
        f"runs (sleep, then spin to each 1 kHz deadline; no work, no I/O): {bare[0]['runs']} "
        "runs of 6 s per mode, interleaved; medians over the runs, and the worst run:",
        "",
        "| scheduling | missed per minute: median (worst run) | lateness p99.9: median (us) "
        "| lateness max (us) |",
        "|---|---|---|---|",
        *(f"| {b['slice']} | {b['missed_min']:.0f} ({b['missed_worst']:.0f}) | "
          f"{b['late_p999']:.0f} | {b['late_max']:.0f} |" for b in bare),
    ]
    runs: dict[tuple[str, float, bool], list[tuple[float, float]]] = {}
    for _ in range(3):  # interleaved; medians
        for k in ("c", "python"):
            for gap, warm in ((0.0, False), (0.001, False), (0.001, True)):
                runs.setdefault((k, gap, warm), []).append(
                    tick_in_process(20000 if gap == 0 else 5000, gap, k, warm))
    ticks = {key: (float(np.median([v[0] for v in vals])),
                   float(np.median([v[1] for v in vals]))) for key, vals in runs.items()}

    def fmt(key: tuple[str, float, bool]) -> str:
        return f"{ticks[key][0]:.1f} / {ticks[key][1]:.1f}"

    p50 = ticks["c", 0.0, False][0]
    s50 = ticks["c", 0.001, False][0]
    lines += [
        "",
        "The same tick in this process, in-memory adapters (decode and validate, reference, "
        "8-axis compensator, flags, encode; no transport), p50 / p99 in us, medians of 3 "
        "interleaved runs (20 000 ticks back to back, 5 000 one per millisecond):",
        "",
        "| code | back to back | 1 ms apart, as the loop waits (naps, spin) | 1 ms apart, "
        "shadow tick before the spin (`loop.warm_up`) |",
        "|---|---|---|---|",
        *(f"| {name} | {fmt((k, 0.0, False))} | {fmt((k, 0.001, False))} | "
          f"{fmt((k, 0.001, True))} |"
          for k, name in (("c", "compiled"), ("python", "Python"))),
        "",
        "Targets (2-core machine, no real-time privileges): compute p99 <= 50 us, "
        "lateness p99.9 <= 500 us, 0 missed ticks, in->out p99 <= period + 0.5 ms (1.5 ms), "
        "RSS <= 150 MB.",
        "",
        f"Reading ({'medians of each mode' if args.repeats > 1 else 'each run'}): "
        f"{verdict(med)}  The service's tick (compute) "
        f"costs {med[0]['compute_p50'] / p50:.1f}x the same tick in a tight loop, and the "
        f"in-process tick after a sleep already costs {s50 / p50:.1f}x: on this virtual "
        "machine a thread that sleeps between ticks resumes on cold caches; zenoh's calls, "
        "which wake zenoh's own threads on the two cores the three processes share, do the "
        f"rest.  Missed ticks come from rare stalls of several milliseconds (the maxima). "
        f"{missed_reading(med)}  {bare_reading(bare)}  Tick on input arrival (sync_to_input) "
        "when the source runs at the loop rate: it cuts the sampling latency of the own clock.",
    ]
    steal = [r["steal"] for r in rows]
    if max(steal) > 1.0:
        lines[-1] += (f"  The host took {min(steal):.1f}-{max(steal):.1f} % of this virtual "
                      "machine's CPU during these runs (steal): such runs measure the host as "
                      "much as the service: compare runs with little steal.")
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        write_section("service", text)


if __name__ == "__main__":
    main()
