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
measurements that chose it).  Frames without ``t`` use their arrival time.

Input reconstruction ``smooth`` (``input.reconstruction = "smooth"``; docs/TUNING.md has its
measurements).  The reference is the input *played back on the sender's timeline, a little
behind its newest sample*, so that it is interpolated between samples already received instead
of guessed::

    sender time  each frame's ``t``; a frame without ``t`` gets an estimate on the loop's
                 clock: the previous estimate plus the input period, pulled towards its arrival
                 by INPUT_PLL_GAIN (jitter moves it by that fraction only), the period from the
                 intervals between arrivals (those shorter than half of it, a burst, left out;
                 those over 1.5 times it weigh a fifth);
                 an arrival further than stale_after_s/2 from the estimate re-anchors it
    offset       loop clock - sender clock: the smallest transit seen (leaking upwards by
                 OFFSET_LEAK), followed by a first-order filter of OFFSET_TAU_S, so that
                 jitter never moves the playback instant
    lag          input period + JITTER_FACTOR x the mean transit beyond the smallest, followed
                 by a critically damped filter of LAG_TAU_S (its changes warp time gently)
    playback     tau = now - offset - lag
    per axis     the last 4 samples; tau between two of them: cubic Hermite through them with
                 Catmull-Rom tangents (continuous velocity); tau beyond the newest (a frame
                 late by more than the lag, a stall): straight on with the slope at the newest
                 sample, at most max_extrapolation_s (or 1.5 input periods if longer), and when
                 the samples come back, the differences of position and velocity to the
                 extrapolation fade out in a minimum-jerk blend of GAP_BLEND_PERIODS input
                 periods (at least GAP_BLEND_S)
    on a frame   dt = t - t_prev (per axis): dt < min_dt_s is the same sample again (its
                 value replaces the previous one); a t that goes back, or a rejoin, restarts
                 the axis' history at the new sample

The lag is what the reconstruction costs: about one input period plus the sender's jitter
(1.3 ms for a 1 kHz sender with 300 us of jitter, 10.3 ms at 100 Hz); a design for such an
input adds it to the delay the compensator cancels.  ``hold`` keeps the last value
(for tests of the rest of the chain).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from motcomp.core.minjerk import PEAK_SPEED_FACTOR, min_jerk_weight

__all__ = ["OFFSET_LEAK", "ReferenceShaper", "ShaperParams"]

