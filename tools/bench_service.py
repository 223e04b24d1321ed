"""Benchmark: the service with 8 axes at 1 kHz, three processes on loopback, each run paired with
the loop's clock alone.

A publisher process sends setpoints for all 8 axes at 1 kHz (absolute deadlines, ``t`` stamped
just before ``put``); ``motcomp run`` compensates them; this process receives the outputs and,
matching each output's ``src_seq`` with the input's publish time, measures the in->out latency.
The service's own status gives tick compute time and lateness (over the steady part: its status
window is set 2 s shorter than the run) and missed ticks (counted from the publisher's first
frame; those of the start-up apart); /proc gives its CPU time and RSS.  Each mode runs on the
service's clock and with ``loop.sync_to_input`` (ticking on input arrival).

Every service run is paired with a run of the loop's clock alone, as long and with the same loop
settings (scheduling, slice, naps, spin; a process of its own, no work, no I/O, nothing else of
the benchmark running), the two in alternating order: the clock's missed ticks are the stalls
the machine imposes, and the ratio service / clock what the service adds (target <= 1.5).  Each
pair also runs the *transport alone* (the loop's clock, taking the input and putting a fixed
output on the service's ports, no tick) with the same publisher and receiver: its CPU share is
what this host's clock and transport take by themselves, beside the service's (target <= 15 %
of a core).  Once per repeat, ``Service.tick`` with in-memory ports is timed in a process of
its own, back to back and paced at 1 kHz as the loop waits, and ``tick.step`` alone back to
back on the same frames (target: ``Service.tick`` <= 1.3x ``tick.step``).  Repeats are
interleaved; the reading uses medians.  Writes the "service" section of docs/BENCHMARKS.md.

Scheduling modes: the example config as it is (normal scheduling, the loop thread's short slice
``loop.slice_us`` and naps of at most ``loop.sleep_max_us``); with ``--plain`` also the kernel's
default slice and one sleep per tick; with ``--rt`` also SCHED_FIFO 50 on CPU 1 (needs the
privilege; the service reports whether it got it).

Usage: ``python tools/bench_service.py [--seconds 40] [--repeats 3] [--plain] [--rt] [--quick]``
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections import deque
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from _bench import machine, process_cpu_s, write_section

from motcomp.core.axes import AXES
from motcomp.io.zenoh_io import (
    ZenohEndpoints,
    first_reply,
    free_tcp_port,
    loopback,
    open_session,
    use_one_zenoh_thread,
)
from motcomp.resources import config_file

SCHEDS = {  # scheduling mode -> [loop] settings over the example config
    "config": "",
    "plain": "slice_us = 0\nsleep_max_us = 0\n",
    "rt": "realtime_priority = 50\ncpu = 1\n",
    "idle": "cpu_latency_us = -1\n",
}
RATIO_MAX = 1.5
"""Target: missed ticks of the service / missed ticks of the clock alone."""
SERVICE_TICK_MAX = 1.3
"""Target: ``Service.tick`` / ``tick.step`` back to back (medians)."""
CPU_MAX = 15.0
"""Target: the service's CPU share at 1 kHz with 8 axes (% of one core)."""
PAIR_OVERHEAD_S = 8.0
"""About what a pair costs beyond its three runs (start-ups, parking, status queries)."""


# --- child processes --------------------------------------------------------------------------
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


def schedule_like_loop(loop: Any) -> str:
    """Schedule the calling thread as the service schedules its loop thread, and hold the CPUs'
    wake-up latency as it does until this process ends; the same report."""
    from motcomp.runtime.rt import schedule_loop

    return schedule_loop(loop)[0]


def bare_clock(cfg_path: str, seconds: float) -> dict[str, Any]:
    """Child process: the loop's clock alone with the config's loop settings (sleep, then spin
    to each deadline, no work, no I/O): the stalls the machine itself imposes."""
    from motcomp.config import load_config
    from motcomp.runtime.probe import measure_clock

    loop = load_config(Path(cfg_path)).loop
    report = schedule_like_loop(loop)
    r = measure_clock(loop.rate_hz, loop.spin_us, loop.sleep_max_us,
                      ticks=int(seconds * loop.rate_hz))
    return {"realtime": report, "missed": r.missed, "late_p999": r.late_p999_us,
            "late_max": r.late_max_us}


