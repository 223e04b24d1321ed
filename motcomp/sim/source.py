"""``motcomp source``: a motion source publishing setpoint frames at a fixed rate.

It stands in for the vehicle model and motion cueing: built-in trajectories (a slalom and a
lane change on the rails, swept sines, a demo mix of rails and hexapod motion) or a file -- a
msgpack stream of input frames (what ``motcomp excite`` writes) or a CSV ``t,<axis>...`` (or
``t,cmd`` with ``--axis``) -- published on ``sim/motion/setpoint`` on absolute deadlines.

Realistic senders (:class:`SenderTiming`): a live vehicle model is not perfectly timed.  Each
frame can go out late by a random amount (jitter), the sender can stop now and then (stalls),
and it can leave ``t`` out (the receiver then times the samples by their arrival).  Sample ``k``
is due at its nominal instant ``t0 + k / rate``, which its frame's ``t`` always carries (a float64
epoch time, rounded by up to 0.12 us: the value sent is the sample's corrected by its slope for
that rounding, so that it is the motion at ``t`` itself, as docs/WIRE.md asks)::

    nominal   |---------|---------|---------|---------|---------|---------|   (1 / rate)
    sent        *          *        [====== stall ======)***    *       *
                (each late by U[0, J])                  (burst: the frames due meanwhile)

A stall holds every frame due during it until its end, where they go out at once, in order, as
a vehicle model catching up does: their ``t`` are their own instants, so with ``t`` the motion
keeps its timeline; without ``t`` a receiver sees a gap, then a burst.  (docs/WIRE.md asks a
sender that falls behind to skip samples instead: this one misbehaves on purpose.)  Stalls of
this process itself (the machine's) are handled as before: a sample whose send instant passed
more than a period ago is dropped.
"""

from __future__ import annotations

import csv
import difflib
import math
import secrets
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import msgpack
import numpy as np

from motcomp.core.axes import AXES, AXIS_INDEX
from motcomp.core.minjerk import min_jerk
from motcomp.core.models import P1D
from motcomp.design.timedomain import fade_envelope, slalom, swept_sine
from motcomp.errors import ConfigError, DataError
from motcomp.io.wire import encode_input
from motcomp.io.zenoh_io import (
    NoPeerError,
    ZenohEndpoints,
    ZenohSink,
    open_session,
    wait_for_subscriber,
)
from motcomp.runtime.clock import (
    TIMER_SLACK_NS,
    SleepLead,
    frozen_heap,
    set_timer_slack,
    sleep_until,
)

__all__ = ["PublishStats", "Send", "SenderTiming", "Trajectory", "band_sweep", "builtin",
           "lane_change", "load_trajectory", "publish", "send_schedule"]

SIGNALS = ("bandsweep", "demo", "driving", "lanechange", "slalom", "sweep")

