"""What a replay shows: apparent delays, saturation, differences from the recorded outputs.

Apparent delay (:func:`~motcomp.core.quality.estimate_delay`, cross-correlation with
sub-sample refinement) of a response behind the motion-cueing reference, per axis, on windows
of :data:`WINDOW_S` (at least :data:`MIN_WINDOW_S`) where the reference moves (peak to peak
above :data:`MIN_MOTION`) and the compensation state does not change, at most
:data:`MAX_WINDOWS` of them spread over the session; the median over windows is reported.

* *simulated*: the config's platform model (``plants``, the full models, not the compensator's
  P1D) driven by the replayed commands (``on``, windows where the replay compensated the axis,
  by its PID or its prediction) and by the reference through the limiter alone (``off``: no
  compensation, :func:`motcomp.core.saturation.limit_axis`, the compensator's own limiter),
  behind the tick's reference plus the delay of the axis' band limit before it
  (``input.band_hz``: a pure delay in the driver's band) and what the replayed tick's input
  reconstruction added (its playback lag and moving average, beyond the smallest transit: the
  median of :attr:`EngineResult.lag_s` over the window), so that both figures are behind the
  motion-cueing input as the recorded ones are (the smallest transit, a fraction of a
  millisecond on one host, is not added: the sender's clock is not the loop's).  Both
  commands reach the model as the platform gets them: held through the deadlines the service
  missed (nothing is sent at a catch-up step).  The reference they are measured behind is the
  tick's, taken between two ticks sent across a stall on the line joining them (the motion
  went on while nothing was sent), and the limiter of ``off`` steps at every step the service
  computed (ticks and catch-up steps), on that reference, as a service with the axis bypassed
  would have (stepped on the reference held through the stalls, it fell behind: a slalom
  recorded while the loop missed 16 % of its deadlines read 494 ms for the rails' 196 ms);
* *recorded*: the recorded feedback position behind the recorded input (both on the
  recorder's receive times), on windows where the service had compensation on, resp. off
  (from the recorded outputs' flags: off is the PID bypassed and, on an axis the config
  predicts, its prediction off too -- :func:`~motcomp.record.frames.compensation_off`).

* *the platform against the model*: the recorded feedback and the config's model, both driven
  by the recorded commands (frame clocks: the outputs' and the feedback's own ``t``; the model
  takes each command at its output's instant, on a grid of them), on windows where the commands
  move: the lag of each behind the commands, and the share of the platform's motion the model
  explains.  The platform's lag holds the stack's share (the setpoints' age when the platform
  applies them), which the compensator does not cancel.  (Sampled on the feedback's grid, the
  commands reached the model only when the platform applied them: the stack's share cancelled
  out of the difference, and *live, about* read that much early.)  Their difference is the
  model's delay error, which the compensator inherits: live, the ``on`` delay is about
  ``delay_on + platform - model``.  With no feedback of the axis, or no motion in it, this
  cannot be judged offline, and the report says so (``model_check``).

Saturation is the replayed tick's own verdict (``TickOutput.limited``: the ``sat:<axis>``
flag), counted in samples and in events (runs of saturated samples).  At catch-up steps nothing
is sent: the platform, and the figures, hold the last command and reference sent.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from motcomp.config import ResolvedAxes, ServiceConfig, tick_params
from motcomp.core.axes import AXES
from motcomp.core.models import ProcessModel, simulate_axis
from motcomp.core.saturation import at_rest, axis_constants, limit_axis
from motcomp.errors import ConfigError, DataError
from motcomp.jsonsafe import finite
from motcomp.record.frames import FLAG_BITS, compensation_off
from motcomp.record.session import Session
from motcomp.replay.engine import EngineResult
from motcomp.replay.plan import TickPlan

__all__ = ["MAX_WINDOWS", "MIN_MOTION", "WINDOW_S", "AxisReport", "analyse", "held_commands",
           "limiter_alone"]

WINDOW_S = 30.0
MIN_WINDOW_S = 3.0
MAX_WINDOWS = 6
MIN_MOTION = 1e-3
"""Least peak-to-peak motion (m or rad) of a window used for delays."""
AFTER_TICK_S = 1e-6
"""The platform-against-model grid lies this far after the outputs' instants (a tick's ``t``
read back from its frame may round a hair after the tick's own instant)."""
SETTLE_S = 5.0
"""After a warm start, the first seconds are left out of the comparison with the recording."""


