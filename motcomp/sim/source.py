"""``motcomp source``: a motion source publishing setpoint frames at a fixed rate.

It stands in for the vehicle model and motion cueing: built-in trajectories (a slalom on the
rails, a swept sine, a demo mix of rails and hexapod motion) or a file -- a msgpack stream of
input frames (what ``motcomp excite`` writes) or a CSV ``t,<axis>...`` (or ``t,cmd`` with
``--axis``) -- published on ``sim/motion/setpoint`` on absolute deadlines.
"""

from __future__ import annotations

import csv
import math
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import msgpack
import numpy as np

from motcomp.core.axes import AXES, AXIS_INDEX
from motcomp.design.timedomain import fade_envelope, slalom, swept_sine
from motcomp.errors import DataError
from motcomp.io.wire import encode_input
from motcomp.io.zenoh_io import (
    NoPeerError,
    ZenohEndpoints,
    ZenohSink,
    open_session,
    wait_for_subscriber,
)
from motcomp.runtime.clock import DeadlineClock

__all__ = ["PublishStats", "Trajectory", "builtin", "load_trajectory", "publish"]

SIGNALS = ("demo", "slalom", "sweep")


@dataclass(frozen=True)
class Trajectory:
    """Positions of some axes on a uniform time grid at ``rate_hz``."""

    rate_hz: float
    pos: dict[str, np.ndarray]
    description: str = ""

    @property
    def samples(self) -> int:
        return len(next(iter(self.pos.values())))

    @property
    def duration_s(self) -> float:
        return self.samples / self.rate_hz


def builtin(name: str, rate_hz: float = 1000.0, duration_s: float | None = None) -> Trajectory:
    """``slalom`` (rails_y, 18 m cones at 40 km/h), ``sweep`` (rails_x, 0.1-3 Hz within the
    rails' acceleration limit) or ``demo`` (~12 s: slalom on rails_y, a 0.2-1 Hz sweep on
    rails_x, heave/roll/pitch sines on the hexapod)."""
    if name == "slalom":
        _, r = slalom(rate_hz)
        return Trajectory(rate_hz, {"rails_y": r}, "slalom on rails_y (18 m cones, 40 km/h)")
    if name == "sweep":
        dur = duration_s or 60.0
        _, r = swept_sine(rate_hz, 0.1, 3.0, dur, 0.0135)
        return Trajectory(rate_hz, {"rails_x": r}, "0.1-3 Hz swept sine on rails_x")
    if name == "demo":
        _, y = slalom(rate_hz, n_cones=7, straight_s=0.5)
        n = y.size
        t = np.arange(n) / rate_hz
        dur = n / rate_hz
        f0, f1 = 0.2, 1.0
        k = f1 / f0
        phase = 2 * math.pi * f0 * dur * (k ** (t / dur) - 1.0) / math.log(k)
        env = fade_envelope(n, int(rate_hz))
        return Trajectory(rate_hz, {
            "rails_y": y,
            "rails_x": 0.06 * np.sin(phase) * env,
            "hex_z": 0.02 * np.sin(2 * math.pi * 0.5 * t) * env,
            "hex_roll": 0.04 * np.sin(2 * math.pi * 0.25 * t) * env,
            "hex_pitch": 0.03 * np.sin(2 * math.pi * 0.35 * t) * env,
        }, "demo: slalom (rails_y), 0.2-1 Hz sweep (rails_x), heave/roll/pitch (hexapod)")
    raise DataError(f"unknown signal {name!r}; signals: {', '.join(SIGNALS)}")


def load_trajectory(path: Path, rate_hz: float, axis: str | None = None) -> Trajectory:
    """A msgpack stream of input frames, or a CSV with a ``t`` column and axis columns (or
    ``t,cmd`` with ``axis``), resampled to ``rate_hz``.

    Raises
    ------
    DataError
        Naming the file, row and column.
    """
    if path.suffix in (".msgpack", ".mp"):
        times: list[float] = []
        rows: dict[str, list[float]] = {}
        try:
            with path.open("rb") as fh:
                for k, frame in enumerate(msgpack.Unpacker(fh, raw=False)):
                    if not isinstance(frame, dict) or "pos" not in frame:
                        raise DataError(f"{path}: frame {k} is not an input frame")
                    times.append(float(frame.get("t", k / rate_hz)))
                    for a, v in frame["pos"].items():
                        rows.setdefault(a, []).append(float(v))
        except (OSError, ValueError, msgpack.UnpackException) as exc:
            raise DataError(f"{path}: cannot read msgpack stream: {exc}") from None
        t = np.array(times)
        cols = {a: np.array(v) for a, v in rows.items()}
    else:
        try:
            with path.open(newline="") as fh:
                reader = csv.reader(fh)
                header = [h.strip() for h in next(reader)]
                data = [[float(x) for x in row] for row in reader if row]
        except (OSError, StopIteration, ValueError) as exc:
            raise DataError(f"{path}: cannot read CSV: {exc}") from None
        if not header or header[0] != "t":
            raise DataError(f"{path}: first column must be 't', got {header[:1]}")
        arr = np.array(data)
        t = arr[:, 0]
        cols = {}
        for j, name in enumerate(header[1:], start=1):
            if name == "cmd":
                if axis is None:
                    raise DataError(f"{path}: column 'cmd' needs --axis to name its axis")
                name = axis
            elif name not in AXIS_INDEX:
                continue  # other columns (acc, ...) are not setpoints
            cols[name] = arr[:, j]
    for a in cols:
        if a not in AXIS_INDEX:
            raise DataError(f"{path}: unknown axis {a!r}")
    if not cols or t.size < 2:
        raise DataError(f"{path}: no setpoint columns or fewer than 2 samples")
    if np.any(np.diff(t) <= 0):
        i = int(np.argmax(np.diff(t) <= 0)) + 1
        raise DataError(f"{path}: time does not increase at sample {i} (t={t[i]!r})")
    grid = t[0] + np.arange(int((t[-1] - t[0]) * rate_hz) + 1) / rate_hz
    return Trajectory(rate_hz, {a: np.interp(grid, t, v) for a, v in cols.items()}, str(path))