RAILS_MODEL = P1D(K=1.0, Td=0.0175, Tp1=0.1857683128)
"""The rails preset's model, whose exact inverse sizes ``bandsweep`` (written out here, so that
the signal does not change when the preset does)."""
RAILS_ACC_MAX_M_S2 = 6.0
"""The rails' acceleration limit (config/motcomp.toml)."""
SIGNAL_ACC_FRACTION = 0.8
"""``lanechange`` and ``bandsweep`` keep within this fraction of :data:`RAILS_ACC_MAX_M_S2`."""


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
    """A built-in trajectory sampled at ``rate_hz``.

    ``slalom``
        rails_y, 18 m cones at 40 km/h (22.2 s).
    ``sweep``
        rails_x, 0.1-3 Hz within the rails' acceleration limit (``duration_s``, default 60 s).
    ``demo``
        ~12 s: slalom on rails_y, a 0.2-1 Hz sweep on rails_x, heave/roll/pitch sines on the
        hexapod.
    ``lanechange``
        rails_y, :func:`lane_change`: 1 s at rest, 1.5 m aside in 2 s (minimum-jerk), 2 s
        there, back in 2 s, 1 s at rest (8 s).  Peak acceleration ``10/sqrt(3) 1.5 / 2^2 =
        2.17 m/s^2``, 36 % of the rails' 6 m/s^2 (its exact inverse, below: 2.6 m/s^2); peak
        speed 1.41 m/s (limit 2 m/s).
    ``driving``
        rails_y, :func:`ordinary_driving`: 0.3 m slaloms at 0.3 Hz and minimum-jerk lane
        changes of 0.5-1 m in 3-4 s, in a seeded order (``duration_s``, default 120 s).
    ``bandsweep``
        rails_x, :func:`band_sweep`: 1 s at rest, a logarithmic sweep over the driver band
        0.1-2 Hz in ``duration_s`` (default 20 s) with 2 s minimum-jerk fades, 1 s at rest.
        Its amplitude (24 mm) is the largest for which the command any lag-free compensation
        must send -- the exact inverse ``r / M`` of the rails' model ``M`` =
        :data:`RAILS_MODEL` (p1d K=1, Td=0.0175, Tp1=0.1857683128), i.e.
        ``(r + Tp1 r')(t + Td) / K`` -- peaks at 80 % of the rails' 6 m/s^2 acceleration limit
        (the sweep itself peaks at 2.3 m/s^2).

    Raises
    ------
    DataError
        For an unknown name.
    """
    if name == "lanechange":
        return Trajectory(rate_hz, {"rails_y": lane_change(rate_hz)},
                          "lane change on rails_y (1.5 m in 2 s and back)")
    if name == "driving":
        dur = duration_s or 120.0
        return Trajectory(rate_hz, {"rails_y": ordinary_driving(rate_hz, dur)},
                          f"ordinary driving on rails_y: slaloms and lane changes, {dur:g} s")
    if name == "bandsweep":
        dur = duration_s or 20.0
        return Trajectory(rate_hz, {"rails_x": band_sweep(rate_hz, dur)},
                          f"0.1-2 Hz swept sine on rails_x in {dur:g} s, sized for the exact "
                          "inverse")
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


def lane_change(rate_hz: float, width_m: float = 1.5, move_s: float = 2.0, hold_s: float = 2.0,
                rest_s: float = 1.0) -> np.ndarray:
    """A step-like lane change: ``rest_s`` at 0, a minimum-jerk move to ``width_m`` in
    ``move_s``, ``hold_s`` there, the same move back, ``rest_s`` at 0.

    Peak acceleration ``10/sqrt(3) width / move^2``, peak speed ``1.875 width / move``.
    """
    n_move, n_hold, n_rest = (round(x * rate_hz) for x in (move_s, hold_s, rest_s))
    up = width_m * min_jerk(np.arange(n_move) / n_move)
    rest = np.zeros(n_rest)
    return np.concatenate([rest, up, np.full(n_hold, width_m), width_m - up, rest])


def ordinary_driving(rate_hz: float, duration_s: float = 120.0, seed: int = 0) -> np.ndarray:
    """Ordinary driving, ``duration_s`` long after 1 s at rest: stretches of 2-4 periods of a
    0.3 m slalom at 0.3 Hz (1 s minimum-jerk fades) about the current lane, and minimum-jerk
    lane changes of 0.5-1 m in 3-4 s (toward the centre) each held 0.5-2 s, in an order drawn
    from ``seed``.  Peak acceleration 2.7 m/s^2 (a slalom's fade; 1.07 m/s^2 in it), peak speed
    0.65 m/s; it stays within +-1.3 m (the rails' range)."""
    rng = np.random.default_rng(seed)
    parts = [np.zeros(round(rate_hz))]
    lane, n, total = 0.0, parts[0].size, round(duration_s * rate_hz)
    while n < total:
        if rng.random() < 0.5:
            span = int(rng.integers(2, 5)) / 0.3
            t = np.arange(round(span * rate_hz)) / rate_hz
            fade = min_jerk(np.clip(np.minimum(t, span - t), 0.0, 1.0))
            part = lane + 0.3 * np.sin(2 * math.pi * 0.3 * t) * fade
        else:
            width = rng.uniform(0.5, 1.0) * (1.0 if lane <= 0 else -1.0)
            move = round(rng.uniform(3.0, 4.0) * rate_hz)
            part = np.concatenate([lane + width * min_jerk(np.arange(move) / move),
                                   np.full(round(rng.uniform(0.5, 2.0) * rate_hz), lane + width)])
            lane += width
        parts.append(part)
        n += part.size
    return np.concatenate(parts)[:total]