@dataclass
class AxisReport:
    axis: str
    compensated: bool
    """The replay compensated the axis at least part of the time."""
    delay_off_ms: float = math.nan
    delay_on_ms: float = math.nan
    delay_windows: int = 0
    recorded_off_ms: float = math.nan
    recorded_on_ms: float = math.nan
    saturated_samples: int = 0
    saturation_events: int = 0
    recorded_saturated: int = -1
    max_diff: float = math.nan
    rms_diff: float = math.nan
    platform_lag_ms: float = math.nan
    """The recorded platform's lag behind the recorded commands (feedback)."""
    model_lag_ms: float = math.nan
    """The config's platform model's lag behind the same commands."""
    model_fit: float = math.nan
    """Share of the platform's recorded motion the model explains (1: all of it)."""
    model_check: str = ""
    """Why the model could not be checked against the recorded platform ("" if it was)."""

    @property
    def reduction_ms(self) -> float:
        return self.delay_off_ms - self.delay_on_ms

    @property
    def model_error_ms(self) -> float:
        """The platform's lag minus the model's (positive: the platform is slower)."""
        return self.platform_lag_ms - self.model_lag_ms

    @property
    def expected_on_ms(self) -> float:
        """The ``on`` delay corrected by the model's delay error: what the platform would
        show live, to first order."""
        return self.delay_on_ms + self.model_error_ms

    @property
    def recorded_reduction_ms(self) -> float:
        return self.recorded_off_ms - self.recorded_on_ms


@dataclass
class ReplayReport:
    label: str
    axes: list[AxisReport]
    ticks: int
    rows: int
    duration_s: float
    compared_ticks: int
    recorded_config: bool = True
    """The replay ran with the config recorded with the session."""

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        for a, rep in zip(out["axes"], self.axes, strict=True):
            a["reduction_ms"] = rep.reduction_ms
            a["recorded_reduction_ms"] = rep.recorded_reduction_ms
            a["model_error_ms"] = rep.model_error_ms
            a["expected_on_ms"] = rep.expected_on_ms
        return finite(out)


def held_commands(plan: TickPlan, u: np.ndarray) -> np.ndarray:
    """The value (command, reference...) in force at each row: the last *emitted* one
    (catch-up steps send nothing)."""
    last = np.maximum.accumulate(np.where(plan.emit, np.arange(plan.rows), 0))
    return u[last]


def limiter_alone(ref: np.ndarray, lim: tuple[float, ...], p0: float) -> np.ndarray:
    """``ref`` through the compensator's limiter alone (one axis, constants of
    :func:`~motcomp.core.saturation.axis_constants`), from rest at ``p0``: the command
    without compensation."""
    out = np.empty(ref.size)
    u, v, track = p0, 0.0, at_rest(p0)
    for k, x in enumerate(ref.tolist()):
        u, v, track, _ = limit_axis(x, u, v, track, lim)
        out[k] = u
    return out


def _windows(mask: np.ndarray, rate_hz: float) -> list[slice]:
    """Windows of at most WINDOW_S (at least MIN_WINDOW_S) inside the runs where ``mask``
    holds; at most MAX_WINDOWS of them, spread evenly."""
    n = int(WINDOW_S * rate_hz)
    n_min = int(MIN_WINDOW_S * rate_hz)
    m = np.concatenate([[False], mask, [False]])
    edges = np.flatnonzero(m[1:] != m[:-1])
    out = []
    for lo, hi in zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True):
        for s in range(lo, hi, n):
            e = min(s + n, hi)
            if e - s >= n_min:
                out.append(slice(s, e))
    if len(out) > MAX_WINDOWS:
        pick = np.linspace(0, len(out) - 1, MAX_WINDOWS).round().astype(int)
        out = [out[i] for i in pick]
    return out


