"""What a replay shows: apparent delays, saturation, differences from the recorded outputs.

Apparent delay (:func:`~motcomp.core.quality.estimate_delay`, cross-correlation with
sub-sample refinement) of a response behind the motion-cueing reference, per axis, on windows
of :data:`WINDOW_S` (at least :data:`MIN_WINDOW_S`) where the reference moves (peak to peak
above :data:`MIN_MOTION`) and the compensation state does not change, at most
:data:`MAX_WINDOWS` of them spread over the session; the median over windows is reported.

* *simulated*: the config's platform model (``plants``, the full models, not the compensator's
  P1D) driven by the replayed commands (``on``, windows where the replay compensated the axis)
  and by the reference through the limiter alone (``off``: no compensation,
  :func:`motcomp.core.saturation.limit_axis`, the compensator's own limiter), behind the tick's
  reference plus the delay of the axis' band limit before it (``input.band_hz``: a pure delay
  in the driver's band), so that both figures are behind the motion-cueing input as the
  recorded ones are (the playback's own lag, about one input period, is not added);
* *recorded*: the recorded feedback position behind the recorded input (both on the
  recorder's receive times), on windows where the service had compensation on, resp. off
  (from the bypass flags of the recorded outputs).

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
from motcomp.core.saturation import at_rest, axis_constants, limit_axis
from motcomp.errors import ConfigError
from motcomp.jsonsafe import finite
from motcomp.record.frames import FLAG_BITS
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

    @property
    def reduction_ms(self) -> float:
        return self.delay_off_ms - self.delay_on_ms

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


PREROLL_S = 5.0
"""Simulated windows start this much earlier, so the platform model's initial transient is
gone when the window begins (the models' time constants are well below a second)."""


def _estimate(r: np.ndarray, y: np.ndarray, rate_hz: float) -> float | None:
    from motcomp.core.quality import estimate_delay

    if not np.all(np.isfinite(r)) or not np.all(np.isfinite(y)) or np.ptp(r) < MIN_MOTION:
        return None
    try:
        return estimate_delay(r, y, rate_hz, max_lag_s=1.0)
    except ConfigError:
        return None


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


def analyse(session: Session, plan: TickPlan, res: EngineResult, cfg: ServiceConfig,
            axes: ResolvedAxes, label: str, recorded_config: bool = True) -> ReplayReport:
    """The report of one replay (see the module docstring)."""
    from motcomp.sim.platform import simulate_axis

    rate = 1e9 / plan.period_ns
    pre = int(PREROLL_S * rate)
    emit = plan.emit
    sat_e = res.limited[emit]
    held = np.maximum.accumulate(np.where(emit, np.arange(plan.rows), 0))
    gi = held[_grid_rows(plan)]  # grid point -> the row whose output is in force
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
        rep = AxisReport(name, compensated=bool((~res.bypass[:, a]).any()))
        rep.saturated_samples = int(np.count_nonzero(sat_e[:, a]))
        rep.saturation_events = _events(sat_e[:, a])
        ref = res.ref[gi, a]
        mask = ~res.bypass[gi, a] if rep.compensated else np.ones(gi.size, bool)
        on_d, off_d = [], []
        for w in _windows(mask, rate):
            if np.ptp(ref[w]) < MIN_MOTION:
                continue
            lo = max(w.start - pre, 0)
            rows = gi[lo:w.stop]
            cut = w.start - lo
            cmd_on = res.u[rows, a]
            lim_lo, lim_hi = float(axes.limits.p_min[a]), float(axes.limits.p_max[a])
            cmd_off = limiter_alone(res.ref[rows, a], lims[a],
                                    min(max(float(res.ref[rows[0], a]), lim_lo), lim_hi))
            d_on = _estimate(ref[w], simulate_axis(axes.plants[a], cmd_on, rate)[cut:], rate)
            d_off = _estimate(ref[w], simulate_axis(axes.plants[a], cmd_off, rate)[cut:], rate)
            if d_on is not None and d_off is not None:
                band = bands[a] if a < len(bands) else None
                lag = 0.0 if band is None else band.delay_s
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
                rep.max_diff = float(np.max(np.abs(d)))
                rep.rms_diff = float(np.sqrt(np.mean(d * d)))
        reports.append(rep)
    _recorded_delays(session, reports, rate)
    n_cmp = 0 if out_idx is None else int(out_idx.size)
    return ReplayReport(label, reports, int(np.count_nonzero(emit)), plan.rows,
                        float(plan.t_s[-1]) if plan.rows else 0.0, n_cmp, recorded_config)


def _recorded_delays(session: Session, reports: list[AxisReport], rate: float) -> None:
    """Input -> feedback delays on the recorded timestamps, split by the recorded bypass.

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
        bypassed = (oflags & FLAG_BITS[f"bypass:{rep.axis}"]) != 0
        for mask, attr in ((~bypassed & usable, "recorded_on_ms"),
                           (bypassed & usable, "recorded_off_ms")):
            vals = []
            for w in _windows(mask, rate):
                g = np.arange(t_ref[w.start], t_ref[w.stop - 1], 1.0 / rate)
                if g.size < MIN_WINDOW_S * rate / 2:
                    continue
                r = _interp_valid(g, t_in, inp.pos[:, a], inp.decoded)
                y = _interp_valid(g, t_fb, fb.pos[:, a], fb.valid)
                d = None if r is None or y is None else _estimate(r, y, rate)
                if d is not None:
                    vals.append(d)
            setattr(rep, attr, _median_ms(vals))


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


def report_text(reps: list[ReplayReport], extra_lines: list[str]) -> str:
    """The table printed by ``motcomp replay``."""
    lines = list(extra_lines)

    def f(x: float, nd: int = 1) -> str:
        return f"{x:.{nd}f}" if math.isfinite(x) else "-"

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
                f"{(f'{a.max_diff:.2e}' if math.isfinite(a.max_diff) else '-'):>16}{note}")
    return "\n".join(lines)