OFFSET_LEAK = 0.05
"""Upward drift (s per s) allowed to the fast estimate of the clock offset (smallest transit)."""
OFFSET_TAU_S = 5.0
"""Time constant of the filter between the fast offset estimate and the playback instant."""
JITTER_FACTOR = 3.0
"""The lag allows this many times the mean transit beyond the smallest."""
JITTER_GAIN = 0.01
"""Weight of each frame in the mean transit beyond the smallest."""
LAG_TAU_S = 0.5
"""Time constant of the critically damped filter the lag follows its target through."""
PERIOD_GAIN = 0.05
"""Weight of each interval in the input period's average."""
INPUT_PLL_GAIN = 0.02
"""How strongly the sender time of a frame without ``t`` is pulled towards its arrival."""
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
    reconstruction: str = "linear"
    """``linear``, ``smooth`` or ``hold`` (module docstring)."""
    max_extrapolation_s: float = 0.02
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
        self._t_last: float | None = None  # sender time of the last frame
        self._fast: float | None = None  # smallest transit, leaking upwards
        self._fast_at = 0.0
        self._offset: float | None = None  # the fast estimate, filtered (OFFSET_TAU_S)
        self._excess = 0.0  # mean transit beyond the smallest
        self._lag = 0.0  # playback lag and its rate (critically damped filter)
        self._lag_rate = 0.0
        self._at: float | None = None  # loop time of the last reference
        self._extra: list[tuple[float, float, float] | None] = [None] * n  # extrapolating from
        self._fix = [0.0] * n  # difference being faded out after an extrapolation, and its
        self._fix_rate = [0.0] * n  # rate of change
        self._fix_t0 = [0.0] * n
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
    def lag_s(self) -> float:
        """The playback lag behind the sender's newest sample (s)."""
        return self._lag

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
        if p.reconstruction == "linear":
            self._on_input_linear(p, pos, now, t_sender, rejoin)
        else:
            self._on_input_smooth(p, pos, now, t_sender, rejoin)
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
                         t_sender: float | None, rejoin: bool) -> None:
        q = self._period
        arrived = self.last_input_s
        if t_sender is None:  # estimate the sender's instant (module docstring)
            tl = self._t_last
            if arrived is not None and not rejoin:  # the period, from arrivals (not bursts)
                dt = now - arrived
                if q == 0.0 or 0.5 * q <= dt <= p.stale_after_s:
                    gain = PERIOD_GAIN if dt <= 1.5 * q else 0.2 * PERIOD_GAIN
                    self._period = q = dt if q == 0.0 else q + gain * (dt - q)
            pred = (tl or 0.0) + q
            if tl is None or rejoin or q == 0.0 or abs(now - pred) > 0.5 * p.stale_after_s:
                t = now
            else:
                t = pred + INPUT_PLL_GAIN * (now - pred)
        else:
            t = t_sender
        transit = now - t
        fast = self._fast
        if fast is None or transit < fast or rejoin:
            self._fast = fast = transit
        else:  # leak upwards so a drifting clock is followed
            self._fast = fast = min(fast + OFFSET_LEAK * (now - self._fast_at), transit)
        self._fast_at = now
        if self._offset is None or rejoin:
            self._offset = fast
            self._excess = 0.0
        else:
            self._excess += JITTER_GAIN * (transit - fast - self._excess)
        tl = self._t_last
        if (t_sender is not None and tl is not None and not rejoin
                and p.min_dt_s <= t - tl <= p.stale_after_s):
            dt = t - tl  # a longer interval than usual (a stall, lost frames) counts for less
            gain = PERIOD_GAIN if dt <= 1.5 * q else 0.2 * PERIOD_GAIN
            self._period = dt if q == 0.0 else q + gain * (dt - q)
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
                if len(h) > 4:
                    del h[0]

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
        if p.reconstruction != "smooth" or self._offset is None:
            return self.live[:]
        at = self._at
        dt = 0.0 if at is None else max(now - at, 0.0)
        self._at = now
        q = self._period
        target = q + JITTER_FACTOR * self._excess
        target = min(target, 0.5 * p.stale_after_s + q)
        if at is None or self._lag == 0.0:
            self._lag, self._lag_rate = target, 0.0
            self._offset = self._fast
        elif dt > 0.0:
            assert self._fast is not None
            a = min(dt / OFFSET_TAU_S, 1.0)
            self._offset += a * (self._fast - self._offset)
            w = 1.0 / LAG_TAU_S  # critically damped: x'' = w^2 (target - x) - 2 w x'
            for _ in range(1 if dt <= 0.002 else int(dt / 0.002) + 1):
                dts = min(dt, 0.002)
                self._lag_rate += dts * (w * w * (target - self._lag)
                                         - 2.0 * w * self._lag_rate)
                self._lag += dts * self._lag_rate
                dt -= dts
        offset = self._offset
        assert offset is not None
        tau = now - offset - self._lag
        bound = max(p.max_extrapolation_s, 1.5 * q)
        blend_s = max(GAP_BLEND_S, GAP_BLEND_PERIODS * q)
        out = []
        for i, h in enumerate(self._hist):
            if not h:
                out.append(self.live[i])
                continue
            t_n, v_n = h[-1]
            if tau <= t_n or len(h) == 1:
                x = _hermite(h, tau) if len(h) > 1 else v_n
                ex = self._extra[i]
                if ex is not None:  # back from an extrapolation: fade the difference out
                    t0, v0, s0 = ex
                    e = 1e-5
                    slope = (_hermite(h, tau + e) - _hermite(h, tau - e)) / (2 * e) \
                        if len(h) > 1 else 0.0
                    self._start_fix(i, now, blend_s, v0 + s0 * min(tau - t0, bound) - x,
                                    (s0 if tau - t0 < bound else 0.0) - slope)
                    self._extra[i] = None
            else:
                slope = _end_slope(h)
                ex = self._extra[i]
                if ex is None or ex[0] != t_n:
                    if ex is not None:  # a newer sample, still behind tau
                        t0, v0, s0 = ex
                        xe = v_n + slope * min(tau - t_n, bound)
                        self._start_fix(i, now, blend_s, v0 + s0 * min(tau - t0, bound) - xe,
                                        (s0 if tau - t0 < bound else 0.0)
                                        - (slope if tau - t_n < bound else 0.0))
                    self._extra[i] = (t_n, v_n, slope)
                x = v_n + slope * min(tau - t_n, bound)
            out.append(x + self._current_fix(i, now, blend_s))
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

    def _current_fix(self, i: int, now: float, blend_s: float) -> float:
        """The correction still faded in: ``(d + r (now - t0)) w((now - t0)/blend)``, which
        starts with the difference ``d`` of position and ``r`` of velocity (min-jerk ``w``)."""
        f, r = self._fix[i], self._fix_rate[i]
        if f == 0.0 and r == 0.0:
            return 0.0
        el = now - self._fix_t0[i]
        w = min_jerk_weight(el / blend_s)
        if w == 0.0:
            self._fix[i] = self._fix_rate[i] = 0.0
        return (f + r * el) * w

    def _start_fix(self, i: int, now: float, blend_s: float, d: float, r: float) -> None:
        """A new correction of ``d`` (position) and ``r`` (velocity) on top of what remains."""
        el = now - self._fix_t0[i]
        w = min_jerk_weight(el / blend_s) if self._fix[i] or self._fix_rate[i] else 0.0
        # what remains of the previous correction, and its rate (to first order)
        rest = (self._fix[i] + self._fix_rate[i] * el) * w
        e = 1e-5
        w2 = min_jerk_weight((el + e) / blend_s) if w else 0.0
        rest_rate = ((self._fix[i] + self._fix_rate[i] * (el + e)) * w2 - rest) / e if w else 0.0
        self._fix[i] = d + rest
        self._fix_rate[i] = r + rest_rate
        self._fix_t0[i] = now

    def stale_time(self, now: float) -> float:
        """Seconds since the last valid frame (0 while live)."""
        if self._stale_since is None:
            return 0.0
        last = self.last_input_s if self.last_input_s is not None else self.started_s
        return now - (last or now)



