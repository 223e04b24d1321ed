"""A simulated motion platform speaking motcomp's wire contract, over zenoh + msgpack only.

Written from docs/WIRE.md ("The platform's side", the axis table and "Output frames") alone,
without reading the motcomp package: it shows that the contract is enough to build a platform.

Each of the 8 axes is a pure delay TD followed by a unit-gain first-order lag TP1,
y' = (u(t - TD) - y) / TP1, with u the held setpoint, simulated at --rate Hz (default 1000) and
discretised exactly for the zero-order-hold input (a fractional delay splits the cycle in two).
Defaults: TD = 20 ms and TP1 = 50 ms, rails_y TP1 = 150 ms; --truth AXIS=TD_MS,TP1_MS overrides.
--drift AXIS=TD_MS,TP1_MS@T changes an axis' truth T seconds after the start, or @usr1 when the
process receives SIGUSR1 (said on stderr): a platform whose lag drifts, to try a supervisor on.

- `platform/setpoint` frames are applied at the first control cycle after they arrive and held
  (zero-order hold); a frame that breaks the contract is counted as bad and ignored.
- `platform/feedback`: one frame per cycle, {"t", "pos", "acc"}; `t` is the cycle's start on
  the wall clock (epoch s), `acc` the second difference of the simulated positions.
- `platform/status`, about 1 Hz: median and mean setpoint age (application instant - `t`, last
  10 s), ticks, missed_ticks, frames, bad_frames, and the service's current flags.
- Missed cycles (a stall) are simulated without publishing, so the model stays on wall time.

Run (Ctrl-C or SIGTERM stops it, exit 0, one summary line on stderr):

    python tools/wire_platform.py -l tcp/127.0.0.1:7448 -e tcp/127.0.0.1:7447 \\
        --truth rails_y=20,150 --truth hex_z=30,5 --duration 60
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import os
import signal
import sys
import threading
import time
from typing import Any

import msgpack
import numpy as np
import zenoh

ONE_THREAD = ("(rx: (handover: app), acc: (handover: app), tx: (handover: app), "
              "net: (handover: app))")
"""zenoh's ZENOH_RUNTIME for all of its tasks on one thread, set at the start unless the
environment says otherwise: at 1 kHz its receiving, transmitting and accepting threads cost more
than the work they share."""

AXES = ("rails_x", "rails_y", "hex_x", "hex_y", "hex_z", "hex_roll", "hex_pitch", "hex_yaw")
DEFAULT_TRUTH_MS = {a: (20.0, 150.0 if a == "rails_y" else 50.0) for a in AXES}
AGE_WINDOW_S = 10.0
TIMEOUT_S = 1.0  # no setpoint for this long: say so, and keep holding the last one


def parse_truth(specs: list[str]) -> dict[str, tuple[float, float]]:
    """Parse --truth AXIS=TD_MS,TP1_MS options over the defaults (ms)."""
    truth = dict(DEFAULT_TRUTH_MS)
    for spec in specs:
        try:
            axis, values = spec.split("=", 1)
            td, tp1 = (float(v) for v in values.split(","))
        except ValueError:
            raise ValueError(f"bad --truth {spec!r} (AXIS=TD_MS,TP1_MS)") from None
        if axis not in AXES or not (td >= 0 and tp1 >= 0 and math.isfinite(td + tp1)):
            raise ValueError(f"bad --truth {spec!r}: axes {', '.join(AXES)}, "
                             "TD and TP1 finite and >= 0")
        truth[axis] = (td, tp1)
    return truth


def parse_drift(spec: str) -> tuple[str, float, float, float]:
    """Parse --drift AXIS=TD_MS,TP1_MS@T: (axis, TD ms, TP1 ms, T s); T = usr1: infinity (the
    drift waits for SIGUSR1)."""
    truth, sep, at = spec.rpartition("@")
    if not sep:
        raise ValueError(f"bad --drift {spec!r} (AXIS=TD_MS,TP1_MS@SECONDS)")
    axis = truth.split("=", 1)[0]
    try:
        td, tp1 = parse_truth([truth])[axis]
    except ValueError as exc:
        raise ValueError(str(exc).replace("--truth", "--drift")) from None
    if at == "usr1":
        return axis, td, tp1, math.inf
    try:
        t = float(at)
    except ValueError:
        raise ValueError(f"bad --drift {spec!r}: SECONDS is not a number nor usr1") from None
    if not (math.isfinite(t) and t >= 0):
        raise ValueError(f"bad --drift {spec!r}: SECONDS finite and >= 0")
    return axis, td, tp1, t


class Plant:
    """The 8 axes' delay + first-order lag, exact for an input held over each cycle."""

    def __init__(self, truth_ms: dict[str, tuple[float, float]], rate: float,
                 max_delay_ms: float = 0.0) -> None:
        self.rate = rate
        self.n = np.zeros(len(AXES), dtype=np.int64)  # whole cycles of delay ...
        self.phi1 = np.zeros(len(AXES))
        self.phi2 = np.zeros(len(AXES))
        for i, a in enumerate(AXES):
            self.set_truth(i, *truth_ms[a])
        longest = max(max(td for td, _ in truth_ms.values()), max_delay_ms)
        self.size = math.floor(longest * rate / 1000.0 + 1e-9) + 2  # u[k-n-1] .. u[k]
        self.u = np.zeros((self.size, len(AXES)))
        self.cols = np.arange(len(AXES))
        self.y = np.zeros(len(AXES))

    def set_truth(self, i: int, td_ms: float, tp1_ms: float) -> None:
        """Axis i's delay and time constant from the next cycle on (the position carries on)."""
        h = 1.0 / self.rate
        delay = td_ms * self.rate / 1000.0
        if abs(delay - round(delay)) < 1e-9:
            delay = float(round(delay))
        self.n[i] = math.floor(delay)
        frac = delay - self.n[i]  # ... and the fraction f of a cycle
        tp1 = tp1_ms / 1000.0
        if tp1 > 0:
            self.phi1[i] = math.exp(-frac * h / tp1)
            self.phi2[i] = math.exp(-(1.0 - frac) * h / tp1)
        else:  # a pure delay (phi = 0 over any interval)
            self.phi1[i], self.phi2[i] = (0.0 if frac > 0 else 1.0), 0.0

    def step(self, k: int, u: np.ndarray) -> None:
        """Hold u over cycle k: y[k] -> y[k+1].

        On [kh, kh + f h) the delayed input is u[k-n-1], on [kh + f h, (k+1) h) it is u[k-n];
        each part applies the exact exponential of its duration.
        """
        self.u[k % self.size] = u
        early = self.u[(k - self.n - 1) % self.size, self.cols]
        late = self.u[(k - self.n) % self.size, self.cols]
        mid = self.phi1 * self.y + (1.0 - self.phi1) * early
        self.y = self.phi2 * mid + (1.0 - self.phi2) * late