FEEDBACK_GAP_S = 1.0
"""Feedback further apart than this is two stretches (the windows a long recording's feedback
is read in: :data:`motcomp.replay.offline.FEEDBACK_WINDOWS`); closer, it is interpolated."""
PREROLL_S = 5.0
"""Simulated windows start this much earlier, so the platform model's initial transient is
gone when the window begins (the models' time constants are well below a second)."""
LOST_BRIDGE_S = 0.02
"""Outputs the recorder lost between two it kept at most this far apart are bridged by the
line joining those two (:meth:`Session.command_in_force`): off the lost commands by at most
``a T**2 / 8``, 0.3 mm at rails_y's 6 m/s^2 over 20 ms.  A recorder on a loaded host loses
a few outputs a second; the model check would otherwise restart its model at each loss."""
SETTLE_FRACTION = 0.01
"""A model started at rest at a run's first command is taken to have forgotten that start once
its step response stays within this part of its gain (:func:`settle_samples`)."""


def settle_samples(model: ProcessModel, rate_hz: float) -> int:
    """Samples at ``rate_hz`` after which the unit step response of ``model`` stays within
    :data:`SETTLE_FRACTION` of its gain (at most :data:`PREROLL_S`): how long a model started at
    rest at a command it was not resting at takes to forget that start."""
    n = int(PREROLL_S * rate_hz)
    y = simulate_axis(model, np.ones(n), rate_hz, initial=0.0)
    gain = model.gain
    off = np.flatnonzero(np.abs(y - gain) > SETTLE_FRACTION * max(abs(gain), 1e-12))
    return n if not off.size else min(n, int(off[-1]) + 1)


ALIGN_STEPS = 10
"""Most correlations of one delay estimate (:func:`_estimate`); three or four suffice."""
ALIGN_TOL = 0.05
"""A delay estimate stops when a step moves it by less than this part of a sample (0.05 ms at
1 kHz: the report shows tenths of a millisecond)."""
TAPER_FRACTION = 0.25
"""Part of a delay window under the taper's cosine edges (half at each end)."""


def _tukey(n: int) -> np.ndarray:
    """A Tukey window of ``n`` samples, :data:`TAPER_FRACTION` of it in cosine edges."""
    edge = max(1, round(TAPER_FRACTION / 2 * n))
    w = np.ones(n)
    ramp = 0.5 * (1.0 - np.cos(np.pi * (np.arange(edge) + 0.5) / edge))
    w[:edge] = ramp
    w[n - edge:] = ramp[::-1]
    return w


def _estimate(r: np.ndarray, y: np.ndarray, rate_hz: float, lead: int = 0) -> float | None:
    """Delay (s) of ``y`` behind the reference ``r[lead:]`` (equal lengths; ``r[:lead]`` is
    the reference before the window, and before that it is taken as ``r[0]``: at rest), or
    None (no motion, a non-finite sample, no peak in -0.5..1 s).

    One correlation of two equal windows pulls a slow motion's estimate towards zero by what
    each window holds that the other lacks (a 0.31 Hz sine delayed 196 ms read 169 ms over
    10 s).  So, as the live monitor does (:mod:`motcomp.runtime.monitor`, step 3), both are
    tapered by the same Tukey window, and the reference is shifted by the delay found --
    taken from before the window -- and correlated again until a step is below
    :data:`ALIGN_TOL` of a sample: at that fixed point the windows are aligned and the pull
    is nil (the same sine: 196.2 ms, its zero-order hold's half sample included)."""
    from motcomp.core.quality import estimate_delay

    win = r[lead:]
    if not np.all(np.isfinite(r)) or not np.all(np.isfinite(y)) or np.ptp(win) < MIN_MOTION:
        return None
    w = _tukey(y.size)
    wsum = float(w.sum())
    y_w = w * (y - float(w @ y) / wsum)
    grid = np.arange(r.size, dtype=float)
    at = grid[lead:]
    d = 0.0
    try:
        for _ in range(ALIGN_STEPS):
            rs = win if d == 0.0 else np.interp(at - d * rate_hz, grid, r)
            step = estimate_delay(w * (rs - float(w @ rs) / wsum), y_w, rate_hz,
                                  max_lag_s=1.0 - d, min_lag_s=-0.5 - d)
            d += step
            if abs(step) * rate_hz < ALIGN_TOL:
                return d
    except ConfigError:
        return None
    return None  # no convergence


