"""From the stream of valid input frames to the compensator's reference, per axis.

Rules (all times from the loop's clock, passed in)::

    start        reference at neutral (0) until the first valid frame
    first frame  blend from neutral to the live input over ``startup_s``           "rejoin"
    live         reference = last valid value of each axis (a frame may carry a subset),
                 reconstructed between frames (below)
    no valid frame for stale_after_s
                 hold the reference for ``hold_s``, then move each axis to neutral  "stale"
                 in a minimum-jerk ramp whose peak speed is ``ramp_speed`` (per axis);
                 the command's own path to rest (braking within v^2 / (2 a_max), then
                 this hold and ramp, uncompensated) is the tick's rule
                 (:mod:`motcomp.core.tick`, "Input loss")
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
                 times resolves only 0.24 us): the instant of its sample, whatever the pattern
                 (a regular grid, jittered instants, skipped samples, variable steps); a
                 least-squares line through (frame count, ``t``) learns the period and, for a
                 frame without ``t`` from a sender that stamps the others, puts it on the
                 sender's grid; from a sender that never stamps, the same line goes through
                 (frame count, arrival on the loop's clock), with gains falling to NO_T_ALPHA
                 (frames read in the same tick carry no timing news; an arrival further than
                 stale_after_s/2 from the line re-anchors it), and the line is the timeline;
                 a stamp is the instant to its own resolution only (``t0 + k/rate`` in
                 epoch seconds: 0.24 us), so where GRID_MIN_FRAMES stamps in a row lie on the
                 line within it, the values decide where their samples lie: at the stamps
                 (computed at the rounded instant), or on the grid the stamps round (computed
                 at ``k/rate``; then the instants follow the line, and the rounding is no
                 longer position noise the compensator amplifies: ``_weigh_grid``)
    period       the interval between frames per seq step (sender time, or arrivals without
                 t), averaged; a single unusual one (a stall) is ignored, PERIOD_RELEARN in a
                 row (a new rate) replace it
    offset       loop clock - sender clock: the smallest transit seen (leaking upwards by
                 SMOOTH_OFFSET_LEAK, 1000 ppm of clock drift; falling at most by
                 SMOOTH_OFFSET_DOWN after the first second: a late tick's frames look early)
    lag          span + JITTER_FACTOR x the mean transit beyond the smallest; the span is the
                 longest recent interval between samples (taken at once, decaying to the
                 period by SPAN_DECAY a sample; stalls left out): an irregular stream is
                 interpolated, not extrapolated
    playback     tau = now - delay + lead_s, where the delay follows offset + lag through a
                 critically damped triple pole of DELAY_TAU_S: neither jitter nor a new
                 smallest transit ever steps the playback instant, its changes warp time
                 gently, and the warp's own rate changes without a step (a step of it is a
                 step of the reference's acceleration, speed x w^2 x the change: a sender's
                 3 ms skip made 0.04 m/s^2 of the compensated rails' command); a lead
                 (0 by default) plays ahead of the lag: prediction along the constant-jerk
                 bridge below, exact on cubics, whose errors on a change of jerk the
                 compensator amplifies (docs/TUNING.md has the trade-off)
    per axis     the last HISTORY samples at least (the playback may lie several samples
                 behind the newest, after a burst), each with the slope, acceleration and jerk
                 of the cubic through it and three before it at least STENCIL_S apart (exact on
                 cubics, value noise divided by that baseline rather than one period, causal:
                 never revised by the next sample, so the curve under the playback never
                 changes); tau between two of them: the quintic Hermite that meets both with
                 their value, slope and acceleration (continuous acceleration); tau beyond the
                 newest (a frame late by more than the lag, a stall): the newest sample's
                 Taylor cubic (constant jerk) goes on for max_extrapolation_s (or 1.5 input
                 periods if longer), then the parabola it reached (no velocity step, which the
                 compensator would turn into its limits; the stale-input rule ends a gap
                 longer still), and when the samples come back, the differences of
                 position and velocity to it are added to a correction that fades out
                 through a critically damped triple pole, settled in about GAP_BLEND_PERIODS
                 input periods (at least GAP_BLEND_S): continuous to the acceleration, each
                 difference on its own schedule however often they come
    average      then, for an input period of MA_MIN_TICKS ticks or more, a moving average over
                 one input period (fractional length, on the tick grid): zero gain at the
                 input's rate and its harmonics, where the playback's roughness lies (the
                 quintic's jerk changes at every sample, and the compensator multiplies it)
    band limit   then each axis' band limit (ShaperParams.band, :mod:`motcomp.core.bandlimit`):
                 a 4th-order Bessel, a pure delay in the driver's band, that keeps what a
                 sender's numbers carry above it (float32, rounded stamps) out of the
                 compensator; started at rest on its first value, restarted with the playback
    on a frame   dt = t - t_prev (per axis): dt < min_dt_s is the same sample again (its
                 value replaces the previous one); a t that goes back, or a rejoin, restarts
                 the axis' history at the new sample

The lag (:attr:`ReferenceShaper.lag_s`) is what the reconstruction costs: the span (one input
period for a regular sender) plus the mean transit beyond the smallest, plus half a period of
averaging from 500 Hz down (1.0-1.2 ms for a 1 kHz sender with 300 us of jitter, 5.5 ms at
250 Hz, 14.5 ms at 100 Hz); a frame later than that is bridged by the extrapolation.  A design
for such an input adds the lag to the delay the compensator cancels (``motcomp design
--input-lag-ms``), and the band limit's delay besides (``--input-band-hz``).  ``hold`` keeps the
last value (for tests of the rest of the chain).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

from mypy_extensions import mypyc_attr

from motcomp.core.bandlimit import BandLimit, BandLimitParams
from motcomp.core.minjerk import PEAK_SPEED_FACTOR, min_jerk, min_jerk_rate, min_jerk_weight
from motcomp.core.native import frozen_reduce

__all__ = ["OFFSET_LEAK", "ReferenceShaper", "ShaperParams"]


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Knot:
    """A sample of one axis: instant ``t``, value ``v``, and the slope ``m``, acceleration
    ``a`` and jerk ``j`` there (:func:`_knot`).  A class, not a tuple: compiled, its floats
    are stored unboxed."""

    t: float
    v: float
    m: float
    a: float
    j: float

    def __init__(self, t: float, v: float, m: float, a: float, j: float) -> None:
        self.t, self.v, self.m, self.a, self.j = t, v, m, a, j

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Knot) and self.fields() == other.fields()

    __hash__ = None  # type: ignore[assignment]  # mutable-looking, compared by value

    def fields(self) -> tuple[float, float, float, float, float]:
        return self.t, self.v, self.m, self.a, self.j

    def __repr__(self) -> str:
        return f"Knot{self.fields()!r}"


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
"""Time constant of the critically damped triple pole the playback delay follows its target
through."""
PERIOD_GAIN = 0.05
"""Weight of each interval in the input period's average."""
TIME_GATE_S = 5e-6
"""A frame ``t`` this close to the line of the sender's grid a whole number of periods on is a
sender that skipped samples (the line's grid goes on; the frame's instant is still its ``t``)."""
TRACK_ALPHA = 0.01
"""The least-squares gains of the sender's grid fall to this (phase) and its square over 4
(period); they move the line only, never a sample's instant."""
PERIOD_RELEARN = 8
"""This many intervals in a row outside half to 1.5 times the period replace it."""
NO_T_ALPHA = 1e-4
"""Frames without ``t``: the least-squares gains of the sender's timeline fall to this (phase)
and its square over 4 (period) and stay there, so that the tracker follows a drifting clock
while an arrival's jitter moves the line by a ten-thousandth of it (and no sample at all)."""
MIN_SKIP_STEP = 1e-6
SKIP_TOLERANCE = 0.15
SKIP_NOISE = 0.25e-6
"""Frames without ``t``: the values' noise for the skip count (axis units; four ulps of a
float32 value where more): a change of the step below it is no steady acceleration, and beside a
crest a step nearer than it (or than four times the spread of the step's last changes) to what
the frames say moves is read as those frames (:meth:`ReferenceShaper._spanned`)."""
MAX_SKIP = 1000
"""Frames without ``t``: a step of the fastest axis within SKIP_TOLERANCE of m >= 2 times the
previous one (per frame), which moved at least MIN_SKIP_STEP (axis units), spans m samples: the
sender skipped m - 1 (a simulation that keeps its schedule after a stall); at most MAX_SKIP, as
for a stamp on the grid MAX_SKIP periods on at most."""
HISTORY = 64
"""Samples kept per axis (at least): a burst of up to :data:`~motcomp.io.zenoh_io.MAX_BURST`
frames leaves the playback instant among them."""
SPAN_DECAY = 1e-3
SPAN_MAX_PERIODS = 4.0
"""The playback's span (:meth:`ReferenceShaper._track_span`) decays by this a sample, and
ignores intervals longer than this many periods (stalls)."""
STENCIL_S: Final = 5e-3
"""A sample's knot (slope, acceleration, jerk) is taken from samples at least this far apart
(:func:`_stencil`): the cubic through them is as exact on cubics, and a 1 kHz sender's value
noise reaches the jerk over 100 times less than over one period (what a late frame's
extrapolation then carries: docs/TUNING.md)."""
MA_MIN_TICKS = 2.0
"""No moving average for an input period shorter than this many ticks (a 1 kHz sender, or an
irregular one of 0.5-2 ms steps): its length would follow the period's jitter, and every change
of length is a step of the playback instant; the band limit takes the roughness out."""
MA_HYSTERESIS = 0.02
"""The moving average's length follows the period only when it moved by more than this
fraction (a length that flickers would warp time)."""
GAP_BLEND_PERIODS = 10.0
GAP_BLEND_S = 0.2
"""After an extrapolation, the difference to the samples fades out over about this many input
periods (at least ``GAP_BLEND_S``)."""
FIX_POLE_FACTOR = 6.0
"""The fade is a triple pole at ``-FIX_POLE_FACTOR / blend``: within 6 % of its start after the
blend time, 0.05 % after twice it."""
FIX_FLOOR = 1e-12
"""A correction below this (axis units, and its rate times the blend time) is dropped."""
GRID_MIN_FRAMES = 32
"""A stamp is read against the sender's grid (:meth:`ReferenceShaper._weigh_grid`) once this
many in a row lay on the line within their resolution."""
GRID_TRACK_ALPHA = 1e-3
"""The line's gains fall to this (phase) and its square over 4 (period) while the stamps lie on
it within their resolution: a grid in the sender's own time is a line."""
GRID_FOLLOW = 0.01
"""The instants read on the grid follow the line through this gain (a frame's phase update
is the line's own jitter, 0.1 ns, which the compensator would still see)."""
GRID_MIN_WEIGHT = 20.0
"""No decision before this many windows' worth of evidence (:meth:`ReferenceShaper._weigh_grid`:
five frames each)."""
GRID_GAIN = 1e-2
"""Weight of each window of five frames in the evidence of where a grid sender's values lie
(about 100 windows: half a second at 1 kHz)."""
GRID_SIGMAS = 3.0
"""The evidence must lie this many standard errors from the midway to change the decision."""


