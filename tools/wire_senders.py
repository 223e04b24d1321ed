"""Motion-setpoint senders written from docs/WIRE.md alone, as a lab's vehicle model would.

Each sender publishes ``{"seq": int, "t": float, "pos": {axis: float}}`` msgpack maps on
``sim/motion/setpoint`` from a motion function of time, in one of these ways (``KINDS``):

==========  ==================================================================================
kind        what it does
==========  ==================================================================================
grid        value at the exact grid instant k/rate, stamped t = t0 + k/rate, sent 0-600 us late
float32     grid, with the positions packed as msgpack float32 (t stays float64)
epoch       grid stamps; each value computed at its stamp, motion(t - t0), in epoch float64
wallclock   each value computed at t = time.time() when the loop wakes, 100-300 us after its
            deadline (plus the sleep's own lateness); late samples skipped
varstep     variable-step solver: steps of 0.5-2 ms at random, value computed at the stamp
no_t        grid values and send times, no ``t`` field
stalls      grid, stalling 50-100 ms about every ``stall_every_s``; afterwards it skips to the
            newest due sample (``stall_policy="skip"``, as WIRE.md asks) or sends the backlog
            in a burst (``"burst"``)
busy        a vehicle model on a busy PC: each value computed at t = time.time() when the loop
            wakes, 400-500 us after its deadline, and a stall of 20-30 ms (``stall_ms``) about
            every ``stall_every_s``, after which it skips to the newest due sample
==========  ==================================================================================

Any kind may pause (``pause``: from ``at`` s after its start, for ``for`` s): it sends nothing
meanwhile, then goes on at the motion's time then (an input pause and resume).

``t0`` is ``time.time()`` when the sender starts; every ``t`` is on that clock (epoch seconds).
Every sender skips a sample it would send later than one period plus its designed jitter
(WIRE.md: "a sender that falls behind should skip samples (with t), not send them late"),
except the backlog of a ``burst`` stall.  ``seq`` counts the frames sent, from ``seq_start``.

Example::

    python tools/wire_senders.py --kind wallclock --rate 1000 --axis rails_y --signal slalom \\
        --duration 30 -e tcp/127.0.0.1:7447
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import msgpack
import numpy as np
import zenoh

KEY = "sim/motion/setpoint"
AXES = ("rails_x", "rails_y", "hex_x", "hex_y", "hex_z", "hex_roll", "hex_pitch", "hex_yaw")
KINDS = ("grid", "float32", "epoch", "wallclock", "varstep", "no_t", "stalls", "busy")

GRID_JITTER_S = (0.0, 600e-6)
WALLCLOCK_LATE_S = (100e-6, 300e-6)
BUSY_LATE_S = (400e-6, 500e-6)
BUSY_STALL_MS = (20.0, 30.0)
VARSTEP_S = (0.5e-3, 2.0e-3)


@dataclass(frozen=True)
class Sine:
    """``amplitude_m * sin(2 pi frequency_hz tau)``, tau in s from the motion's start."""

    amplitude: float
    frequency_hz: float

    def __call__(self, tau_s: float) -> float:
        return self.amplitude * math.sin(2.0 * math.pi * self.frequency_hz * tau_s)


# name -> (signal, axis it drives by default)
SIGNALS: dict[str, tuple[Sine, str]] = {
    "slalom": (Sine(0.4, 0.31), "rails_y"),
    "heave": (Sine(0.05, 0.5), "hex_z"),
}


@dataclass(frozen=True)
class SenderSpec:
    """How a sender times, stamps and encodes its samples (see the module docstring)."""

    kind: str = "grid"
    rate_hz: float = 1000.0
    seed: int | None = None
    seq_start: int = 0
    stall_every_s: float = 3.0
    stall_ms: tuple[float, float] = (50.0, 100.0)
    stall_policy: str = "skip"
    pause: tuple[float, float] | None = None
    """``(at_s, for_s)``: send nothing from ``at_s`` after the start for ``for_s``."""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"sender kind {self.kind!r}: expected one of {', '.join(KINDS)}")
        if not (math.isfinite(self.rate_hz) and 1.0 <= self.rate_hz <= 10000.0):
            raise ValueError(f"sender rate_hz = {self.rate_hz!r}: expected 1-10000 Hz")
        if self.stall_policy not in ("skip", "burst"):
            raise ValueError(f"stall_policy = {self.stall_policy!r}: expected 'skip' or 'burst'")
        lo, hi = self.stall_ms
        if not (0.0 <= lo <= hi) or not self.stall_every_s > 0.0:
            raise ValueError(
                f"stalls: stall_ms = {self.stall_ms!r} (need 0 <= A <= B), "
                f"stall_every_s = {self.stall_every_s!r} (need > 0)"
            )
        if self.pause is not None and not (self.pause[0] >= 0.0 and self.pause[1] > 0.0):
            raise ValueError(f"pause = {self.pause!r}: expected (at >= 0 s, for > 0 s)")