def band_sweep(rate_hz: float, duration_s: float = 20.0, rest_s: float = 1.0) -> np.ndarray:
    """A logarithmic 0.1-2 Hz sweep of ``duration_s`` (2 s fades) between ``rest_s`` at rest,
    sized so that the exact inverse of :data:`RAILS_MODEL` peaks at
    :data:`SIGNAL_ACC_FRACTION` of :data:`RAILS_ACC_MAX_M_S2` (see :func:`builtin`).

    The size is computed once on a 1 kHz grid, whatever ``rate_hz`` (one amplitude at every
    rate): the inverse's acceleration ``(r'' + Tp1 r''') / K`` as differences of the sweep.
    """
    def shape(rate: float) -> np.ndarray:
        _, r = swept_sine(rate, 0.1, 2.0, duration_s, 1.0, fade_s=2.0)
        rest = np.zeros(round(rest_s * rate))
        return np.concatenate([rest, r, rest])

    fine = 1000.0
    r = shape(fine)
    inverse = (r + RAILS_MODEL.Tp1 * np.gradient(r, 1.0 / fine)) / RAILS_MODEL.K
    peak = float(np.max(np.abs(np.diff(inverse, 2)))) * fine**2
    return shape(rate_hz) * (SIGNAL_ACC_FRACTION * RAILS_ACC_MAX_M_S2 / peak)


def load_trajectory(path: Path, rate_hz: float, axis: str | None = None) -> Trajectory:
    """A msgpack stream of input frames, or a CSV with a ``t`` column and axis columns (or
    ``t,cmd`` with ``axis``), resampled to ``rate_hz``.

    Raises
    ------
    DataError
        Naming the file, row and column (or ``--axis``, an unknown axis).
    """
    if axis is not None and axis not in AXIS_INDEX:
        raise DataError(f"--axis: unknown axis {axis!r}; axes: {', '.join(AXES)}")
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
        description = f"{path} ({', '.join(cols)})"
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
        ignored = []
        for j, name in enumerate(header[1:], start=1):
            if name == "cmd":
                if axis is None:
                    raise DataError(f"{path}: column 'cmd' needs --axis to name its axis")
                name = axis
            elif name not in AXIS_INDEX:
                near = difflib.get_close_matches(name, AXES, n=1, cutoff=0.75)
                if near:  # a misspelt axis would go unplayed
                    raise DataError(f"{path}: column {j + 1} {name!r} is not an axis (did you "
                                    f"mean {near[0]!r}?); axes: {', '.join(AXES)}")
                ignored.append(name)  # other columns (acc, ...) are not setpoints
                continue
            cols[name] = arr[:, j]
        if not cols:
            raise DataError(f"{path}: no setpoint column among {header[1:]}: name them after "
                            f"the axes ({', '.join(AXES)}), or 'cmd' with --axis")
        description = (f"{path} ({', '.join(cols)}"
                       + (f"; columns ignored: {', '.join(ignored)})" if ignored else ")"))
    for a in cols:
        if a not in AXIS_INDEX:
            raise DataError(f"{path}: unknown axis {a!r}")
    if not cols or t.size < 2:
        raise DataError(f"{path}: no setpoint columns or fewer than 2 samples")
    if np.any(np.diff(t) <= 0):
        i = int(np.argmax(np.diff(t) <= 0)) + 1
        raise DataError(f"{path}: time does not increase at sample {i} (t={t[i]!r})")
    grid = t[0] + np.arange(int((t[-1] - t[0]) * rate_hz) + 1) / rate_hz
    return Trajectory(rate_hz, {a: np.interp(grid, t, v) for a, v in cols.items()},
                      description)


LOST_PEER_S = 1.0
"""A sender that finds no subscriber of its key for this long says so (:func:`publish`)."""


