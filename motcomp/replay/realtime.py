"""``motcomp replay --realtime``: republish a recording's inputs on zenoh at their recorded
timing, to drive a running service.

Frames are read from the file as a stream (memory stays bounded), by a thread of their own a
few chunks ahead of the sender, so that no frame waits for the file's reading, and sent on
absolute deadlines: frame ``i`` goes out at ``start + (T_i - T_0) / speed`` on the monotonic clock,
where ``T`` is the message's recorded publish time (the sender's own ``t``; default) or log time
(when the recorder received it).  Waiting is sleep-then-spin, as the service's loop does, so
the schedule does not drift and late frames do not accumulate lateness; while sending, the
interpreter's switch interval is :data:`SWITCH_INTERVAL_S` and the heap is frozen out of the
collector's reach (docs/REPLAY.md, "Real time").  Payloads go out as
recorded; with ``restamp`` their ``t`` is shifted by the time elapsed since the recording, so
that the service sees current sender times.  Nothing is sent until a subscriber of the key is
reachable (``wait_peer_s``).
"""

from __future__ import annotations

import queue
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import msgpack

from motcomp.io.zenoh_io import (
    NoPeerError,
    ZenohEndpoints,
    ZenohSink,
    open_session,
    wait_for_subscriber,
)
from motcomp.record.mcapio import Record, ScanResult, iter_record_batches, metadata_dict, scan
from motcomp.record.session import DEFAULT_KEYS, session_parts
from motcomp.runtime.clock import (
    TIMER_SLACK_NS,
    SleepLead,
    frozen_heap,
    set_timer_slack,
    sleep_until,
)

__all__ = ["RepublishStats", "input_key", "republish"]

SPIN_NS = 200_000
"""The longest spin before a frame's deadline (learned shorter, as the service's loop does)."""
READ_BATCH_BYTES = 256 << 10
"""The reading thread's batches: a chunk or two (about a millisecond's work each, quiet)."""
READ_AHEAD_BATCHES = 16
"""Batches read ahead of the sender at most (memory stays bounded)."""
SWITCH_INTERVAL_S = 0.0005
"""The interpreter's thread switch interval while republishing: how long the reading thread
may hold the interpreter when a frame is due (Python's default is 5 ms)."""


@dataclass
class RepublishStats:
    sent: int
    duration_s: float
    late_max_us: float
    late_p99_us: float
    key: str
    stopped: bool = False
    """Stopped by SIGTERM/SIGINT (or ``stop``) before the last frame."""

    def text(self) -> str:
        return (f"republished {self.sent} frames on {self.key!r} in {self.duration_s:.1f} s; "
                f"lateness p99 {self.late_p99_us:.0f} us, max {self.late_max_us:.0f} us"
                + ("; stopped by a signal before the end" if self.stopped else ""))


def input_key(path: Path) -> str:
    """The input key of a recording: from its recorded config, else the default."""
    import json

    res = ScanResult(path)
    for _ in scan(path, topics=set(), batch_bytes=1 << 20, result=res):
        break
    for name, _media, data in res.attachments:
        if name == "config.json":
            try:
                key = json.loads(data).get("input", {}).get("key")
                if isinstance(key, str):
                    return key
            except (ValueError, AttributeError):
                pass
    meta = metadata_dict(res)
    del meta
    return DEFAULT_KEYS["input"]


class _ReadAhead:
    """The frames of ``key`` in ``parts``, read by a thread of their own up to
    :data:`READ_AHEAD_BATCHES` batches ahead; iterating yields them in order and raises what the
    reading raised."""

    _END = object()

    def __init__(self, parts: list[Path], key: str) -> None:
        self._q: queue.Queue[object] = queue.Queue(maxsize=READ_AHEAD_BATCHES)
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._read, args=(parts, key), daemon=True,
                                        name="replay-read")
        self._thread.start()

    def _put(self, item: object) -> bool:
        while not self._closed.is_set():
            try:
                self._q.put(item, timeout=0.1)
                return True
            except queue.Full:
                pass
        return False

    def _read(self, parts: list[Path], key: str) -> None:
        try:
            for part in parts:
                for batch in iter_record_batches(part, {key}, batch_bytes=READ_BATCH_BYTES):
                    if not self._put(batch):
                        return
        except BaseException as exc:  # handed to the sender, raised there
            self._put(exc)
            return
        self._put(self._END)

    def __iter__(self) -> Iterator[Record]:
        while (item := self._q.get()) is not self._END:
            if isinstance(item, BaseException):
                raise item
            yield from cast("list[Record]", item)

    def close(self) -> None:
        self._closed.set()
        self._thread.join(timeout=5)