@dataclass(frozen=True)
class ShaperParams:
    """The shaper's settings, per axis where a tuple (in :data:`~motcomp.core.axes.AXES` order)."""

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return frozen_reduce(self)

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
    lead_s: float = 0.0
    """``smooth``: play back this far ahead (s): prediction along the newest sample's
    constant-jerk cubic, which takes this much off the reconstruction's lag."""
    tick_s: float = 1e-3
    """The loop's period (the moving average of ``smooth`` counts ticks)."""
    min_dt_s: float = 1e-5
    """Two samples of an axis closer than this on the sender's timeline are one sample."""
    band: tuple[BandLimitParams | None, ...] = ()
    """``smooth``: each axis' reference band limit (:mod:`motcomp.core.bandlimit`; None, or
    an empty tuple: none)."""

    def __post_init__(self) -> None:
        if not self.min_dt_s > 0:
            raise ValueError(f"min_dt_s must be > 0 s, got {self.min_dt_s!r}")
        if not 0.0 <= self.lead_s <= 0.1:
            raise ValueError(f"lead_s must be within [0, 0.1] s, got {self.lead_s!r}")
        if self.reconstruction not in ("linear", "smooth", "hold"):
            raise ValueError(f"reconstruction must be linear, smooth or hold, got "
                             f"{self.reconstruction!r}")


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
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


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class ReferenceShaper:
    """The state of the rules in the module docstring; every method takes the settings."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.live = [0.0] * n
        self._hist: list[list[Knot]] = [[] for _ in range(n)]  # per axis, newest last
        self._period = 0.0  # average interval between frames (sender time)
        self._t_base: float | None = None  # sender time origin (a whole second)
        self._stamped = False  # the timeline is the sender's (frames with t), not the loop's
        self._line = 0.0  # the least-squares line of the sender's instants: its newest point
        self._line_n = 0  # and the frames on it since it was anchored
        self._odd: list[float] = []  # unusual intervals in a row
        self._grid_err: float | None = None  # the last frame's stamp - its grid instant
        self._grid_ring: list[tuple[float, dict[int, float]]] = []  # _weigh_grid's frames
        self._grid_sums = [0.0, 0.0, 0.0, 0.0]  # its evidence: sum r u, u u, r r, weight
        self.at_stamps = True  # a grid sender's values lie at its stamps (else on its grid)
        self._grid_t: float | None = None  # the last instant read on the grid
        self._grid_run = 0  # frames in a row whose stamps lie on the line within their ulp
        self._ma_len = 0.0  # length of the moving average (ticks)
        self._span = 0.0  # the longest recent interval between samples (_track_span)
        self._t_last: float | None = None  # sender time of the last frame
        self._fast: float | None = None  # smallest transit, leaking upwards
        self._fast_at = 0.0
        self._fast_since = 0.0
        self._excess = 0.0  # mean transit beyond the smallest
        self._delay: float | None = None  # playback delay (now - tau) and its rate
        self._delay_rate = 0.0
        self._delay_acc = 0.0
        self._lead_s = 0.0  # the lead in force (ShaperParams.lead_s)
        self._at: float | None = None  # loop time of the last reference
        self._extra: list[Knot | None] = [None] * n
        """Per axis while extrapolating: the sample extrapolated from."""
        self._fix: list[list[float] | None] = [None] * n
        """Per axis, the correction being faded out after an extrapolation: its value, rate and
        acceleration (None: none)."""
        self._fix_step: tuple[float, float, tuple[float, ...]] = (0.0, 0.0, ())
        self._rings: list[deque[float]] = [deque() for _ in range(n)]  # moving average
        self._ma_delay_s = 0.0
        self._band = BandLimit(n)
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
        self._blend_pending = False
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
        """``smooth``: how far the playback lies behind the fastest transit (s), less the lead:
        what the reconstruction adds to the delay (negative when the lead exceeds the lag),
        not including the band limit's delay (``input.band_hz``, shown apart)."""
        if self._delay is None or self._fast is None:
            return 0.0
        return self._delay - self._fast + self._ma_delay_s - self._lead_s

    # --- events ---------------------------------------------------------------------------
    def is_stale(self, p: ShaperParams, now: float) -> bool:
        """No valid input for ``stale_after_s`` (or none yet, after start-up)."""
        last = self.last_input_s if self.last_input_s is not None else self.started_s
        return last is not None and now - last > p.stale_after_s

    def on_input(self, p: ShaperParams, pos: dict[int, float], now: float,
                 t_sender: float | None = None, frames: int = 1) -> None:
        """A valid frame (axis index -> finite value; sender time ``t_sender``, if any), the
        ``frames``-th the sender sent since the last one taken (its ``seq`` step).  ``pos`` is
        kept (up to five frames', :meth:`_weigh_grid`): the caller does not change it."""
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
            self._blend_s = p.startup_s if first else p.rejoin_s
            self._blend_offset = None
            self._blend_pending = True  # from the reference the next tick plays back
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
        tl = self._t_last
        if t_sender is None and not rejoin:
            frames = self._spanned(p, pos, frames)
        t, rejoin = self._timeline(p, now, t_sender, rejoin, frames)
        ring = self._grid_ring
        if self._grid_err is None or frames != 1:
            ring.clear()
        else:
            ring.append((self._grid_err, pos))
            if len(ring) == 5:  # windows of five frames, each frame in one
                self._weigh_grid(p)
                ring.clear()
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
            self._band.reset()
            n = self.n
            self._extra = [None] * n
            self._fix = [None] * n
        else:
            self._excess += JITTER_GAIN * (max(transit - fast, 0.0) - self._excess)
        if tl is not None and not rejoin and t > tl:
            self._track_span((t - tl) / frames, p.stale_after_s)
        if tl is None or t - tl >= p.min_dt_s or t < tl:
            self._t_last = t
        driven, live, hist = p.driven, self.live, self._hist
        min_dt = p.min_dt_s
        for i, v in pos.items():
            if not driven[i]:
                continue
            live[i] = v
            h = hist[i]
            if rejoin or not h or t < h[-1].t:  # start, rejoin, or a t that goes back
                h.clear()
                h.append(_knot(h, t, v))
            elif t - h[-1].t < min_dt:  # the same sample again: replace it
                h[-1] = _knot(_stencil(h, len(h) - 1), h[-1].t, v)
            else:
                h.append(_knot(_stencil(h, len(h)), t, v))
                if len(h) > 2 * HISTORY:  # (trimmed in batches: no shift per sample)
                    del h[:HISTORY]

    def _spanned(self, p: ShaperParams, pos: dict[int, float], frames: int) -> int:
        """A frame without ``t``, ``frames`` after the previous one (its seq step): how many of
        the sender's samples its step spans (``frames``, or more when the sender skipped some).
        Read from the motion itself, on the axis moving fastest: where its last two steps (per
        sample) agree within SKIP_TOLERANCE (a steady motion) and moved at least MIN_SKIP_STEP,
        or, at a reversal, where the last three changes of its step agree so and changed it by
        more than the values' noise, SKIP_NOISE (a steady acceleration: a recorded skip 2 ms
        past a trough, read as one step, put the compensated rails at their acceleration limit;
        the hexapod's 5 cm heave changes by 0.5 um a sample), a new step
        SKIP_TOLERANCE-close to what m > ``frames`` samples move along the last step and its
        change (a constant second difference: the steps of a slowing motion shrink, so m
        samples move less than m times the next step) spans m samples; a wrong count, where
        the motion is too slow or unsteady to tell, misplaces a sample by little.  Beside a
        crest two counts give the same step, one each side of it: the nearer, unless, read at a
        reversal, it is not ``frames`` while the step is off what ``frames`` move by more than
        the values' noise (a recorded skip of the slalom's trough sample read 0.33 for 2)."""
        q = self._period
        best, ratio, other, gap, noise, bent = 0.0, 1.0, 0.0, 0.0, 0.0, False
        for i, v in pos.items():
            h = self._hist[i]
            if not p.driven[i] or len(h) < 3 or q <= 0.0:
                continue
            k0, k1, k2 = h[-3], h[-2], h[-1]
            t0, v0, t1, v1, t2, v2 = k0.t, k0.v, k1.t, k1.v, k2.t, k2.v
            s0 = (v1 - v0) * q / (t1 - t0)  # steps per frame
            s1 = (v2 - v1) * q / (t2 - t1)
            curved, floor = False, 0.0
            score = abs(s1)
            steady = score >= MIN_SKIP_STEP and abs(s1 - s0) <= SKIP_TOLERANCE * score
            if not steady and len(h) >= 5:  # a reversal: its steps change steadily
                km, kn = h[-4], h[-5]
                sm = (v0 - km.v) * q / (t0 - km.t)
                c1, c0, cm = s1 - s0, s0 - sm, sm - (km.v - kn.v) * q / (km.t - kn.t)
                floor = max(SKIP_NOISE, 4.0 * _float32_ulp(v))
                steady = (abs(c1) >= floor and abs(c1 - c0) <= SKIP_TOLERANCE * abs(c1)
                          and abs(c0 - cm) <= SKIP_TOLERANCE * abs(c1))
                score = max(score, abs(c1))
                curved = steady
                # the changes' own spread: the values' noise as they show it
                floor = max(floor, 4.0 * max(abs(c1 - c0), abs(c0 - cm)))
            if steady and score > best:
                # the k-th step on is s1 + dd (k + e): m of them move a m^2 + b m
                dd = (s1 - s0) * 2.0 * q / (t2 - t0)  # change of the step per sample
                a = 0.5 * dd
                b = s1 + dd * (0.5 + (0.5 * (t2 - t1) - 0.5 * q) / q)
                dv = v - v2
                disc = b * b + 4.0 * a * dv
                den = b + math.copysign(math.sqrt(disc), b) if disc >= 0.0 else 0.0
                # both roots of a m^2 + b m = dv, the nearer by the stable form
                best, ratio = score, (2.0 * dv / den if den != 0.0 else 0.0)
                other = -0.5 * den / a if a != 0.0 and den != 0.0 else 0.0
                gap = dv - frames * (a * frames + b)
                noise, bent = floor, curved
        if best == 0.0 or abs(ratio - frames) <= SKIP_TOLERANCE:  # the usual case
            return frames
        if bent and not frames + 0.5 <= ratio <= MAX_SKIP and abs(gap) >= noise:
            # beside a crest (its steps' change steady: the curvature known) both roots can
            # count: dv is what m = frames would move only if the nearer says so; else the
            # farther, past the crest, may
            ratio = other
        if not frames + 0.5 <= ratio <= MAX_SKIP:
            return frames
        m = round(ratio)
        return m if abs(ratio - m) <= SKIP_TOLERANCE else frames

    def _timeline(self, p: ShaperParams, now: float, t_sender: float | None, rejoin: bool,
                  frames: int) -> tuple[float, bool]:
        """The sender instant of a frame (seconds from :attr:`_t_base` or on the loop's clock) and
        whether the timeline starts anew (module docstring, "sender time")."""
        q = self._period
        tl = self._t_last
        self._grid_err = None
        if t_sender is None and self._stamped and tl is not None and not rejoin and q > 0.0:
            self._line += frames * q  # a stamping sender's frame without t: on its grid
            if self._grid_t is not None:
                self._grid_t += frames * q
            return tl + frames * q, rejoin
        skipped = False
        grid_t, run = self._grid_t, self._grid_run
        self._grid_t, self._grid_run = None, 0  # kept only from one frame on the grid to the next
        if t_sender is None:  # timed by its arrival
            self._stamped = False
            x, gate, floor = now, 0.5 * p.stale_after_s, NO_T_ALPHA
            arrived = self.last_input_s
            news = arrived is None or now > arrived  # frames read in one tick: no timing news
        else:
            if not self._stamped:  # from the loop's clock to the sender's: a new timeline
                rejoin = True
                self._stamped = True
                self._grid_sums = [0.0, 0.0, 0.0, 0.0]
                self.at_stamps = True
            if self._t_base is None or rejoin:  # sender times relative to a whole second
                self._t_base = math.floor(t_sender) if math.isfinite(t_sender) else 0.0
            x, gate, floor = t_sender - self._t_base, TIME_GATE_S, TRACK_ALPHA
            news = True
            if q > 0.0 and self._line_n > 0 and not rejoin and tl is not None:
                ratio = (x - self._line) / q
                m = round(ratio) if frames < ratio <= MAX_SKIP else 0
                if m > frames and abs(x - self._line - m * q) <= TIME_GATE_S:
                    # on the grid, samples skipped: the sender's grid goes on, unless this
                    # keeps happening (then the sender changed its rate)
                    if self._learn_period((x - tl) / frames):
                        self._line, self._line_n = x, 1
                        return x, rejoin
                    frames, skipped = m, True
        if tl is None or rejoin or self._line_n == 0:
            self._line, self._line_n = x, 1
            return x, rejoin
        pred = self._line + frames * q
        err = x - pred
        if not news:
            self._line = pred
            return tl + frames * q, rejoin
        if abs(err) > gate:
            if t_sender is not None and p.min_dt_s <= x - tl <= p.stale_after_s:
                self._learn_period((x - tl) / frames)  # irregular: the stamps are right
            self._line = x  # off the line: anchored anew where the frame says
            if t_sender is None:  # and, timed by arrival, its slope learnt anew
                self._line_n = 1
            return x, rejoin
        n = self._line_n + 1
        run = run + 1 if t_sender is not None and abs(err) <= math.ulp(t_sender) \
            else 0  # stamps within their resolution of the line, in a row
        self._grid_run = run
        on_grid = run > GRID_MIN_FRAMES
        if on_grid:
            floor = GRID_TRACK_ALPHA
        alpha = max(2.0 * (2 * n - 1) / (n * (n + 1)), floor)
        beta = max(6.0 / (n * (n + 1)), floor * floor / 4)
        new_q = q + beta * err / frames
        if new_q <= 0.0 or (n > 2 and not 0.25 * q < new_q < 4.0 * q):  # another sender
            self._line, self._line_n = x, 1
            return x, rejoin
        self._line, self._line_n, self._period = pred + alpha * err, n, new_q
        if not skipped:
            self._odd.clear()
        if t_sender is None:
            return tl + frames * new_q, rejoin
        if not on_grid:
            return x, rejoin
        if not skipped:
            self._grid_err = err
        g = pred if grid_t is None else grid_t + frames * new_q
        g += GRID_FOLLOW * (pred - g)
        self._grid_t = g
        return (x if self.at_stamps else g), rejoin

    def _weigh_grid(self, p: ShaperParams) -> None:
        """Where a grid sender's values lie: at its stamps, or on the grid the stamps round
        (``t0 + k/rate`` in epoch seconds is a float64 0.24 us coarse: the stamp is the instant
        only to its resolution).  Five consecutive frames on the grid, each stamp ``d`` off it
        within its resolution: the middle value's residual from the cubic through the other
        four (uniform grid: exact on cubics, so the motion leaves ~nothing) is ``r ~ 0`` if the
        values lie on the grid, ``r ~ u = slope (d - the same cubic's d)`` if they lie at the
        stamps.  ``alpha = sum r u / sum u u`` (recent windows, GRID_GAIN) decides, once it lies
        GRID_SIGMAS standard errors beyond 1/2; until then the stamps are the instants."""
        ring = self._grid_ring
        (d0, p0), (d1, p1), (d2, p2), (d3, p3), (d4, p4) = ring[0], ring[1], ring[2], ring[3], \
            ring[4]
        big_d = d2 - (4.0 * (d1 + d3) - d0 - d4) / 6.0
        half_q = 0.5 / self._period
        ru = uu = rr = 0.0
        for i, v2 in p2.items():
            if not p.driven[i] or i not in p0 or i not in p1 or i not in p3 or i not in p4:
                continue
            v1, v3 = p1[i], p3[i]
            r = v2 - (4.0 * (v1 + v3) - p0[i] - p4[i]) / 6.0
            u = (v3 - v1) * half_q * big_d
            ru += r * u
            uu += u * u
            rr += r * r
        sums = self._grid_sums
        keep = 1.0 - GRID_GAIN
        sums[0] = keep * sums[0] + ru
        sums[1] = keep * sums[1] + uu
        sums[2] = keep * sums[2] + rr
        sums[3] = keep * sums[3] + 1.0
        s_ru, s_uu, s_rr, s_n = sums[0], sums[1], sums[2], sums[3]
        if not s_uu > 0.0 or s_n < GRID_MIN_WEIGHT:
            return
        a = s_ru / s_uu
        se = math.sqrt(max(s_rr - a * s_ru, 0.0) / (s_n * s_uu))
        if self.at_stamps and a + GRID_SIGMAS * se < 0.5:
            self.at_stamps = False
        elif not self.at_stamps and a - GRID_SIGMAS * se > 0.5:
            self.at_stamps = True

    def _track_span(self, dt: float, stale_after_s: float) -> None:
        """The longest recent interval between samples (per seq step): the playback must stay
        that far behind the newest sample to interpolate an irregular stream (a variable-step
        solver's steps, a sender that computes each sample when it wakes up).  A new longest
        one is taken at once, and the span decays to the period by :data:`SPAN_DECAY` a
        sample; a stall (longer than :data:`SPAN_MAX_PERIODS` periods, or half the stale
        time) is not sampling and is left to the extrapolation."""
        q = self._period
        if q <= 0.0 or dt > SPAN_MAX_PERIODS * q or dt > 0.5 * stale_after_s:
            return
        span = self._span
        self._span = dt if dt > span else span + SPAN_DECAY * (max(q, dt) - span)

    def _learn_period(self, dt: float) -> bool:
        """One interval between frames (per frame): averaged when within half to 1.5 times the
        period; :data:`PERIOD_RELEARN` unusual ones in a row (the sender changed its rate)
        replace the period by their median (then True is returned, and the line's slope is
        learnt anew); a single one (a stall) changes nothing."""
        q = self._period
        if q == 0.0:
            if dt > 0.0:
                self._period = dt
            return False
        if 0.5 * q <= dt <= 1.5 * q:
            self._period = q + PERIOD_GAIN * (dt - q)
            self._odd.clear()
            return False
        self._odd.append(dt)
        if len(self._odd) >= PERIOD_RELEARN:
            self._period = sorted(self._odd)[len(self._odd) // 2]
            self._odd.clear()
            self._line_n = 1  # the line's slope is learnt anew
            return True
        return False

    def park(self, p: ShaperParams, now: float) -> None:
        """Stop requested: ramp to neutral, ignoring input from now on."""
        if self.parking:
            return
        self.parking = True
        self._blend_offset = None
        self._blend_pending = False
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
                self._blend_pending = False
            if now - self._stale_since < p.hold_s:
                return self.ref, mode
            if self._move is None:
                self._move = _Move(now, self.ref, [0.0] * self.n, p.ramp_speed)
            ref, _ = self._move.at(now)
        else:
            ref = self._live_now(p, now)
            mode = ""
            if self._blend_pending:  # the blend starts where the reference is
                self._blend_pending = False
                self._blend_t0 = now
                self._blend_offset = [r - v for r, v in zip(self.ref, ref, strict=True)]
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
            self._band.reset()
            return self.live[:]
        at = self._at
        dt = 0.0 if at is None else max(now - at, 0.0)
        self._at = now
        blend_s = max(GAP_BLEND_S, GAP_BLEND_PERIODS * q)
        phi = self._fade_step(dt, blend_s)
        span = max(self._span, q)
        target = fast + min(span + JITTER_FACTOR * self._excess, span + 0.5 * p.stale_after_s)
        d = self._delay
        if d is None:
            d, self._delay_rate, self._delay_acc = target, 0.0, 0.0
        elif dt > 0.0:
            w = 1.0 / DELAY_TAU_S  # a critically damped triple pole:
            r, a = self._delay_rate, self._delay_acc  # x3 = w^3 (target - x) - 3 w^2 x1 - 3 w x2
            for _ in range(1 if dt <= 0.002 else int(dt / 0.002) + 1):
                dts = min(dt, 0.002)
                a += dts * (w * w * w * (target - d) - 3.0 * w * w * r - 3.0 * w * a)
                r += dts * a
                d += dts * r
                dt -= dts
            self._delay_rate, self._delay_acc = r, a
        self._delay = d
        self._lead_s = p.lead_s
        tau = now - d + p.lead_s
        bound = max(p.max_extrapolation_s, 1.5 * q) + p.lead_s
        out = []
        extra = self._extra
        for i, h in enumerate(self._hist):
            if not h:
                out.append(self.live[i])
                continue
            prev = extra[i]
            if tau <= h[-1].t or len(h) == 1:
                x, xs = _quintic(h, tau) if len(h) > 1 else (h[0].v, 0.0)
                src = None
            else:  # beyond the newest sample: its Taylor cubic goes on
                src = h[-1]
                x, xs = _extrapolate(src, tau, bound)
            fix = self._fix[i]
            if fix is not None:  # the correction fades on its own schedule
                f, f1, f2 = fix
                fix[0] = phi[0] * f + phi[1] * f1 + phi[2] * f2
                fix[1] = phi[3] * f + phi[4] * f1 + phi[5] * f2
                fix[2] = phi[6] * f + phi[7] * f1 + phi[8] * f2
                if abs(fix[0]) < FIX_FLOOR and abs(fix[1]) * blend_s < FIX_FLOOR:
                    self._fix[i] = fix = None
            if prev is not None and (src is None or src.t != prev.t):
                xo, so = _extrapolate(prev, tau, bound)  # the samples changed under it
                if fix is None:
                    self._fix[i] = fix = [0.0, 0.0, 0.0]
                fix[0] += xo - x  # continuous in position and velocity, added to what fades
                fix[1] += so - xs
            extra[i] = src
            out.append(x if fix is None else x + fix[0])
        length = q / p.tick_s
        if abs(length - self._ma_len) > MA_HYSTERESIS * max(self._ma_len, 1.0):
            self._ma_len = length  # only a real change of the input's rate moves it
        out = self._average(out, p.tick_s, self._ma_len)
        if not p.band:
            return out
        return self._band.step(p.band, out)

    def _average(self, x: list[float], tick_s: float, length: float) -> list[float]:
        """Moving average of each axis over the last ``length`` ticks (fractional: the oldest
        tick weighs what is left), i.e. one input period: zero gain at the input's rate and its
        harmonics, where the playback's roughness lies."""
        if length < MA_MIN_TICKS:
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

    def _fade_step(self, dt: float, blend_s: float) -> tuple[float, ...]:
        """The transition over ``dt`` of a correction's (value, rate, acceleration): a triple
        pole at ``-w``, ``w = FIX_POLE_FACTOR / blend_s`` (critically damped, settled in about
        ``blend_s``).  A new difference adds to the value and rate, so the reference stays
        continuous to its acceleration, and each fades on its own schedule however often they
        come (every sample, with a lead): ``exp(A dt) = exp(-w dt) (I + N dt + N^2 dt^2 / 2)``,
        ``N = A + w I`` nilpotent."""
        key = (dt, blend_s)
        if self._fix_step[:2] == key:
            return self._fix_step[2]
        w = FIX_POLE_FACTOR / blend_s
        e = math.exp(-w * dt)
        h, h2 = dt, 0.5 * dt * dt
        # N = [[w, 1, 0], [0, w, 1], [-w^3, -3w^2, -2w]] (row-major), N^2 by its sums
        n = [w, 1.0, 0.0, 0.0, w, 1.0, -w ** 3, -3.0 * w * w, -2.0 * w]
        phi: list[float] = []
        for r in range(3):
            for c in range(3):
                n2 = 0.0
                for k in range(3):
                    n2 += n[3 * r + k] * n[3 * k + c]
                phi.append(e * ((1.0 if r == c else 0.0) + n[3 * r + c] * h + n2 * h2))
        out = tuple(phi)
        self._fix_step = (dt, blend_s, out)
        return out

    def stale_time(self, now: float) -> float:
        """Seconds since the last valid frame (0 while live)."""
        if self._stale_since is None:
            return 0.0
        last = self.last_input_s if self.last_input_s is not None else self.started_s
        return now - (last or now)



def _float32_ulp(v: float) -> float:
    """The ulp of ``v`` as a float32 where ``v`` is one (a sender's float32 value), else 0."""
    m, e = math.frexp(v)
    m24 = m * 16777216.0
    return math.ldexp(1.0, e - 24) if m24 == math.floor(m24) and v != 0.0 else 0.0


def _stencil(h: list[Knot], end: int) -> list[Knot]:
    """The (up to) three samples before ``h[end]`` (or before a new one at ``end``) that its
    knot is computed from: each at least :data:`STENCIL_S` before the next, going back, so that
    the derivatives of a fast sender's samples are taken over a few ms rather than one period:
    the noise of its values (float32, rounded stamps: 0.1 um) reaches the slope, acceleration
    and jerk divided by the baseline, its cube for the jerk (docs/WIRE.md)."""
    out: list[Knot] = []
    if end == 0:
        return out
    newest = end >= len(h)  # a new sample: the one before it is taken whatever its time
    t_next = 0.0 if newest else h[end].t
    j = end - 1
    while j >= 0 and len(out) < 3:
        if newest or t_next - h[j].t >= STENCIL_S or j == 0:
            out.append(h[j])
            t_next = h[j].t
            newest = False
        j -= 1
    out.reverse()
    return out


def _knot(before: list[Knot], t: float, v: float) -> Knot:
    """The sample ``(t, v)`` with the slope, acceleration and jerk at ``t`` of the polynomial
    through it and the (up to) three samples ``before`` it (a cubic, exact on cubics): causal,
    so never revised when the next sample comes."""
    if len(before) >= 3:  # the usual case, written out: Newton's divided differences
        k1, k2, k3 = before[-1], before[-2], before[-3]
        t1, v1, t2, v2, t3, v3 = k1.t, k1.v, k2.t, k2.v, k3.t, k3.v
        f01 = (v - v1) / (t - t1)
        f12 = (v1 - v2) / (t1 - t2)
        f23 = (v2 - v3) / (t2 - t3)
        f012 = (f01 - f12) / (t - t2)
        f123 = (f12 - f23) / (t1 - t3)
        f0123 = (f012 - f123) / (t - t3)
        d1 = t - t1
        d2 = t - t2
        return Knot(t, v, f01 + f012 * d1 + f0123 * d1 * d2,
                    2.0 * f012 + 2.0 * f0123 * (d1 + d2), 6.0 * f0123)
    ts = [t]
    f = [v]  # Newton divided differences about the newest: f[0], f[0,1], f[0,1,2], f[0..3]
    col = [v]
    for k in range(len(before) - 1, -1, -1):
        tk = before[k].t
        new = [before[k].v]
        for j in range(len(col)):
            new.append((col[j] - new[j]) / (ts[-1 - j] - tk))
        ts.append(tk)
        col = new
        f.append(col[-1])
    f += [0.0] * (4 - len(f))
    d1 = t - ts[1] if len(ts) > 1 else 0.0
    d2 = t - ts[2] if len(ts) > 2 else 0.0
    return Knot(t, v, f[1] + f[2] * d1 + f[3] * d1 * d2, 2.0 * f[2] + 2.0 * f[3] * (d1 + d2),
                6.0 * f[3])


def _quintic(h: list[Knot], tau: float) -> tuple[float, float]:
    """Value and slope at ``tau`` of the quintic Hermite between the two samples of ``h`` (at
    least 2, time-ordered) around it (``tau`` clamped to their span), which meets each with its
    value, slope and acceleration (:func:`_knot`): continuous to the acceleration."""
    n = len(h)
    j = n - 2
    while j > 0 and tau < h[j].t:
        j -= 1
    k0, k1 = h[j], h[j + 1]
    t0, v0, m0, a0 = k0.t, k0.v, k0.m, k0.a
    t1, v1, m1, a1 = k1.t, k1.v, k1.m, k1.a
    span = t1 - t0
    x = min(max((tau - t0) / span, 0.0), 1.0)
    m0 *= span
    m1 *= span
    a0 *= span * span
    a1 *= span * span
    x2 = x * x
    x3 = x2 * x
    y = 1.0 - x
    s = min_jerk(x)  # H3, and H0 = 1 - s
    value = (v0 + (v1 - v0) * s + m0 * x * (1.0 - x2 * (6.0 - 8.0 * x + 3.0 * x2))
             + 0.5 * a0 * x2 * y ** 3 + x3 * (m1 * (-4.0 + 7.0 * x - 3.0 * x2)
                                              + 0.5 * a1 * (1.0 - 2.0 * x + x2)))
    ds = min_jerk_rate(x)
    slope = ((v1 - v0) * ds + m0 * (1.0 - x2 * (18.0 - 32.0 * x + 15.0 * x2))
             + 0.5 * a0 * x * y * y * (2.0 - 5.0 * x)
             + m1 * x2 * (-12.0 + 28.0 * x - 15.0 * x2)
             + 0.5 * a1 * x2 * (3.0 - 8.0 * x + 5.0 * x2)) / span
    return value, slope


def _extrapolate(src: Knot, tau: float, bound: float) -> tuple[float, float]:
    """Value and slope at ``tau`` of the cubic that leaves the sample ``src`` with its value,
    slope, acceleration and jerk; beyond ``bound`` after it, the jerk stops and the parabola
    with the value, slope and acceleration reached there goes on (continuous to the
    acceleration: stopping there would be a step of velocity, which the compensator turns into
    its limits; the stale-input rule ends a longer gap)."""
    t_n, v, s, a, j = src.t, src.v, src.m, src.a, src.j
    el = tau - t_n
    e = min(el, bound)
    value = v + e * (s + e * (0.5 * a + e * j / 6.0))
    slope = s + e * (a + 0.5 * j * e)
    if el <= bound:
        return value, slope
    acc = a + j * bound
    r = el - bound
    return value + r * (slope + 0.5 * acc * r), slope + acc * r
