"""Admin load against the running service (subprocess, zenoh on loopback): requests beyond the
admin worker's queue are answered ``busy`` at once, status queries are all answered, and SIGTERM
parks and exits within ``loop.park_timeout_s`` whatever is queued or being read.  What the load
costs the loop in missed ticks is measured by tools/bench_admin.py (docs/BENCHMARKS.md)."""

from __future__ import annotations

import itertools
import signal
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import msgpack
import pytest

from motcomp.io.wire import decode_output, encode_input
from motcomp.io.zenoh_io import ZenohEndpoints, free_tcp_port, loopback, open_session
from motcomp.runtime.probe import HostProbe
from motcomp.runtime.service import ADMIN_QUEUE, QUERY_CHANNEL
from tests.conftest import judge_realtime
from tests.test_reload import BASE, status
from tests.test_service_process import process, wait_status

pytestmark = pytest.mark.slow

PARK_TIMEOUT_S = 4.0
EXIT_MARGIN_S = 5.0
"""Beyond park_timeout_s: the process' own exit (queryables, zenoh session, interpreter)."""


def fire(session: Any, reqs: list[tuple[str, bytes | None]]) -> list[Any]:
    """Send every request at once (replies collected later with :func:`kinds`)."""
    return [session.get(key, payload=body, timeout=20.0) if body is not None
            else session.get(key, timeout=20.0) for key, body in reqs]


def kinds(pending: list[Any]) -> Counter[str]:
    """Replies by kind: ok, busy, stopping, error text, none."""
    out: Counter[str] = Counter()
    for handler in pending:
        replies = [r for r in handler if r.ok is not None]
        if not replies:
            out["none"] += 1
            continue
        rep = msgpack.unpackb(replies[0].ok.payload.to_bytes())
        out["ok" if rep.get("ok", "mode" in rep) else str(rep.get("error"))] += 1
    return out


def test_admin_burst_gets_busy_beyond_the_queue(tmp_path: Path) -> None:
    cfg = tmp_path / "site.toml"
    cfg.write_text(BASE)
    p_svc = free_tcp_port()
    with process(["run", "--config", str(cfg), "-l", loopback(p_svc)],
                 tmp_path / "svc.log") as svc, \
            open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
        st0 = wait_status(session)
        n = 200
        bypass = fire(session, [("motcomp/admin/bypass",
                                 msgpack.packb({"on": k % 2 == 0, "axes": ["rails_y"]}))
                                for k in range(n)])
        queries = fire(session, [("motcomp/status", None)] * n)
        got = kinds(bypass)
        assert got["ok"] + got["busy"] == n, got  # every request answered, ok or busy
        # the queue filled and was served; the rest was refused at once, not queued (beyond the
        # queue, the worker serves ADMIN_RATE_HZ a second while the burst is taken in)
        assert ADMIN_QUEUE <= got["ok"] < n // 2 and got["busy"] > 0, got
        assert kinds(queries) == Counter(ok=n)
        st = status(session)
        assert st["mode"] == st0["mode"] and st["ticks"] > st0["ticks"]
        # the worker is free again: a request is served, not refused
        assert kinds(fire(session, [("motcomp/admin/bypass", msgpack.packb(
            {"on": False, "axes": ["rails_y"]}))])) == Counter(ok=1)
        assert "rails_y" not in status(session)["bypass"]
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(timeout=30) == 0


def test_sigterm_parks_during_a_burst_of_reloads(tmp_path: Path) -> None:
    """A burst of reloads (the first of /dev/zero, which an unconfined reader never finishes)
    and then SIGTERM while the platform holds rails_x at 0.5 m: the output ramps to neutral and
    the service exits 0 within park_timeout_s (+ its own exit)."""
    cfg = tmp_path / "site.toml"
    cfg.write_text(BASE + f"[loop]\npark_timeout_s = {PARK_TIMEOUT_S}\n")
    other = tmp_path / "other.toml"
    other.write_text(BASE + f'[loop]\npark_timeout_s = {PARK_TIMEOUT_S}\n[defaults]\nrule = '
                     '"amigo"\n')
    p_svc = free_tcp_port()
    with process(["run", "--config", str(cfg), "-l", loopback(p_svc)],
                 tmp_path / "svc.log") as svc, \
            open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
        import zenoh

        out_sub = session.declare_subscriber("platform/setpoint", zenoh.handlers.RingChannel(1))
        wait_status(session)
        pub = session.declare_publisher("sim/motion/setpoint")
        stop = threading.Event()

        def feed() -> None:  # hold rails_x at 0.5 m until stopped
            k = 0
            while not stop.is_set():
                pub.put(encode_input(k, time.time(), {"rails_x": 0.5}))
                k += 1
                time.sleep(0.001)

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        try:
            t_end = time.monotonic() + 20
            while time.monotonic() < t_end:
                s = out_sub.try_recv()
                if s is not None and decode_output(s.payload.to_bytes())["pos"]["rails_x"] > 0.4:
                    break
                time.sleep(0.05)
            else:
                raise AssertionError("rails_x never reached 0.4 m")
            reqs: list[tuple[str, bytes | None]] = [
                ("motcomp/admin/reload", msgpack.packb({"path": "/dev/zero"}))]
            reqs += [("motcomp/admin/reload", msgpack.packb({"path": str((cfg, other)[k % 2])}))
                     for k in range(500)]
            pending = fire(session, reqs)
            time.sleep(0.3)  # the main thread has taken the burst in
            svc.send_signal(signal.SIGTERM)
            t_term = time.monotonic()
            last = None
            while svc.poll() is None and time.monotonic() < t_term + PARK_TIMEOUT_S + 30:
                s = out_sub.try_recv()
                if s is not None:
                    last = decode_output(s.payload.to_bytes())
                time.sleep(0.005)
            took = time.monotonic() - t_term
        finally:
            stop.set()
            feeder.join()
        assert svc.wait(timeout=5) == 0, "did not park"
        assert took <= PARK_TIMEOUT_S + EXIT_MARGIN_S, took
        assert last is not None and abs(last["pos"]["rails_x"]) < 1e-3
        assert "parking" in last["flags"]
        (dev_zero,) = kinds(pending[:1])  # refused, not read: the worker was free after it
        assert "refused" in dev_zero and "config directory" in dev_zero, dev_zero
        got = kinds(pending[1:])
        assert got["busy"] > 0 and got["ok"] <= ADMIN_QUEUE + 5, got
        out_sub.undeclare()


