"""``motcomp replay --realtime``: republish a recording's inputs on zenoh at their recorded
timing, to drive a running service.

Frames are read from the file as a stream (memory stays bounded) and sent on absolute
deadlines: frame ``i`` goes out at ``start + (T_i - T_0) / speed`` on the monotonic clock,
where ``T`` is the message's recorded publish time (the sender's own ``t``; default) or log time
(when the recorder received it).  Waiting is sleep-then-spin, as the service's loop does, so
the schedule does not drift and late frames do not accumulate lateness.  Payloads go out as
recorded; with ``restamp`` their ``t`` is shifted by the time elapsed since the recording, so
that the service sees current sender times.  Nothing is sent until a subscriber of the key is
reachable (``wait_peer_s``).
"""

from __future__ import annotations

import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack

from motcomp.io.zenoh_io import (
    NoPeerError,
    ZenohEndpoints,
    ZenohSink,
    open_session,
    wait_for_subscriber,
)
from motcomp.record.mcapio import ScanResult, iter_messages, metadata_dict, scan
from motcomp.record.session import DEFAULT_KEYS, session_parts

__all__ = ["RepublishStats", "input_key", "republish"]

SPIN_NS = 200_000


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


def _wait_until(deadline_ns: int) -> int:
    now = time.perf_counter_ns()
    if deadline_ns - now > SPIN_NS:
        time.sleep((deadline_ns - now - SPIN_NS) / 1e9)
    while (now := time.perf_counter_ns()) < deadline_ns:
        pass
    return now


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
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    parts = session_parts(path)
    key = key or input_key(parts[0])
    late: list[int] = []
    sent = 0
    t_start = time.monotonic()
    with open_session(endpoints) as session:
        if wait_peer_s > 0 and not wait_for_subscriber(session, key, wait_peer_s, stop):
            if not stop.is_set():
                raise NoPeerError(f"no subscriber of {key} reachable within {wait_peer_s:g} s "
                                  f"({endpoints.describe()})")
            return RepublishStats(0, time.monotonic() - t_start, 0.0, 0.0, key, True)
        sink = ZenohSink(session, key)
        try:
            stop.wait(lead_in_s)
            start = time.perf_counter_ns()
            t0: int | None = None
            wall_shift = 0.0
            for part in parts:
                for _topic, log_ns, pub_ns, payload in iter_messages(part, {key}):
                    if stop.is_set():
                        break
                    ref = pub_ns if timing == "publish" else log_ns
                    if t0 is None:
                        t0 = ref
                        wall_shift = time.time() - ref / 1e9
                    deadline = start + round((ref - t0) / speed)
                    now = _wait_until(deadline)
                    sink.put(_restamped(payload, wall_shift) if restamp else payload)
                    late.append(now - deadline)
                    sent += 1
                    if progress is not None and sent % 250 == 0:
                        progress((ref - t0) / 1e9)
        finally:
            sink.close()
    late.sort()
    p99 = late[min(len(late) - 1, int(0.99 * len(late)))] / 1e3 if late else 0.0
    return RepublishStats(sent, time.monotonic() - t_start, (late[-1] / 1e3 if late else 0.0),
                          p99, key, stop.is_set())
