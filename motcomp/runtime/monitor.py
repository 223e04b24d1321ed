"""Live motion quality of the running service, per driven axis: :class:`MotionMonitor`.

Three figures for ``motcomp status`` (why and how: docs/DEPLOYMENT.md, "Motion quality"):

``apparent_delay_ms``
    how late the platform's feedback position follows the sender's samples at their own ``t``
    (what a user means by the delay: the input's reconstruction and band limit included), by
    :func:`motcomp.core.quality.estimate_delay` over the last ``window_s``; with
    ``delay_valid``, ``delay_reason`` and ``delay_corr`` (below).
``limited_share``
    the fraction of ticks over the window on which the limiter changed the axis' command
    (:attr:`motcomp.core.tick.TickState.acted`).
``hf_acc_rms``, ``jerk_rms``, ``acc_peak``
    :func:`motcomp.core.quality.command_quality` of the command ``u`` sent over the last
    :data:`COMMAND_WINDOW_S`, taken on the loop's period grid from the tick instants, the
    grid's points at missed deadlines marked (:func:`motcomp.core.quality.command_quality_masked`):
    a missed tick is neither read as a jump of the command nor bridged in position (a straight
    line over it reads the command's own acceleration as a jerk of ``a / h``: 350-550 m/s^3 for
    the rails' ordinary driving at 1.5-5 % missed, against 3-8 on the ticks sent); None without
    four consecutive ticks.

Threads and cost: the loop thread calls :meth:`MotionMonitor.record` once per tick (a row written
into a preallocated ring: about a microsecond): the input as the shaper plays it back
(:attr:`motcomp.core.shaper.ReferenceShaper.played`, before its averaging and band limit) at its own
instant on the loop clock (the tick's, less the playback's lag beyond the smallest transit: the
sample's ``t`` plus that transit), and the command ``u`` at the tick's instant; the feedback
subscriber's thread calls :meth:`MotionMonitor.on_feedback` per frame (an append to a bounded
deque); one other thread (the service's main thread) calls :meth:`MotionMonitor.drain` and
:meth:`MotionMonitor.report`, which decode, average and estimate.  Nothing here reads a clock: every
instant is an argument, in ns on the loop's monotonic clock (``time.perf_counter_ns``).

The delay, step by step (``h`` = :data:`BIN_S`)
-----------------------------------------------
0. Each feedback frame is placed on the loop clock at ``t + min(arrival - t)``: its sender's ``t``
   shifted by the smallest transit over the frames held (the fastest delivery; the input's samples
   are placed the same way, by the shaper's own smallest transit).  The arrival instants themselves
   carry the receiving side's dispatch delays (the interpreter lock, a busy host), which are not the
   platform's.  If a frame held lacks a finite ``t``, the arrival instants are used.
1. Both signals are averaged into bins of ``h`` on that clock -- the input ``r`` at its own
   instants, the feedback at its instants of step 0 -- keeping each bin's mean instant; each
   is resampled linearly from those mean instants onto the bin centres (so the sampling
   phase of the two streams within a bin biases nothing; empty bins are bridged).
2. The window ``[A, B)`` of the feedback: its last ``window_s`` (at most :data:`MAX_WINDOW_S`)
   such that ``r`` is known, and live, over ``[A - max_lag, B - min_lag)``
   (:data:`LAG_RANGE_S`): a tick that was not live (the input's start-up or resume blend, a
   stale input, parking: the tick's mode) moves the platform otherwise than by the compensated
   reference, so the window holds the last span of live ticks only, as far as it lies within
   the last ``window_s``.  Per axis likewise, the window starts as after a tick that was not
   live after the last tick at which the axis' compensation changed (a bypass switch or a
   reload, the blends they start, its prediction fading in or out): a window holds one way of
   moving the platform, not a mixture of two.
3. From ``d = 0``: ``r(t - d)`` over ``[A, B)`` (linear between bins) and ``y``, each with its
   weighted mean removed and tapered by the same Tukey window (cosine edges over
   :data:`TAPER_FRACTION` of it), go to ``estimate_delay`` (lags within the range); ``d`` grows
   by the delay it finds, until a step is below 1 % of a bin (two to five steps; at most ten).
   A step's estimate is pulled towards zero by the windows (for a slow motion, by a fraction of
   the remaining delay), which the next step removes: at the fixed point the two windows are
   aligned and the pull is nil.  (A single correlation of two equal windows is off by 5-100 ms
   for a 0.2-0.3 Hz motion over 10 s, and so is one of a motion that starts or stops within the
   window.)  ``delay_corr`` is the Pearson correlation of ``r(t - d)`` and ``y`` over
   ``[A, B)``.

Validity (``delay_valid`` false, ``delay_reason`` says which; the value is None unless a delay
was computed): no feedback yet, or none for :data:`FEEDBACK_STALE_S`; less than
:data:`MIN_SPAN_S` of feedback (of live input: after a start or a resume, the first ``max_lag -
min_lag + MIN_SPAN_S`` (2.7 s) after the blend -- and after an axis' change of compensation;
once the input stops, from ``window_s`` less ``MIN_SPAN_S`` after); the axis in fewer than
:data:`MIN_FEEDBACK_COVERAGE` of the bins; the reference's standard deviation over the window
below :data:`MIN_MOTION_FRACTION` of the axis range; the feedback constant, the correlation's
peak on the edge of the lags, or no convergence (the iteration of step 3 still moving by more
than 1 % of a bin after ten steps: the motion does not tell one delay);
``delay_corr`` below :data:`MIN_CORRELATION`; the limiter acting on more than
:data:`MAX_LIMITED_SHARE` of the window's ticks (the value is still given).

Feedback frames (docs/WIRE.md ``{"t", "pos", "acc"}``): any bytes are accepted by
:meth:`~MotionMonitor.on_feedback`; a frame that is larger than :data:`MAX_FEEDBACK_BYTES`, does
not decode, or whose ``pos`` or ``acc`` is not a map of finite numbers is counted (``bad``,
``last_bad``) and ignored; axes this service does not know are ignored.  Nothing here raises
because of a frame.

Example
-------
>>> m = MotionMonitor(rate_hz=1000.0, window_s=10.0)
>>> m.record(0, [0.0] * 8, [0.0] * 8)
>>> m.report(1_000_000, 1, [0] * 8, [True] + [False] * 7, [-1.0] * 8, [1.0] * 8
...          )["axes"]["rails_x"]["delay_reason"]
'no feedback received'
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from motcomp.core.axes import AXES, AXIS_INDEX, N_AXES
from motcomp.core.quality import command_quality_masked, estimate_delay
from motcomp.core.tick import MAX_ERROR_CHARS
from motcomp.errors import ConfigError, FrameError
from motcomp.io.wire import decode_feedback

__all__ = [
    "BIN_S",
    "COMMAND_WINDOW_S",
    "FEEDBACK_STALE_S",
    "LAG_RANGE_S",
    "MAX_FEEDBACK_BYTES",
    "MAX_JUDGED_MISSED_SHARE",
    "MAX_LIMITED_SHARE",
    "MAX_WINDOW_S",
    "MIN_CORRELATION",
    "MIN_FEEDBACK_COVERAGE",
    "MIN_MOTION_FRACTION",
    "MIN_SPAN_S",
    "MotionMonitor",
    "feedback_positions",
    "starved_out",
]

BIN_S = 0.005
"""Averaging bin of both signals before the correlation (200 Hz)."""
LAG_RANGE_S = (-0.1, 0.6)
"""Lags searched (s): a bypassed rails axis shows ~190 ms, a compensated one a few ms."""
MAX_WINDOW_S = 60.0
"""Longest delay window (memory: the rings hold it at the loop rate)."""
COMMAND_WINDOW_S = 2.0
"""The command's smoothness is measured over its last this long."""
MIN_SPAN_S = 2.0
"""Shortest feedback span a delay is estimated on."""
MIN_FEEDBACK_COVERAGE = 0.5
"""Fraction of the window's bins that must hold a feedback value of the axis."""
MIN_MOTION_FRACTION = 1e-3
"""The reference's standard deviation over the window, as a fraction of the axis range, below
which the motion is too small to tell a delay (5 mm on the 5.2 m rails)."""
MIN_CORRELATION = 0.9
"""Lowest normalised correlation of the feedback with the delayed reference for a valid delay."""
MAX_LIMITED_SHARE = 0.25
"""A delay measured while the limiter acted on more of the window's ticks is not valid: the
platform then follows the limits, not the compensation (a 256 ms "delay" at 82 %)."""
MAX_JUDGED_MISSED_SHARE = 0.2
"""A window in which the loop missed more than this share of its deadlines judges nothing -- no
valid delay here, no informative estimate in supervision: its stalls are cut out, but between
them a loop that starved ticks late and the figures carry it (an unchanged hexapod read 5.5 ms
late, an alarm, at 45-55 % missed; none of 88 windows at 12 %)."""
FEEDBACK_STALE_S = 0.5
"""No feedback for this long: no delay (the figure would describe the past)."""
MAX_FEEDBACK_BYTES = 65536
"""Longest feedback frame read (a frame of 8 axes is about 300 bytes)."""
TAPER_FRACTION = 0.25
"""Part of the delay window under the taper's cosine edges (half at each end): the middle 75 %
weighs uniformly."""
_MAX_ITERATIONS = 10
_CONVERGED_BINS = 0.01
"""Step 3 stops when a step moves the delay by less than this fraction of a bin."""