def transport_alone(cfg_path: str, port: int, seconds: float) -> None:
    """Child process: what the service's loop does without its tick -- the config's clock and
    scheduling, taking the input frames (polling them in input-synchronous mode) and putting one
    fixed output frame a tick on the service's ports, listening where the service listens: the
    CPU that the clock and the transport take by themselves on this host."""
    import threading

    from motcomp.config import load_config
    from motcomp.io.wire import encode_output
    from motcomp.io.zenoh_io import ZenohSink, ZenohSource
    from motcomp.runtime.clock import DeadlineClock

    cfg = load_config(Path(cfg_path))
    loop = cfg.loop
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    payload = encode_output(0, time.time(), 0, [0.0] * len(AXES), [])

    def run(src: ZenohSource, sink: ZenohSink) -> None:
        schedule_like_loop(loop)
        clock = DeadlineClock(loop.rate_hz, loop.spin_us, sleep_max_us=loop.sleep_max_us)
        end = time.monotonic() + seconds
        while not stop.is_set() and time.monotonic() < end:
            if loop.sync_to_input:
                clock.wait_or_poll(lambda: bool(src.drain()), loop.poll_us)
            else:
                clock.wait()
            src.drain()
            sink.put(payload)

    with open_session(ZenohEndpoints(listen=(loopback(port),))) as session:
        src = ZenohSource(session, cfg.input.key)
        sink = ZenohSink(session, cfg.output.key)
        thread = threading.Thread(target=run, args=(src, sink), name="loop")
        thread.start()
        thread.join()
        src.close()
        sink.close()


def tick_in_process(cfg_path: str, ticks: int) -> dict[str, list[float]]:
    """Child process: (p50, p99) us of ``Service.tick`` with in-memory ports (a valid 8-axis
    frame in every tick, the encoded output out; no transport), back to back and paced at the
    config's rate as the loop waits (its scheduling, naps and spin), and of ``tick.step`` alone
    back to back on the same frames; GC frozen as in the loop.
    The tick instants are the ideal grid in both, so the two do the same work."""
    import gc

    from motcomp.config import load_config
    from motcomp.core.tick import step
    from motcomp.io.memory import MemorySink, MemorySource
    from motcomp.io.wire import encode_input
    from motcomp.runtime.clock import DeadlineClock
    from motcomp.runtime.service import Service

    cfg = load_config(Path(cfg_path))
    schedule_like_loop(cfg.loop)
    period_ns = round(1e9 / cfg.loop.rate_hz)
    settle = round(2 * cfg.loop.rate_hz)  # past the shaper's start-up ramp, untimed
    frames = [encode_input(k, k * period_ns / 1e9, {a: 0.05 * math.sin(k / 300 + i)
                                                    for i, a in enumerate(AXES)})
              for k in range(settle + ticks)]
    perf = time.perf_counter_ns
    out = {}
    for name, paced in (("tight", False), ("paced", True)):
        svc = Service(cfg, ZenohEndpoints())
        src = MemorySource(burst=True)
        svc.attach(src, [MemorySink(keep=1)])
        gc.collect()
        gc.freeze()
        times = np.empty(ticks)
        clock = None
        for k, frame in enumerate(frames):
            src.push(frame)
            if paced and k >= settle:
                if clock is None:
                    clock = DeadlineClock(cfg.loop.rate_hz, cfg.loop.spin_us,
                                          sleep_max_us=cfg.loop.sleep_max_us)
                clock.wait()
            t0 = perf()
            svc.tick(k * period_ns)
            if k >= settle:
                times[k - settle] = perf() - t0
        gc.unfreeze()
        if svc.state.accepted != len(frames):
            raise SystemExit(f"the tick accepted {svc.state.accepted} of {len(frames)} frames")
        out[name] = [float(np.percentile(times, 50)) / 1e3, float(np.percentile(times, 99)) / 1e3]
    # tick.step alone on the same frames, as Service.tick calls it (its state and parameters)
    svc = Service(cfg, ZenohEndpoints())
    gc.collect()
    gc.freeze()
    times = np.empty(ticks)
    for k, frame in enumerate(frames):
        t0 = perf()
        step(svc.state, svc.params, k * period_ns, [frame], 0, k * period_ns)
        if k >= settle:
            times[k - settle] = perf() - t0
    gc.unfreeze()
    if svc.state.accepted != len(frames):
        raise SystemExit(f"tick.step accepted {svc.state.accepted} of {len(frames)} frames")
    out["step"] = [float(np.percentile(times, 50)) / 1e3, float(np.percentile(times, 99)) / 1e3]
    return out