def test_queries_beyond_the_channel_are_answered_empty_at_once_not_held() -> None:
    """The library fact the service's query channels rely on (``QUERY_CHANNEL``): a
    ``RingChannel`` queryable that nobody drains drops the oldest queries of a burst, and their
    askers get an empty answer at once -- zenoh's thread is never held by a full channel."""
    import zenoh

    port = free_tcp_port()
    with open_session(ZenohEndpoints(listen=(loopback(port),))) as server, \
            open_session(ZenohEndpoints(connect=(loopback(port),))) as client:
        queryable = server.declare_queryable("test/q", zenoh.handlers.RingChannel(2))
        time.sleep(0.3)
        t0 = time.monotonic()
        pending = [client.get("test/q", timeout=20.0) for _ in range(5)]
        first = [list(h) for h in pending[:3]]  # the three the ring dropped
        waited = time.monotonic() - t0
        served = 0
        while (q := queryable.try_recv()) is not None:
            q.reply("test/q", msgpack.packb({"mode": "x"}))
            served += 1
        assert first == [[], [], []] and waited < 10.0, (first, waited)
        assert served == 2 and kinds(pending[3:]) == Counter(ok=2)
        queryable.undeclare()


def test_a_burst_of_queries_beyond_the_channel_never_holds_the_data_path(tmp_path: Path) -> None:
    """Twice ``QUERY_CHANNEL`` status queries at once while a sender feeds rails_x at
    1 kHz: the service answers what its channel kept, and zenoh's thread -- which carries the
    input and the output too -- is never held by the burst: no input goes stale and the outputs
    keep coming (a FIFO channel holds the thread until the main thread has drained the burst,
    64 queries a poll: the outputs stopped for 251-345 ms).  The outputs' gaps are judged where
    the host held the loop's rate (docs/TESTING.md)."""
    cfg = tmp_path / "site.toml"
    cfg.write_text(BASE)
    p_svc = free_tcp_port()
    arrivals: list[float] = []
    with HostProbe() as probe, \
            process(["run", "--config", str(cfg), "-l", loopback(p_svc)],
                    tmp_path / "svc.log") as svc, \
            open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
        wait_status(session)
        out_sub = session.declare_subscriber(
            "platform/setpoint", lambda _s: arrivals.append(time.monotonic()))
        pub = session.declare_publisher("sim/motion/setpoint", express=True)
        stop = threading.Event()

        def feed() -> None:
            k = 0
            t_next = time.monotonic()
            while not stop.is_set():
                pub.put(encode_input(k, time.time(), {"rails_x": 0.0}))
                k += 1
                t_next += 0.001
                time.sleep(max(0.0, t_next - time.monotonic()))

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        try:
            time.sleep(1.0)
            st0 = status(session)
            t_burst = time.monotonic()
            pending = fire(session, [("motcomp/status", None)] * (2 * QUERY_CHANNEL))
            time.sleep(2.0)
            st1 = status(session)
        finally:
            stop.set()
            feeder.join()
        got = kinds(pending)
        out_sub.undeclare()
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(timeout=30) == 0
    # every query answered or dropped (answered empty), at least the channel's worth answered
    assert got["ok"] + got["none"] == 2 * QUERY_CHANNEL and got["ok"] >= QUERY_CHANNEL, got
    judge_realtime(probe.result, "the data path during a burst of queries", st1)
    # measured: 8 ms at most between two outputs, no stale input; with a FIFO channel, the
    # outputs stopped for 251-345 ms
    during = [t for t in arrivals if t_burst - 0.1 <= t <= t_burst + 2.0]
    gap = max(b - a for a, b in itertools.pairwise(during))
    assert gap < 0.05, f"the outputs stopped for {gap * 1e3:.0f} ms during the burst"
    assert st1["stale_episodes"] == st0["stale_episodes"], (st0["stale_episodes"],
                                                            st1["stale_episodes"])