def _restamped(payload: bytes, shift_s: float) -> bytes:
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception:  # not msgpack: sent as recorded
        return payload
    if isinstance(obj, dict) and isinstance(obj.get("t"), int | float) and \
            not isinstance(obj.get("t"), bool):
        obj["t"] = obj["t"] + shift_s
        return bytes(msgpack.packb(obj, use_bin_type=True))
    return payload


def republish(path: str | Path, endpoints: ZenohEndpoints, key: str | None = None,
              timing: str = "publish", speed: float = 1.0, restamp: bool = False,
              lead_in_s: float = 0.5, stop: threading.Event | None = None,
              progress: Any = None, wait_peer_s: float = 0.0) -> RepublishStats:
    """Send the recorded frames of ``key`` (default: the recording's input key) on the same
    key, on their recorded schedule (see the module docstring); ``progress`` is called with
    the recorded seconds sent so far.

    Raises
    ------
    NoPeerError
        If ``wait_peer_s`` > 0 and no subscriber of the key was reachable within it.
    """
    stop = stop or threading.Event()
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            previous[sig] = signal.signal(sig, lambda *_: stop.set())
    try:
        return _republish(path, endpoints, key, timing, speed, restamp, lead_in_s, stop,
                          progress, wait_peer_s)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _republish(path: str | Path, endpoints: ZenohEndpoints, key: str | None, timing: str,
               speed: float, restamp: bool, lead_in_s: float, stop: threading.Event,
               progress: Any, wait_peer_s: float) -> RepublishStats:
    parts = session_parts(path)
    key = key or input_key(parts[0])
    late: list[int] = []
    sent = 0
    t_start = time.monotonic()
    with open_session(endpoints) as session, frozen_heap():
        if wait_peer_s > 0 and not wait_for_subscriber(session, key, wait_peer_s, stop):
            if not stop.is_set():
                raise NoPeerError(f"no subscriber of {key} reachable within {wait_peer_s:g} s "
                                  f"({endpoints.describe()})")
            return RepublishStats(0, time.monotonic() - t_start, 0.0, 0.0, key, True)
        sink = ZenohSink(session, key)
        frames = _ReadAhead(parts, key)
        switch = sys.getswitchinterval()
        sys.setswitchinterval(min(switch, SWITCH_INTERVAL_S))
        try:
            stop.wait(lead_in_s)
            set_timer_slack(TIMER_SLACK_NS)
            lead = SleepLead(SPIN_NS)
            start = time.perf_counter_ns()
            t0: int | None = None
            wall_shift = 0.0
            for rec in frames:
                if stop.is_set():
                    break
                ref = rec.publish_ns if timing == "publish" else rec.log_ns
                if t0 is None:
                    t0 = ref
                    wall_shift = time.time() - ref / 1e9
                deadline = start + round((ref - t0) / speed)
                sleep_until(deadline, lead)
                now = time.perf_counter_ns()
                sink.put(_restamped(rec.data, wall_shift) if restamp else rec.data)
                late.append(now - deadline)
                sent += 1
                if progress is not None and sent % 250 == 0:
                    progress((ref - t0) / 1e9)
        finally:
            sys.setswitchinterval(switch)
            frames.close()
            sink.close()
    late.sort()
    p99 = late[min(len(late) - 1, int(0.99 * len(late)))] / 1e3 if late else 0.0
    return RepublishStats(sent, time.monotonic() - t_start, (late[-1] / 1e3 if late else 0.0),
                          p99, key, stop.is_set())