def _reconstruction_lag(res: EngineResult, rows: np.ndarray) -> float:
    """The median over ``rows`` of what the replayed tick's input reconstruction added to the
    delay (s; 0 where the engine did not say)."""
    if res.lag_s is None:
        return 0.0
    lag = res.lag_s[rows]
    lag = lag[np.isfinite(lag)]
    return float(np.median(lag)) if lag.size else 0.0


def _median_ms(values: list[float]) -> float:
    return float(np.median(values)) * 1e3 if values else math.nan


def _events(mask: np.ndarray) -> int:
    if not mask.size:
        return 0
    return int(np.count_nonzero(mask[1:] & ~mask[:-1]) + int(mask[0]))


def _grid_rows(plan: TickPlan) -> np.ndarray:
    """Row index at each point of a uniform grid at the plan's period (the last row not
    after it); the identity when the rows are uniform."""
    d = np.diff(plan.now_ns)
    if np.all(d == plan.period_ns):
        return np.arange(plan.rows)
    t = plan.now_ns - plan.now_ns[0]
    g = np.arange(0, int(t[-1]) + 1, plan.period_ns)
    return np.searchsorted(t, g, side="right") - 1


def _grid_ns(plan: TickPlan) -> np.ndarray:
    """The instants of the uniform grid of :func:`_grid_rows` (ns, the plan's clock)."""
    d = np.diff(plan.now_ns)
    if np.all(d == plan.period_ns):
        return np.asarray(plan.now_ns)
    span = int(plan.now_ns[-1] - plan.now_ns[0])
    return np.asarray(plan.now_ns[0] + np.arange(0, span + 1, plan.period_ns, dtype=np.int64))


def flush_subnormal(x: float) -> float:
    """``x``, or 0.0 if it is a subnormal number (below the smallest normal double, about
    2.2e-308: the residue of a decay or of a difference at the bottom of the range, which is
    0 for any purpose of a report)."""
    return 0.0 if abs(x) < _TINY else x


_TINY = float(np.finfo(float).tiny)


