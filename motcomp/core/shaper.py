"""From the stream of valid input frames to the compensator's reference, per axis.

Modes (all times from the loop's clock, passed in)::

    start        reference at neutral (0) until the first valid frame
    first frame  blend from neutral to the live input over ``startup_s``           "rejoin"
    live         the input reconstructed (below)
    no valid frame for stale_after_s
                 hold the reference for ``hold_s``, then move each axis to neutral  "stale"
                 in a minimum-jerk ramp whose peak speed is ``ramp_speed`` and peak
                 acceleration ``blend_acc`` (per axis, the shorter within both);
                 the command's own path to rest is the tick's rule
                 (:mod:`motcomp.core.tick`, "Input loss")
    frames again blend from the held/ramped reference to the live input over
                 ``rejoin_s``                                                       "rejoin"
    park         (stop requested) ramp every axis to neutral as above, ignoring
                 input; :attr:`ReferenceShaper.parked` once there                  "parking"
    always       the reference lies within ``[reach_lo, reach_hi]`` per axis (the range of
                 accepted input); a non-finite value keeps the previous reference

Ramps are minimum-jerk (:mod:`motcomp.core.minjerk`).  A blend (:mod:`motcomp.core.blend`)
adds to the live input the difference of the held reference (or the ramp it interrupts) to it,
in position, velocity, acceleration and jerk, faded out to zero in all four: the reference
leaves the held path and meets the live one with no step in any of them (the compensator turns
a jerk step into a step of its command's acceleration).  It starts once the live input is what
the reference will follow: the playback past its second sample, the instants of a sender
without ``t`` estimated over :data:`UNSTAMPED_SETTLE_S` of its frames (or played for
:data:`UNSTAMPED_WAIT_S`), the moving average full and the band limit
:data:`BAND_SETTLE_DELAYS` of its delays past its seeding (seeded at rest, it follows a moving
input only after a transient), and :data:`FIT_S` more for the live input's motion (a
least-squares cubic), until a window of :data:`FIT_S` the cubic explains to within
:data:`FIT_TOL` (a bend of the live input inside the window is not its motion; after
:data:`FIT_WAIT_S` the blend carries the live velocity only); the held reference stays until
then.  It lasts ``startup_s``/``rejoin_s``, or longer per axis where its gap and velocity change
need more than a quarter of the axis' acceleration limit (``blend_acc``: the compensator
multiplies the reference's acceleration by its in-band gain), or its gap, velocity and
acceleration changes more than its jerk budget (``blend_jerk``: ``blend_acc`` over the model's
lag, which the compensator multiplies the jerk by); the jerk difference fades out over
:data:`JERK_CARRY_S` at most.  Undriven axes stay at neutral.

Input reconstruction ``smooth`` (the default): the input *played back on the sender's timeline, a
little behind its newest sample*, interpolated between samples already received.  Three parts,
each with its own contract and tests:

    :mod:`motcomp.core.timeline`   each sample's instant: from ``t``, or from ``seq`` and the
                                   arrivals (skips counted from the motion), a grid sender's
                                   rounding read as the values show
    :mod:`motcomp.core.playback`   how far behind to play: the smallest transit plus
                                   ``max(playback_lag_s, the samples' spacing)``, reached
                                   through a fifth-order pole that settles in a second
    :mod:`motcomp.core.interp`     each axis' curve: quintic Hermite between samples, the
                                   newest sample's cubic beyond it (for ``max_extrapolation_s``
                                   or 1.5 input periods, then its parabola), a correction faded
                                   out when a sample lands under an extrapolation

then, for an input period of :data:`MA_MIN_TICKS` ticks or more, a moving average over one input
period (zero gain at the input's rate and its harmonics), then each axis' band limit
(:mod:`motcomp.core.bandlimit`).  The lag (:attr:`ReferenceShaper.lag_s`) is what the
reconstruction costs beyond the smallest transit: the playback lag, plus half a period of
averaging below 500 Hz, less the lead.  ``lead_s`` plays ahead along the newest sample's cubic.

``linear``: each axis extrapolated along the line through its last two frames on the sender's
timeline to the tick (no lag, no band limit: every irregularity becomes a step).  ``hold``: the
last value (for tests of the rest of the chain).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from mypy_extensions import mypyc_attr

from motcomp.core.bandlimit import BandLimit, BandLimitParams
from motcomp.core.blend import (
    blend_coefficients,
    blend_duration,
    horner,
    jerk_duration,
    local_cubic,
)
from motcomp.core.interp import Curve, Transition
from motcomp.core.minjerk import (
    min_jerk_derivatives,
    min_jerk_weight,
    move_duration,
)
from motcomp.core.native import frozen_reduce
from motcomp.core.playback import Playback, min_transit
from motcomp.core.timeline import Timeline

__all__ = ["LINEAR_OFFSET_LEAK", "ReferenceShaper", "ShaperParams"]

LINEAR_OFFSET_LEAK = 0.05
"""``linear``: upward drift (s per s) allowed to its clock offset (smallest transit)."""
LANDED_SLACK_S = 1e-6
"""A sample whose landing at the smallest transit is this close after a deadline had landed
by it (rounding of the two clocks' arithmetic)."""
MA_MIN_TICKS = 2.0
"""No moving average for an input period shorter than this many ticks."""
MA_HYSTERESIS = 0.02
"""The moving average's length follows the period only when it moved by more than this
fraction (a length that flickers would warp time)."""
BAND_SETTLE_DELAYS = 4.0
"""A blend starts once the band limit has run this many of its delays since it was seeded at
rest: before, its output lags a moving input by a transient (5.5 mm at 0.78 m/s through 48 Hz)
that a blend would take for part of the gap and its motion for the input's."""
UNSTAMPED_SETTLE_S = 0.3
"""... and, for a sender without ``t``, once its instants' line spans this long: from fewer
arrivals the estimated period is off by up to a few % on a starved host, and the blend merged a
motion played that much too fast or slow (the limiter acting for a second, the blend stretched
to 3.6 s, recorded on one core; docs/WIRE.md "Without t") ..."""
UNSTAMPED_WAIT_S = 1.0
"""... or once it has played this long (a line anchored anew again and again, by arrivals
bunched beyond the 25 ms gate, never spans it)."""
FIT_S = 0.02
"""... and once the live input has run this long more: its velocity, acceleration and jerk at
the blend's start are those of the least-squares cubic through the last ticks this long ..."""
FIT_TOL = 3e-7
"""... which the cubic must explain to within this (m or rad, every tick of every axis): a
window that holds a bend of the live input (a transient of its reconstruction) gives a cubic
whose acceleration and jerk at its end are not the input's (3 m/s^2 and 373 m/s^3 were read
on one core, 20 um off the ticks, and the blend carried them into a 2.3 m excursion of the
rails, the input within +-0.4 m; at 0.7 um still -0.46 m/s^2 and -42 m/s^3), so the blend
waits for a window that is a cubic (the slalom's read 0.002-0.08 um, the band limit's seeding
fading; that start, 7 ms later: -0.16 m/s^2 and 0.2 m/s^3) ..."""
FIT_WAIT_S = 0.25
"""... for at most this long after the first full window; then it carries the live input's
velocity only (its acceleration and jerk taken as the held path's: the reference's own step
to the live ones at the start, no estimate carried over the blend)."""
JERK_CARRY_S = 0.5
"""A blend carries the jerk difference over this long at most (its gap, velocity and
acceleration over the whole blend): a jerk estimated from a few tens of milliseconds is the
least certain figure (some m/s^3 from 0.1 um off a cubic), and carried over a blend of
seconds, within its acceleration budget, it swings the reference as ``j T^3`` (0.37 m from
42 m/s^3 over 1.9 s); over 0.5 s, at its clip, it moves it by 0.069 ``blend_acc`` x 0.5^2 at
most (2.6 cm on the rails), and the reference's jerk still changes without a step."""
GAP_BLEND_PERIODS = 10.0
GAP_BLEND_S = 0.2
"""After an extrapolation, the difference to the samples fades out over about this many input
periods (at least ``GAP_BLEND_S``)."""


@dataclass(frozen=True)
class ShaperParams:
    """The shaper's settings, per axis where a tuple (in :data:`~motcomp.core.axes.AXES` order)."""

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return frozen_reduce(self)

    driven: tuple[bool, ...]
    ramp_speed: tuple[float, ...]
    """Peak speed of the ramps to neutral (axis units/s); their peak acceleration is
    ``blend_acc``'s."""
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
    """``smooth``: play back this far ahead (s) along the newest sample's cubic."""
    playback_lag_s: float = 0.0017
    """``smooth``: the least lag behind the smallest transit (s): what the design cancels."""
    tick_s: float = 1e-3
    """The loop's period (the moving average of ``smooth`` counts ticks)."""
    min_dt_s: float = 1e-5
    """Two samples of an axis closer than this on the sender's timeline are one sample."""
    band: tuple[BandLimitParams | None, ...] = ()
    """``smooth``: each axis' reference band limit (None, or an empty tuple: none)."""
    blend_acc: tuple[float, ...] = ()
    """Per axis, the acceleration a start-up or rejoin blend, or a ramp to neutral, may take
    (axis units/s^2): a blend lasts ``startup_s``/``rejoin_s`` or longer, as its gap and
    velocity change need (empty: no bound)."""
    blend_jerk: tuple[float, ...] = ()
    """Per axis, the jerk a start-up or rejoin blend may take (axis units/s^3): a blend lasts
    longer where its gap, velocity and acceleration changes would need more (empty, or 0: no
    bound)."""
    home_lo: tuple[float, ...] = ()
    home_hi: tuple[float, ...] = ()
    """Per axis, the position limits (empty: none): a ramp to neutral starts from the
    reference brought within them, where the command is (docs/DEPLOYMENT.md, "What happens
    when the input stops")."""

    def __post_init__(self) -> None:
        if not self.min_dt_s > 0:
            raise ValueError(f"min_dt_s must be > 0 s, got {self.min_dt_s!r}")
        if not 0.0 <= self.lead_s <= 0.1:
            raise ValueError(f"lead_s must be within [0, 0.1] s, got {self.lead_s!r}")
        if not 0.0 <= self.playback_lag_s <= 0.1:
            raise ValueError(f"playback_lag_s must be within [0, 0.1] s, got "
                             f"{self.playback_lag_s!r}")
        if len(self.home_lo) != len(self.home_hi):
            raise ValueError(f"home_lo and home_hi must have one value per axis each, got "
                             f"{len(self.home_lo)} and {len(self.home_hi)}")
        if self.reconstruction not in ("linear", "smooth", "hold"):
            raise ValueError(f"reconstruction must be linear, smooth or hold, got "
                             f"{self.reconstruction!r}")


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class _Move:
    """Minimum-jerk moves from ``start`` to ``end`` per axis, each with its own duration: the
    shortest (at least ``min_s``) whose peak speed is at most ``speed`` and, where ``acc`` gives
    one, whose peak acceleration is at most ``acc``."""

    def __init__(self, t0: float, start: Sequence[float], end: Sequence[float],
                 speed: Sequence[float], acc: Sequence[float] = (),
                 min_s: float = 0.05) -> None:
        self.t0 = t0
        self.start = list(start)
        self.end = list(end)
        self.duration: list[float] = []
        for i, (s, e, v) in enumerate(zip(start, end, speed, strict=True)):
            self.duration.append(move_duration(e - s, v, acc[i] if i < len(acc) else 0.0,
                                               min_s))

    def derivatives(self, t: float) -> list[tuple[float, float, float]]:
        """Each axis' velocity, acceleration and jerk at ``t``."""
        out = []
        for s, e, d in zip(self.start, self.end, self.duration, strict=True):
            x = (t - self.t0) / d
            if 0.0 < x < 1.0:
                v, a, j = min_jerk_derivatives(x)
                out.append(((e - s) * v / d, (e - s) * a / (d * d), (e - s) * j / (d * d * d)))
            else:
                out.append((0.0, 0.0, 0.0))
        return out

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
        self.timeline = Timeline(n)
        self.playback = Playback()
        self.curves = [Curve() for _ in range(n)]
        self.played = [0.0] * n
        """``smooth``: the input at the instant played back this tick, before the moving
        average and the band limit (:attr:`played_lag_s` behind the tick on the loop clock)."""
        self._lead_s = 0.0  # the lead in force (ShaperParams.lead_s)
        self._playing = False  # the playback has passed the second sample since a restart
        self._at: float | None = None  # loop time of the last reference
        self._fix_step = Transition()  # the correction's fade over one tick
        self._rings: list[deque[float]] = [deque() for _ in range(n)]  # moving average
        self._ma_len = 0.0  # its length (ticks)
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
        self._blend_each: list[float] = []  # each axis' blend duration
        self._blend_poly: list[list[float]] | None = None  # each axis' difference faded out
        self._blend_jerk: list[list[float]] = []  # and its jerk's, over JERK_CARRY_S at most
        self._blend_jerk_s: list[float] = []
        self._blend_move: _Move | None = None  # the ramp to neutral a rejoin interrupts
        self._blend_pending = False
        self._run_s = 0.0  # smooth: time the moving average and band limit ran since a reset
        self._live_hist: list[tuple[float, list[float]]] = []  # the live input since settled
        self._fit_full_at: float | None = None  # when that window first spanned FIT_S
        self._fit_trusted = True  # the cubic explains the window (FIT_TOL)
        self._live_fit: list[tuple[float, float, float]] | None = None  # its derivatives now
        self._stale_since: float | None = None
        self._move: _Move | None = None
        self.parking = False
        self.parked = False
        self.stale_total_s = 0.0
        """Time the input was stale, and how many times (the wait for a first frame aside)."""
        self.stale_episodes = 0

    @property
    def period_s(self) -> float:
        """``smooth``: the input's period as learnt (0 before two frames)."""
        return self.timeline.period

    @property
    def playback_delay_s(self) -> float | None:
        """``smooth``: loop time minus the sender instant played back (None before it starts)."""
        return self.playback.delay

    @property
    def played_lag_s(self) -> float:
        """``smooth``: how far :attr:`played` lies behind the tick on the loop clock, the
        smallest transit excluded: the playback delay less the offset and the lead."""
        pb = self.playback
        if pb.delay is None or pb.offset is None:
            return 0.0
        return pb.delay - pb.offset - self._lead_s

    @property
    def blend_s(self) -> float:
        """The blend in progress (or pending): its longest axis' duration (s)."""
        return max(self._blend_each) if self._blend_poly is not None and self._blend_each \
            else self._blend_s

    @property
    def lag_s(self) -> float:
        """``smooth``: what the reconstruction adds to the delay beyond the smallest transit
        (s): the playback lag, plus the moving average's delay, less the lead (negative when the
        lead exceeds the lag); the band limit's delay is shown apart."""
        if self.playback.delay is None:
            return 0.0
        return self.played_lag_s + self._ma_delay_s

    # --- events ---------------------------------------------------------------------------
    def is_stale(self, p: ShaperParams, now: float) -> bool:
        """No valid input for ``stale_after_s`` (or none yet, after start-up)."""
        last = self.last_input_s if self.last_input_s is not None else self.started_s
        return last is not None and now - last > p.stale_after_s

    def on_input(self, p: ShaperParams, pos: dict[int, float], now: float,
                 t_sender: float | None = None, frames: int = 1,
                 arrived: float | None = None) -> None:
        """A valid frame (axis index -> finite value; sender time ``t_sender``, if any), the
        ``frames``-th the sender sent since the last one taken (its ``seq`` step), taken at the
        loop instant ``arrived`` (default ``now``; never before it landed).  ``pos`` is kept
        (up to five frames'): the caller does not change it."""
        if self.parking:
            return
        first = self.last_input_s is None
        rejoin = first or self._stale_since is not None
        if p.reconstruction == "linear":
            self._on_input_linear(p, pos, now, t_sender, rejoin)
        else:
            self._on_input_smooth(p, pos, now if arrived is None else arrived, t_sender,
                                  rejoin, max(frames, 1))
        if rejoin:
            if self._stale_since is not None and not first:  # not the wait for a first frame
                self.stale_total_s += now - self._stale_since
            self._stale_since = None
            self._blend_move, self._move = self._move, None
            self._blend_s = p.startup_s if first else p.rejoin_s
            self._blend_poly = None
            self._blend_pending = True  # from the reference the next tick plays back
        self.last_input_s = now

    def landing_known(self, t_sender: float | None) -> bool:
        """Whether when a sample landed can be bounded from its ``t``: a stamped sample on a
        stamped timeline whose smallest transit is known."""
        return t_sender is not None and self.playback.offset is not None \
            and self.timeline.stamped

    def landed_by(self, t_sender: float | None, now: float) -> bool:
        """Whether a stamped sample at ``t_sender`` had landed by the loop instant ``now`` at
        the smallest transit seen (where :meth:`landing_known` is not: yes): which of the frames
        a tick after a stall takes is due at each deadline it missed."""
        if not self.landing_known(t_sender):
            return True
        off = self.playback.offset
        assert t_sender is not None and off is not None  # (landing_known)
        return t_sender - self.timeline.base() + off <= now + LANDED_SLACK_S

    def next_t_bound(self, p: ShaperParams, now: float, arrived: float
                     ) -> tuple[float, float] | None:
        """``(lo, hi)``: the sender instants (s, as ``t``) a live stamped frame taken at the
        loop instant ``arrived`` may carry: not before the newest sample (less ``min_dt_s``, the
        same sample again), and not after ``arrived`` on the sender's clock (the loop's, less
        the smallest transit: no sample lands before it is computed) by more than
        ``stale_after_s`` -- once that transit is read over a completed bin of arrivals since
        the timeline (re)started (:meth:`Playback.settled`; ``hi`` infinite before).  None:
        any, the input is not live at ``now`` or not stamped."""
        tl = self.timeline
        pb = self.playback
        off = pb.offset
        if tl.t_last is None or off is None or not tl.stamped or self.is_stale(p, now):
            return None
        base = tl.base()
        lo = tl.t_last + base - p.min_dt_s
        if not pb.settled():
            return lo, math.inf
        return lo, arrived - off + base + p.stale_after_s

    def _on_input_linear(self, p: ShaperParams, pos: dict[int, float], now: float,
                         t_sender: float | None, rejoin: bool) -> None:
        t = now if t_sender is None else t_sender
        transit = now - t
        off = self._lin_offset
        if off is None or rejoin:
            self._lin_offset = transit
        else:  # leak upwards so a drifting clock is followed
            self._lin_offset = min_transit(off, self._lin_offset_at, transit, now,
                                           LINEAR_OFFSET_LEAK)
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

    def _on_input_smooth(self, p: ShaperParams, pos: dict[int, float], arrived: float,
                         t_sender: float | None, rejoin: bool, frames: int) -> None:
        tl = self.timeline
        t_prev = tl.t_last
        t, samples, rejoin = tl.place(t_sender, frames, arrived, pos, self.curves, rejoin,
                                      p.driven, p.min_dt_s, p.stale_after_s)
        pb = self.playback
        if rejoin:
            pb.restart()
            self._playing = False
            for r in self._rings:
                r.clear()
            self._band.reset()
            self._run_s = 0.0
            self._at = None  # the reconstruction's clock restarts with it (not from before)
            for c in self.curves:
                c.clear()
        interval = (t - t_prev) / samples if t_prev is not None and not rejoin \
            and t > t_prev else 0.0
        pb.on_sample(t, arrived, interval, tl.period, tl.stamped)
        driven, live, curves = p.driven, self.live, self.curves
        min_dt = p.min_dt_s
        t_res = math.ulp(t_sender) if t_sender is not None else 0.0
        for i, v in pos.items():
            if driven[i]:
                live[i] = v
                curves[i].add(t, v, min_dt, t_res)

    def park(self, p: ShaperParams, now: float) -> None:
        """Stop requested: ramp to neutral, ignoring input from now on."""
        if self.parking:
            return
        self.parking = True
        self._blend_poly = self._blend_move = None
        self._blend_pending = False
        self._move = self._home(p, now)

    def _home(self, p: ShaperParams, now: float) -> _Move:
        """The ramp to neutral from ``now``, from the reference within ``home_lo``-``home_hi``."""
        start = self.ref[:]
        for i, (lo, hi) in enumerate(zip(p.home_lo, p.home_hi, strict=True)):
            start[i] = min(max(start[i], lo), hi)
        return _Move(now, start, [0.0] * self.n, p.ramp_speed, p.blend_acc)

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
                if self.last_input_s is not None:  # not the wait for a first frame
                    self.stale_episodes += 1
                self._blend_poly = self._blend_move = None
                self._blend_pending = False
            if now - self._stale_since < p.hold_s:
                return self.ref, mode
            if self._move is None:
                self._move = self._home(p, now)
            ref, _ = self._move.at(now)
        else:
            ref = self._live_now(p, now)
            mode = ""
            if self._blend_pending and p.reconstruction == "smooth" and self._blend_s > 0.0 \
                    and not self._live_known(p, now, ref):  # the blend waits (module docstring)
                ref = (self._blend_move.at(now)[0] if self._blend_move is not None
                       else self.ref[:])
                mode = "rejoin"
            elif self._blend_pending:  # the blend starts where the reference is
                self._blend_pending = False
                self._blend_start(p, ref, now)
            if self._blend_poly is not None:
                done = True
                el = now - self._blend_t0
                for i, (d, c) in enumerate(zip(self._blend_each, self._blend_poly,
                                               strict=True)):
                    if el < d:
                        done = False
                        ref[i] += horner(c, el / d)
                        dj = self._blend_jerk_s[i]
                        if el < dj:
                            ref[i] += horner(self._blend_jerk[i], el / dj)
                if done:
                    self._blend_poly = None
                else:
                    mode = "rejoin"
        prev = self.ref
        for i, (x, lo, hi) in enumerate(zip(ref, p.reach_lo, p.reach_hi, strict=True)):
            if not lo <= x <= hi:  # beyond the reach, or not a number
                ref[i] = lo if x < lo else hi if x > hi else prev[i]
        self.ref = ref
        return ref, mode

    def _live_known(self, p: ShaperParams, now: float, live: list[float]) -> bool:
        """``smooth``: whether the live input has run long enough for a blend to start (module
        docstring, :data:`FIT_S` to :data:`FIT_WAIT_S`); keeps its values over the last
        ``FIT_S`` from the moment it settled."""
        hist = self._live_hist
        if not self._playing or (self.timeline.span() < UNSTAMPED_SETTLE_S
                                 and self._run_s < UNSTAMPED_WAIT_S):
            self._fit_reset()
            return False
        band_s = max((b.delay_s for b in p.band if b is not None), default=0.0)
        ma_s = self._ma_len * p.tick_s if self._ma_len >= MA_MIN_TICKS else 0.0
        if self._run_s < BAND_SETTLE_DELAYS * band_s + ma_s:
            self._fit_reset()
            return False
        self._live_fit = None
        hist.append((now, live[:]))
        while not self._fit_trusted and len(hist) > 4 and now - hist[1][0] >= FIT_S:
            del hist[0]  # waiting for a window the cubic explains: it slides
        if len(hist) < 4 or now - hist[0][0] < FIT_S:
            return False
        if self._fit_full_at is None:
            self._fit_full_at = now
        fit = local_cubic([t for t, _ in hist], [x for _, x in hist])
        self._live_fit = fit[0] if fit is not None else None
        self._fit_trusted = fit is None or fit[1] <= FIT_TOL
        return self._fit_trusted or now - self._fit_full_at >= FIT_WAIT_S

    def _fit_reset(self) -> None:
        """Forget the live input's window and its fit (:meth:`_live_known`)."""
        self._live_hist.clear()
        self._live_fit = self._fit_full_at = None
        self._fit_trusted = True

    def _blend_start(self, p: ShaperParams, live: list[float], now: float) -> None:
        """A blend from the reference held (or ramping) to ``live`` (:mod:`motcomp.core.blend`):
        the held path's position and motion (a ramp's, or at rest) less the live one's (the
        least-squares cubic through its ticks since it settled, ``smooth``; else its line),
        over ``_blend_s`` or longer where that would need more than ``blend_acc``."""
        self._blend_t0 = now
        move, self._blend_move = self._blend_move, None
        rest = (0.0, 0.0, 0.0)
        held, held_d = (move.at(now)[0], move.derivatives(now)) if move is not None \
            else (self.ref, [rest] * self.n)
        live_d: list[tuple[float, float, float]] | None = None
        if p.reconstruction == "smooth":
            live_d = self._live_fit  # this tick's (_live_known)
            if live_d is not None and not self._fit_trusted:  # its velocity only (FIT_WAIT_S)
                live_d = [(v, hd[1], hd[2]) for (v, _, _), hd in zip(live_d, held_d,
                                                                     strict=True)]
        elif p.reconstruction == "linear":
            live_d = [(v, 0.0, 0.0) for v in self._lin_slope]
        self._fit_reset()
        base = self._blend_s
        polys, each = [], []
        jerks: list[list[float]] = []
        jerk_s: list[float] = []
        for i, (x, h) in enumerate(zip(live, held, strict=True)):
            hv, ha, hj = held_d[i]
            lv, la, lj = live_d[i] if live_d is not None else rest
            g, r = h - x, hv - lv
            a = p.blend_acc[i] if p.blend_acc and p.driven[i] and base > 0.0 else 0.0
            d = blend_duration(g, r, a, base)
            if p.blend_jerk and p.driven[i] and d > 0.0:
                d = jerk_duration(g, r, ha - la, a, p.blend_jerk[i], d)
            each.append(d)
            polys.append(blend_coefficients(g, r, ha - la, 0.0, d, a) if d > 0.0 else [])
            dj = min(d, JERK_CARRY_S)
            jerks.append(blend_coefficients(0.0, 0.0, 0.0, hj - lj, dj, a) if dj > 0.0 else [])
            jerk_s.append(dj)
        self._blend_poly, self._blend_each = polys, each
        self._blend_jerk, self._blend_jerk_s = jerks, jerk_s

    def _live_now(self, p: ShaperParams, now: float) -> list[float]:
        """The live values at this tick: reconstructed as ``p.reconstruction`` says."""
        if p.reconstruction == "linear":
            out = self._live_linear(p, now)
            self.played = out[:]
            return out
        pb = self.playback
        if p.reconstruction != "smooth" or not pb.ready():
            self._band.reset()
            self._run_s = 0.0
            self._at = None
            self._playing = False
            self.played = self.live[:]
            return self.live[:]
        q = self.timeline.period
        at = self._at
        dt = 0.0 if at is None else max(now - at, 0.0)
        self._at = now
        blend_s = max(GAP_BLEND_S, GAP_BLEND_PERIODS * q)
        phi = self._fix_step.of(dt, blend_s)
        d = pb.step(now, p.playback_lag_s)
        self._lead_s = p.lead_s
        tau = now - d + p.lead_s
        bound = max(p.max_extrapolation_s, 1.5 * q) + p.lead_s
        out = []
        playing = True
        for i, c in enumerate(self.curves):
            h = c.knots
            if h:
                out.append(c.at(tau, bound, phi, blend_s))
                playing = playing and (len(h) > 1 and tau >= h[1].t)
            else:
                out.append(self.live[i])
        self._playing = self._playing or playing  # (before the second sample: its first
        # knot has no slope yet, the curve starts flat)
        self.played = out[:]
        length = q / p.tick_s
        if abs(length - self._ma_len) > MA_HYSTERESIS * max(self._ma_len, 1.0):
            self._ma_len = length  # only a real change of the input's rate moves it
        out = self._average(out, p.tick_s, self._ma_len)
        self._run_s += dt
        if not p.band:
            return out
        return self._band.step(p.band, out)

    def _average(self, x: list[float], tick_s: float, length: float) -> list[float]:
        """Moving average of each axis over the last ``length`` ticks (fractional: the oldest
        tick weighs what is left), i.e. one input period."""
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
        """``linear``: extrapolated along the last two frames to this tick."""
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

    def stale_time(self, now: float) -> float:
        """Seconds since the last valid frame (0 while live)."""
        if self._stale_since is None:
            return 0.0
        last = self.last_input_s if self.last_input_s is not None else self.started_s
        return now - (last or now)
