"""From the stream of valid input frames to the compensator's reference, per axis.

Rules (all times from the loop's clock, passed in)::

    start        reference at neutral (0) until the first valid frame
    first frame  blend from neutral to the live input over ``startup_s``           "rejoin"
    live         reference = last valid value of each axis (a frame may carry a subset)
    no valid frame for stale_after_s
                 hold the reference for ``hold_s``, then move each axis to neutral  "stale"
                 in a raised-cosine ramp whose peak speed is ``ramp_speed`` (per axis)
    frames again blend from the held/ramped reference to the live input over
                 ``rejoin_s``                                                       "rejoin"
    park         (stop requested) ramp every axis to neutral as above, ignoring
                 input; :attr:`parked` once there                                   "parking"

Blends and ramps use raised cosines: continuous position *and* velocity at both ends, so the
compensator and the limiter see no step.  Undriven axes stay at neutral.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from motcomp.core.axes import AXES, AXIS_INDEX

__all__ = ["ReferenceShaper"]


def _cos_weight(progress: float) -> float:
    """1 -> 0 raised cosine over progress 0 -> 1."""
    if progress >= 1.0:
        return 0.0
    return 0.5 + 0.5 * math.cos(math.pi * progress)


class _Move:
    """Raised-cosine moves from ``start`` to ``end`` per axis, each with its own duration."""

    def __init__(self, t0: float, start: Sequence[float], end: Sequence[float],
                 speed: Sequence[float], min_s: float = 0.05) -> None:
        self.t0 = t0
        self.start = list(start)
        self.end = list(end)
        # peak speed of a raised cosine over T is (pi/2) * distance / T
        self.duration = [max(math.pi / 2 * abs(e - s) / v, min_s) if v > 0 else min_s
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
                 stale_after_s: float, hold_s: float, rejoin_s: float, startup_s: float) -> None:
        self.n = len(AXES)
        self.driven = list(driven)
        self.configure(ramp_speed, stale_after_s, hold_s, rejoin_s, startup_s)
        self.live = [0.0] * self.n
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

    def on_input(self, pos: dict[str, float], now: float) -> None:
        """A valid frame: update the live values of the axes it carries."""
        if self.parking:
            return
        first = self.last_input_s is None
        rejoin = first or self._stale_since is not None
        for axis, value in pos.items():
            i = AXIS_INDEX[axis]
            if self.driven[i]:
                self.live[i] = float(value)
        if rejoin:
            if self._stale_since is not None:
                self.stale_total_s += now - self._stale_since
            self._stale_since = None
            self._move = None
            self._blend_t0 = now
            self._blend_s = self.startup_s if first else self.rejoin_s
            self._blend_offset = [r - v for r, v in zip(self.ref, self.live, strict=True)]
        self.last_input_s = now

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
                self.ref = [v + o * w for v, o in zip(self.live, self._blend_offset,
                                                      strict=True)]
                return self.ref, "rejoin"
        self.ref = self.live[:]
        return self.ref, ""

    def stale_time(self, now: float) -> float:
        """Seconds since the last valid frame (0 while live)."""
        if self._stale_since is None:
            return 0.0
        last = self.last_input_s if self.last_input_s is not None else self.started_s
        return now - (last or now)
