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

Input reconstruction ``linear``: each axis is extrapolated along the line
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
measurements that chose it).  Frames without ``t`` use their arrival time.

Input reconstruction ``smooth`` (the default; docs/TUNING.md has its measurements).  The
reference is the input *played back on the sender's timeline, a little behind its newest
sample*, so that it is interpolated between samples already received instead of guessed::

    sender time  each frame's ``t``, relative to a whole second (float64 arithmetic on epoch
                 times resolves only 0.24 us), on a grid: a ``t`` within TIME_GATE_S of the
                 previous one plus the period (times the seq step) is taken as rounded, and a
                 tracker of the grid (TRACK_ALPHA, TRACK_BETA) replaces it, so that the
                 rounding of the stamps does not reach the reference (0.24 us at 0.5 m/s is
                 0.1 um: 0.1 m/s^2 of acceleration from sample to sample, 6 m/s^2 once
                 compensated); a ``t`` further off is the sender's real timing and is used
                 as it is; a frame without ``t`` from a sender that stamps the others is
                 put on its grid (the previous instant plus the period times the seq step);
                 from a sender that never stamps, the instants are the line through (frame
                 count, arrival on the loop's clock), fitted by recursive least squares whose
                 gains fall to NO_T_ALPHA (frames read in the same tick carry no timing news;
                 an arrival further than stale_after_s/2 from the line re-anchors it)
    period       the interval between frames per seq step (sender time, or arrivals without
                 t), averaged; a single unusual one (a stall) is ignored, PERIOD_RELEARN in a
                 row (a new rate) replace it
    offset       loop clock - sender clock: the smallest transit seen (leaking upwards by
                 SMOOTH_OFFSET_LEAK, 1000 ppm of clock drift; falling at most by
                 SMOOTH_OFFSET_DOWN after the first second: a late tick's frames look early)
    lag          input period + JITTER_FACTOR x the mean transit beyond the smallest
    playback     tau = now - delay, where the delay follows offset + lag through a critically
                 damped filter of DELAY_TAU_S: neither jitter nor a new smallest transit ever
                 steps the playback instant, its changes warp time gently
    per axis     the last HISTORY samples at least (the playback may lie several samples behind the
                 newest, after a burst); tau between two of them: cubic Hermite through them with
                 Catmull-Rom tangents (continuous velocity); tau beyond the newest (a frame late by
                 more than the lag, a stall): the parabola through the last three goes on, at most
                 max_extrapolation_s (or 1.5 input periods if longer), and when the samples come
                 back, the differences of position and velocity to it fade out in a minimum-jerk
                 blend of GAP_BLEND_PERIODS input periods (at least GAP_BLEND_S)
    average      then a moving average over one input period (fractional length, on the
                 tick grid): zero gain at the input's rate and its harmonics, where the
                 playback's roughness lies (the Hermite's acceleration changes at every sample,
                 and the compensator multiplies them); nothing at the loop's own rate
    on a frame   dt = t - t_prev (per axis): dt < min_dt_s is the same sample again (its
                 value replaces the previous one); a t that goes back, or a rejoin, restarts
                 the axis' history at the new sample

The lag (:attr:`ReferenceShaper.lag_s`) is what the reconstruction costs: one input period plus
the mean transit beyond the smallest, plus half a period of averaging below 1 kHz (1.0-1.2 ms
for a 1 kHz sender with 300 us of jitter, 5.5 ms at 250 Hz, 14.5 ms at 100 Hz); a frame later
than that is bridged by the extrapolation.  A design for such an input adds the lag to the
delay the compensator cancels (``motcomp design --input-lag-ms``).  ``hold`` keeps the last
value (for tests of the rest of the chain).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

from motcomp.core.minjerk import PEAK_SPEED_FACTOR, min_jerk_weight

__all__ = ["OFFSET_LEAK", "ReferenceShaper", "ShaperParams"]

OFFSET_LEAK = 0.05
"""Upward drift (s per s) allowed to the fast estimate of the clock offset (smallest transit)."""
SMOOTH_OFFSET_LEAK = 1e-3
"""``smooth``: the same leak, small enough that its steps never reach the playback instant."""
SMOOTH_OFFSET_DOWN = 2e-2
"""``smooth``: after its first second, the smallest transit falls at most this fast (s per s).
A tick that runs late reads frames at its deadline, before they arrived: their transit looks
short by the lateness, and taken at face value it would pull the playback ahead of the
samples."""
JITTER_FACTOR = 1.0
"""The lag allows this many times the mean transit beyond the smallest."""
JITTER_GAIN = 0.01
"""Weight of each frame in the mean transit beyond the smallest."""
DELAY_TAU_S = 0.5
"""Time constant of the critically damped filter the playback delay follows its target
through."""
PERIOD_GAIN = 0.05
"""Weight of each interval in the input period's average."""
TIME_GATE_S = 5e-6
"""A frame ``t`` this close to the sender's regular grid is on it: the difference is the
rounding of its stamp (a float64 epoch time resolves 0.24 us; many senders stamp whole us)."""
TRACK_ALPHA = 0.01
TRACK_BETA = TRACK_ALPHA ** 2 / 4
"""Gains of the tracker of the sender's grid (phase, period; critically damped)."""
PERIOD_RELEARN = 8
"""This many intervals in a row outside half to 1.5 times the period replace it."""
NO_T_ALPHA = 1e-4
"""Frames without ``t``: the least-squares gains of the sender's timeline fall to this (phase)
and its square over 4 (period) and stay there, so that the tracker follows a drifting clock
while an arrival's jitter moves the timeline by a ten-thousandth of it."""
HISTORY = 64
"""Samples kept per axis (at least): a burst of up to :data:`~motcomp.io.zenoh_io.MAX_BURST`
frames leaves the playback instant among them."""
MA_HYSTERESIS = 0.02
"""The moving average's length follows the period only when it moved by more than this
fraction (a length that flickers would warp time)."""
GAP_BLEND_PERIODS = 10.0
GAP_BLEND_S = 0.2
"""After an extrapolation, the difference to the samples fades out over this many input periods
(at least ``GAP_BLEND_S``)."""


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
    reconstruction: str = "smooth"
    """``smooth``, ``linear`` or ``hold`` (module docstring)."""
    max_extrapolation_s: float = 0.02
    tick_s: float = 1e-3
    """The loop's period (the moving average of ``smooth`` counts ticks)."""
    min_dt_s: float = 1e-5
    """Two samples of an axis closer than this on the sender's timeline are one sample."""

    def __post_init__(self) -> None:
        if not self.min_dt_s > 0:
            raise ValueError(f"min_dt_s must be > 0 s, got {self.min_dt_s!r}")
        if self.reconstruction not in ("linear", "smooth", "hold"):
            raise ValueError(f"reconstruction must be linear, smooth or hold, got "
                             f"{self.reconstruction!r}")


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
        self._hist: list[list[tuple[float, float]]] = [[] for _ in range(n)]  # (t, v), newest last
        self._period = 0.0  # average interval between frames (sender time)
        self._t_base: float | None = None  # sender time origin (a whole second)
        self._stamped = False  # the timeline is the sender's (frames with t), not the loop's
        self._nt_n = 0  # frames without t since the timeline was anchored
        self._odd: list[float] = []  # unusual intervals in a row
        self._ma_len = 0.0  # length of the moving average (ticks)
        self._t_last: float | None = None  # sender time of the last frame
        self._fast: float | None = None  # smallest transit, leaking upwards
        self._fast_at = 0.0
        self._fast_since = 0.0
        self._excess = 0.0  # mean transit beyond the smallest
        self._delay: float | None = None  # playback delay (now - tau) and its rate
        self._delay_rate = 0.0
        self._at: float | None = None  # loop time of the last reference
        self._extra: list[tuple[tuple[float, float], ...] | None] = [None] * n  # extrapolating
        self._fix = [0.0] * n  # difference being faded out after an extrapolation, and its
        self._fix_rate = [0.0] * n  # and its rate of change
        self._fix_t0 = [0.0] * n
        self._rings: list[deque[float]] = [deque() for _ in range(n)]  # moving average
        self._ma_delay_s = 0.0
        self._lin_t = [0.0] * n  # linear: sender time of each axis' last value, its slope,
        self._lin_slope = [0.0] * n
        self._lin_period = [0.0] * n  # the average interval between its frames,
        self._lin_offset: float | None = None  # the clock offset (smallest transit)
        self._lin_offset_at = 0.0
        self._lin_excess = 0.0  # and the last frame's transit beyond it
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

    @property
    def period_s(self) -> float:
        """``smooth``: the input's period as learnt (0 before two frames)."""
        return self._period

    @property
    def playback_delay_s(self) -> float | None:
        """``smooth``: loop time minus the sender instant played back (None before it starts)."""
        return self._delay

    @property
    def lag_s(self) -> float:
        """``smooth``: how far the playback lies behind the fastest transit (s): what the
        reconstruction adds to the delay."""
        if self._delay is None or self._fast is None:
            return 0.0
        return self._delay - self._fast + self._ma_delay_s

    # --- events ---------------------------------------------------------------------------
    def is_stale(self, p: ShaperParams, now: float) -> bool:
        """No valid input for ``stale_after_s`` (or none yet, after start-up)."""
        last = self.last_input_s if self.last_input_s is not None else self.started_s
        return last is not None and now - last > p.stale_after_s

    def on_input(self, p: ShaperParams, pos: dict[int, float], now: float,
                 t_sender: float | None = None, frames: int = 1) -> None:
        """A valid frame (axis index -> finite value; sender time ``t_sender``, if any), the
        ``frames``-th the sender sent since the last one taken (its ``seq`` step)."""
        if self.parking:
            return
        first = self.last_input_s is None
        rejoin = first or self._stale_since is not None
        if p.reconstruction == "linear":
            self._on_input_linear(p, pos, now, t_sender, rejoin)
        else:
            self._on_input_smooth(p, pos, now, t_sender, rejoin, max(frames, 1))
        if rejoin:
            if self._stale_since is not None:
                self.stale_total_s += now - self._stale_since
            self._stale_since = None
            self._move = None
            self._blend_t0 = now
            self._blend_s = p.startup_s if first else p.rejoin_s
            self._blend_offset = [r - v for r, v in zip(self.ref, self.live, strict=True)]
        self.last_input_s = now

    def _on_input_linear(self, p: ShaperParams, pos: dict[int, float], now: float,
                         t_sender: float | None, rejoin: bool) -> None:
        t = now if t_sender is None else t_sender
        transit = now - t
        off = self._lin_offset
        if off is None or transit < off or rejoin:
            self._lin_offset = transit
        else:  # leak upwards so a drifting clock is followed
            self._lin_offset = min(off + OFFSET_LEAK * (now - self._lin_offset_at), transit)
        self._lin_offset_at = now
        self._lin_excess = transit - self._lin_offset  # how late this frame is beyond the fastest
        fresh_allowed = not rejoin
        driven, live, t_frame, slope, period = (p.driven, self.live, self._lin_t, self._lin_slope,
                                                self._lin_period)
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

    def _on_input_smooth(self, p: ShaperParams, pos: dict[int, float], now: float,
                         t_sender: float | None, rejoin: bool, frames: int) -> None:
        q = self._period
        tl = self._t_last
        if t_sender is None and self._stamped and tl is not None and not rejoin and q > 0.0:
            t = tl + frames * q  # a stamping sender's frame without t: on its grid
        elif t_sender is None:  # estimate the sender's instant (module docstring)
            self._stamped = False
            arrived = self.last_input_s
            burst = arrived is not None and now <= arrived  # within one tick: no timing news
            pred = (tl or 0.0) + frames * q
            if tl is None or rejoin or abs(now - pred) > 0.5 * p.stale_after_s:
                t = now
                self._nt_n = 1
            elif burst:
                t = pred
            else:  # the line through (frame count, arrival): recursive least squares
                self._nt_n = n = self._nt_n + 1
                alpha = max(2.0 * (2 * n - 1) / (n * (n + 1)), NO_T_ALPHA)
                beta = max(6.0 / (n * (n + 1)), NO_T_ALPHA ** 2 / 4)
                err = now - pred
                new_q = q + beta * err / frames
                if q > 0.0 and not 0.25 * q < new_q < 4.0 * q:  # not the same sender: anew
                    t, self._nt_n = now, 1
                else:
                    t = pred + alpha * err
                    self._period = q = new_q
        else:
            if not self._stamped:  # from the loop's clock to the sender's: a new timeline
                rejoin = True
                self._stamped = True
            if self._t_base is None or rejoin:  # sender times relative to a whole second
                self._t_base = math.floor(t_sender) if math.isfinite(t_sender) else 0.0
            t = t_sender - self._t_base
            pred = (tl or 0.0) + frames * q
            if tl is None or rejoin:
                pass
            elif q > 0.0 and abs(t - pred) <= TIME_GATE_S:  # on the grid but for rounding
                err = t - pred
                t = pred + TRACK_ALPHA * err
                self._period = q = q + TRACK_BETA * err / frames
                self._odd.clear()
            elif p.min_dt_s <= t - tl <= p.stale_after_s:  # irregular: the stamps are right
                self._learn_period((t - tl) / frames)
        transit = now - t
        fast = self._fast
        if fast is None or rejoin:
            self._fast = fast = transit
            self._fast_since = now
        elif transit < fast:  # down, at most SMOOTH_OFFSET_DOWN after the first second
            floor = (fast - SMOOTH_OFFSET_DOWN * (now - self._fast_at)
                     if now - self._fast_since > 1.0 else transit)
            self._fast = fast = max(transit, floor)
        else:  # leak upwards so a drifting clock is followed
            self._fast = fast = min(fast + SMOOTH_OFFSET_LEAK * (now - self._fast_at), transit)
        self._fast_at = now
        if rejoin:
            self._delay = None
            self._excess = 0.0
            for r in self._rings:
                r.clear()
            n = self.n
            self._extra = [None] * n
            self._fix = [0.0] * n
            self._fix_rate = [0.0] * n
        else:
            self._excess += JITTER_GAIN * (max(transit - fast, 0.0) - self._excess)
        if tl is None or t - tl >= p.min_dt_s or t < tl:
            self._t_last = t
        driven, live, hist = p.driven, self.live, self._hist
        min_dt = p.min_dt_s
        for i, v in pos.items():
            if not driven[i]:
                continue
            live[i] = v
            h = hist[i]
            if rejoin or not h or t < h[-1][0]:  # start, rejoin, or a t that goes back
                h.clear()
                h.append((t, v))
            elif t - h[-1][0] < min_dt:  # the same sample again: replace it
                h[-1] = (h[-1][0], v)
            else:
                h.append((t, v))
                if len(h) > 2 * HISTORY:  # (trimmed in batches: no shift per sample)
                    del h[:HISTORY]

    def _learn_period(self, dt: float) -> None:
        """One interval between frames (per frame): averaged when within half to 1.5 times the
        period; :data:`PERIOD_RELEARN` unusual ones in a row (the sender changed its rate)
        replace the period by their median; a single one (a stall) changes nothing."""
        q = self._period
        if q == 0.0:
            if dt > 0.0:
                self._period = dt
            return
        if 0.5 * q <= dt <= 1.5 * q:
            self._period = q + PERIOD_GAIN * (dt - q)
            self._odd.clear()
            return
        self._odd.append(dt)
        if len(self._odd) >= PERIOD_RELEARN:
            self._period = sorted(self._odd)[len(self._odd) // 2]
            self._odd.clear()

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
        """The live values at this tick: reconstructed as ``p.reconstruction`` says."""
        if p.reconstruction == "linear":
            return self._live_linear(p, now)
        q = self._period
        fast = self._fast
        if p.reconstruction != "smooth" or fast is None or q == 0.0:
            self._delay = None  # (re)starts once the input's period is known
            return self.live[:]
        at = self._at
        dt = 0.0 if at is None else max(now - at, 0.0)
        self._at = now
        target = fast + min(q + JITTER_FACTOR * self._excess, q + 0.5 * p.stale_after_s)
        d = self._delay
        if d is None:
            d, self._delay_rate = target, 0.0
        elif dt > 0.0:
            w = 1.0 / DELAY_TAU_S  # critically damped: x'' = w^2 (target - x) - 2 w x'
            r = self._delay_rate
            for _ in range(1 if dt <= 0.002 else int(dt / 0.002) + 1):
                dts = min(dt, 0.002)
                r += dts * (w * w * (target - d) - 2.0 * w * r)
                d += dts * r
                dt -= dts
            self._delay_rate = r
        self._delay = d
        tau = now - d
        bound = max(p.max_extrapolation_s, 1.5 * q)
        blend_s = max(GAP_BLEND_S, GAP_BLEND_PERIODS * q)
        out = []
        extra = self._extra
        for i, h in enumerate(self._hist):
            if not h:
                out.append(self.live[i])
                continue
            prev = extra[i]
            if tau <= h[-1][0] or len(h) == 1:
                x, xs = _hermite(h, tau) if len(h) > 1 else (h[0][1], 0.0)
                src = None
            else:  # beyond the newest sample: the parabola through the last three goes on
                src = tuple(h[-3:])
                x, xs = _extrapolate(src, tau, bound)
            if prev is not None and (src is None or src[-1][0] != prev[-1][0]):
                xo, so = _extrapolate(prev, tau, bound)  # the samples changed under it
                self._start_fix(i, now, blend_s, xo - x, so - xs)
            extra[i] = src
            out.append(x + self._current_fix(i, now, blend_s))
        length = q / p.tick_s
        if abs(length - self._ma_len) > MA_HYSTERESIS * max(self._ma_len, 1.0):
            self._ma_len = length  # only a real change of the input's rate moves it
        return self._average(out, p.tick_s, self._ma_len)

    def _average(self, x: list[float], tick_s: float, length: float) -> list[float]:
        """Moving average of each axis over the last ``length`` ticks (fractional: the oldest
        tick weighs what is left), i.e. one input period: zero gain at the input's rate and its
        harmonics, where the playback's roughness lies."""
        if length <= 1.0 + MA_HYSTERESIS:
            self._ma_delay_s = 0.0
            for r in self._rings:
                r.clear()
            return x
        n = int(length)
        frac = length - n
        keep = n + 1 if frac > 0.0 else n
        out = []
        for v, r in zip(x, self._rings, strict=True):
            r.append(v)
            while len(r) > keep:
                r.popleft()
            if len(r) < keep:  # filling up: average what there is
                out.append(sum(r) / len(r))
                continue
            total = sum(r)
            if frac > 0.0:
                total -= (1.0 - frac) * r[0]
            out.append(total / length)
        self._ma_delay_s = 0.5 * (length - 1.0) * tick_s
        return out

    def _live_linear(self, p: ShaperParams, now: float) -> list[float]:
        """``linear``: extrapolated along the last two frames to this tick (module docstring)."""
        if self._lin_offset is None:
            return self.live[:]
        assert self.last_input_s is not None
        t_now = now - self._lin_offset
        age = now - self.last_input_s
        late = self._lin_excess
        mx = p.max_extrapolation_s
        out = []
        for v, s, tf, q in zip(self.live, self._lin_slope, self._lin_t, self._lin_period,
                               strict=True):
            tau = t_now - tf
            c = 1.5 * q  # the transit jitter allowed for
            b = min(max(mx, c) if late <= c else c + c, age + c)
            out.append(v + s * (tau if 0.0 < tau < b else b if tau >= b else 0.0))
        return out

    def _fix_at(self, i: int, el: float, blend_s: float) -> float:
        """The correction ``el`` after it started: ``(d + r el) w(el/blend)``, which starts with
        the differences ``d`` and ``r`` of position and velocity (min-jerk ``w``: flat at both
        ends) and fades them out."""
        return (self._fix[i] + self._fix_rate[i] * el) * min_jerk_weight(el / blend_s)

    def _current_fix(self, i: int, now: float, blend_s: float) -> float:
        if self._fix[i] == 0.0 and self._fix_rate[i] == 0.0:
            return 0.0
        el = now - self._fix_t0[i]
        if el >= blend_s:
            self._fix[i] = self._fix_rate[i] = 0.0
            return 0.0
        return self._fix_at(i, el, blend_s)

    def _start_fix(self, i: int, now: float, blend_s: float, d: float, r: float) -> None:
        """A new correction (position ``d``, velocity ``r``) on top of what remains of the
        previous one, so that the reference stays continuous in position and velocity."""
        rest = rest_rate = 0.0
        if self._fix[i] or self._fix_rate[i]:
            el = now - self._fix_t0[i]
            e = 1e-5
            rest = self._fix_at(i, el, blend_s)
            rest_rate = (self._fix_at(i, el + e, blend_s) - self._fix_at(i, el - e, blend_s)) \
                / (2 * e)
        self._fix[i] = d + rest
        self._fix_rate[i] = r + rest_rate
        self._fix_t0[i] = now

    def stale_time(self, now: float) -> float:
        """Seconds since the last valid frame (0 while live)."""
        if self._stale_since is None:
            return 0.0
        last = self.last_input_s if self.last_input_s is not None else self.started_s
        return now - (last or now)



def _hermite(h: Sequence[tuple[float, float]], tau: float) -> tuple[float, float]:
    """Value and slope at ``tau`` of the cubic Hermite through the samples ``h`` (at least 2,
    time-ordered; ``tau`` clamped to their span), Catmull-Rom tangents; at the
    newest sample, the slope of the parabola through the last three (:func:`_end_slope`), which
    the central tangent replaces when the next sample comes with a difference of order
    jerk x period^2 only."""
    n = len(h)
    j = n - 2
    while j > 0 and tau < h[j][0]:
        j -= 1
    (t0, v0), (t1, v1) = h[j], h[j + 1]
    span = t1 - t0
    m0 = (v1 - h[j - 1][1]) / (t1 - h[j - 1][0]) if j > 0 else (v1 - v0) / span
    m1 = (h[j + 2][1] - v0) / (h[j + 2][0] - t0) if j + 2 < n else _end_slope(h[max(j - 1, 0):])
    x = min(max((tau - t0) / span, 0.0), 1.0)
    x2 = x * x
    x3 = x2 * x
    value = ((2 * x3 - 3 * x2 + 1) * v0 + (x3 - 2 * x2 + x) * span * m0
             + (-2 * x3 + 3 * x2) * v1 + (x3 - x2) * span * m1)
    slope = ((6 * x2 - 6 * x) * (v0 - v1) / span + (3 * x2 - 4 * x + 1) * m0
             + (3 * x2 - 2 * x) * m1)
    return value, slope


def _extrapolate(h: Sequence[tuple[float, float]], tau: float, bound: float
                 ) -> tuple[float, float]:
    """Value and slope at ``tau`` of the parabola through the samples ``h`` (the last 3, or 2:
    a line), continued at most ``bound`` beyond the newest and held after that."""
    t_n, v_n = h[-1]
    e = min(tau - t_n, bound)
    t1, v1 = h[-2]
    s1 = (v_n - v1) / (t_n - t1)
    if len(h) < 3:
        return v_n + s1 * e, (s1 if tau - t_n < bound else 0.0)
    t0, v0 = h[-3]
    curv = 2.0 * ((v_n - v1) / (t_n - t1) - (v1 - v0) / (t1 - t0)) / (t_n - t0)  # 2nd deriv.
    slope_n = s1 + 0.5 * curv * (t_n - t1)  # = _end_slope(h)
    value = v_n + slope_n * e + 0.5 * curv * e * e
    return value, (slope_n + curv * e if tau - t_n < bound else 0.0)


def _end_slope(h: Sequence[tuple[float, float]]) -> float:
    """Slope at the newest of the samples ``h`` (at least 2): of the parabola through the last
    three, or of the line through the last two."""
    (t1, v1), (t2, v2) = h[-2], h[-1]
    if len(h) < 3:
        return (v2 - v1) / (t2 - t1)
    t0, v0 = h[-3]
    return (v0 * (t2 - t1) / ((t0 - t1) * (t0 - t2)) + v1 * (t2 - t0) / ((t1 - t0) * (t1 - t2))
            + v2 * (2 * t2 - t0 - t1) / ((t2 - t0) * (t2 - t1)))
