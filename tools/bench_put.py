"""What one zenoh ``put`` costs the thread that calls it, at 1 kHz: the floor under every 1 kHz
process of motcomp (the service's output, the source's input, the platforms' feedback).

Each run is a process of its own publishing a feedback-sized msgpack frame through
:class:`motcomp.io.zenoh_io.ZenohSink` (express, drop, real time: the data path's publisher)
to a subscriber in another process, once a millisecond; the calling thread's CPU time is read
around each ``put`` (``time.thread_time_ns``), the process' CPU over the whole run.  The modes:
zenoh's default runtime or its tasks on one thread (:data:`~motcomp.io.zenoh_io.ONE_THREAD`,
as every motcomp command runs), over TCP or a unix socket.

    python tools/bench_put.py [--puts 5000] [--no-write]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench import machine, percentiles, write_section

MODES = (("default runtime", "tcp", False, True), ("one thread", "tcp", True, True),
         ("one thread", "unixsock-stream", True, True), ("one thread", "tcp", True, False))
"""(zenoh, transport, one thread, put): the last waits as the others and puts nothing."""


def child(endpoint: str, one_thread: bool, puts: int, put: bool = True) -> dict[str, float]:
    if one_thread:
        from motcomp.io.zenoh_io import use_one_zenoh_thread

        use_one_zenoh_thread()
    else:
        os.environ.pop("ZENOH_RUNTIME", None)
    import msgpack

    from motcomp.io.zenoh_io import ZenohEndpoints, ZenohSink, open_session

    axes = [f"a{i}" for i in range(8)]
    frame = msgpack.packb({"t": 1.8e9, "pos": {a: 0.1 for a in axes},
                           "acc": {a: 0.2 for a in axes}})
    with open_session(ZenohEndpoints(connect=(endpoint,))) as session:
        sink = ZenohSink(session, "bench/put")
        time.sleep(1.0)  # the subscriber matched
        costs = []
        cpu0, t0 = time.process_time(), time.perf_counter()
        due = t0
        for _ in range(puts):
            due += 1e-3
            while (left := due - time.perf_counter()) > 0:
                time.sleep(max(0.0, left - 1e-4))
            a = time.thread_time_ns()
            if put:
                sink.put(frame)
            costs.append((time.thread_time_ns() - a) / 1e3)
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    p = percentiles(costs, (50, 90, 99))
    return {"p50": p[50], "p90": p[90], "p99": p[99], "cpu_pct": 100 * cpu / wall,
            "errors": sink.errors}


SUBSCRIBER = """
import sys, time, json
from motcomp.io.zenoh_io import ZenohEndpoints, open_session
import zenoh
with open_session(ZenohEndpoints(listen=(sys.argv[1],))) as s:
    sub = s.declare_subscriber("bench/put", zenoh.handlers.RingChannel(64))
    n, t_end = 0, time.monotonic() + float(sys.argv[2])
    while time.monotonic() < t_end:
        time.sleep(0.01)
        while sub.try_recv() is not None:
            n += 1
    print(n)
"""


def run(puts: int) -> list[tuple[str, str, bool, dict[str, float], int]]:
    rows = []
    for label, kind, one, put in MODES:
        with tempfile.TemporaryDirectory() as tmp:
            if kind == "tcp":
                from motcomp.io.zenoh_io import free_tcp_port, loopback

                endpoint = loopback(free_tcp_port())
            else:
                endpoint = f"unixsock-stream/{tmp}/z.sock"
            sub = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, endpoint,
                                    str(puts / 1000 + 4)], stdout=subprocess.PIPE, text=True)
            time.sleep(0.5)
            out = subprocess.run([sys.executable, __file__, "--child", endpoint,
                                  "--one-thread" if one else "--default", "--puts", str(puts),
                                  *([] if put else ["--no-put"])],
                                 capture_output=True, text=True, check=True)
            got = int(sub.communicate(timeout=60)[0].strip() or 0)
        rows.append((label, kind, put, json.loads(out.stdout), got))
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--puts", type=int, default=5000)
    ap.add_argument("--no-write", action="store_true", help="print, do not write the doc")
    ap.add_argument("--child", metavar="ENDPOINT", help=argparse.SUPPRESS)
    ap.add_argument("--one-thread", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--default", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--no-put", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.one_thread, args.puts, not args.no_put)))
        return 0
    rows = run(args.puts)
    lines = [f"Machine: {machine()}.", "",
             f"`python tools/bench_put.py --puts {args.puts}`: a feedback-sized frame "
             f"({8} axes' position and acceleration, msgpack) put once a millisecond through the "
             "data path's publisher to a subscriber in another process; the calling thread's "
             "CPU per put, and the publishing process' CPU (its loop does nothing else: it "
             "sleeps until 0.1 ms before each millisecond, then naps to it).  The last row "
             "waits the same way and puts nothing.", "",
             "| zenoh | transport | put, thread CPU p50 / p90 / p99 (us) | process CPU "
             "(% of a core) | received |", "|---|---|---|---|---|"]
    for label, kind, put, r, got in rows:
        cost = (f"{r['p50']:.1f} / {r['p90']:.1f} / {r['p99']:.1f}" if put
                else "no put")
        lines.append(f"| {label} | {kind} | {cost} | {r['cpu_pct']:.1f} | "
                     f"{got} of {args.puts if put else 0} |")
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        write_section("zenoh-put", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