@dataclass(frozen=True)
class SenderTiming:
    """How a sender departs from perfect timing (the defaults: it does not).

    Attributes
    ----------
    jitter_us
        Each frame goes out late by a random amount, uniform in ``[0, jitter_us]``, after its
        nominal instant; shorter than a period (frames keep their order).
    stall_every_s
        Mean time between stalls (0: none): from the start, or the end of a stall, to the next
        stall is exponential with this mean (stalls come at random, about every
        ``stall_every_s``).
    stall_ms
        ``(shortest, longest)`` stall in ms: each lasts a uniform draw in that range.
    seed
        Of the jitter and stall draws (two independent streams: adding stalls does not change
        the jitter).  None: a fresh one, which :func:`publish` reports.

    Raises
    ------
    ConfigError
        Naming the value: negative or non-finite numbers, an inverted or empty stall range,
        stalls with only one of interval and durations.
    """

    jitter_us: float = 0.0
    stall_every_s: float = 0.0
    stall_ms: tuple[float, float] | None = None
    seed: int | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.jitter_us) and self.jitter_us >= 0):
            raise ConfigError(f"jitter must be a number of us >= 0, got {self.jitter_us!r}")
        if not (math.isfinite(self.stall_every_s) and self.stall_every_s >= 0):
            raise ConfigError(f"the mean interval between stalls must be a number of s >= 0, "
                              f"got {self.stall_every_s!r}")
        if self.stall_ms is not None:
            lo, hi = self.stall_ms
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
                raise ConfigError(f"stall durations must be 0 < shortest <= longest (ms), got "
                                  f"{lo:g}-{hi:g}")
        if (self.stall_every_s > 0) != (self.stall_ms is not None):
            raise ConfigError("stalls need both a mean interval (s) and a range of durations "
                              "(ms)")
        if self.seed is not None and self.seed < 0:
            raise ConfigError(f"seed must be >= 0, got {self.seed}")

    @property
    def random(self) -> bool:
        """Whether any draw is made (jitter or stalls)."""
        return self.jitter_us > 0 or self.stall_ms is not None

    def check_rate(self, rate_hz: float) -> None:
        """Raise :class:`ConfigError` unless the jitter is shorter than a period at ``rate_hz``."""
        period_us = 1e6 / rate_hz
        if self.jitter_us >= period_us:
            raise ConfigError(f"jitter of {self.jitter_us:g} us is not shorter than a period "
                              f"({period_us:g} us at {rate_hz:g} Hz): frames would overtake "
                              "each other")

    def describe(self) -> str:
        parts = []
        if self.jitter_us > 0:
            parts.append(f"jitter 0-{self.jitter_us:g} us")
        if self.stall_ms is not None:
            parts.append(f"stalls of {self.stall_ms[0]:g}-{self.stall_ms[1]:g} ms about every "
                         f"{self.stall_every_s:g} s")
        return ", ".join(parts) or "on time"


class Send(NamedTuple):
    """When a frame goes out: ``at_ns`` after sample 0's nominal instant; ``held`` when a stall
    delayed it (it leaves in the burst at the stall's end)."""

    at_ns: int
    held: bool


_DRAW_BLOCK = 4096


