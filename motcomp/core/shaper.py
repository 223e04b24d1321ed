"""From the stream of valid input frames to the compensator's reference, per axis.

Rules (all times from the loop's clock, passed in)::

    start        reference at neutral (0) until the first valid frame
    first frame  blend from neutral to the live input over ``startup_s``           "rejoin"
    live         reference = last valid value of each axis (a frame may carry a subset),
                 reconstructed between frames (below)
    no valid frame for stale_after_s
                 hold the reference for ``hold_s``, then move each axis to neutral  "stale"
                 in a minimum-jerk ramp whose peak speed is ``ramp_speed`` (per axis)
    frames again blend from the held/ramped reference to the live input over
                 ``rejoin_s``                                                       "rejoin"
    park         (stop requested) ramp every axis to neutral as above, ignoring
                 input; :attr:`ReferenceShaper.parked` once there                  "parking"
    always       the reference lies within ``[reach_lo, reach_hi]`` per axis (the range of
                 accepted input); a non-finite value keeps the previous reference

Blends and ramps are minimum-jerk (:mod:`motcomp.core.minjerk`): continuous position, velocity
*and* acceleration at both ends, so the compensator sees no step it would amplify.  Undriven axes
stay at neutral.

Input reconstruction (``linear``, the default): each axis is extrapolated along the line
through its last two frames *on the sender's timeline* (frame ``t``), to the sender time that
corresponds to the tick.  The offset between the clocks is the smallest transit seen
(``arrival - t``), leaking upwards by :data:`OFFSET_LEAK` so that a sender whose clock runs up to
5 % off is followed.  How far::

    on a frame   dt = t - t_prev (per axis)
                 dt < min_dt_s          a duplicate sample: the value replaces the previous one,
                                        slope, period and t_prev are kept (never divide by ~0)
                 min_dt_s <= dt <= stale_after_s
                                        slope = (v - v_prev) / dt, period += 0.05 (dt - period)
                 otherwise (after a gap, a rejoin or a t that goes back): slope = 0
    per tick     tau = (now - offset) - t_prev,  c = 1.5 period,  age = now - last arrival
                 bound = min(max(max_extrapolation_s, c), age + c)     (a frame on time)
                       = min(2 c, age + c)                              (the last one came late)
                 ref = v + slope * clip(tau, 0, bound)

Through a gap -- frames lost, a sender that stalls -- ``age`` grows and the reference goes on along
the motion up to ``max_extrapolation_s`` (docs/REPLAY.md and tests/test_shaper_gaps.py have the
measurements that chose it).  Frames without ``t`` use their arrival time.  ``hold`` keeps the
last value.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from motcomp.core.minjerk import PEAK_SPEED_FACTOR, min_jerk_weight

__all__ = ["OFFSET_LEAK", "ReferenceShaper", "ShaperParams"]

OFFSET_LEAK = 0.05
"""Upward drift (s per s) allowed to the estimated clock offset between sender and loop."""


@dataclass(frozen=True)
class ShaperParams:
    """The shaper's settings, per axis where a tuple (in :data:`~motcomp.core.axes.AXES` order)."""

    driven: tuple[bool, ...]
    ramp_speed: tuple[float, ...]
    """Peak speed of the ramps to neutral (axis units/s)."""
    reach_lo: tuple[float, ...]
    reach_hi: tuple[float, ...]
    """The reference never leaves ``[reach_lo, reach_hi]``."""
    stale_after_s: float = 0.05
    hold_s: float = 0.5
    rejoin_s: float = 0.5
    startup_s: float = 1.0
    linear: bool = True
    max_extrapolation_s: float = 0.02
    min_dt_s: float = 1e-5
    """Two samples of an axis closer than this on the sender's timeline are one sample."""

    def __post_init__(self) -> None:
        if not self.min_dt_s > 0:
            raise ValueError(f"min_dt_s must be > 0 s, got {self.min_dt_s!r}")


class _Move:
    """Minimum-jerk moves from ``start`` to ``end`` per axis, each with its own duration."""

    def __init__(self, t0: float, start: Sequence[float], end: Sequence[float],
                 speed: Sequence[float], min_s: float = 0.05) -> None:
        self.t0 = t0
        self.start = list(start)
        self.end = list(end)
        self.duration = [max(PEAK_SPEED_FACTOR * abs(e - s) / v, min_s) if v > 0 else min_s
                         for s, e, v in zip(start, end, speed, strict=True)]

    def at(self, t: float) -> tuple[list[float], bool]:
        out = []
        done = True
        for s, e, d in zip(self.start, self.end, self.duration, strict=True):
            w = min_jerk_weight((t - self.t0) / d)
            done = done and w == 0.0
            out.append(e + (s - e) * w)
        return out, done