def feedback_positions(payload: bytes) -> tuple[float, list[float], list[float]]:
    """The sender's ``t`` (NaN unless a finite number), the positions and the accelerations in
    :data:`AXES` order (NaN for an axis it lacks) of a feedback frame.

    Raises
    ------
    FrameError
        ``oversize``, ``decode``, ``schema``, ``type`` or ``nonfinite``, naming the key.
    """
    if len(payload) > MAX_FEEDBACK_BYTES:
        raise FrameError("oversize", f"feedback frame of {len(payload)} bytes exceeds "
                                     f"{MAX_FEEDBACK_BYTES}")
    frame = decode_feedback(payload)
    t = frame["t"]
    t = float(t) if t.__class__ is float or t.__class__ is int else math.nan
    return (t if math.isfinite(t) else math.nan), _axis_row(frame, "pos"), _axis_row(frame,
                                                                                      "acc")


def _axis_row(frame: dict[str, Any], key: str) -> list[float]:
    """``frame[key]``, a map of axis -> number, as a row in :data:`AXES` order."""
    values = frame[key]
    if values.__class__ is not dict:
        raise FrameError("type", f"feedback {key} must be a map, got a {type(values).__name__}")
    row = [math.nan] * N_AXES
    for axis, value in values.items():
        i = AXIS_INDEX.get(axis) if axis.__class__ is str else None
        if i is None:
            continue  # an axis this service does not know
        if value.__class__ is not float:
            if value.__class__ is not int:
                raise FrameError("type", f"feedback {key}.{axis} must be a number, got a "
                                         f"{type(value).__name__}")
            value = float(value)
        if not math.isfinite(value):
            raise FrameError("nonfinite", f"feedback {key}.{axis} is {value!r}")
        row[i] = value
    return row


