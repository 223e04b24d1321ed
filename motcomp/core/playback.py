"""How far behind its newest sample the input is played back: :class:`Playback`.

Contract
--------
Fed each accepted sample's instant ``t`` on the sender's timeline and the loop instant
``arrived`` at which it was taken (never before it landed: the service passes the instant it
drained its input), :class:`Playback` gives, per tick at ``now``, the playback delay ``D``: the
reference is the input at the sender instant ``now - D`` (plus the configured lead)::

    offset   loop clock - sender clock: the smallest transit ``arrived - t`` seen, rising at
             most OFFSET_LEAK s per s so that a drifting clock is followed.  Every ``arrived``
             is an upper bound of the frame's landing, so no late tick can pull it below the
             truth (it only lowers on a frame taken promptly)
    need     the lag the samples' spacing needs to be interpolated: the SPACING_QUANTILE
             quantile of the last SPACING_WINDOW intervals per seq step (0 before one);
             intervals longer than STALL_PERIODS periods are stalls, left to the extrapolation
    lag      max(lag_s, need): ``lag_s`` is the lag the compensator's design cancels
             (``input.playback_lag_s``), so a sender whose spacing fits in it (any regular
             1 kHz sender) is played back exactly that far behind, and the design's delay
             holds; a slower or irregular one lags by its spacing (the status shows the
             excess)
    D        follows ``offset + lag`` through a critically damped triple pole at
             SETTLE_POLE / settle_s: continuous to its second derivative (the reference's
             acceleration never steps), a change of its target within 6 % after settle_s
    restart  (a new timeline: the first frame, a rejoin): offset and spacing from the new
             samples; D starts at its target at the first tick that has two samples

Jitter, late frames and stalls never raise the lag: a sample later than the playback is
bridged by the extrapolation (:mod:`motcomp.core.interp`) and corrected as it arrives.
Nothing here reads a clock.
"""

from __future__ import annotations

from bisect import bisect_left, insort

from mypy_extensions import mypyc_attr

from motcomp.core.interp import Transition

__all__ = ["OFFSET_LEAK", "SETTLE_S", "Playback", "min_transit"]

OFFSET_LEAK = 1e-3
"""Upward drift (s per s) allowed to the smallest transit: 1000 ppm of clock drift."""
SPACING_WINDOW = 64
SPACING_QUANTILE = 0.9
STALL_PERIODS = 4.0
"""The spacing the lag covers: the 90th percentile of the last 64 intervals per seq step,
stalls (longer than four periods) left out."""
SETTLE_S = 1.0
"""The playback delay's triple pole settles a change of its target within 6 % in this time
(its pole at 6 / SETTLE_S)."""


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
        """Loop clock minus sender clock (s): the smallest transit, leaking upwards."""
        self._offset_at = 0.0
        self._ring: list[float] = []  # the last intervals, oldest first
        self._sorted: list[float] = []  # the same, sorted
        self.delay: float | None = None
        """The playback delay (s; None before it starts)."""
        self._rate = 0.0  # its first and second derivatives
        self._acc = 0.0
        self._at: float | None = None  # loop instant of the last step
        self._phi = Transition()  # the triple pole over one tick

    def restart(self) -> None:
        """A new timeline: forget the offset, the spacing and the delay."""
        self.offset = None
        self._ring = []
        self._sorted = []
        self.delay = None
        self._at = None

    def on_sample(self, t: float, arrived: float, interval: float, period: float) -> None:
        """A sample at sender instant ``t`` taken at loop instant ``arrived``; ``interval`` is
        its distance to the previous sample per seq step (0: none, a restart)."""
        self.offset = min_transit(self.offset, self._offset_at, arrived - t, arrived,
                                  OFFSET_LEAK)
        self._offset_at = arrived
        if interval > 0.0 and (period <= 0.0 or interval <= STALL_PERIODS * period):
            ring, srt = self._ring, self._sorted
            ring.append(interval)
            insort(srt, interval)
            if len(ring) > SPACING_WINDOW:
                del srt[bisect_left(srt, ring.pop(0))]

    @property
    def need(self) -> float:
        """The spacing's quantile (0 before an interval)."""
        srt = self._sorted
        if not srt:
            return 0.0
        return srt[min(int(SPACING_QUANTILE * len(srt)), len(srt) - 1)]

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
        if d is None or at is None:
            self.delay, self._rate, self._acc = target, 0.0, 0.0
            return target
        dt = now - at
        if dt <= 0.0:
            return d
        phi = self._phi.of(dt, SETTLE_S)
        e, r, a = d - target, self._rate, self._acc
        self.delay = target + phi[0] * e + phi[1] * r + phi[2] * a
        self._rate = phi[3] * e + phi[4] * r + phi[5] * a
        self._acc = phi[6] * e + phi[7] * r + phi[8] * a
        return self.delay
