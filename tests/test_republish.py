"""``replay --realtime``'s sender (:func:`motcomp.replay.realtime.republish`): every recorded
input frame of every part of a rotated session goes out once, in order, as recorded, read ahead
by a thread of its own that ends with the sender.  A real zenoh subscriber on loopback (scouting
off, a free port) receives them."""

from __future__ import annotations

import threading
import time
from pathlib import Path

from motcomp.core.axes import AXES
from motcomp.io.wire import encode_input, encode_output
from motcomp.io.zenoh_io import ZenohEndpoints, free_tcp_port, loopback, open_session
from motcomp.record.recorder import SessionWriter
from motcomp.replay.realtime import republish

KEYS = ["sim/motion/setpoint", "platform/setpoint"]


def write_rotated(path: Path, n: int) -> list[bytes]:
    """A session of ``n`` input frames at 1 kHz beside the outputs, in several parts of small
    chunks (so that the reading runs in many batches); the input payloads, in order."""
    t0 = 1_750_000_000.0
    sent = []
    with SessionWriter(path, KEYS, {}, b"{}", rotate_bytes=60_000, chunk_bytes=8 << 10) as w:
        for k in range(n):
            t = t0 + k * 1e-3
            frame = encode_input(k, t, {"rails_x": 0.001 * k, "hex_z": -0.0005 * k})
            w.write(KEYS[0], round(t * 1e9), frame)
            w.write(KEYS[1], round(t * 1e9) + 1000,
                    encode_output(k, t, k, [0.0] * len(AXES), []))
            sent.append(frame)
    assert len(list(path.parent.glob(f"{path.stem}-*.mcap"))) >= 3
    return sent


def test_every_frame_goes_out_once_in_order_from_every_part(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    frames = write_rotated(path, 2000)
    port = free_tcp_port()
    with open_session(ZenohEndpoints(listen=(loopback(port),))) as session:
        got: list[bytes] = []
        sub = session.declare_subscriber(KEYS[0], lambda s: got.append(s.payload.to_bytes()))
        stats = republish(path, ZenohEndpoints(connect=(loopback(port),)), speed=2.0,
                          lead_in_s=0.2, wait_peer_s=10)
        t_end = time.monotonic() + 5
        while len(got) < len(frames) and time.monotonic() < t_end:
            time.sleep(0.05)
        sub.undeclare()
    assert stats.sent == len(frames) and not stats.stopped
    # each frame as recorded, once, in order; the data path's publisher drops rather than
    # blocks when zenoh's queue is full (a few frames as the link starts, seen once in 20 runs)
    at = {f: i for i, f in enumerate(frames)}
    order = [at[f] for f in got]
    assert order == sorted(set(order)), order[:20]
    assert len(got) >= 0.95 * len(frames), len(got)
    assert not [t for t in threading.enumerate() if t.name == "replay-read"]


def test_a_stopped_republish_ends_its_reading_thread(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    frames = write_rotated(path, 3000)
    port = free_tcp_port()
    stop = threading.Event()
    with open_session(ZenohEndpoints(listen=(loopback(port),))) as session:
        # stopped once its first frame arrives (a timer of 1 s fired before a starved host's
        # first frame was sent); the recording lasts 3 s
        sub = session.declare_subscriber(KEYS[0], lambda _sample: stop.set())
        stats = republish(path, ZenohEndpoints(connect=(loopback(port),)), stop=stop,
                          lead_in_s=0.1, wait_peer_s=10)
        sub.undeclare()
    assert stats.stopped and 0 < stats.sent < len(frames)
    assert not [t for t in threading.enumerate() if t.name == "replay-read"]