def starved_out(axes: dict[str, dict[str, Any]], missed_share: float) -> None:
    """Mark each valid delay of ``axes`` (:meth:`MotionMonitor.report`'s) not valid, with the
    reason, where the loop missed more than :data:`MAX_JUDGED_MISSED_SHARE` of its deadlines."""
    if not missed_share > MAX_JUDGED_MISSED_SHARE:
        return
    for fig in axes.values():
        if fig.get("delay_valid"):
            fig["delay_valid"] = False
            fig["delay_reason"] = (f"the loop missed {100 * missed_share:.0f} % of its "
                                   f"deadlines (more than {100 * MAX_JUDGED_MISSED_SHARE:g} %): "
                                   "the figure carries its stalls")



def _short_of(seconds: float, need: float) -> str:
    """``seconds`` (>= 0) to a tenth, rounded down where rounding would reach ``need``: a span
    short of a need never reads as it ("2.0 s (needs 2 s)" for 1.96 s)."""
    x = max(0.0, seconds)
    text = f"{x:.1f}"
    return f"{math.floor(x * 10.0) / 10.0:.1f}" if x < need <= float(text) else text

class MotionMonitor:
    """The figures of the module docstring, from per-tick samples and feedback frames.

    Parameters
    ----------
    rate_hz
        The loop's rate (sizes the rings; the command's sampling rate).
    window_s
        Delay and limiter-share window (the service's ``status.window_s``), at most
        :data:`MAX_WINDOW_S`.
    feedback_rate_max_hz
        Highest feedback rate that fills the window (default: twice ``rate_hz``); faster
        feedback shortens the window the ring holds.
    bin_s
        The averaging bin (:data:`BIN_S`).
    min_span_s
        The rings hold at least this long (what :meth:`chunk`'s caller reads between calls).

    Raises
    ------
    ConfigError
        If the rate, window or bin is not a positive number.
    """

    def __init__(self, rate_hz: float, window_s: float, feedback_rate_max_hz: float = 0.0,
                 bin_s: float = BIN_S, min_span_s: float = 0.0) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0 and math.isfinite(window_s)
                and window_s > 0 and bin_s > 0):
            raise ConfigError(f"monitor needs a positive rate, window and bin, got {rate_hz!r}, "
                              f"{window_s!r}, {bin_s!r}")
        self.rate_hz = float(rate_hz)
        self.window_s = min(float(window_s), MAX_WINDOW_S)
        self.bin_ns = round(bin_s * 1e9)
        self._lo = math.floor(LAG_RANGE_S[0] / bin_s)
        self._hi = math.ceil(LAG_RANGE_S[1] / bin_s)
        span_s = self.window_s + (self._hi - self._lo) * bin_s + 1.0
        # loop thread: tick instants, and per tick r then u (AXES order) in one row; the ring
        # holds half a second more than is read (a report reads its own span, the rows
        # kept for chunk() may be more), which the loop may overwrite meanwhile
        self._report_rows = max(math.ceil(max(span_s, COMMAND_WINDOW_S + 1.0) * rate_hz), 64)
        self._keep = max(self._report_rows, math.ceil(min_span_s * rate_hz))
        self._cap = self._keep + max(math.ceil(0.5 * rate_hz), 16)
        self._t = np.zeros(self._cap, dtype=np.int64)
        self._t_in = np.zeros(self._cap, dtype=np.int64)
        self._ru = np.zeros((self._cap, 2 * N_AXES))
        self._n = 0
        self._live: tuple[int | None, int | None] = (None, None)
        """The last span of live ticks: the input instants of the last tick before it that was
        not (None: none was) and of the first after it (None: live now)."""
        self._was_live = False
        self._not_live_ns: int | None = None
        self._changed_ns: list[int | None] = [None] * N_AXES
        """Per axis, the input instant of the last tick whose compensation was changing (a
        bypass switch or a reload, and the blends they start; None: none was)."""
        self._changes = 0
        # feedback subscriber's thread -> main thread
        self._inbox: deque[tuple[int, bytes]] = deque(maxlen=1 << 14)
        self.fb_dropped = 0
        """Frames the inbox overflowed with (the main thread did not drain it in time)."""
        # main thread: arrival instants and positions of the frames that decoded
        fb_rate = feedback_rate_max_hz or 2.0 * rate_hz
        self._report_frames = max(math.ceil((self.window_s + 2.0) * fb_rate), 64)
        self._fcap = max(self._report_frames, math.ceil((min_span_s + 2.0) * fb_rate))
        self._ft = np.zeros(self._fcap, dtype=np.int64)
        self._fsent = np.zeros(self._fcap)
        self._fpos = np.zeros((self._fcap, N_AXES))
        self._facc = np.zeros((self._fcap, N_AXES))
        self._fn = 0
        self.fb_received = 0
        self.fb_bad = 0
        self.fb_last_bad = ""
        self._window_cache = np.zeros(0)
        # (instant, ticks, acted) at each report; the first, from before any tick, is the base
        # until one is a window old (the service makes the tick's counters and this together)
        self._snaps: deque[tuple[int, int, tuple[int, ...]]] = deque([(-(2**62), 0,
                                                                      (0,) * N_AXES)])

    # --- the loop thread ------------------------------------------------------------------
    def record(self, t_ns: int, ref: list[float], u: list[float], lag_ns: int = 0,
               live: bool = True, changing: int = 0) -> None:
        """One tick at ``t_ns``: the input ``ref`` at the instant ``t_ns - lag_ns`` and the
        command ``u`` the tick sent (lists in :data:`AXES` order); ``live`` False for a tick
        whose mode was not (start-up or resume blend, stale input, parking); bit ``i`` of
        ``changing`` set where axis ``i``'s compensation was changing (blending between
        compensation and bypass, its prediction fading)."""
        k = self._n % self._cap
        self._t[k] = t_ns
        self._t_in[k] = t_ns - lag_ns
        changing |= self._changes
        if changing:
            self._changes = 0
            for i in range(N_AXES):
                if changing >> i & 1:
                    self._changed_ns[i] = t_ns - lag_ns
        if live:
            if not self._was_live:  # a live span starts
                self._was_live = True
                self._live = (self._not_live_ns, None)
        else:
            if self._was_live:  # it ends
                self._was_live = False
                self._live = (self._live[0], t_ns - lag_ns)
            self._not_live_ns = t_ns - lag_ns
        self._ru[k] = ref + u
        self._n += 1

    def changed(self, axes: int) -> None:
        """The compensation of the axes whose bits are set changed at once (gains, models or
        prediction swapped, a bypass switch): the next tick recorded is the first of the new
        one.  Called from the loop thread, between ticks."""
        self._changes |= axes

    # --- the feedback subscriber's thread -------------------------------------------------
    def on_feedback(self, t_ns: int, payload: bytes) -> None:
        """A feedback frame arrived at ``t_ns``; any bytes (decoded later by :meth:`drain`)."""
        inbox = self._inbox
        if len(inbox) == inbox.maxlen:
            self.fb_dropped += 1
        inbox.append((t_ns, payload))

    # --- the main thread ------------------------------------------------------------------
    def drain(self) -> int:
        """Decode the frames that arrived since the last call; returns how many were good."""
        inbox = self._inbox
        good = 0
        while inbox:
            t_ns, payload = inbox.popleft()
            self.fb_received += 1
            try:
                sent, row, acc = feedback_positions(payload)
            except FrameError as exc:
                self._bad(f"{exc.reason}: {exc}")
                continue
            except Exception as exc:  # any bytes: a decoder's surprise is counted, not raised
                self._bad(f"internal: {type(exc).__name__}: {str(exc)[:80]}")
                continue
            k = self._fn % self._fcap
            self._ft[k] = t_ns
            self._fsent[k] = sent
            self._fpos[k] = row
            self._facc[k] = acc
            self._fn += 1
            good += 1
        return good

    def feedback_age_s(self, now_ns: int) -> float | None:
        """Seconds from the arrival of the newest good feedback frame drained to ``now_ns``
        (None: none yet)."""
        if not self._fn:
            return None
        return (now_ns - int(self._ft[(self._fn - 1) % self._fcap])) / 1e9

    def _bad(self, text: str) -> None:
        self.fb_bad += 1
        self.fb_last_bad = (text if len(text) <= MAX_ERROR_CHARS
                            else text[:MAX_ERROR_CHARS - 3] + "...")

    def chunk(self, since: tuple[int, int]) -> tuple[tuple[int, int], dict[str, Any]]:
        """What came since the cursors ``since`` (``(0, 0)`` at first): the new ticks'
        instants ``t_ns`` and commands ``u`` (rows in :data:`AXES` order), the new feedback
        frames' ``fb_sent`` (their ``t``; NaN if none), ``fb_ns`` (arrival) and ``acc``, and
        ``lost``: whether the rings overwrote some of it meanwhile (skipped); with the cursors
        for the next call.  Main thread, after :meth:`drain`."""
        n, fn = self._n, self._fn
        a = max(since[0], n - self._keep)
        fa = max(since[1], fn - self._fcap)
        idx = np.arange(a, n) % self._cap
        fidx = np.arange(fa, fn) % self._fcap
        return (n, fn), {"t_ns": self._t[idx], "u": self._ru[idx, N_AXES:],
                         "fb_sent": self._fsent[fidx], "fb_ns": self._ft[fidx],
                         "acc": self._facc[fidx], "lost": a > since[0] or fa > since[1]}

    def report(self, now_ns: int, ticks: int, acted: Sequence[int], driven: Sequence[bool],
               p_min: Sequence[float] | np.ndarray, p_max: Sequence[float] | np.ndarray,
               pause: Callable[[], None] | None = None) -> dict[str, Any]:
        """The figures at ``now_ns``, after draining the feedback inbox.

        ``ticks`` and ``acted`` are the tick's counters (total ticks, ticks on which the limiter
        acted per axis); ``driven`` selects the axes reported; ``p_min``/``p_max`` give each
        axis' range (for the motion threshold); ``pause`` is called between two axes (the
        service sleeps a little there, handing the interpreter lock to the loop thread).
        Returns ``{"span_ns": (A, B) | None, "feedback": {...}, "axes": {axis: {...}}}``
        (layout in docs/DEPLOYMENT.md); a figure that fails says so in its ``delay_reason``
        (``internal: ...``) instead of raising.
        """
        self.drain()
        share = self._limited_share(now_ns, ticks, acted)
        n, live = self._n, self._live  # (the live span as of the ticks read)
        changed = list(self._changed_ns)
        m = min(n, self._report_rows)
        idx = np.arange(n - m, n) % self._cap
        t_r = self._t[idx]
        t_in = self._t_in[idx]
        if t_in.size > 1 and np.any(t_in[1:] < t_in[:-1]):  # the playback's lag grew: in order
            t_in = np.maximum.accumulate(t_in)
        # r and u of the driven axes, copied now: the loop overwrites the ring's oldest rows
        # while this report runs (it may be preempted for longer than the ring's margin)
        cols = [i for i in range(N_AXES) if driven[i]]
        ru = self._ru[np.ix_(idx, np.array(cols + [N_AXES + i for i in cols], dtype=np.intp))]
        col = {i: k for k, i in enumerate(cols)}
        fn = self._fn
        fm = min(fn, self._report_frames)
        fidx = np.arange(fn - fm, fn) % self._fcap
        arrived = self._ft[fidx]
        t_y, fidx = self._feedback_instants(arrived, self._fsent[fidx], fidx)
        window = self._window(t_in, t_y, arrived, live)
        cmd = self._command_grid(t_r)
        ticked = self._ticked(t_r, cmd[0]) if cmd is not None else None
        axes: dict[str, Any] = {}
        for i, axis in enumerate(AXES):
            if not driven[i]:
                continue
            if axes and pause is not None:
                pause()
            fig: dict[str, Any] = {"apparent_delay_ms": None, "delay_valid": False,
                                   "delay_reason": "", "delay_corr": None,
                                   "limited_share": share[i] if share else None,
                                   "hf_acc_rms": None, "jerk_rms": None, "acc_peak": None}
            try:
                own = window
                if changed[i] is not None and not isinstance(window, str):
                    own = self._window(t_in, t_y, arrived, live, changed[i])
                if isinstance(own, str):
                    fig["delay_reason"] = own
                else:
                    fig.update(self._delay(t_in, ru[:, col[i]], t_y, self._fpos[fidx, i],
                                           own, float(p_max[i]) - float(p_min[i])))
                    if fig["delay_valid"] and share and share[i] > MAX_LIMITED_SHARE:
                        fig["delay_valid"] = False
                        fig["delay_reason"] = (
                            f"the limiter acted on {100 * share[i]:.0f} % of the ticks (more "
                            f"than {100 * MAX_LIMITED_SHARE:g} %): the platform follows its "
                            "limits, not the compensation")
                if cmd is not None and ticked is not None:
                    grid, first = cmd
                    u = np.interp(grid, t_r[first:], ru[first:, len(cols) + col[i]])
                    q = command_quality_masked(u, ticked, self.rate_hz).as_dict()
                    fig.update({k: v if math.isfinite(v) else None for k, v in q.items()})
            except Exception as exc:  # a figure must never stop the status
                fig["delay_reason"] = f"internal: {type(exc).__name__}: {str(exc)[:80]}"
            axes[axis] = fig
        return {
            "span_ns": None if isinstance(window, str) else
            (window[0] * self.bin_ns, window[1] * self.bin_ns),
            "feedback": {"received": self.fb_received, "bad": self.fb_bad,
                         "dropped": self.fb_dropped, "last_bad": self.fb_last_bad,
                         "age_s": (now_ns - int(arrived[-1])) / 1e9 if fm else None},
            "axes": axes,
        }

    def _command_grid(self, t_r: np.ndarray) -> tuple[np.ndarray, int] | None:
        """The loop's period grid over the last :data:`COMMAND_WINDOW_S` (plus the two samples
        the second difference takes) ending at the newest tick, and the first tick it needs;
        None before 8 ticks."""
        if t_r.size < 8:
            return None
        period = round(1e9 / self.rate_hz)
        last = int(t_r[-1])
        n = min(round(COMMAND_WINDOW_S * self.rate_hz) + 2, (last - int(t_r[0])) // period + 1)
        grid = last - period * np.arange(n - 1, -1, -1, dtype=np.int64)
        first = max(int(np.searchsorted(t_r, grid[0], side="right")) - 1, 0)
        return grid, first

    def _ticked(self, t_r: np.ndarray, grid: np.ndarray) -> np.ndarray:
        """Per point of ``grid``, whether no deadline was missed there: it is a tick's instant
        or lies between two ticks at most 1.5 periods apart (input-synchronous ticks come
        0.5-1.25 periods apart; a missed deadline leaves two)."""
        pos = np.clip(np.searchsorted(t_r, grid), 1, t_r.size - 1)
        after, before = t_r[pos], t_r[pos - 1]
        return np.asarray((after - before <= round(1.5e9 / self.rate_hz)) | (after == grid)
                          | (before == grid))

    def _limited_share(self, now_ns: int, ticks: int, acted: Sequence[int]
                       ) -> list[float] | None:
        """Per axis, acted ticks / ticks since the newest report at least a window old (since
        the start until there is one); None without a tick since."""
        snaps = self._snaps
        snaps.append((now_ns, ticks, tuple(acted)))
        horizon = now_ns - round(self.window_s * 1e9)
        while len(snaps) > 2 and snaps[1][0] <= horizon:
            snaps.popleft()
        _, ticks0, acted0 = snaps[0]
        if ticks - ticks0 <= 0:
            return None
        return [(a - a0) / (ticks - ticks0) for a, a0 in zip(acted, acted0, strict=True)]

    @staticmethod
    def _feedback_instants(arrived: np.ndarray, sent: np.ndarray, fidx: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
        """Each frame's instant on the loop clock (step 0), in time order, and the ring rows
        in that order."""
        if arrived.size == 0 or not np.isfinite(sent).all():
            return arrived, fidx
        transit = arrived / 1e9 - sent
        t = np.rint((sent + float(transit.min())) * 1e9).astype(np.int64)
        if np.any(t[1:] < t[:-1]):  # a sender's clock stepped back: keep time order
            order = np.argsort(t, kind="stable")
            t, fidx = t[order], fidx[order]
        return t, fidx

    def _window(self, t_r: np.ndarray, t_y: np.ndarray, arrived: np.ndarray,
                live: tuple[int | None, int | None] = (None, None),
                changed: int | None = None) -> tuple[int, int] | str:
        """The feedback window ``(A, B)`` in absolute bins (step 2), or why there is none;
        ``changed``: the input instant of the axis' last change of compensation (the window
        starts as after a tick that was not live)."""
        if t_y.size == 0:
            return "no feedback received"
        if t_r.size == 0:
            return "no tick yet"
        b = self.bin_ns
        r_first, r_end = int(t_r[0]) // b + 1, int(t_r[-1]) // b  # whole bins only
        y_first, y_end = int(t_y[0]) // b + 1, int(t_y[-1]) // b
        silent = (int(t_r[-1]) - int(arrived[-1])) / 1e9
        if silent > FEEDBACK_STALE_S:
            return f"no feedback for {silent:.1f} s"
        end = min(r_end + self._lo, y_end)
        start = max(end - round(self.window_s * 1e9 / b), r_first + self._hi, y_first)
        # the reference live over [A - max_lag, B - min_lag)
        live_from, live_to = live
        clipped = False
        if live_from is not None and live_from // b + 1 + self._hi > start:
            start, clipped = live_from // b + 1 + self._hi, True
        if live_to is not None and live_to // b + self._lo < end:
            end, clipped = live_to // b + self._lo, True
        if changed is not None and changed // b + 1 + self._hi > start:
            start = changed // b + 1 + self._hi
            if (end - start) * b < MIN_SPAN_S * 1e9:
                return (f"{_short_of((end - start) * b / 1e9, MIN_SPAN_S)} s of feedback "
                        "since the axis' "
                        f"compensation changed (needs {MIN_SPAN_S:g} s; left out: a bypass "
                        "switch or a reload, the blends they start, a prediction's fade (in after "
                        "a stale input returned, or out and in after its band monitor fell "
                        "back) and "
                        f"the next {LAG_RANGE_S[1]:g} s)")
        if clipped and (end - start) * b < MIN_SPAN_S * 1e9:
            return (f"{_short_of((end - start) * b / 1e9, MIN_SPAN_S)} s of feedback on live "
                    "input in the "
                    f"last {self.window_s:g} s (needs {MIN_SPAN_S:g} s; left out: the input's "
                    "start-up or resume blend and the next "
                    f"{LAG_RANGE_S[1]:g} s, a stale input, parking)")
        if (end - start) * b < MIN_SPAN_S * 1e9:
            return (f"{_short_of((end - start) * b / 1e9, MIN_SPAN_S)} s of feedback and "
                    "reference so far "
                    f"(needs {MIN_SPAN_S:g} s)")
        return start, end

    def _binned(self, t_ns: np.ndarray, x: np.ndarray, b0: int, nb: int
                ) -> tuple[np.ndarray, int] | None:
        """``x`` (sampled at ``t_ns``, NaN = no value) averaged into the bins ``b0 ..
        b0 + nb - 1`` and resampled from each bin's mean instant onto the bin centres (step 1);
        with the number of bins that held a value.  None if none did."""
        b = self.bin_ns
        lo, hi = np.searchsorted(t_ns, [b0 * b, (b0 + nb) * b])
        t, v = t_ns[lo:hi], x[lo:hi]
        ok = np.isfinite(v)
        if not ok.all():
            t, v = t[ok], v[ok]
        rel = t - b0 * b
        k = rel // b
        count = np.bincount(k, minlength=nb)
        full = count > 0
        if not full.any():
            return None
        c = count[full]
        t_mean = np.bincount(k, weights=rel, minlength=nb)[full] / c
        x_mean = np.bincount(k, weights=v, minlength=nb)[full] / c
        centres = (np.arange(nb) + 0.5) * b
        return np.interp(centres, t_mean, x_mean), int(full.sum())

    def _taper(self, n: int) -> np.ndarray:
        """The Tukey window of step 3 over ``n`` bins (cached)."""
        w = self._window_cache
        if w.size != n:
            edge = max(1, round(TAPER_FRACTION / 2 * n))
            w = np.ones(n)
            ramp = 0.5 * (1.0 - np.cos(np.pi * (np.arange(edge) + 0.5) / edge))
            w[:edge] = ramp
            w[n - edge:] = ramp[::-1]
            self._window_cache = w
        return w

    def _delay(self, t_r: np.ndarray, r_raw: np.ndarray, t_y: np.ndarray, y_raw: np.ndarray,
               window: tuple[int, int], axis_range: float) -> dict[str, Any]:
        """Steps 1 and 3 of the module docstring for one axis."""
        start, end = window
        n = end - start
        lo, hi = self._lo, self._hi
        yb = self._binned(t_y, y_raw, start, n)
        if yb is None or yb[1] < MIN_FEEDBACK_COVERAGE * n:
            held = 0 if yb is None else yb[1]
            return {"delay_reason": f"too few feedback samples ({held} of {n} bins)"}
        rb = self._binned(t_r, r_raw, start - hi, n + hi - lo)
        if rb is None:
            return {"delay_reason": "no reference samples"}
        r, y = rb[0], yb[0]
        r_win = r[hi:hi + n]
        motion = float(np.std(r_win))
        floor = MIN_MOTION_FRACTION * axis_range
        if not motion >= floor:
            return {"delay_reason": f"motion too small (reference std {motion:.3g} < "
                                    f"{floor:.3g})"}
        rate = 1e9 / self.bin_ns
        w = self._taper(n)
        wsum = float(w.sum())
        y_w = w * (y - float(w @ y) / wsum)
        grid = np.arange(r.size, dtype=float)
        at = grid[hi:hi + n]
        d = 0.0
        try:
            for _ in range(_MAX_ITERATIONS):
                rs = np.interp(at - d * rate, grid, r)
                step = estimate_delay(w * (rs - float(w @ rs) / wsum), y_w, rate,
                                      max_lag_s=hi / rate - d, min_lag_s=lo / rate - d)
                d += step
                if abs(step) * rate < _CONVERGED_BINS:
                    break
            else:
                return {"delay_reason": f"no convergence ({d * 1e3:.1f} ms after "
                                        f"{_MAX_ITERATIONS} steps)"}
        except ConfigError as exc:  # a constant signal, or the peak on the range's edge
            return {"delay_reason": "the feedback does not move" if "constant" in str(exc)
                    else f"no correlation peak within {LAG_RANGE_S[0] * 1e3:g}.."
                         f"{LAG_RANGE_S[1] * 1e3:g} ms"}
        rs = np.interp(at - d * rate, grid, r)
        rs = rs - rs.mean()
        yc = y - y.mean()
        den = math.sqrt(float(rs @ rs) * float(yc @ yc))
        corr = float(rs @ yc) / den if den > 0 else 0.0
        out: dict[str, Any] = {"apparent_delay_ms": d * 1e3, "delay_corr": corr}
        if corr < MIN_CORRELATION:
            out["delay_reason"] = f"correlation {corr:.2f} < {MIN_CORRELATION:g}"
        else:
            out["delay_valid"] = True
        return out
