"""Each input sample's instant on the sender's timeline: :class:`Timeline`.

Contract
--------
:meth:`Timeline.place` takes one accepted frame -- its ``t`` (or None), its ``seq`` step
``frames``, the loop instant it was taken at, its values -- and returns the sample's instant
(seconds, on the sender's clock relative to a whole second, or on the loop's clock for a sender
that never stamps), the number of the sender's sample periods since the previous frame, and
whether the timeline starts anew (a restart: the first frame, a rejoin, a switch between stamped
and unstamped frames, a rate no longer followed).  Nothing here reads a clock.

How:

* **Stamped frames** (``t``): the stamp is the instant.  A least-squares line through
  (frame count, stamp) learns the sender's period (gains falling to :data:`TRACK_ALPHA`); a stamp
  a whole number of periods on (within :data:`TIME_GATE_S`) counts the skipped samples; a stamp
  off the line by more is an irregular sender's instant (the line re-anchors there); a frame
  without ``t`` from a sender that stamps the others lies on its grid.
* **A grid sender's rounding**: ``t0 + k/rate`` in epoch seconds is a float64 0.24 us coarse.
  Where :data:`GRID_MIN_FRAMES` stamps in a row lie on the line within their resolution, the
  values decide where their samples lie (:meth:`Timeline._weigh_grid`): at the stamps, or on the
  grid the stamps round (then the instants follow the line, and the rounding is not position
  noise the compensator would amplify).
* **Unstamped frames** (no ``t`` ever): the same line through (frame count, arrival) is the
  timeline, its gains falling to :data:`NO_T_ALPHA` (an arrival's jitter moves it by a
  ten-thousandth); frames read in the same tick carry no timing news.  Samples the sender
  skipped are counted from the motion (:meth:`Timeline.count`: a step as long as several
  steps of a steady motion, or of a steady acceleration at a reversal); where the motion cannot
  tell (too slow, too noisy, the very crest) the ``seq`` step stands.
* **Period**: the interval per seq step, averaged (:data:`PERIOD_GAIN`) within half to 1.5
  times the period; a single unusual one (a stall) is ignored, :data:`PERIOD_RELEARN` in a row (a
  new rate) replace it.
"""

from __future__ import annotations

import math

from mypy_extensions import mypyc_attr

from motcomp.core.interp import Curve, float32_ulp, value_ulp

__all__ = ["MAX_SKIP", "Timeline"]