def analyse(session: Session, plan: TickPlan, res: EngineResult, cfg: ServiceConfig,
            axes: ResolvedAxes, label: str, recorded_config: bool = True) -> ReplayReport:
    """The report of one replay (see the module docstring)."""
    rate = 1e9 / plan.period_ns
    pre = int(PREROLL_S * rate)
    emit = plan.emit
    sat_e = res.limited[emit]
    held = np.maximum.accumulate(np.where(emit, np.arange(plan.rows), 0))
    gi = held[_grid_rows(plan)]  # grid point -> the row whose output is in force
    grid_ns = _grid_ns(plan)
    sent = np.flatnonzero(emit)
    lims = axis_constants(axes.limits, plan.period_ns / 1e9)
    bands = tick_params(cfg, axes).shaper.band
    rec_rows = np.flatnonzero(plan.output >= 0)
    out = session.outputs
    compared: np.ndarray | None = rec_rows
    if plan.warm and rec_rows.size:
        compared = rec_rows[plan.now_ns[rec_rows] - plan.now_ns[0] >= SETTLE_S * 1e9]
    rec_flags = None
    out_idx = None
    if out is not None and rec_rows.size:
        rec_flags = out.flags[plan.output[rec_rows]]
        if compared.size:  # type: ignore[union-attr]
            out_idx = plan.output[compared]
            if compared.size == plan.rows:  # type: ignore[union-attr]
                compared = None  # every row: no gather
    reports = []
    for a, name in enumerate(AXES):
        if not axes.driven[a]:
            continue
        off = (res.bypass[:, a] if res.flags is None
               else compensation_off(res.flags, name, predicts(axes, a)))
        rep = AxisReport(name, compensated=bool((~off[emit]).any()))
        rep.saturated_samples = int(np.count_nonzero(sat_e[:, a]))
        rep.saturation_events = _events(sat_e[:, a])
        ref_sent = res.ref[sent, a]
        ref = np.interp(grid_ns, plan.now_ns[sent], ref_sent) if sent.size else res.ref[gi, a]
        mask = ~off[gi] if rep.compensated else np.ones(gi.size, bool)
        on_d, off_d = [], []
        for w in _windows(mask, rate):
            if np.ptp(ref[w]) < MIN_MOTION:
                continue
            lo = max(w.start - pre, 0)
            rows = gi[lo:w.stop]
            cut = w.start - lo
            cmd_on = res.u[rows, a]
            # the limiter at every step computed from the first row in force to the last
            r0, r1 = int(rows[0]), int(rows[-1]) + 1
            ref_rows = np.interp(plan.now_ns[r0:r1], plan.now_ns[sent], ref_sent)
            lim_lo, lim_hi = float(axes.limits.p_min[a]), float(axes.limits.p_max[a])
            off_rows = limiter_alone(ref_rows, lims[a], min(max(float(ref_rows[0]), lim_lo),
                                                            lim_hi))
            cmd_off = off_rows[rows - r0]  # held through the missed deadlines, as on
            r = ref[lo:w.stop]
            d_on = _estimate(r, simulate_axis(axes.plants[a], cmd_on, rate)[cut:], rate, cut)
            d_off = _estimate(r, simulate_axis(axes.plants[a], cmd_off, rate)[cut:], rate, cut)
            if d_on is not None and d_off is not None:
                band = bands[a] if a < len(bands) else None
                lag = (0.0 if band is None else band.delay_s) + _reconstruction_lag(res, rows)
                on_d.append(d_on + lag)
                off_d.append(d_off + lag)
        rep.delay_on_ms, rep.delay_off_ms, rep.delay_windows = (_median_ms(on_d),
                                                                _median_ms(off_d), len(on_d))
        if rec_flags is not None:
            rep.recorded_saturated = int(np.count_nonzero(rec_flags & FLAG_BITS[f"sat:{name}"]))
        if out_idx is not None:
            assert out is not None
            mine = res.u[:, a] if compared is None else res.u[:, a][compared]
            d = mine - out.pos[:, a][out_idx]
            d = d[np.isfinite(d)]
            if d.size:
                rep.max_diff = flush_subnormal(float(np.max(np.abs(d))))
                rep.rms_diff = flush_subnormal(float(np.sqrt(np.mean(d * d))))
        reports.append(rep)
    _recorded_delays(session, reports, axes, rate)
    _model_against_platform(session, reports, axes, rate)
    n_cmp = 0 if out_idx is None else int(out_idx.size)
    return ReplayReport(label, reports, int(np.count_nonzero(emit)), plan.rows,
                        float(plan.t_s[-1]) if plan.rows else 0.0, n_cmp, recorded_config)