@dataclass(frozen=True)
class PublishStats:
    """What :func:`publish` did."""

    key: str
    seq_start: int
    next_seq: int
    samples: int
    """Samples of the whole run (the trajectory times ``repeat``)."""
    skipped: int
    """Samples not sent because their instants passed while the loop was stalled."""
    stopped: bool
    """Stopped (SIGTERM/SIGINT or ``stop``) before the end."""
    duration_s: float

    @property
    def sent(self) -> int:
        return self.next_seq - self.seq_start

    def text(self) -> str:
        out = (f"published {self.sent} frames (seq {self.seq_start}-{self.next_seq - 1}) of "
               f"{self.samples} samples on {self.key} in {self.duration_s:.1f} s")
        if self.skipped:
            out += (f"; {self.skipped} not sent: their instants passed while this process was "
                    "stalled")
        if self.stopped:
            left = self.samples - self.sent - self.skipped
            out += f"; stopped by a signal with {left} samples still to send"
        return out


def publish(traj: Trajectory, endpoints: ZenohEndpoints, key: str = "sim/motion/setpoint",
            seq_start: int = 0, repeat: int = 1, stop: threading.Event | None = None,
            spin_us: float = 100.0, lead_in_s: float = 0.0, wait_peer_s: float = 0.0,
            progress: Callable[[float], None] | None = None) -> PublishStats:
    """Publish the trajectory (``repeat`` times) on absolute deadlines.

    The motion stays on wall time, as a vehicle model's does: samples whose instants pass while
    this loop is stalled are dropped, not published late (that would stretch the motion in
    time).  ``seq`` counts the frames sent, so it stays consecutive.  With ``wait_peer_s`` > 0
    nothing is sent until a subscriber of ``key`` is reachable; ``progress`` is called with the
    seconds of motion sent so far, about ten times a second.

    Raises
    ------
    NoPeerError
        If no subscriber of ``key`` was reachable within ``wait_peer_s``.
    """
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    axes = [a for a in AXES if a in traj.pos]
    columns = [traj.pos[a].tolist() for a in axes]
    seq = seq_start
    total = traj.samples * repeat
    skipped = 0
    every = max(1, round(traj.rate_hz / 10))
    t_start = time.monotonic()
    with open_session(endpoints) as session:
        if wait_peer_s > 0 and not wait_for_subscriber(session, key, wait_peer_s, stop):
            if not stop.is_set():
                raise NoPeerError(f"no subscriber of {key} reachable within {wait_peer_s:g} s "
                                  f"({endpoints.describe()})")
            return PublishStats(key, seq_start, seq, total, 0, True,
                                time.monotonic() - t_start)
        sink = ZenohSink(session, key)
        if lead_in_s > 0:
            stop.wait(lead_in_s)
        clock = DeadlineClock(traj.rate_hz, spin_us)
        t_wall0, t_mono0 = time.time(), time.perf_counter_ns()
        k = 0  # the sample due at the next deadline
        try:
            while not stop.is_set():
                deadline, _ = clock.wait()
                if clock.skipped:
                    skipped += min(clock.skipped, max(0, total - k))
                    k += clock.skipped
                if k >= total:
                    break
                t = t_wall0 + (deadline - t_mono0) / 1e9  # the sample's nominal time
                i = k % traj.samples
                sink.put(encode_input(seq, t, {a: col[i] for a, col in
                                               zip(axes, columns, strict=True)}))
                seq += 1
                k += 1
                if progress is not None and k % every == 0:
                    progress(k / traj.rate_hz)
        finally:
            sink.close()
    return PublishStats(key, seq_start, seq, total, skipped, stop.is_set() and k < total,
                        time.monotonic() - t_start)