# --- this process -----------------------------------------------------------------------------
def proc_cpu_rss(pid: int) -> tuple[float, float]:
    """(user+system CPU seconds, RSS MB) of a process."""
    cpu = process_cpu_s(pid)
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


def child_json(*args: str) -> Any:
    """Run this script as a child with ``args``; its JSON answer."""
    p = subprocess.run([sys.executable, __file__, *args], env=child_env(), capture_output=True,
                       text=True, check=True)
    return json.loads(p.stdout)


def write_config(tmp: Path, sched: str, sync: bool, seconds: float,
                 spin_us: float | None) -> Path:
    """The example config with the mode's [loop] settings and a status window over the steady
    part of a run (the start-up left out)."""
    cfg = tmp / f"bench-{sched}-{sync}.toml"
    spin = f"spin_us = {spin_us:g}\n" if spin_us is not None else ""
    cfg.write_text(f'include = ["{config_file("motcomp.toml")}"]\n[loop]\nsync_to_input = '
                   f'{"true" if sync else "false"}\n{spin}{SCHEDS[sched]}[status]\nwindow_s = '
                   f'{max(seconds - 2, 1):g}\n')
    return cfg


def run_service(seconds: float, cfg: Path) -> dict[str, Any]:
    """One run of ``motcomp run`` with ``cfg``, the publisher and this process as receiver."""
    import zenoh

    p_svc, p_me = free_tcp_port(), free_tcp_port()
    env = child_env()
    svc = subprocess.Popen([sys.executable, "-m", "motcomp", "run", "--config", str(cfg), "-l",
                            loopback(p_svc), "--log-level", "warning"], env=env)
    try:
        ep = ZenohEndpoints(connect=(loopback(p_svc),), listen=(loopback(p_me),))
        with open_session(ep) as session:
            sub_in = session.declare_subscriber("sim/motion/setpoint",
                                                zenoh.handlers.FifoChannel(500_000))
            # outputs are stamped as zenoh delivers them (its thread), not when this loop next
            # polls: the latency measured is the service's, not this process' polling
            arrived: deque[tuple[float, bytes]] = deque()
            sub_out = session.declare_subscriber(
                "platform/setpoint",
                lambda s: arrived.append((time.time(), s.payload.to_bytes())))
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
            t_start = 0.0
            while time.monotonic() < drain_until:
                if drain_until == math.inf and pub.poll() is not None:
                    drain_until = time.monotonic() + 0.5  # the last outputs are in flight
                while (s := sub_in.try_recv()) is not None:
                    f = msgpack.unpackb(s.payload.to_bytes())
                    sent[f["seq"]] = f["t"]
                    if start is None:  # the publisher is up: its start-up ends here
                        start = msgpack.unpackb(first_reply(session, "motcomp/status", None, 3.0))
                        t_start = time.monotonic()
                while arrived:
                    now, payload = arrived.popleft()
                    f = msgpack.unpackb(payload)
                    src = f["src_seq"]
                    if src >= 0 and src not in seen and src in sent:
                        seen.add(src)
                        lat.append(now - sent[src])
                time.sleep(0.0002)
            wall = time.monotonic() - w0
            cpu1, rss = proc_cpu_rss(svc.pid)
            host = [b - a for a, b in zip(host0, cpu_times(), strict=True)]
            st = msgpack.unpackb(first_reply(session, "motcomp/status", None, 3.0))
            counted_s = time.monotonic() - t_start
            sub_in.undeclare()
            sub_out.undeclare()
    finally:
        svc.send_signal(signal.SIGTERM)
        svc.wait(timeout=30)
    if start is None or not lat:
        raise SystemExit("the publisher's frames or the service's outputs never arrived")
    lat_ms = np.array(lat) * 1e3
    loop = st["loop"]
    missed = st["missed_ticks"] - start["missed_ticks"]
    return {
        "ticks": st["ticks"] - start["ticks"], "missed": missed,
        "missed_start": start["missed_ticks"], "missed_min": missed * 60 / counted_s,
        "compute_p50": loop["compute_p50_us"], "compute_p99": loop["compute_p99_us"],
        "tick_p50": loop["tick_p50_us"], "tick_p99": loop["tick_p99_us"],
        "io_p50": loop["io_p50_us"], "io_p99": loop["io_p99_us"],
        "late_p50": loop["late_p50_us"], "late_p99": loop["late_p99_us"],
        "late_p999": loop["late_p999_us"], "late_max": loop["late_max_us"],
        "lat_p50": float(np.percentile(lat_ms, 50)), "lat_p99": float(np.percentile(lat_ms, 99)),
        "cpu": 100 * (cpu1 - cpu0) / wall, "rss": rss,
        "steal": 100 * host[7] / max(sum(host), 1), "realtime": st.get("realtime", ""),
        "period_ms": 1e3 / st["rate_hz"],
    }


