"""From the stream of valid input frames to the compensator's reference, per axis.

Rules (all times from the loop's clock, passed in)::

    start        reference at neutral (0) until the first valid frame
    first frame  blend from neutral to the live input over ``startup_s``           "rejoin"
    live         reference = last valid value of each axis (a frame may carry a subset)
    no valid frame for stale_after_s
                 hold the reference for ``hold_s``, then move each axis to neutral  "stale"
                 in a minimum-jerk ramp whose peak speed is ``ramp_speed`` (per axis)
    frames again blend from the held/ramped reference to the live input over
                 ``rejoin_s``                                                       "rejoin"
    park         (stop requested) ramp every axis to neutral as above, ignoring
                 input; :attr:`parked` once there                                   "parking"

Blends and ramps are minimum-jerk (quintic): continuous position, velocity *and* acceleration
at both ends, so the compensator sees no step it would amplify.  Undriven axes stay at neutral.

Input reconstruction (``linear``, the default): the loop and the source run on different clocks,
so each tick sees zero, one or two new frames; holding the last value turns that into a
one-sample sawtooth, which a high-gain compensator amplifies ~100x at high frequency.  Instead
each axis is extrapolated along the line through its last two frames *on the sender's
timeline* (frame ``t``), to the sender time that corresponds to the tick: the offset between
the clocks is the smallest transit time seen (``arrival - t``), with an upward leak of
:data:`OFFSET_LEAK` so that a sender whose clock runs up to 5 % off real time is followed.
How far: by at most ``min(max(max_extrapolation_s, c), age + c)``, with ``c`` = 1.5 input
periods (average per axis: the transit jitter allowed for) and ``age`` the time since the last
frame *arrived*.  While frames arrive, that is about ``c``.  Through a gap in the input --
frames lost, a sender that stalls -- ``age`` grows and the reference goes on along the motion,
up to ``max_extrapolation_s`` (default 20 ms; or ``c`` if longer, so that a slow source is
followed between its frames).  Stopping sooner stops the reference dead in the middle of a
motion, and the compensator turns that velocity step into a transient: on the demo motion, with
sender stalls of 3-15 ms every 0.5 s, the rails' command strayed up to 21 mm from the
stall-free one when extrapolation stopped after 1.5 periods, and 2.7 mm when it bridged the
stalls (tests/test_shaper_gaps.py).  Bridging presumes a sender that keeps its timeline on real
time (after a stall it skips samples, as ``motcomp source`` does); one whose timeline falls
behind -- it sends the samples of a stall late, or its clock runs more than 5 % slow -- shows it
in its frames' transit: when the last frame arrived more than ``c`` later than the offset
predicts, the bound is ``min(2 c, age + c)``, so a gap costs at most 3 periods of lead.  A step
in the input followed by a gap is extrapolated as a ramp for as long (the limiter keeps the
command within the axis' limits).
Measured on the slalom with ZN and 50-150 us of jitter: hold -> 18 mm worst error, linear ->
8 mm, and the slalom delay within 0.1 ms of the jitter-free one.  Frames without ``t`` use their
arrival time.  ``hold`` keeps the last value.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

from motcomp.core.axes import AXES, AXIS_INDEX

__all__ = ["OFFSET_LEAK", "ReferenceShaper"]

_cshaper: Any = None
if os.environ.get("MOTCOMP_KERNEL", "").strip().lower() != "python":
    try:  # the per-axis loops in C (motcomp/runtime/_cshaper.c): bit-identical results
        from motcomp.runtime import _cshaper
    except ImportError:  # pragma: no cover - exercised where no C compiler was available
        _cshaper = None

OFFSET_LEAK = 0.05
"""Upward drift (s per s) allowed to the estimated clock offset between sender and loop."""


def _cos_weight(progress: float) -> float:
    """1 -> 0 over progress 0 -> 1, minimum-jerk (quintic): zero velocity *and* acceleration at
    both ends.  (A raised cosine has an acceleration step at its ends, which a high-gain
    compensator turns into a command spike.)"""
    if progress >= 1.0:
        return 0.0
    if progress <= 0.0:
        return 1.0
    return 1.0 - progress**3 * (10.0 - 15.0 * progress + 6.0 * progress * progress)


class _Move:
    """Raised-cosine moves from ``start`` to ``end`` per axis, each with its own duration."""

    def __init__(self, t0: float, start: Sequence[float], end: Sequence[float],
                 speed: Sequence[float], min_s: float = 0.05) -> None:
        self.t0 = t0
        self.start = list(start)
        self.end = list(end)
        # peak speed of the minimum-jerk move over T is 1.875 * distance / T
        self.duration = [max(1.875 * abs(e - s) / v, min_s) if v > 0 else min_s
                         for s, e, v in zip(start, end, speed, strict=True)]

    def at(self, t: float) -> tuple[list[float], bool]:
        out = []
        done = True
        for s, e, d in zip(self.start, self.end, self.duration, strict=True):
            w = _cos_weight((t - self.t0) / d)
            done = done and w == 0.0
            out.append(e + (s - e) * w)
        return out, done


class ReferenceShaper:
    """See the module docstring.

    Parameters
    ----------
    driven
        Which of the :data:`AXES` are driven (the others stay at neutral).
    ramp_speed
        Peak speed of the ramps to neutral, per axis (axis units/s).
    """

    def __init__(self, driven: Sequence[bool], ramp_speed: Sequence[float],
                 stale_after_s: float, hold_s: float, rejoin_s: float, startup_s: float,
                 linear: bool = True, max_extrapolation_s: float = 0.02) -> None:
        self.n = len(AXES)
        self.driven = list(driven)
        self.linear = linear
        self.max_extrapolation_s = max_extrapolation_s
        self.configure(ramp_speed, stale_after_s, hold_s, rejoin_s, startup_s)
        self.live = [0.0] * self.n
        self._t_frame = [0.0] * self.n  # sender time of each axis' last value
        self._slope = [0.0] * self.n
        self._period = [0.0] * self.n  # average interval between an axis' frames
        self._offset: float | None = None  # local clock - sender clock (smallest transit)
        self._offset_at = 0.0
        self._excess = 0.0  # the last frame's transit beyond the offset (s)
        self.ref = [0.0] * self.n
        self.last_input_s: float | None = None
        self.started_s: float | None = None
        self._blend_t0 = 0.0
        self._blend_s = 0.0
        self._blend_offset: list[float] | None = None
        self._stale_since: float | None = None
        self._move: _Move | None = None
        self.parking = False
        self.parked = False
        self.stale_total_s = 0.0
        self.stale_episodes = 0
        self._last_t: float | None = None

    def configure(self, ramp_speed: Sequence[float], stale_after_s: float, hold_s: float,
                  rejoin_s: float, startup_s: float) -> None:
        """Live-changeable settings (applied between ticks)."""
        self.ramp_speed = list(ramp_speed)
        self.stale_after_s = stale_after_s
        self.hold_s = hold_s
        self.rejoin_s = rejoin_s
        self.startup_s = startup_s

    # --- events ---------------------------------------------------------------------------
    def is_stale(self, now: float) -> bool:
        """No valid input for ``stale_after_s`` (or none yet, after start-up)."""
        last = self.last_input_s if self.last_input_s is not None else self.started_s
        return last is not None and now - last > self.stale_after_s

    def on_input(self, pos: dict[str, float], now: float, t_sender: float | None = None
                 ) -> None:
        """A valid frame (sender time ``t_sender``, if any): update the axes it carries."""
        if self.parking:
            return
        first = self.last_input_s is None
        rejoin = first or self._stale_since is not None
        t = now if t_sender is None else t_sender
        transit = now - t
        off = self._offset
        if off is None or transit < off or rejoin:
            self._offset = transit
        else:  # leak upwards so a drifting clock is followed
            self._offset = min(off + OFFSET_LEAK * (now - self._offset_at), transit)
        self._offset_at = now
        self._excess = transit - self._offset  # how late this frame is beyond the fastest
        if _cshaper is not None:
            _cshaper.update_axes(pos, AXIS_INDEX, self.driven, t, self.linear and not rejoin,
                                 self.stale_after_s, self.live, self._t_frame, self._slope,
                                 self._period)
        else:
            self._update_axes(pos, t, self.linear and not rejoin)
        if rejoin:
            if self._stale_since is not None:
                self.stale_total_s += now - self._stale_since
            self._stale_since = None
            self._move = None
            self._blend_t0 = now
            self._blend_s = self.startup_s if first else self.rejoin_s
            self._blend_offset = [r - v for r, v in zip(self.ref, self.live, strict=True)]
        self.last_input_s = now

    def _update_axes(self, pos: dict[str, float], t: float, fresh_allowed: bool) -> None:
        """The axes a frame carries: value, slope, input period (the
        reference of motcomp/runtime/_cshaper.c's ``update_axes``)."""
        for axis, value in pos.items():
            i = AXIS_INDEX[axis]
            if self.driven[i]:
                v = float(value)
                dt = t - self._t_frame[i]
                fresh = fresh_allowed and 0.0 < dt <= self.stale_after_s
                self._slope[i] = (v - self.live[i]) / dt if fresh else 0.0
                if fresh:
                    p = self._period[i]
                    p = dt if p == 0.0 else p + 0.05 * (dt - p)
                    self._period[i] = p
                self.live[i] = v
                self._t_frame[i] = t

    def park(self, now: float) -> None:
        """Stop requested: ramp to neutral, ignoring input from now on."""
        if self.parking:
            return
        self.parking = True
        self._blend_offset = None
        self._move = _Move(now, self.ref, [0.0] * self.n, self.ramp_speed)

    # --- the reference --------------------------------------------------------------------
    def reference(self, now: float) -> tuple[list[float], str]:
        """``(reference, mode)`` for this tick; mode is ``""`` when live and settled, else one of
        ``"rejoin"``, ``"stale"``, ``"parking"``."""
        if self.started_s is None:
            self.started_s = now
        if self.parking:
            assert self._move is not None
            self.ref, done = self._move.at(now)
            self.parked = done
            return self.ref, "parking"
        if self.is_stale(now):
            if self._stale_since is None:
                self._stale_since = now
                self.stale_episodes += 1
                self._blend_offset = None
            held = now - self._stale_since
            if held >= self.hold_s:
                if self._move is None:
                    self._move = _Move(now, self.ref, [0.0] * self.n, self.ramp_speed)
                self.ref, _ = self._move.at(now)
            return self.ref, "stale"
        if self._blend_offset is not None:
            w = _cos_weight((now - self._blend_t0) / self._blend_s) if self._blend_s > 0 else 0.0
            if w == 0.0:
                self._blend_offset = None
            else:
                self.ref = [v + o * w for v, o in zip(self._live_now(now), self._blend_offset,
                                                      strict=True)]
                return self.ref, "rejoin"
        self.ref = self._live_now(now)
        return self.ref, ""

    def _live_now(self, now: float) -> list[float]:
        """The live values, extrapolated to the sender time of this tick, each by at most
        ``min(max(max_extrapolation_s, c), age + c)`` -- or ``min(2 c, age + c)`` after a late
        frame -- (``c`` = 1.5 input periods, ``age`` = time since the last frame arrived; see
        the module docstring)."""
        if not self.linear or self._offset is None:
            return self.live[:]
        assert self.last_input_s is not None
        t_now = now - self._offset
        age = now - self.last_input_s
        late = self._excess
        mx = self.max_extrapolation_s
        if _cshaper is not None:
            return _cshaper.live_now(t_now, age, late, mx, self.live, self._slope,
                                     self._t_frame, self._period)
        out = []
        for v, s, tf, p in zip(self.live, self._slope, self._t_frame, self._period, strict=True):
            tau = t_now - tf
            c = 1.5 * p  # the transit jitter allowed for
            b = min(max(mx, c) if late <= c else c + c, age + c)
            out.append(v + s * (tau if 0.0 < tau < b else b if tau >= b else 0.0))
        return out

    def stale_time(self, now: float) -> float:
        """Seconds since the last valid frame (0 while live)."""
        if self._stale_since is None:
            return 0.0
        last = self.last_input_s if self.last_input_s is not None else self.started_s
        return now - (last or now)