TIME_GATE_S = 5e-6
"""A stamp this close to the line a whole number of periods on is a sender that skipped
samples."""
TRACK_ALPHA = 0.01
"""The least-squares gains of the sender's grid fall to this (phase) and its square over 4
(period); they move the line only, never a stamped sample's instant."""
NO_T_ALPHA = 1e-4
"""Unstamped frames: the gains fall to this (phase) and its square over 4 (period)."""
PERIOD_GAIN = 0.05
"""Weight of each interval in the period's average."""
PERIOD_RELEARN = 8
"""This many intervals in a row outside half to 1.5 times the period replace it."""
MAX_SKIP = 1000
"""Most samples one frame may span (a stamp on the grid, or a skip counted from the motion)."""
MIN_SKIP_STEP = 1e-6
"""A steady step of at least this (axis units) a sample can be told from its multiples."""
SKIP_TOLERANCE = 0.15
"""Steps (or their changes) agree within this fraction; a count within it of a whole number."""
SKIP_NOISE = 0.25e-6
"""The values' noise for the skip count (axis units; four ulps of a float32 value where more):
a change of the step below it is no steady acceleration."""
GRID_MIN_FRAMES = 32
"""A stamp is read against the sender's grid once this many in a row lay on the line within
their resolution."""
GRID_TRACK_ALPHA = 1e-3
"""The line's gains fall to this while the stamps lie on it within their resolution."""
GRID_FOLLOW = 0.01
"""The instants read on the grid follow the line through this gain."""
GRID_WINDOW = 7
"""Frames in each window of that evidence (the middle one against the quintic through the
others)."""
GRID_OUTLIER = 2.0
GRID_NOISE_ULPS = 4.0
"""A window whose residual is more than GRID_OUTLIER times the rounding's share plus
GRID_NOISE_ULPS of the value's own rounding (float32 or float64) is the motion's own shape (a
step, a kink), which neither reading explains: it is left out of the evidence."""
GRID_MIN_WEIGHT = 20.0
"""No decision on where a grid sender's values lie before this many windows' evidence."""
GRID_GAIN = 1e-2
"""Weight of each window of GRID_WINDOW frames in that evidence (about 100 windows)."""
GRID_SIGMAS = 3.0
"""The evidence must lie this many standard errors from the midway to change the decision."""


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Timeline:
    """The state of the rules in the module docstring."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.period = 0.0
        """The sender's period (s per seq step; 0 before two frames)."""
        self.t_last: float | None = None
        """The newest sample's instant."""
        self.at_stamps = True
        """A grid sender's values lie at its stamps (else on the grid the stamps round)."""
        self._t_base: float | None = None  # sender time origin (a whole second)
        self._stamped = False  # the timeline is the sender's (frames with t)
        self._line = 0.0  # the least-squares line of the instants: its newest point
        self._line_n = 0  # and the frames on it since it was anchored
        self._odd: list[float] = []  # unusual intervals in a row
        self._grid_err: float | None = None  # the last frame's stamp - its grid instant
        self._grid_ring: list[tuple[float, dict[int, float]]] = []
        self._grid_sums = [0.0, 0.0, 0.0, 0.0]  # sum r u, u u, r r, weight
        self._grid_t: float | None = None  # the last instant read on the grid
        self._grid_run = 0  # frames in a row whose stamps lie on the line within their ulp
        self._arrived: float | None = None  # loop instant the last frame was taken

    @property
    def stamped(self) -> bool:
        """The timeline is the sender's (its frames carry ``t``), not the loop's."""
        return self._stamped

    def base(self) -> float:
        """The whole second stamps are counted from (0 before the first stamp)."""
        return self._t_base if self._t_base is not None else 0.0

    # --- the frame's instant --------------------------------------------------------------
    def span(self) -> float:
        """How long (s) the line through the instants of a sender without ``t`` has run since
        it was anchored (its frames times the period); a stamping sender's: infinite."""
        return math.inf if self._stamped else self._line_n * self.period

    def place(self, t_sender: float | None, frames: int, arrived: float, pos: dict[int, float],
              curves: list[Curve], restart: bool, driven: tuple[bool, ...], min_dt: float,
              stale_after_s: float) -> tuple[float, int, bool]:
        """``(instant, samples, restart)`` of a frame (module docstring): ``samples`` is the
        number of sender periods since the previous frame (``frames``, or more where samples
        were skipped), ``restart`` whether the timeline starts anew here.  ``curves`` are the
        axes' samples so far (read only), ``pos`` is kept (up to GRID_WINDOW frames'); only the
        ``driven`` axes' values count."""
        if t_sender is None and not restart:
            frames = self.count(pos, frames, curves, driven)
        t, restart, frames = self._instant(t_sender, frames, arrived, restart, min_dt,
                                           stale_after_s)
        ring = self._grid_ring
        if self._grid_err is None or frames != 1:
            ring.clear()
        else:
            ring.append((self._grid_err, pos))
            if len(ring) == GRID_WINDOW:  # windows of seven frames, each frame in one
                self._weigh_grid(driven)
                ring.clear()
        self._arrived = arrived
        tl = self.t_last
        if tl is None or restart or t - tl >= min_dt or t < tl:
            self.t_last = t
        return t, frames, restart

    def _instant(self, t_sender: float | None, frames: int, now: float, rejoin: bool,
                 min_dt: float, stale_after_s: float) -> tuple[float, bool, int]:
        q = self.period
        tl = self.t_last
        self._grid_err = None
        if t_sender is None and self._stamped and tl is not None and not rejoin and q > 0.0:
            self._line += frames * q  # a stamping sender's frame without t: on its grid
            if self._grid_t is not None:
                self._grid_t += frames * q
            return tl + frames * q, rejoin, frames
        skipped = False
        grid_t, run = self._grid_t, self._grid_run
        self._grid_t, self._grid_run = None, 0
        if t_sender is None:  # timed by its arrival
            if self._stamped:
                rejoin = True  # from the sender's clock to the loop's: a new timeline
            self._stamped = False
            x, gate, floor = now, 0.5 * stale_after_s, NO_T_ALPHA
            news = self._arrived is None or now > self._arrived  # one tick's frames: no news
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
                    # on the grid, samples skipped: the grid goes on, unless this keeps
                    # happening (then the sender changed its rate)
                    if self._learn_period((x - tl) / frames):
                        self._line, self._line_n = x, 1
                        return x, rejoin, frames
                    frames, skipped = m, True
        if tl is None or rejoin or self._line_n == 0:
            self._line, self._line_n = x, 1
            return x, rejoin, frames
        pred = self._line + frames * q
        err = x - pred
        if not news:
            self._line = pred
            return tl + frames * q, rejoin, frames
        if abs(err) > gate:
            if t_sender is not None and min_dt <= x - tl <= stale_after_s:
                self._learn_period((x - tl) / frames)  # irregular: the stamps are right
            self._line = x  # off the line: anchored anew where the frame says
            if t_sender is None:  # and, timed by arrival, its slope learnt anew
                self._line_n = 1
            return x, rejoin, frames
        n = self._line_n + 1
        run = run + 1 if t_sender is not None and abs(err) <= math.ulp(t_sender) else 0
        self._grid_run = run
        on_grid = run > GRID_MIN_FRAMES
        if on_grid:
            floor = GRID_TRACK_ALPHA
        alpha = max(2.0 * (2 * n - 1) / (n * (n + 1)), floor)
        beta = max(6.0 / (n * (n + 1)), floor * floor / 4)
        new_q = q + beta * err / frames
        if new_q <= 0.0 or (n > 2 and not 0.25 * q < new_q < 4.0 * q):  # another sender
            self._line, self._line_n = x, 1
            return x, rejoin, frames
        self._line, self._line_n, self.period = pred + alpha * err, n, new_q
        if not skipped:
            self._odd.clear()
        if t_sender is None:
            return tl + frames * new_q, rejoin, frames
        if not on_grid:
            return x, rejoin, frames
        if not skipped:
            self._grid_err = err
        g = pred if grid_t is None else grid_t + frames * new_q
        g += GRID_FOLLOW * (pred - g)
        self._grid_t = g
        return (x if self.at_stamps else g), rejoin, frames

    def _learn_period(self, dt: float) -> bool:
        """One interval per seq step: averaged within half to 1.5 times the period;
        PERIOD_RELEARN unusual ones in a row replace the period by their median (True is
        returned, and the line's slope is learnt anew); a single one changes nothing."""
        q = self.period
        if q == 0.0:
            if dt > 0.0:
                self.period = dt
            return False
        if 0.5 * q <= dt <= 1.5 * q:
            self.period = q + PERIOD_GAIN * (dt - q)
            self._odd.clear()
            return False
        self._odd.append(dt)
        if len(self._odd) >= PERIOD_RELEARN:
            self.period = sorted(self._odd)[len(self._odd) // 2]
            self._odd.clear()
            self._line_n = 1
            return True
        return False

    # --- samples a sender without t skipped -------------------------------------------------
    def count(self, pos: dict[int, float], frames: int, curves: list[Curve],
              driven: tuple[bool, ...]) -> int:
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
        q = self.period
        best, ratio, other, gap, noise, bent = 0.0, 1.0, 0.0, 0.0, 0.0, False
        for i, v in pos.items():
            h = curves[i].knots
            if not driven[i] or len(h) < 3 or q <= 0.0:
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
                floor = max(SKIP_NOISE, 4.0 * float32_ulp(v))
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

    # --- where a grid sender's values lie ---------------------------------------------------
    def _weigh_grid(self, driven: tuple[bool, ...]) -> None:
        """Seven consecutive frames on the grid, each stamp ``d`` off it within its resolution:
        the middle value's residual from the quintic through the other six (uniform grid: exact
        on quintics, so a smooth motion's own shape leaves ``h^6 x^(6) / 20`` of it, nothing
        beside the rounding's ``slope x 0.1 us`` even at 50 Hz) is ``r ~ 0`` if the values lie
        on the grid, ``r ~ u = slope (d - the same quintic's d)`` if they lie at the stamps.
        ``alpha = sum r u / sum u u`` (recent windows, GRID_GAIN) decides, once it lies
        GRID_SIGMAS standard errors beyond 1/2; until then the stamps are the instants.
        Windows neither reading explains (GRID_OUTLIER) are left out."""
        ring = self._grid_ring
        d = [e for e, _ in ring]
        big_d = d[3] - _quintic_mid(d[0], d[1], d[2], d[4], d[5], d[6])
        half_q = 0.5 / self.period
        ru = uu = rr = 0.0
        p3 = ring[3][1]
        for i, v3 in p3.items():
            if not driven[i]:
                continue
            vals = [p.get(i, math.nan) for _, p in ring]
            r = v3 - _quintic_mid(vals[0], vals[1], vals[2], vals[4], vals[5], vals[6])
            u = (vals[4] - vals[2]) * half_q * big_d
            noise = GRID_NOISE_ULPS * value_ulp(v3)
            if not abs(r) <= GRID_OUTLIER * abs(u) + noise:
                continue  # the motion's own shape (a step, a kink), or an axis not in each
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


def _quintic_mid(f0: float, f1: float, f2: float, f4: float, f5: float, f6: float) -> float:
    """The quintic through six equally spaced points at -3, -2, -1, 1, 2, 3 evaluated at 0 (exact
    on quintics; off by ``h^6 f^(6) / 20`` on a smooth motion)."""
    return (15.0 * (f2 + f4) - 6.0 * (f1 + f5) + (f0 + f6)) / 20.0