def run_transport(seconds: float, cfg: Path) -> float:
    """The CPU share (% of a core) of :func:`transport_alone` with ``cfg``, the publisher and
    this process as receiver, counted as a service run counts it (from its first output, over
    the publisher's run and the last half second)."""
    p_svc = free_tcp_port()
    env = child_env()
    child = subprocess.Popen([sys.executable, __file__, "--transport", str(cfg), "--port",
                              str(p_svc), "--seconds", str(seconds + 60)], env=env)
    try:
        with open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
            arrived = [0]
            sub = session.declare_subscriber(
                "platform/setpoint", lambda _: arrived.__setitem__(0, arrived[0] + 1))
            t_end = time.monotonic() + 30
            while arrived[0] == 0:
                if time.monotonic() > t_end or child.poll() is not None:
                    raise SystemExit("the transport-alone run never sent an output")
                time.sleep(0.05)
            cpu0 = process_cpu_s(child.pid)
            w0 = time.monotonic()
            pub = subprocess.Popen([sys.executable, __file__, "--publisher", str(p_svc),
                                    "--seconds", str(seconds)], env=env)
            pub.wait()
            time.sleep(0.5)
            cpu1 = process_cpu_s(child.pid)
            wall = time.monotonic() - w0
            sub.undeclare()
    finally:
        child.send_signal(signal.SIGTERM)
        child.wait(timeout=30)
    return 100 * (cpu1 - cpu0) / wall


def run_pair(seconds: float, sync: bool, sched: str, tmp: Path, spin_us: float | None,
             clock_first: bool) -> dict[str, Any]:
    """A service run, a clock-alone run and a transport-alone run of the same length and loop
    settings."""
    cfg = write_config(tmp, sched, sync, seconds, spin_us)
    bare = child_json("--bare", str(cfg), "--seconds", str(seconds)) if clock_first else None
    row = run_service(seconds, cfg)
    if bare is None:
        bare = child_json("--bare", str(cfg), "--seconds", str(seconds))
    row.update(sync=sync, sched=sched, clock_missed=bare["missed"],
               clock_missed_min=bare["missed"] * 60 / seconds, clock_late_p999=bare["late_p999"],
               clock_late_max=bare["late_max"], clock_realtime=bare["realtime"])
    row["ratio"] = ratio(row["missed_min"], row["clock_missed_min"])
    row["transport_cpu"] = run_transport(seconds, cfg)
    return row


def ratio(service: float, clock: float) -> float:
    """service / clock; 1 when both are 0 (the service added nothing), inf when only the clock
    missed none."""
    if clock > 0:
        return service / clock
    return 1.0 if service == 0 else math.inf