def _model_against_platform(session: Session, reports: list[AxisReport], axes: ResolvedAxes,
                            rate: float) -> None:
    """The config's platform models against the recorded platform, both driven by the recorded
    commands (the module docstring); fills ``platform_lag_ms``, ``model_lag_ms``,
    ``model_fit``, or ``model_check`` with the reason it cannot be judged."""
    out, fb = session.outputs, session.feedback
    for rep in reports:
        if out is None or not len(out):
            rep.model_check = "no outputs recorded"
        elif fb is None or not len(fb):
            rep.model_check = "no platform feedback recorded"
        if rep.model_check:
            continue
        assert out is not None and fb is not None
        a = AXES.index(rep.axis)
        ok = fb.valid & np.isfinite(fb.pos[:, a]) & np.isfinite(fb.t)
        t_fb, y_fb = fb.t[ok], fb.pos[ok, a]
        if t_fb.size < 10 or np.any(np.diff(t_fb) <= 0):
            rep.model_check = ("no feedback of this axis in the recording" if t_fb.size < 10
                               else "the feedback's t is not increasing (several platforms?)")
            continue
        try:
            _, known_all = session.command_in_force(rep.axis, t_fb)
        except DataError as exc:
            rep.model_check = str(exc)
            continue
        # stretches of feedback without a gap (a busy platform skips cycles: up to a few
        # hundred ms); windows in them where the commands are known
        brk = np.flatnonzero(np.diff(t_fb) > FEEDBACK_GAP_S) + 1
        settle = settle_samples(axes.plants[a], rate)
        spans = []
        lost_cut = False
        t_out = np.sort(out.t[out.valid & np.isfinite(out.t)])
        for s0, s1 in zip(np.concatenate([[0], brk]).tolist(),
                          np.concatenate([brk, [t_fb.size]]).tolist(), strict=True):
            # the grid of the outputs' instants (just after them: each sample takes its own
            # tick's output), so that the model takes each command when the service sent it,
            # as the platform's lag behind the commands holds the stack's share
            k0 = int(np.searchsorted(t_out, t_fb[s0]))
            if k0 >= t_out.size:
                continue
            g = _uniform(float(t_out[k0]) + AFTER_TICK_S, t_fb[s1 - 1], rate)
            if g.size < MIN_WINDOW_S * rate or not known_all[s0:s1].any():
                continue
            cmd, _ = session.command_in_force(rep.axis, g, bridge_s=LOST_BRIDGE_S)
            known = np.isfinite(cmd)
            unknown = np.flatnonzero(~known)
            # a window starts `settle` samples into its run of known commands: the model starts
            # there at rest at the run's first command, which the platform need not be
            i = np.arange(g.size)
            run_start = np.maximum.accumulate(np.where(known & ~np.r_[False, known[:-1]], i, 0))
            ws = _windows(known & (i - run_start >= settle), rate)
            lost_cut |= unknown.size > 0 and not ws
            for w in ws:
                k = int(np.searchsorted(unknown, w.start))
                spans.append((g, cmd, s0, s1, w, int(unknown[k - 1]) + 1 if k else 0))
        if len(spans) > MAX_WINDOWS:
            spans = [spans[i] for i in np.linspace(0, len(spans) - 1, MAX_WINDOWS).round()
                     .astype(int)]
        plat, model, fits = [], [], []
        for g, cmd, s0, s1, w, first in spans:
            lo = max(w.start - int(PREROLL_S * rate), first)
            c = cmd[lo:w.stop]
            if np.ptp(cmd[w]) < MIN_MOTION:
                continue
            y_p = np.interp(g[w], t_fb[s0:s1], y_fb[s0:s1])
            y_m = simulate_axis(axes.plants[a], c, rate)[w.start - lo:]
            d_p = _estimate(c, y_p, rate, w.start - lo)
            d_m = _estimate(c, y_m, rate, w.start - lo)
            if d_p is None or d_m is None:
                continue
            plat.append(d_p)
            model.append(d_m)
            v = y_p - y_p.mean()
            e = v - (y_m - y_m.mean())
            fits.append(1.0 - float(np.dot(e, e)) / float(np.dot(v, v)))
        if not plat:
            rep.model_check = (
                f"the recorder lost outputs too often: no {settle / rate + MIN_WINDOW_S:.1f} s "
                f"with every command known (losses over {LOST_BRIDGE_S * 1e3:g} ms are not "
                f"bridged); record where the recorder gets its CPU"
                if lost_cut and not spans else
                "the recorded commands do not move this axis where the platform's feedback was "
                "recorded")
            continue
        rep.platform_lag_ms, rep.model_lag_ms = _median_ms(plat), _median_ms(model)
        rep.model_fit = float(np.median(fits))