def wall_time_at(instant: float) -> float:
    """The wall clock (epoch s) at a time.perf_counter() instant, read between two perf reads."""
    for _ in range(3):  # a read pre-empted between the clocks is retried
        before, wall, after = time.perf_counter(), time.time(), time.perf_counter()
        if after - before < 20e-6:
            break
    return wall - (0.5 * (before + after) - instant)


def decode_setpoint(payload: bytes) -> tuple[int, float, np.ndarray, list[str]]:
    """Check one `platform/setpoint` frame against the contract; ValueError if it breaks it."""
    try:
        frame = msgpack.unpackb(payload, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types
        raise ValueError(f"not msgpack: {exc}") from None
    if not isinstance(frame, dict):
        raise ValueError("not a map")
    seq, t, pos, flags = frame.get("seq"), frame.get("t"), frame.get("pos"), frame.get("flags", [])
    if not isinstance(seq, int) or isinstance(seq, bool):
        raise ValueError("seq is not an int")
    if not isinstance(t, (int, float)) or isinstance(t, bool) or not math.isfinite(t):
        raise ValueError("t is not a finite number")
    if not isinstance(pos, dict) or set(pos) != set(AXES):
        raise ValueError("pos does not carry exactly the 8 axes")
    values = [pos[a] for a in AXES]
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        raise ValueError("a position is not a number")
    arr = np.array(values, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise ValueError("a position is not finite")
    if not isinstance(flags, list) or not all(isinstance(f, str) for f in flags):
        raise ValueError("flags is not a list of strings")
    return seq, float(t), arr, flags


class Platform:
    """The control loop: setpoints in, simulation, feedback and status out."""

    def __init__(self, session: Any, args: argparse.Namespace,
                 truth_ms: dict[str, tuple[float, float]], stop: threading.Event,
                 drifts: list[tuple[str, float, float, float]] | None = None) -> None:
        self.rate = float(args.rate)
        self.h = 1.0 / self.rate
        drifts = drifts or []
        self.plant = Plant(truth_ms, self.rate, max((d[1] for d in drifts), default=0.0))
        self.drifts = sorted(drifts, key=lambda d: d[3])  # (axis, TD ms, TP1 ms, at s)
        self.usr1 = threading.Event()  # the drifts @usr1 are due
        self.feedback = session.declare_publisher(args.feedback_key, express=True)
        self.status = session.declare_publisher(args.status_key)
        self.inbox: collections.deque[tuple[float, bytes]] = collections.deque()
        self.frames = self.bad = self.ticks = self.missed = 0
        self.u = np.zeros(len(AXES))  # the setpoint in force (neutral until the first frame)
        self.y1 = self.y2 = np.zeros(len(AXES))  # y[k-1], y[k-2]
        self.seq: int | None = None
        self.flags: list[str] = []
        self.last_bad = ""
        self.flags_logged_at = -math.inf
        self.last_frame_at: float | None = None
        self.timed_out = False
        n_ages = int(AGE_WINDOW_S * self.rate) + 16
        self.ages = np.full(n_ages, np.nan)  # ring of (application instant, age)
        self.age_at = np.full(n_ages, -np.inf)
        self.n_ages = 0
        self.stop = stop
        self.sub = session.declare_subscriber(args.setpoint_key, self._on_setpoint)

    def _on_setpoint(self, sample: Any) -> None:
        """zenoh's thread: stamp the arrival and queue the bytes (decoded by the loop)."""
        self.inbox.append((time.perf_counter(), sample.payload.to_bytes()))
        self.frames += 1

    def _take_frames(self, deadline: float, t_wall: float) -> None:
        """Apply the newest valid frame that arrived before this cycle's start (zero-order hold)."""
        newest: tuple[int, float, np.ndarray, list[str]] | None = None
        while self.inbox and self.inbox[0][0] <= deadline:
            _, payload = self.inbox.popleft()
            try:
                newest = decode_setpoint(payload)
            except ValueError as exc:
                self.bad += 1
                self.last_bad = str(exc)[:200]
        if newest is None:
            return
        seq, t, self.u, flags = newest
        if self.seq is not None and seq <= self.seq:
            print(f"wire_platform: setpoint seq {self.seq} -> {seq}: a restarted service",
                  file=sys.stderr)
        if flags != self.flags and t_wall - self.flags_logged_at >= 1.0:  # at most 1/s
            print(f"wire_platform: flags {flags}", file=sys.stderr)  # informational only
            self.flags_logged_at = t_wall
        self.seq, self.flags = seq, flags
        i = self.n_ages % len(self.ages)
        self.ages[i], self.age_at[i] = t_wall - t, t_wall
        self.n_ages += 1
        if self.timed_out:
            print("wire_platform: setpoints are back", file=sys.stderr)
        self.last_frame_at, self.timed_out = t_wall, False

    def _cycle(self, k: int, deadline: float, publish: bool) -> None:
        """Cycle k starting at `deadline` (perf_counter): take setpoints, sample, step."""
        t_wall = wall_time_at(deadline)  # the cycle's start, epoch s
        self._take_frames(deadline, t_wall)
        y = self.plant.y
        if publish:
            acc = (y - 2.0 * self.y1 + self.y2) * self.rate**2
            self.feedback.put(msgpack.packb({
                "t": t_wall, "pos": dict(zip(AXES, y.tolist(), strict=True)),
                "acc": dict(zip(AXES, acc.tolist(), strict=True))}))
        if (not self.timed_out and self.last_frame_at is not None
                and t_wall - self.last_frame_at > TIMEOUT_S):
            self.timed_out = True
            print(f"wire_platform: no setpoint for {TIMEOUT_S} s, holding the last one",
                  file=sys.stderr)
        self.plant.step(k, self.u)
        self.y2, self.y1 = self.y1, y

    def age_stats(self) -> tuple[float, float] | None:
        """Median and mean setpoint age (ms) over the last AGE_WINDOW_S, None without data."""
        recent = self.ages[self.age_at >= time.time() - AGE_WINDOW_S]
        if recent.size == 0:
            return None
        return float(np.median(recent)) * 1e3, float(np.mean(recent)) * 1e3

    def _publish_status(self) -> None:
        status: dict[str, Any] = {"t": time.time(), "ticks": self.ticks,
                                  "missed_ticks": self.missed, "frames": self.frames,
                                  "bad_frames": self.bad, "last_bad": self.last_bad,
                                  "flags": self.flags, "rate_hz": self.rate}
        if (ages := self.age_stats()) is not None:
            status["setpoint_age_ms"], status["setpoint_age_mean_ms"] = ages
        self.status.put(msgpack.packb(status))

    def run(self, duration: float | None) -> None:
        """Run cycles on absolute deadlines until stopped; missed cycles are simulated silently."""
        start = deadline = time.perf_counter() + self.h
        next_status = start + 1.0
        k = 0
        while not self.stop.is_set() and (duration is None or deadline - start < duration):
            while self.drifts and (deadline - start >= self.drifts[0][3] or (
                    self.usr1.is_set() and math.isinf(self.drifts[0][3]))):
                axis, td, tp1, _ = self.drifts.pop(0)
                self.plant.set_truth(AXES.index(axis), td, tp1)
                print(f"wire_platform: {axis} truth now TD = {td:g} ms, TP1 = {tp1:g} ms "
                      f"({deadline - start:.2f} s after the start, at epoch "
                      f"{wall_time_at(deadline):.3f} s)", file=sys.stderr, flush=True)
            # one sleep, no spin: a cycle that wakes late still takes only the frames stamped
            # on arrival before its start, and its feedback carries the start as `t`
            while (wait := deadline - time.perf_counter()) > 0:
                time.sleep(wait)
            late = int((time.perf_counter() - deadline) / self.h)
            for _ in range(late):  # a stall: stay on wall time without a burst of feedback
                self._cycle(k, deadline, publish=False)
                k, deadline, self.missed = k + 1, deadline + self.h, self.missed + 1
            self._cycle(k, deadline, publish=True)
            k, deadline, self.ticks = k + 1, deadline + self.h, self.ticks + 1
            if deadline >= next_status:
                self._publish_status()
                next_status = max(next_status + 1.0, deadline)

    def close(self) -> None:
        self.sub.undeclare()
        self.feedback.undeclare()
        self.status.undeclare()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("-c", "--zenoh-config", help="zenoh config file (JSON5)")
    ap.add_argument("-e", "--connect", action="append", default=[], help="endpoint to connect to")
    ap.add_argument("-l", "--listen", action="append", default=[], help="endpoint to listen on")
    ap.add_argument("--rate", type=float, default=1000.0, help="control rate, Hz (1000)")
    ap.add_argument("--truth", action="append", default=[], metavar="AXIS=TD_MS,TP1_MS",
                    help="an axis' delay and time constant, ms (default 20,50; rails_y 20,150)")
    ap.add_argument("--drift", action="append", default=[], metavar="AXIS=TD_MS,TP1_MS@T",
                    help="change an axis' delay and time constant T seconds after the start "
                         "(T = usr1: when the process receives SIGUSR1)")
    ap.add_argument("--duration", type=float, help="stop after this many seconds")
    ap.add_argument("--feedback-key", default="platform/feedback")
    ap.add_argument("--setpoint-key", default="platform/setpoint")
    ap.add_argument("--status-key", default="platform/status")
    args = ap.parse_args()
    if not (math.isfinite(args.rate) and 1.0 <= args.rate <= 20000.0):
        ap.error("--rate must be within 1-20000 Hz")
    if not (args.connect or args.listen or args.zenoh_config):
        ap.error("give -e/--connect and/or -l/--listen endpoints (multicast scouting is off)")
    try:
        truth = parse_truth(args.truth)  # reject bad --truth and --drift before opening zenoh
        drifts = [parse_drift(d) for d in args.drift]
    except ValueError as exc:
        ap.error(str(exc))
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)  # before zenoh opens: a stop at any time exits 0
    signal.signal(signal.SIGINT, on_signal)
    usr1 = threading.Event()
    signal.signal(signal.SIGUSR1, lambda *_: usr1.set())

    os.environ.setdefault("ZENOH_RUNTIME", ONE_THREAD)  # before zenoh's runtime starts
    conf = zenoh.Config.from_file(args.zenoh_config) if args.zenoh_config else zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    if args.connect:
        conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    if args.listen:
        conf.insert_json5("listen/endpoints", json.dumps(args.listen))
    sys.setswitchinterval(2e-4)  # let zenoh's callbacks in promptly while the loop runs
    with zenoh.open(conf) as session:
        platform = Platform(session, args, truth, stop, drifts)
        platform.usr1 = usr1
        try:
            platform.run(args.duration)
        finally:
            platform.close()
    ages = platform.age_stats()
    print(f"wire_platform: {platform.frames} setpoint frames received, {platform.bad} bad, "
          f"{platform.ticks} cycles, {platform.missed} missed, median setpoint age "
          + (f"{ages[0]:.2f} ms" if ages else "n/a"), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