def send_schedule(rate_hz: float, timing: SenderTiming) -> Iterator[Send]:
    """The send instants of samples 0, 1, 2, ... (endless).

    Sample ``k`` is due at ``k * period`` (ns, ``period = round(1e9 / rate_hz)``) and sent
    ``U[0, jitter]`` later, or at the end of the stall that instant falls in (stalls span
    ``[begin, end)`` on the same timeline).  Pure: a ``timing`` with a seed always gives the
    same schedule.

    Raises
    ------
    ConfigError
        If the jitter is not shorter than a period.
    """
    timing.check_rate(rate_hz)
    period_ns = round(1e9 / rate_hz)
    rng_jitter, rng_stall = (np.random.default_rng(s)
                             for s in np.random.SeedSequence(timing.seed).spawn(2))
    jitter_ns = timing.jitter_us * 1e3
    every_ns = timing.stall_every_s * 1e9
    stall_ms = timing.stall_ms

    def stall_after(t_ns: float) -> tuple[float, float]:
        if stall_ms is None:
            return math.inf, math.inf
        begin = t_ns + float(rng_stall.exponential(every_ns))
        return begin, begin + float(rng_stall.uniform(*stall_ms)) * 1e6

    begin, end = stall_after(0.0)
    k = 0
    while True:
        draws = (rng_jitter.uniform(0.0, jitter_ns, _DRAW_BLOCK) if jitter_ns > 0
                 else np.zeros(_DRAW_BLOCK))
        for j in draws.tolist():
            at = k * period_ns + j
            while at >= end:
                begin, end = stall_after(end)
            held = at >= begin
            yield Send(round(end if held else at), held)
            k += 1


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
    rate_hz: float = 0.0
    t0_s: float = math.nan
    """Nominal instant of sample 0 (wall clock, s): sample ``k`` is due at ``t0_s + k /
    rate_hz``, the ``t`` its frame carries (or would carry, without ``t``)."""
    with_t: bool = True
    timing: str = "on time"
    seed: int | None = None
    """The seed of the jitter and stall draws (None: none were made)."""
    stalls: int = 0
    """Stalls that held at least one frame."""
    held: int = 0
    """Frames sent late, in a burst at the end of a stall."""
    unheard: int = 0
    """Frames published while no subscriber of the key was reachable (the service gone)."""

    @property
    def sent(self) -> int:
        return self.next_seq - self.seq_start

    def as_dict(self) -> dict[str, Any]:
        """The fields and ``sent`` (JSON-ready but for a NaN ``t0_s`` when nothing ran)."""
        return asdict(self) | {"sent": self.sent}

    def text(self) -> str:
        out = (f"published {self.sent} frames (seq {self.seq_start}-{self.next_seq - 1}) of "
               f"{self.samples} samples on {self.key} in {self.duration_s:.1f} s")
        if self.timing != "on time" or not self.with_t:
            out += f"; {self.timing}{'' if self.with_t else ', without t'}"
            if self.seed is not None:
                out += f" (seed {self.seed})"
        if self.stalls:
            out += f"; {self.stalls} stalls held {self.held} frames, sent in bursts"
        if self.skipped:
            out += (f"; {self.skipped} not sent: their instants passed while this process was "
                    "stalled")
        if self.unheard:
            out += f"; {self.unheard} published with no subscriber reachable"
        if self.stopped:
            left = self.samples - self.sent - self.skipped
            out += f"; stopped by a signal with {left} samples still to send"
        return out


def _wait_until(due_ns: int, lead: SleepLead, stop: threading.Event) -> None:
    """Wait for ``due_ns`` on ``perf_counter_ns`` as the service's loop waits for a deadline
    (:func:`~motcomp.runtime.clock.sleep_until`: one sleep, then a spin as long as ``lead``
    learned), a wait longer than 5 ms on ``stop`` first; returns early if ``stop`` is set
    during that."""
    rest = due_ns - lead.ns - time.perf_counter_ns()
    if rest > 5_000_000 and stop.wait((rest - 2_000_000) / 1e9):
        return
    sleep_until(due_ns, lead)