def predicts(axes: ResolvedAxes, a: int) -> bool:
    """Whether the config predicts axis ``a`` (a prefilter, and ``predict`` on)."""
    return (a < len(axes.prediction) and axes.prediction[a] is not None
            and a < len(axes.predict) and bool(axes.predict[a]))


def _recorded_delays(session: Session, reports: list[AxisReport], axes: ResolvedAxes,
                     rate: float) -> None:
    """Input -> feedback delays on the recorded timestamps, split by whether the recorded
    outputs had the axis compensated (:func:`~motcomp.record.frames.compensation_off`, with the
    replayed config's prediction settings).

    Both streams are taken on the recorder's clock (receive times): the sender's and the
    platform's own clocks need not agree, nor run at the same rate (a sender clock 20 ppm fast
    is 72 ms off after an hour), while the transport adds well under a millisecond to each.
    Windows are chosen on the recorded outputs (one per tick, with their bypass flags), or on
    the inputs when no outputs were recorded, and resampled at ``rate``."""
    inp, fb, out = session.inputs, session.feedback, session.outputs
    if inp is None or fb is None or not len(fb) or not len(inp):
        return
    t_in = inp.log_ns / 1e9
    t_fb = fb.log_ns / 1e9
    if np.any(t_in[1:] < t_in[:-1]) or np.any(t_fb[1:] < t_fb[:-1]):
        return  # not on one timeline (several senders): no recorded delays
    if out is not None and len(out) and out.valid.all():
        t_ref, oflags = out.log_ns / 1e9, out.flags
    else:
        t_ref, oflags = t_in, np.zeros(t_in.size, np.int64)
    # the feedback may have been read in windows only (see read_session): use its coverage
    gaps = np.flatnonzero(np.diff(t_fb) > 0.1) + 1
    starts, ends = t_fb[np.concatenate([[0], gaps])], t_fb[np.concatenate([gaps - 1, [-1]])]
    k = np.searchsorted(starts, t_ref, side="right") - 1
    usable = (k >= 0) & (t_ref <= ends[np.maximum(k, 0)]) & (t_ref >= t_in[0]) & \
        (t_ref <= t_in[-1])
    for rep in reports:
        a = AXES.index(rep.axis)
        bypassed = compensation_off(oflags, rep.axis, predicts(axes, a))
        for mask, attr in ((~bypassed & usable, "recorded_on_ms"),
                           (bypassed & usable, "recorded_off_ms")):
            vals = []
            for w in _windows(mask, rate):
                g = _uniform(t_ref[w.start], t_ref[w.stop - 1], rate)
                if g.size < MIN_WINDOW_S * rate / 2:
                    continue
                lead = int(min(PREROLL_S, g[0] - t_in[0]) * rate)  # the input before it
                r = _interp_valid(np.concatenate([g[0] - np.arange(lead, 0, -1) / rate, g]),
                                  t_in, inp.pos[:, a], inp.decoded)
                y = _interp_valid(g, t_fb, fb.pos[:, a], fb.valid)
                d = None if r is None or y is None else _estimate(r, y, rate, lead)
                if d is not None:
                    vals.append(d)
            setattr(rep, attr, _median_ms(vals))


def _uniform(t0: float, t1: float, rate: float) -> np.ndarray:
    """Instants ``t0 + k / rate`` up to ``t1`` (s; each rounded once: ``np.arange`` from an
    epoch-seconds start accumulates its step's rounding, 2.9 ms over 40 s at 1 kHz)."""
    return np.asarray(t0 + np.arange(int(np.floor((t1 - t0) * rate)) + 1) / rate)