@dataclass
class SendLog:
    """What a run did: per frame its sample instant and send instant (s, time.time())."""

    spec: SenderSpec
    t0_s: float = 0.0
    sample_s: list[float] = field(default_factory=list)
    nominal_s: list[float] = field(default_factory=list)
    sent_s: list[float] = field(default_factory=list)
    skipped: int = 0
    stalls: int = 0
    paused: int = 0
    """Samples not sent during the pause."""
    resumed_s: float | None = None
    """``t`` of the first sample sent after the pause."""

    def summary(self) -> dict[str, object]:
        """Counts and timing percentiles (us): sample instant vs its nominal, send vs sample."""
        sample = np.asarray(self.sample_s)
        offset_us = (sample - np.asarray(self.nominal_s)) * 1e6
        late_us = (np.asarray(self.sent_s) - sample) * 1e6

        def pct(x: np.ndarray) -> dict[str, float]:
            if x.size == 0:
                return {}
            p50, p99 = np.percentile(x, [50, 99])
            return {"p50": round(float(p50), 1), "p99": round(float(p99), 1),
                    "max": round(float(x.max()), 1)}

        span = float(sample[-1] - sample[0]) if sample.size > 1 else 0.0
        return {
            "kind": self.spec.kind,
            "rate_hz": self.spec.rate_hz,
            "t0_s": self.t0_s,
            "frames": int(sample.size),
            "mean_rate_hz": round((sample.size - 1) / span, 2) if span > 0 else None,
            "skipped": self.skipped,
            "stalls": self.stalls,
            "paused": self.paused,
            "resumed_s": self.resumed_s,
            "sample_offset_us": pct(offset_us),
            "send_late_us": pct(late_us),
        }


def encode_frame(seq: int, t_s: float | None, pos: Mapping[str, float],
                 float32: bool = False) -> bytes:
    """One input frame as WIRE.md defines it; ``t_s=None`` leaves ``t`` out.

    With ``float32`` the positions are packed as msgpack float32, ``seq`` and ``t`` as usual.
    """
    head = {"seq": seq} if t_s is None else {"seq": seq, "t": t_s}
    packer = msgpack.Packer()
    return (
        packer.pack_map_header(len(head) + 1)
        + b"".join(packer.pack(k) + packer.pack(v) for k, v in head.items())
        + packer.pack("pos")
        + msgpack.Packer(use_single_float=float32).pack(dict(pos))
    )


