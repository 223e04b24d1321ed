"""How far behind its newest sample the input is played back: :class:`Playback`.

Contract
--------
Fed each accepted sample's instant ``t`` on the sender's timeline and the loop instant
``arrived`` at which it was taken (never before it landed: the service passes the instant it
drained its input), :class:`Playback` gives, per tick at ``now``, the playback delay ``D``: the
reference is the input at the sender instant ``now - D`` (plus the configured lead)::

    offset   loop clock - sender clock: the smallest transit ``arrived - t`` of the last
             OFFSET_BINS bins of BIN_S of arrivals, each leaking upwards since it was taken
             at the drift (below).  Every ``arrived`` is an upper bound of the frame's
             landing, so no late tick can pull it below the truth (it only lowers on a frame
             taken promptly).  Frames are taken at ticks: a transit is the landing's plus up to
             a period of waiting, and a frame that lands just before its tick reads a period
             "faster" than the others.  Such a frame sets the offset for the whole window (a
             fixed leak made the offset climb by up to a period between two of them and drop
             back at the next: the playback instant swung by hundreds of microseconds)
    drift    how fast the transits rise (s per s, within [0, MAX_DRIFT]; 0 before DRIFT_BINS
             bins): between the medians of the two halves of the bins' smallest transits,
             against the medians of their instants (a few prompt frames move neither).  For
             frames without ``t`` MAX_DRIFT: their instants are the timeline's estimate from
             the arrivals, moved by each correction of its fit (hundreds of ppm, both ways),
             and a smallest transit held for the window put the playback up to 6 ms ahead of
             the samples
    need     the lag the samples' spacing needs to be interpolated: the SPACING_QUANTILE
             quantile of the last SPACING_WINDOW intervals per seq step (0 before one);
             intervals longer than STALL_PERIODS periods are stalls, left to the extrapolation
    lag      max(lag_s, need): ``lag_s`` is the lag the compensator's design cancels
             (``input.playback_lag_s``), so a sender whose spacing fits in it (any regular
             1 kHz sender) is played back exactly that far behind, and the design's delay
             holds; a slower or irregular one lags by its spacing (the status shows the
             excess)
    D        follows ``offset + lag`` through a critically damped pole of order DELAY_POLES
             (5) at DELAY_POLE_FACTOR / SETTLE_S: continuous to its fourth derivative (a
             step of the target -- a new smallest transit -- never steps the reference's
             jerk nor its rate, which the compensator amplifies above the band), a change of
             its target within 6 % after SETTLE_S
    restart  (a new timeline: the first frame, a rejoin): offset and spacing from the new
             samples; D starts at its target at the first tick that has two samples.  The
             offset is *settled* once a bin is complete: until then it may rest on one frame
             that left late (its sender stalled between computing and sending it: a transit
             hundreds of ms long), which the fresher frames after it lower -- the bound on a
             live sender's ``t`` (``shaper.next_t_bound``) waits for it

Jitter, late frames and stalls never raise the lag: a sample later than the playback is
bridged by the extrapolation (:mod:`motcomp.core.interp`) and corrected as it arrives.
Nothing here reads a clock.
"""

from __future__ import annotations

import math
from bisect import bisect_left, insort

from mypy_extensions import mypyc_attr

from motcomp.core.interp import Transition

__all__ = ["BIN_S", "DELAY_POLES", "DELAY_POLE_FACTOR", "DRIFT_BINS", "MAX_DRIFT", "OFFSET_BINS",
           "SETTLE_S", "Playback", "median_slope", "min_transit"]

BIN_S = 0.1
OFFSET_BINS = 100
"""The offset and the drift are read over the smallest transit of each BIN_S of arrivals, the
last OFFSET_BINS bins (10 s) and the current one."""
MAX_DRIFT = 1e-3
"""The drift followed, at most (s per s): 1000 ppm of clock drift."""
DRIFT_BINS = 20
"""The drift is read once this many bins (2 s) are complete (0 before)."""
SPACING_WINDOW = 64
SPACING_QUANTILE = 0.9
STALL_PERIODS = 4.0
"""The spacing the lag covers: the 90th percentile of the last 64 intervals per seq step,
stalls (longer than four periods) left out."""
SETTLE_S = 1.0
"""The playback delay settles a change of its target within 6 % in this time."""
DELAY_POLES = 5
DELAY_POLE_FACTOR = 9.0
"""The playback delay follows its target through a critically damped pole of order DELAY_POLES
at DELAY_POLE_FACTOR / SETTLE_S: a change of its target within 6 % after SETTLE_S (5.5 %), and
the delay continuous to its fourth derivative (docs/TUNING.md, "Input reconstruction")."""