def _hermite(h: Sequence[tuple[float, float]], tau: float) -> float:
    """Cubic Hermite through the samples ``h`` (2-4, time-ordered) at ``tau`` (clamped to
    their span), Catmull-Rom tangents; at the newest sample, the slope of the parabola through
    the last three (:func:`_end_slope`), which the central tangent replaces when the next sample
    comes with a difference of order jerk x period^2 only."""
    n = len(h)
    j = n - 2
    while j > 0 and tau < h[j][0]:
        j -= 1
    (t0, v0), (t1, v1) = h[j], h[j + 1]
    span = t1 - t0
    if tau <= t0:
        return v0
    if tau >= t1:
        return v1
    m0 = (v1 - h[j - 1][1]) / (t1 - h[j - 1][0]) if j > 0 else (v1 - v0) / span
    m1 = (h[j + 2][1] - v0) / (h[j + 2][0] - t0) if j + 2 < n else _end_slope(h[:j + 2])
    x = (tau - t0) / span
    x2 = x * x
    x3 = x2 * x
    return ((2 * x3 - 3 * x2 + 1) * v0 + (x3 - 2 * x2 + x) * span * m0
            + (-2 * x3 + 3 * x2) * v1 + (x3 - x2) * span * m1)


def _end_slope(h: Sequence[tuple[float, float]]) -> float:
    """Slope at the newest of the samples ``h`` (at least 2): of the parabola through the last
    three, or of the line through the last two."""
    (t1, v1), (t2, v2) = h[-2], h[-1]
    if len(h) < 3:
        return (v2 - v1) / (t2 - t1)
    t0, v0 = h[-3]
    return (v0 * (t2 - t1) / ((t0 - t1) * (t0 - t2)) + v1 * (t2 - t0) / ((t1 - t0) * (t1 - t2))
            + v2 * (2 * t2 - t0 - t1) / ((t2 - t0) * (t2 - t1)))