class ReferenceShaper:
    """The state of the rules in the module docstring; every method takes the settings."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.live = [0.0] * n
        self._t_frame = [0.0] * n  # sender time of each axis' last value
        self._slope = [0.0] * n
        self._period = [0.0] * n  # average interval between an axis' frames
        self._offset: float | None = None  # local clock - sender clock (smallest transit)
        self._offset_at = 0.0
        self._excess = 0.0  # the last frame's transit beyond the offset (s)
        self.ref = [0.0] * n
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

    # --- events ---------------------------------------------------------------------------
    def is_stale(self, p: ShaperParams, now: float) -> bool:
        """No valid input for ``stale_after_s`` (or none yet, after start-up)."""
        last = self.last_input_s if self.last_input_s is not None else self.started_s
        return last is not None and now - last > p.stale_after_s

    def on_input(self, p: ShaperParams, pos: dict[int, float], now: float,
                 t_sender: float | None = None) -> None:
        """A valid frame (axis index -> finite value; sender time ``t_sender``, if any)."""
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
        fresh_allowed = p.linear and not rejoin
        driven, live, t_frame, slope, period = (p.driven, self.live, self._t_frame, self._slope,
                                                self._period)
        min_dt, max_dt = p.min_dt_s, p.stale_after_s
        for i, v in pos.items():
            if not driven[i]:
                continue
            dt = t - t_frame[i]
            if fresh_allowed and 0.0 <= dt < min_dt:  # the same sample again: replace it
                live[i] = v
                continue
            if fresh_allowed and min_dt <= dt <= max_dt:  # not when t goes back
                slope[i] = (v - live[i]) / dt
                q = period[i]
                period[i] = dt if q == 0.0 else q + 0.05 * (dt - q)
            else:
                slope[i] = 0.0
            live[i] = v
            t_frame[i] = t
        if rejoin:
            if self._stale_since is not None:
                self.stale_total_s += now - self._stale_since
            self._stale_since = None
            self._move = None
            self._blend_t0 = now
            self._blend_s = p.startup_s if first else p.rejoin_s
            self._blend_offset = [r - v for r, v in zip(self.ref, self.live, strict=True)]
        self.last_input_s = now

    def park(self, p: ShaperParams, now: float) -> None:
        """Stop requested: ramp to neutral, ignoring input from now on."""
        if self.parking:
            return
        self.parking = True
        self._blend_offset = None
        self._move = _Move(now, self.ref, [0.0] * self.n, p.ramp_speed)

    # --- the reference --------------------------------------------------------------------
    def reference(self, p: ShaperParams, now: float) -> tuple[list[float], str]:
        """``(reference, mode)`` for this tick; mode is ``""`` when live and settled, else one of
        ``"rejoin"``, ``"stale"``, ``"parking"``."""
        if self.started_s is None:
            self.started_s = now
        if self.parking:
            assert self._move is not None
            ref, self.parked = self._move.at(now)
            mode = "parking"
        elif self.is_stale(p, now):
            mode = "stale"
            if self._stale_since is None:
                self._stale_since = now
                self.stale_episodes += 1
                self._blend_offset = None
            if now - self._stale_since < p.hold_s:
                return self.ref, mode
            if self._move is None:
                self._move = _Move(now, self.ref, [0.0] * self.n, p.ramp_speed)
            ref, _ = self._move.at(now)
        else:
            ref = self._live_now(p, now)
            mode = ""
            if self._blend_offset is not None:
                w = min_jerk_weight((now - self._blend_t0) / self._blend_s) if self._blend_s > 0 \
                    else 0.0
                if w == 0.0:
                    self._blend_offset = None
                else:
                    ref = [v + o * w for v, o in zip(ref, self._blend_offset, strict=True)]
                    mode = "rejoin"
        prev = self.ref
        for i, (x, lo, hi) in enumerate(zip(ref, p.reach_lo, p.reach_hi, strict=True)):
            if not lo <= x <= hi:  # beyond the reach, or not a number
                ref[i] = lo if x < lo else hi if x > hi else prev[i]
        self.ref = ref
        return ref, mode

    def _live_now(self, p: ShaperParams, now: float) -> list[float]:
        """The live values, extrapolated to the sender time of this tick (module docstring)."""
        if not p.linear or self._offset is None:
            return self.live[:]
        assert self.last_input_s is not None
        t_now = now - self._offset
        age = now - self.last_input_s
        late = self._excess
        mx = p.max_extrapolation_s
        out = []
        for v, s, tf, q in zip(self.live, self._slope, self._t_frame, self._period, strict=True):
            tau = t_now - tf
            c = 1.5 * q  # the transit jitter allowed for
            b = min(max(mx, c) if late <= c else c + c, age + c)
            out.append(v + s * (tau if 0.0 < tau < b else b if tau >= b else 0.0))
        return out

    def stale_time(self, now: float) -> float:
        """Seconds since the last valid frame (0 while live)."""
        if self._stale_since is None:
            return 0.0
        last = self.last_input_s if self.last_input_s is not None else self.started_s
        return now - (last or now)