class Clock:
    """The sender's wall clock and sleep (injectable for tests)."""

    def __init__(self, now: Callable[[], float] = time.time,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.now = now
        self.sleep = sleep

    def sleep_until(self, t_s: float) -> None:
        remaining = t_s - self.now()
        if remaining > 0.0:
            self.sleep(remaining)


def run_sender(publish: Callable[[bytes], None], motion: Mapping[str, Callable[[float], float]],
               spec: SenderSpec, duration_s: float, clock: Clock | None = None) -> SendLog:
    """Publish ``motion`` (axis -> position at tau s) for ``duration_s`` the way ``spec`` says.

    Raises ValueError for an unknown axis or a non-positive duration.
    """
    unknown = sorted(set(motion) - set(AXES))
    if unknown or not motion:
        raise ValueError(f"motion axes {sorted(motion)!r}: expected a non-empty subset of {AXES}")
    if not (math.isfinite(duration_s) and duration_s > 0.0):
        raise ValueError(f"duration_s = {duration_s!r}: expected a positive number of seconds")
    clock = clock or Clock()
    rng = np.random.default_rng(spec.seed)
    log = SendLog(spec)
    t0 = log.t0_s = clock.now()
    end = t0 + duration_s
    seq = spec.seq_start

    pause = ((t0 + spec.pause[0], t0 + spec.pause[0] + spec.pause[1]) if spec.pause
             else (math.inf, math.inf))

    def send(tau_s: float, t_s: float | None, nominal_s: float) -> None:
        nonlocal seq
        if pause[0] <= nominal_s < pause[1]:
            log.paused += 1
            return
        if log.resumed_s is None and nominal_s >= pause[1]:
            log.resumed_s = t0 + tau_s if t_s is None else t_s
        pos = {axis: f(tau_s) for axis, f in motion.items()}
        publish(encode_frame(seq, t_s, pos, float32=spec.kind == "float32"))
        log.sent_s.append(clock.now())
        log.sample_s.append(t0 + tau_s if t_s is None else t_s)
        log.nominal_s.append(nominal_s)
        seq += 1

    if spec.kind == "varstep":
        _run_varstep(send, clock, rng, log, t0, end)
    elif spec.kind in ("wallclock", "busy"):
        _run_wallclock(send, clock, rng, log, spec, t0, end)
    else:
        _run_grid(send, clock, rng, log, spec, t0, end)
    return log


def _run_grid(send: Callable[[float, float | None, float], None], clock: Clock,
              rng: np.random.Generator, log: SendLog, spec: SenderSpec, t0: float,
              end: float) -> None:
    """grid, float32, epoch, no_t, stalls: samples on t0 + k/rate, sent 0-600 us late."""
    period = 1.0 / spec.rate_hz
    late_limit = period + GRID_JITTER_S[1]
    stalling = spec.kind == "stalls"
    next_stall = t0 + rng.exponential(spec.stall_every_s) if stalling else math.inf
    backlog_until = -1  # burst policy: samples up to this index go out however late
    k = 0
    while (t_k := t0 + k / spec.rate_hz) < end:
        clock.sleep_until(t_k + rng.uniform(*GRID_JITTER_S))
        now = clock.now()
        if now >= next_stall:
            clock.sleep(rng.uniform(*spec.stall_ms) / 1000.0)
            log.stalls += 1
            next_stall = clock.now() + rng.exponential(spec.stall_every_s)
            now = clock.now()
            if spec.stall_policy == "burst":
                backlog_until = math.floor((now - t0) * spec.rate_hz)
        if k > backlog_until and now - t_k > late_limit:
            newest = math.floor((now - t0) * spec.rate_hz)
            log.skipped += newest - k
            k = newest
            continue  # send the newest due sample (after its own jitter)
        tau = (t_k - t0) if spec.kind == "epoch" else k / spec.rate_hz
        send(tau, None if spec.kind == "no_t" else t_k, t_k)
        k += 1


def _run_wallclock(send: Callable[[float, float | None, float], None], clock: Clock,
                   rng: np.random.Generator, log: SendLog, spec: SenderSpec, t0: float,
                   end: float) -> None:
    """Wake 100-300 us (busy: 400-500 us) after each deadline, compute and stamp at
    time.time(); busy: a stall of 20-30 ms now and then, then on with the newest sample."""
    rate_hz = spec.rate_hz
    period = 1.0 / rate_hz
    late = BUSY_LATE_S if spec.kind == "busy" else WALLCLOCK_LATE_S
    next_stall = t0 + rng.exponential(spec.stall_every_s) if spec.kind == "busy" else math.inf
    k = 0
    while (deadline := t0 + k * period) < end:
        clock.sleep_until(deadline + rng.uniform(*late))
        if clock.now() >= next_stall:
            clock.sleep(rng.uniform(*spec.stall_ms) / 1000.0)
            log.stalls += 1
            next_stall = clock.now() + rng.exponential(spec.stall_every_s)
        t = clock.now()
        if t - deadline > period + late[1]:
            newest = math.floor((t - t0) * rate_hz)
            log.skipped += newest - k
            k = newest
            continue
        send(t - t0, t, deadline)
        k += 1


def _run_varstep(send: Callable[[float, float | None, float], None], clock: Clock,
                 rng: np.random.Generator, log: SendLog, t0: float, end: float) -> None:
    """Steps of 0.5-2 ms at random; each sample sent at its instant, stamped with it."""
    t = t0
    while t < end:
        clock.sleep_until(t)
        while clock.now() - t > VARSTEP_S[1]:  # fell behind: skip whole steps
            t += rng.uniform(*VARSTEP_S)
            log.skipped += 1
        send(t - t0, t, t)
        t += rng.uniform(*VARSTEP_S)


def zenoh_config(connect: list[str], listen: list[str], config_file: str | None = None,
                 scouting: bool = False) -> zenoh.Config:
    """A zenoh config as the service's clients take it (-c, -e, -l, --scouting)."""
    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(scouting))
    return conf