def _interp_valid(g: np.ndarray, t: np.ndarray, v: np.ndarray, ok: np.ndarray
                  ) -> np.ndarray | None:
    """``v`` (where ``ok`` and finite) at the times ``g``, from the part of ``t`` covering
    them."""
    lo = max(int(np.searchsorted(t, g[0])) - 1, 0)
    hi = int(np.searchsorted(t, g[-1])) + 2
    tt, vv = t[lo:hi], v[lo:hi]
    sel = ok[lo:hi] & np.isfinite(vv)
    if sel.sum() < 10:
        return None
    return np.interp(g, tt[sel], vv[sel])


def number(x: float, fmt: str) -> str:
    """``x`` formatted for a report: ``-`` if it is not finite, ``0`` if it is zero or a
    subnormal (:func:`flush_subnormal`), else ``format(x, fmt)``."""
    if not math.isfinite(x):
        return "-"
    x = flush_subnormal(x)
    return "0" if x == 0 else format(x, fmt)


def report_text(reps: list[ReplayReport], extra_lines: list[str]) -> str:
    """The tables printed by ``motcomp replay``: per config, the replay's figures, then its
    platform model against the recorded platform."""
    lines = list(extra_lines)

    def f(x: float, fmt: str = ".1f") -> str:
        return number(x, fmt)

    for rep in reps:
        lines += ["", f"{rep.label}: {rep.ticks} ticks ({rep.duration_s:.1f} s)", "",
                  f"{'axis':<10} {'delay off':>10} {'on':>8} {'gained':>8} | {'recorded off':>12}"
                  f" {'on':>8} | {'saturated':>9} {'events':>6} | {'max |replay-rec|':>16}",
                  "-" * 100]
        for a in rep.axes:
            note = "" if a.compensated else "  (bypass)"
            lines.append(
                f"{a.axis:<10} {f(a.delay_off_ms):>8}ms {f(a.delay_on_ms):>6}ms "
                f"{f(a.reduction_ms):>6}ms | {f(a.recorded_off_ms):>10}ms "
                f"{f(a.recorded_on_ms):>6}ms | {a.saturated_samples:>9} {a.saturation_events:>6} | "
                f"{f(a.max_diff, '.2e'):>16}{note}")
        lines += model_lines(rep)
    return "\n".join(lines)


def model_lines(rep: ReplayReport) -> list[str]:
    """The model check of one replay (:func:`_model_against_platform`) in words and figures."""
    judged = [a for a in rep.axes if not a.model_check]
    lines = ["", "the config's platform model against the recorded platform (both driven by the "
             "recorded commands):"]
    if judged:
        lines += [f"{'axis':<10} {'platform lag':>12} {'model lag':>10} {'error':>8} | "
                  f"{'fit %':>7} | {'on':>8} {'live, about':>12}", "-" * 78]
        for a in judged:
            lines.append(
                f"{a.axis:<10} {number(a.platform_lag_ms, '.1f'):>10}ms "
                f"{number(a.model_lag_ms, '.1f'):>8}ms {number(a.model_error_ms, '+.1f'):>6}ms | "
                f"{number(100 * a.model_fit, '.2f'):>7} | {number(a.delay_on_ms, '.1f'):>6}ms "
                f"{number(a.expected_on_ms, '.1f'):>10}ms")
        lines += ["(error: the platform's lag minus the model's, which the compensator "
                  "inherits: live, the delay is", " about 'on' + error; fit: the share of the "
                  "platform's motion the model explains)"]
    why: dict[str, list[str]] = {}  # axes with an 'on' delay the recording cannot check
    for a in rep.axes:
        if a.model_check and math.isfinite(a.delay_on_ms):
            why.setdefault(a.model_check, []).append(a.axis)
    for reason, names in why.items():
        lines.append(f"{', '.join(names)}: a model error cannot be judged offline ({reason}): "
                     "'on' is what the config's model says; a platform that differs from the "
                     "model gets another delay")
    if len(lines) == 2:
        return []
    return lines