def _median(v: list[float]) -> float:
    w = sorted(v)
    n = len(w)
    return w[n // 2] if n % 2 else 0.5 * (w[n // 2 - 1] + w[n // 2])


def median_slope(x: list[float], y: list[float]) -> float:
    """The slope between the medians of the two halves of the points ``(x[k], y[k])`` (``x``
    rising; the middle point of an odd count in neither): 0 for fewer than two points or no
    spread in ``x``."""
    half = len(x) // 2
    if half < 1:
        return 0.0
    dx = _median(x[-half:]) - _median(x[:half])
    return (_median(y[-half:]) - _median(y[:half])) / dx if dx > 0.0 else 0.0


def min_transit(offset: float | None, offset_at: float, transit: float, now: float,
                leak: float) -> float:
    """The smallest transit seen, leaking upwards by ``leak`` s per s since ``offset_at``."""
    if offset is None:
        return transit
    return min(offset + leak * (now - offset_at), transit)


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Playback:
    """The state of the policy in the module docstring."""

    def __init__(self) -> None:
        self.offset: float | None = None
        """Loop clock minus sender clock (s): the smallest transit, leaking at the drift."""
        self.drift = 0.0
        """How fast the smallest transit rises (s per s; module docstring)."""
        self._bin_at: list[float] = []  # each bin's smallest transit: its arrival, oldest first,
        self._bin_tr: list[float] = []  # and the transit (the current bin last)
        self._bin_end = 0.0  # the current bin's end (arrival instant)
        self._floor = 0.0  # the completed bins' smallest transit less the drift's line, at 0
        self._origin = 0.0  # the arrival instant the bins are counted from
        self._ring: list[float] = []  # the last intervals, oldest first
        self._sorted: list[float] = []  # the same, sorted
        self.delay: float | None = None
        """The playback delay (s; None before it starts)."""
        self._x = [0.0] * DELAY_POLES  # its distance to the target, then its first derivatives
        self._y = [0.0] * DELAY_POLES  # scratch for the next state (a tick allocates nothing)
        self._at: float | None = None  # loop instant of the last step
        self._phi = Transition(DELAY_POLES, DELAY_POLE_FACTOR)  # the pole over one tick

    def restart(self) -> None:
        """A new timeline: forget the offset, the spacing and the delay."""
        self.offset = None
        self.drift = 0.0
        self._bin_at = []
        self._bin_tr = []
        self._floor = 0.0
        self._ring = []
        self._sorted = []
        self.delay = None
        self._at = None

    def on_sample(self, t: float, arrived: float, interval: float, period: float,
                  stamped: bool = True) -> None:
        """A sample at sender instant ``t`` taken at loop instant ``arrived``; ``interval`` is
        its distance to the previous sample per seq step (0: none, a restart); ``stamped``:
        ``t`` is the sender's own (not the timeline's estimate)."""
        self._offset_at(arrived, arrived - t, stamped)
        if interval > 0.0 and (period <= 0.0 or interval <= STALL_PERIODS * period):
            ring, srt = self._ring, self._sorted
            ring.append(interval)
            insort(srt, interval)
            if len(ring) > SPACING_WINDOW:
                del srt[bisect_left(srt, ring.pop(0))]

    def _offset_at(self, arrived: float, transit: float, stamped: bool) -> None:
        """The bins, at a new bin the drift and the completed bins' floor, and the offset."""
        at, tr = self._bin_at, self._bin_tr
        if not tr:
            self._origin = arrived
        x = arrived - self._origin
        if not tr or arrived >= self._bin_end:
            at.append(x)
            tr.append(transit)
            self._bin_end = arrived + BIN_S
            if len(tr) > OFFSET_BINS + 1:
                del at[0]
                del tr[0]
            done = len(tr) - 1
            drift = (MAX_DRIFT if not stamped else
                     min(max(median_slope(at[:done], tr[:done]), 0.0), MAX_DRIFT)
                     if done >= DRIFT_BINS else 0.0)
            floor = math.inf
            for k in range(done):
                floor = min(floor, tr[k] - drift * at[k])
            self.drift, self._floor = drift, floor
        elif transit - self.drift * x < tr[-1] - self.drift * at[-1]:
            at[-1] = x
            tr[-1] = transit
        drift = self.drift
        self.offset = min(self._floor, tr[-1] - drift * at[-1]) + drift * x

    @property
    def need(self) -> float:
        """The spacing's quantile (0 before an interval)."""
        srt = self._sorted
        if not srt:
            return 0.0
        return srt[min(int(SPACING_QUANTILE * len(srt)), len(srt) - 1)]

    def settled(self) -> bool:
        """The offset is read over a completed bin (BIN_S of arrivals) since the restart: one
        frame's transit bounds it only from above, since a frame may leave late (its sender
        stalled between computing and sending it), and the frames after it lower it."""
        return len(self._bin_tr) > 1

    def ready(self) -> bool:
        """Playback can start: an offset and one interval are known."""
        return self.offset is not None and bool(self._sorted)

    def step(self, now: float, lag_s: float) -> float:
        """The playback delay at ``now`` (:meth:`ready` must be true): its target is
        ``offset + max(lag_s, need)``."""
        assert self.offset is not None
        target = self.offset + max(lag_s, self.need)
        d = self.delay
        at = self._at
        self._at = now
        x = self._x
        n = DELAY_POLES
        if d is None or at is None:
            self.delay = target
            for r in range(n):
                x[r] = 0.0
            return target
        dt = now - at
        if dt <= 0.0:
            return d
        phi = self._phi.of(dt, SETTLE_S)
        x[0] = d - target
        y = self._y
        for r in range(n):
            acc = 0.0
            for c in range(n):
                acc += phi[r * n + c] * x[c]
            y[r] = acc
        self._x, self._y = y, x
        self.delay = target + y[0]
        return self.delay