def main(conf: zenoh.Config, key: str, motion: Mapping[str, Callable[[float], float]],
         spec: SenderSpec, duration_s: float, wait_peer_s: float) -> dict[str, object]:
    """Open a session, wait for a subscriber of ``key``, send, return the run's summary.

    Raises TimeoutError when no subscriber matches within ``wait_peer_s`` (0: don't wait).
    """
    with zenoh.open(conf) as session:
        publisher = session.declare_publisher(key)
        deadline = time.monotonic() + wait_peer_s
        # zenoh 1.x returns a MatchingStatus here (its type stub says bool)
        while wait_peer_s > 0 and not publisher.matching_status.matching:  # type: ignore[attr-defined]
            if time.monotonic() > deadline:
                raise TimeoutError(f"no subscriber of {key!r} within {wait_peer_s} s")
            time.sleep(0.05)
        log = run_sender(publisher.put, motion, spec, duration_s)
        publisher.undeclare()
    return log.summary()


def _parse_stall_ms(text: str) -> tuple[float, float]:
    lo, sep, hi = text.partition("-")
    try:
        return (float(lo), float(hi)) if sep else (float(lo), float(lo))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--stall-ms {text!r}: expected A-B in ms") from None


def cli(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--kind", choices=KINDS, default="grid")
    p.add_argument("--rate", type=float, default=1000.0, help="sample rate, Hz (not varstep)")
    p.add_argument("--signal", action="append", choices=sorted(SIGNALS),
                   help="motion to send, each on its own axis (repeatable: one frame carries "
                        "them all; default: slalom)")
    p.add_argument("--axis", action="append", choices=AXES,
                   help="axis driven by the signal (repeatable, with one --signal; default: "
                        "the signal's own)")
    p.add_argument("--duration", type=float, default=20.0, help="seconds of motion")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--seq-start", type=int, default=0)
    p.add_argument("--stall-every-s", type=float, default=3.0, help="stalls: mean interval")
    p.add_argument("--stall-ms", type=_parse_stall_ms, default=None,
                   help="stalls, busy: durations A-B ms (default 50-100; busy 20-30)")
    p.add_argument("--pause-at", type=float, default=None,
                   help="send nothing from S s after the start ...")
    p.add_argument("--pause-for", type=float, default=4.0, help="... for S s (default 4)")
    p.add_argument("--stall-policy", choices=("skip", "burst"), default="skip")
    p.add_argument("--key", default=KEY)
    p.add_argument("--wait-peer", type=float, default=5.0,
                   help="wait up to S s for a subscriber, exit 3 if none (0: don't wait)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    z = p.add_argument_group("zenoh")
    z.add_argument("-c", "--zenoh-config", default=None)
    z.add_argument("-e", "--connect", action="append", default=[])
    z.add_argument("-l", "--listen", action="append", default=[])
    z.add_argument("--scouting", action="store_true")
    a = p.parse_args(argv)

    names = list(dict.fromkeys(a.signal or ["slalom"]))
    if a.axis and len(names) > 1:
        p.error("--axis goes with one --signal (several signals each drive their own axis)")
    motion = ({axis: SIGNALS[names[0]][0] for axis in a.axis} if a.axis else
              {SIGNALS[name][1]: SIGNALS[name][0] for name in names})
    try:
        stall_ms = a.stall_ms or (BUSY_STALL_MS if a.kind == "busy" else (50.0, 100.0))
        pause = None if a.pause_at is None else (a.pause_at, a.pause_for)
        spec = SenderSpec(a.kind, a.rate, a.seed, a.seq_start, a.stall_every_s, stall_ms,
                          a.stall_policy, pause)
        conf = zenoh_config(a.connect, a.listen, a.zenoh_config, a.scouting)
        summary = main(conf, a.key, motion, spec, a.duration, a.wait_peer)
    except ValueError as exc:
        print(f"wire_senders: {exc}", file=sys.stderr)
        return 2
    except TimeoutError as exc:
        print(f"wire_senders: {exc}", file=sys.stderr)
        return 3
    if a.json:
        print(json.dumps(summary))
    else:
        print(f"{summary['kind']}: {summary['frames']} frames on {a.key} "
              f"({summary['mean_rate_hz']} Hz mean), {summary['skipped']} skipped, "
              f"{summary['stalls']} stalls; sample offset us {summary['sample_offset_us']}, "
              f"send lateness us {summary['send_late_us']}")
    return 0


if __name__ == "__main__":
    sys.exit(cli())