# --- the report -------------------------------------------------------------------------------
def mode_medians(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per mode (scheduling, sync): the median of each number over its runs; the
    missed-tick ratio is that of the sums over the mode's pairs (runs of equal length)."""
    out = []
    for mode in dict.fromkeys((r["sched"], r["sync"]) for r in rows):
        runs = [r for r in rows if (r["sched"], r["sync"]) == mode]
        med = {k: float(np.median([r[k] for r in runs]))
               if isinstance(v, int | float) and not isinstance(v, bool) else v
               for k, v in runs[0].items()}
        med["ratio"] = ratio(sum(r["missed_min"] for r in runs),
                             sum(r["clock_missed_min"] for r in runs))
        med["runs"] = len(runs)
        out.append(med)
    return out


def sched_name(report: str) -> str:
    """How the loop thread was scheduled, from the service's own report."""
    parts = [p.split(" (")[0] for p in report.split("; ") if p and p != "not pinned"
             and not p.startswith(("normal scheduling", "slice not set", "subnormals"))]
    return "; ".join(parts)


def mode_name(r: dict[str, Any]) -> str:
    return ("sync to input" if r["sync"] else "own clock") + f", {sched_name(r['realtime'])}"


def targets(r: dict[str, Any]) -> list[tuple[str, float, float]]:
    """(label, value, bound) per target; a mode meets a target when value <= bound."""
    return [("compute p99 <= 50 us", r["compute_p99"], 50.0),
            ("lateness p99.9 <= 500 us", r["late_p999"], 500.0),
            (f"missed ticks <= {RATIO_MAX:g}x the clock's", r["ratio"], RATIO_MAX),
            (f"in->out p99 <= {r['period_ms'] + 0.5:g} ms", r["lat_p99"], r["period_ms"] + 0.5),
            ("RSS <= 150 MB", r["rss"], 150.0),
            (f"CPU <= {CPU_MAX:g} % of a core", r["cpu"], CPU_MAX)]


def verdict(rows: list[dict[str, Any]]) -> str:
    """Which targets each mode meets and misses, from its numbers."""
    out = []
    for r in rows:
        met = [f"{label} ({v:.4g})" for label, v, bound in targets(r) if v <= bound]
        unmet = [f"{label} ({v:.4g})" for label, v, bound in targets(r) if not v <= bound]
        out.append(f"{mode_name(r)} meets {', '.join(met) or 'none'}; misses "
                   f"{', '.join(unmet) or 'none'}.")
    return " ".join(out)


def plural(n: int, word: str) -> str:
    return f"{n} {word}{'s' if n != 1 else ''}"


def fmt_ratio(x: float) -> str:
    return "inf" if math.isinf(x) else f"{x:.2f}"


def report(args: argparse.Namespace, rows: list[dict[str, Any]],
           ticks: list[dict[str, list[float]]], elapsed_s: float) -> str:
    med = mode_medians(rows)
    tick = {name: [float(np.median([t[name][i] for t in ticks])) for i in (0, 1)]
            for name in ticks[0]}
    opts = (f"--seconds {args.seconds:g} --repeats {args.repeats}"
            f"{' --plain' if args.plain else ''}{' --rt' if args.rt else ''}"
            f"{' --idle' if args.idle else ''}"
            f"{f' --spin-us {args.spin_us:g}' if args.spin_us is not None else ''}")
    lines = [
        f"Machine: {machine()}.",
        "",
        f"`python tools/bench_service.py {opts}` ({elapsed_s / 60:.1f} min): `motcomp run` with "
        "the example config (8 axes, 1 kHz; no real-time privileges unless the mode names "
        "SCHED_FIFO; slice and naps are the loop thread's, see docs/DEPLOYMENT.md), a publisher "
        "process (naps of 100 us) sending all 8 axes at 1 kHz, this process receiving the "
        f"outputs; {plural(args.repeats, 'run')} of {args.seconds:g} s per mode, interleaved, each "
        "paired with a run of the loop's clock alone as long and with the same loop settings "
        "(a process of its own, no work, no I/O, nothing else of the benchmark running; the "
        "two in alternating order).  Missed ticks count from the publisher's first frame; tick "
        f"times are the service's own status over the last {max(args.seconds - 2, 1):g} s: "
        "*compute* is the tick's own work (validation, reference, compensator, saturation "
        "verdicts), *io* its ports' (taking the newest input; encoding and sending the "
        "output), *whole* the two together (percentiles of each series apart: they do not add "
        "up); latency = output received (stamped as zenoh delivers it) - input published "
        "(same clock); steal = the share of this virtual machine's CPU time the host took "
        "during the run; *CPU* the service process' share of one core (all its threads) from "
        "its first output to the last, beside that of the *transport alone*: a process of its "
        "own doing what the loop does without the tick (the same clock and scheduling, taking "
        "the input frames and putting one fixed output frame a tick, listening where the "
        "service listens; the same publisher and receiver), run after the service in each "
        "pair: what this host's clock and transport cost by themselves.",
        "",
        "Per mode, medians over the runs; the missed-tick ratio is service / clock alone over "
        "the sums of the mode's pairs:",
        "",
        "| mode | runs | compute p50 / p99 (us) | lateness p99.9 (us) | missed per minute: "
        "service / clock alone (ratio) | in->out p50 / p99 (ms) | CPU %: service / transport "
        "alone | RSS (MB) | steal % |",
        "|---|---|---|---|---|---|---|---|---|",
        *(f"| {mode_name(r)} | {r['runs']} | {r['compute_p50']:.0f} / {r['compute_p99']:.0f} "
          f"| {r['late_p999']:.0f} | {r['missed_min']:.1f} / {r['clock_missed_min']:.1f} "
          f"({fmt_ratio(r['ratio'])}) | {r['lat_p50']:.2f} / {r['lat_p99']:.2f} | "
          f"{r['cpu']:.0f} / {r['transport_cpu']:.0f} | {r['rss']:.0f} | {r['steal']:.1f} |"
          for r in med),
        "",
        "`Service.tick` in a process of its own with in-memory ports (a valid 8-axis frame in, "
        "the encoded output out; no transport), GC frozen as in the loop, p50 / p99 in us, "
        f"medians of {plural(len(ticks), 'run')} of {args.ticks} ticks each way:",
        "",
        "| back to back | 1 kHz, waiting as the loop waits (its slice, naps and spin) | "
        "`tick.step` alone back to back | `Service.tick` / `tick.step` (p50) |",
        "|---|---|---|---|",
        f"| {tick['tight'][0]:.1f} / {tick['tight'][1]:.1f} | "
        f"{tick['paced'][0]:.1f} / {tick['paced'][1]:.1f} | "
        f"{tick['step'][0]:.1f} / {tick['step'][1]:.1f} | "
        f"{tick['tight'][0] / tick['step'][0]:.2f} (target <= {SERVICE_TICK_MAX:g}) |",
        "",
        "Every run (clock alone: the paired run's missed ticks per minute and lateness):",
        "",
        "| mode | ticks | missed (start-up) | missed per minute: service / clock alone (ratio) "
        "| compute p50 / p99 (us) | io p50 / p99 (us) | whole tick p50 / p99 (us) "
        "| lateness p50 / p99 / p99.9 / max (us) | clock alone lateness p99.9 / max (us) "
        "| in->out p50 / p99 (ms) | CPU %: service / transport alone | RSS (MB) | steal % |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {mode_name(r)}, run {r['run']} | {r['ticks']} | {r['missed']} "
            f"({r['missed_start']}) | {r['missed_min']:.1f} / {r['clock_missed_min']:.1f} "
            f"({fmt_ratio(r['ratio'])}) | {r['compute_p50']:.0f} / {r['compute_p99']:.0f} | "
            f"{r['io_p50']:.0f} / {r['io_p99']:.0f} | {r['tick_p50']:.0f} / {r['tick_p99']:.0f} "
            f"| {r['late_p50']:.0f} / {r['late_p99']:.0f} / {r['late_p999']:.0f} / "
            f"{r['late_max']:.0f} | {r['clock_late_p999']:.0f} / {r['clock_late_max']:.0f} | "
            f"{r['lat_p50']:.2f} / {r['lat_p99']:.2f} | {r['cpu']:.1f} / "
            f"{r['transport_cpu']:.1f} | {r['rss']:.0f} | {r['steal']:.1f} |")
    own = next(r for r in med if not r["sync"])
    cold = tick["paced"][0] / tick["tight"][0]
    cold_text = (" already: the tick after a millisecond's gap costs more, whether its thread "
                 "slept or spun (`bench_core.py --gaps`, docs/BENCHMARKS.md)")
    lines += [
        "",
        f"Targets (2-core machine, no real-time privileges): compute p99 <= 50 us, lateness "
        f"p99.9 <= 500 us, missed ticks <= {RATIO_MAX:g}x those of the clock alone in the same "
        "mode, in->out p99 <= period + 0.5 ms (1.5 ms), RSS <= 150 MB, CPU <= "
        f"{CPU_MAX:g} % of a core.",
        "",
        f"Reading ({'medians of each mode' if args.repeats > 1 else 'one run per mode'}): "
        f"{verdict(med)}  The service's compute p50 ({own['compute_p50']:.0f} us, "
        f"{mode_name(own)}) is {own['compute_p50'] / tick['tight'][0]:.1f}x the same tick back "
        f"to back in a process of its own; paced as the loop waits, that tick costs "
        f"{cold:.1f}x{cold_text if cold >= 1.5 else ''}.",
    ]
    for r in med:
        lines[-1] += (f"  {mode_name(r).capitalize()}: the transport alone takes "
                      f"{r['transport_cpu']:.1f} % of a core ({r['transport_cpu'] / CPU_MAX:.0%} "
                      f"of the {CPU_MAX:g} % target), the service {r['cpu']:.1f} % "
                      f"({r['cpu'] / r['transport_cpu']:.2f}x the transport alone): its own "
                      f"work adds {r['cpu'] - r['transport_cpu']:.1f} %.")
    steal = [r["steal"] for r in rows]
    if max(steal) > 1.0:
        lines[-1] += (f"  The host took {min(steal):.1f}-{max(steal):.1f} % of this virtual "
                      "machine's CPU during these runs (steal): such runs measure the host as "
                      "much as the service: compare runs with little steal.")
    return "\n".join(lines)


def main() -> None:
    # every process of the benchmark runs zenoh as motcomp's commands do (docs/DEPLOYMENT.md,
    # "zenoh's threads"): the transport alone then costs what the service's transport costs
    use_one_zenoh_thread()
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=40.0, help="length of each run")
    ap.add_argument("--repeats", type=int, default=3,
                    help="runs of each mode, interleaved; the reading uses their medians")
    ap.add_argument("--ticks", type=int, default=5000,
                    help="timed ticks of the in-process measurement, each way")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke test: runs of 15 s, 1 repeat, 2000 in-process ticks")
    ap.add_argument("--no-write", action="store_true", help="print only")
    ap.add_argument("--spin-us", type=float, help="loop.spin_us of the service (default: config)")
    ap.add_argument("--plain", action="store_true",
                    help="also run with the kernel's default slice and one sleep per tick "
                         "(loop.slice_us = 0, loop.sleep_max_us = 0)")
    ap.add_argument("--rt", action="store_true",
                    help="also run with SCHED_FIFO 50 and the loop pinned to CPU 1 (needs the "
                         "privilege; the service reports whether it got it)")
    ap.add_argument("--idle", action="store_true",
                    help="also run with the system's idle states (loop.cpu_latency_us = -1: "
                         "the CPUs' wake-up latency not held)")
    ap.add_argument("--publisher", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--bare", help=argparse.SUPPRESS)
    ap.add_argument("--tick-child", help=argparse.SUPPRESS)
    ap.add_argument("--transport", help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.transport is not None:
        transport_alone(args.transport, args.port, args.seconds)
        return
    if args.publisher:
        publisher(args.publisher, args.seconds)
        return
    if args.bare is not None:
        print(json.dumps(bare_clock(args.bare, args.seconds)))
        return
    if args.tick_child is not None:
        print(json.dumps(tick_in_process(args.tick_child, args.ticks)))
        return
    if args.quick:
        args.seconds, args.repeats, args.ticks = 15.0, 1, 2000
    scheds = ["config"] + ["plain"] * args.plain + ["rt"] * args.rt + ["idle"] * args.idle
    pairs = args.repeats * len(scheds) * 2
    estimate = pairs * (3 * args.seconds + PAIR_OVERHEAD_S) + args.repeats * (
        args.ticks / 1000 + 5)
    print(f"{pairs} paired runs of {args.seconds:g} s: about {estimate / 60:.0f} min",
          file=sys.stderr)
    t0 = time.monotonic()
    rows: list[dict[str, Any]] = []
    ticks: list[dict[str, list[float]]] = []
    with tempfile.TemporaryDirectory() as tmp:
        n = 0
        for rep in range(args.repeats):  # interleaved, so slow spells of the host spread out
            ticks.append(child_json("--tick-child", str(write_config(
                Path(tmp), "config", False, args.seconds, args.spin_us)), "--ticks",
                str(args.ticks)))
            for sched in scheds:
                for sync in (False, True):
                    rows.append(dict(run_pair(args.seconds, sync, sched, Path(tmp),
                                              args.spin_us, clock_first=n % 2 == 1), run=rep + 1))
                    n += 1
    rows.sort(key=lambda r: (scheds.index(r["sched"]), r["sync"], r["run"]))
    text = report(args, rows, ticks, time.monotonic() - t0)
    print(text)
    if not args.no_write:
        write_section("service", text)


if __name__ == "__main__":
    main()