def publish(traj: Trajectory, endpoints: ZenohEndpoints, key: str = "sim/motion/setpoint",
            seq_start: int = 0, repeat: int = 1, stop: threading.Event | None = None,
            spin_us: float = 50.0, lead_in_s: float = 0.0, wait_peer_s: float = 0.0,
            progress: Callable[[float], None] | None = None,
            timing: SenderTiming | None = None, with_t: bool = True,
            wait_peer_asked_s: float | None = None,
            warn: Callable[[str], None] | None = None) -> PublishStats:
    """Publish the trajectory (``repeat`` times) on absolute deadlines.

    The motion stays on wall time, as a vehicle model's does: samples whose send instants pass
    while this loop is stalled (by a period or more) are dropped, not published late (that
    would stretch the motion in time).  ``seq`` counts the frames sent, so it stays
    consecutive.  ``timing`` makes the sender misbehave on purpose: jitter, and stalls whose
    frames go out in a burst (module docstring); ``with_t`` False leaves ``t`` out of the
    frames.  With ``wait_peer_s`` > 0 nothing is sent until a subscriber of ``key`` is
    reachable, waiting at most ``wait_peer_s`` from this call (opening the session included;
    ``wait_peer_asked_s``, default the same, is the wait the caller was asked for, which the
    error names); ``progress`` is called with the seconds of motion sent so far, about ten times
    a second.  When no subscriber of ``key`` is reachable for :data:`LOST_PEER_S` (the service
    gone), ``warn`` is told once, and again when one is back; the frames go on (counted in
    :attr:`PublishStats.unheard`).

    Raises
    ------
    NoPeerError
        If no subscriber of ``key`` was reachable within ``wait_peer_s``.
    ConfigError
        If the jitter is not shorter than a period.
    """
    timing = timing or SenderTiming()
    timing.check_rate(traj.rate_hz)
    if timing.random and timing.seed is None:
        timing = replace(timing, seed=secrets.randbelow(2**31))
    seed = timing.seed if timing.random else None
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    axes = [a for a in AXES if a in traj.pos]
    columns = [traj.pos[a].tolist() for a in axes]
    # each sample's slope: the value sent is the motion at the stamp itself (docs/WIRE.md), whose
    # float64 epoch seconds round the nominal instant by up to 0.12 us
    slopes = [(np.gradient(traj.pos[a]) * traj.rate_hz if traj.samples > 1
               else np.zeros(traj.samples)).tolist() for a in axes]
    seq = seq_start
    total = traj.samples * repeat
    skipped = stalls = held = unheard = 0
    lost_at: float | None = None  # when no subscriber was found reachable (checked at 10 Hz)
    warned = False
    every = max(1, round(traj.rate_hz / 10))
    period_ns = round(1e9 / traj.rate_hz)
    lead = SleepLead(int(spin_us * 1000))
    t0 = math.nan
    k = 0
    t_start = time.monotonic()

    def stats() -> PublishStats:
        return PublishStats(key, seq_start, seq, total, skipped, stop.is_set() and k < total,
                            time.monotonic() - t_start, traj.rate_hz, t0, with_t,
                            timing.describe(), seed, stalls, held, unheard)

    with open_session(endpoints) as session, frozen_heap():
        left = max(0.1, wait_peer_s - (time.monotonic() - t_start))
        if wait_peer_s > 0 and not wait_for_subscriber(session, key, left, stop):
            if not stop.is_set():
                asked = wait_peer_s if wait_peer_asked_s is None else wait_peer_asked_s
                raise NoPeerError(f"no subscriber of {key} reachable within {asked:g} s "
                                  f"({endpoints.describe()})")
            return stats()
        sink = ZenohSink(session, key)
        if lead_in_s > 0:
            stop.wait(lead_in_s)
        schedule = send_schedule(traj.rate_hz, timing)
        set_timer_slack(TIMER_SLACK_NS)  # as the service's loop: sleeps end on time
        perf = time.perf_counter_ns
        t_wall0, t_mono0 = time.time(), perf()
        start_ns = t_mono0 + period_ns  # sample 0 is due one period from now
        t0 = t_wall0 + period_ns / 1e9
        burst_at = -1
        try:
            while k < total and not stop.is_set():
                send = next(schedule)
                due = start_ns + send.at_ns
                _wait_until(due, lead, stop)
                if stop.is_set():
                    break
                if perf() - due >= period_ns:  # this process was stalled: the instant passed
                    skipped += 1
                else:
                    if send.held:
                        held += 1
                        stalls += send.at_ns != burst_at
                        burst_at = send.at_ns
                    off = (start_ns + k * period_ns - t_mono0) / 1e9
                    t = t_wall0 + off  # the nominal instant, as a float64 epoch time
                    d = (t - t_wall0) - off if with_t else 0.0  # its rounding (exact)
                    i = k % traj.samples
                    sink.put(encode_input(seq, t if with_t else None,
                                          {a: col[i] + d * sl[i] for a, col, sl in
                                           zip(axes, columns, slopes, strict=True)}))
                    seq += 1
                    if lost_at is not None:
                        unheard += 1
                k += 1
                if k % every == 0:
                    if progress is not None:
                        progress(k / traj.rate_hz)
                    now = time.monotonic()
                    if not sink.heard():
                        lost_at = now if lost_at is None else lost_at
                        if not warned and now - lost_at >= LOST_PEER_S and warn is not None:
                            warn(f"no subscriber of {key} reachable for {now - lost_at:.1f} s: "
                                 "is the service still running? (publishing on)")
                            warned = True
                    elif lost_at is not None:
                        if warned and warn is not None:
                            warn(f"a subscriber of {key} again after {now - lost_at:.1f} s")
                        lost_at, warned = None, False
        finally:
            sink.close()
    return stats()
